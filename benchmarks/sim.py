"""Speed of the can world: throws per second per core, today's simulation beside the new one.

    python benchmarks/sim.py                 # a sample of 600 data-set rows, one core
    python benchmarks/sim.py --full          # also generate the whole data set, timed
    python benchmarks/sim.py --full --executor dask-local:2

The sample draws rows of the full data set (every stable configuration x 195 fields x
3 angles x 3 repeats) uniformly at random and simulates them on this core with four
simulations, interleaved and repeated (median of the repeats):

- format 1 (the peer): data-set format 1's stopping rules, stepped through pymunk's
  public API: the simulation as it was before the can world was split;
- format 2 (today's): the current stopping rules (:data:`sim2d.materials.STOPPING`) and
  stepping (:data:`sim2d.materials.STEPPING`: 1 ms, 10 solver iterations, the cans awake)
  through pymunk's C binding: what ``generate_dataset`` runs;
- 2 ms, 10 it.: the same with a 2 ms step, measured and rejected (Table I at full scale
  moved by up to 3.8 points);
- 2 ms, 5 it., asleep: 2 ms, 5 iterations and the cans asleep until touched, so that clear
  misses are answered without pymunk (:func:`sim2d.world.clear_miss`): the fastest
  stepping measured, rejected (Table I moved by up to 7.2 points; the pyramid is weaker:
  asleep cans have no contact impulses to start from when the ball strikes).

Times are this process's CPU seconds (one core; on a shared machine wall time also counts
other people's work). It prints each one's simulated throws/s and data-set rows/s per
core, the speed-up over the peer beside the goal (3x), how many sample throws end in a
different configuration than under format 2 (any change to the stepping changes about a
fifth of them: the outcome of a throw is chaotic) and the statistics that should not
change (the share of throws that hit, cans thrown off per throw), and the full data set's
wall time on two free cores estimated from the rows/s, beside the goal (90 s on 2 cores).
``--full`` measures that wall time. Unthrowable rows cost nothing (they are not
simulated).
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
from effect_networks.sim2d import can_dataset, materials
from effect_networks.sim2d.configurations import stable_configurations
from effect_networks.sim2d.executors import default_spec
from effect_networks.sim2d.field_throws import (
    aim_offset,
    aim_seed,
    is_throwable,
    launch_state,
    outcome_of,
)
from effect_networks.sim2d.world import run_ball

GOAL_SPEEDUP = 3.0
GOAL_FULL_SECONDS = 90.0  # on 2 cores
PEER, TODAY = "format 1 (peer)", "format 2 (today)"
STEP2, FASTEST = "2 ms, 10 it.", "2 ms, 5 it., asleep"
VARIANTS = {
    PEER: {"stopping": materials.STOPPING_FORMAT_1, "reference": True},
    TODAY: {"stopping": materials.STOPPING},
    STEP2: {
        "stopping": materials.STOPPING,
        "stepping": materials.Stepping(time_step=0.002, solver_iterations=10, start_asleep=False),
    },
    FASTEST: {
        "stopping": materials.STOPPING,
        "stepping": materials.Stepping(time_step=0.002, solver_iterations=5, start_asleep=True),
    },
}


def sample(n: int, seed: int) -> tuple[list, int, int]:
    """``(throws, sampled rows, rows of the full data set)``; throws are ``(config, p, v)``."""
    configs = np.array(stable_configurations())
    rows = can_dataset._rows(configs, [0, 1, 2], 3)
    picked = rows[np.random.default_rng(seed).choice(len(rows), size=n, replace=False)]
    throws = []
    for config, field, angle, repeat in picked.tolist():
        if is_throwable(field, angle):
            offset = aim_offset(0.003, aim_seed(0, config, field, angle, repeat))
            throws.append((config, *launch_state(field, angle, offset=offset)))
    return throws, n, len(rows)


def run(throws, variant: dict) -> tuple[float, list]:
    """CPU seconds to simulate ``throws`` and their outcomes."""
    start = time.process_time()
    outcomes = [outcome_of(c, run_ball(c, p, v, **variant)) for c, p, v in throws]
    return time.process_time() - start, outcomes


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--throws", type=int, default=600, help="sample size (rows)")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per simulation")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--full", action="store_true", help="generate the full data set")
    parser.add_argument("--executor", default=None, help=f"for --full (default {default_spec()})")
    parser.add_argument("--out", type=Path, default=None, help="where --full writes")
    args = parser.parse_args(argv)

    cores = len(os.sched_getaffinity(0))
    stable = stable_configurations()
    throws, n_rows, total = sample(args.throws, args.seed)
    print(
        f"{len(stable)} stable configurations; sample: {n_rows} rows, {len(throws)} simulated "
        f"throws; median of {args.repeats} interleaved runs, CPU time of one core"
    )
    seconds = {name: [] for name in VARIANTS}
    outcomes = {}
    for _ in range(args.repeats):
        for name, variant in VARIANTS.items():
            elapsed, outcomes[name] = run(throws, variant)
            seconds[name].append(elapsed)
    peer = statistics.median(seconds[PEER])
    print(
        f"{'simulation':<19} {'throws/s':>8} {'rows/s':>7} {'speed-up':>8} {'goal':>4}  "
        f"{'hit':>5} {'off/throw':>9}  end configuration differs from format 2"
    )
    for name in VARIANTS:
        s = statistics.median(seconds[name])
        ends = [o.end_config for o in outcomes[name]]
        differ = sum(a != o.end_config for a, o in zip(ends, outcomes[TODAY], strict=True))
        hit = np.mean([o.hit_any_can for o in outcomes[name]])
        off = np.mean([o.count_before - o.count_after for o in outcomes[name]])
        print(
            f"{name:<19} {len(throws) / s:>8.0f} {n_rows / s:>7.0f} {peer / s:>7.2f}x"
            f" {'-' if name == PEER else f'{GOAL_SPEEDUP:.0f}x':>4}  {hit:>5.1%} {off:>9.3f}"
            f"  {differ} of {len(throws)}"
        )
    for name in (TODAY, STEP2, FASTEST):
        rows_per_s = n_rows / statistics.median(seconds[name])
        print(
            f"full data set, {name}: {total} rows, estimated {total / (2 * rows_per_s):.0f} s "
            f"on 2 free cores (goal < {GOAL_FULL_SECONDS:.0f} s; format 1 peer: "
            f"{total / (2 * n_rows / peer):.0f} s); this machine has {cores} cores"
        )
    if args.full:
        with tempfile.TemporaryDirectory() as tmp:
            out = args.out or Path(tmp) / "can_dataset.npz"
            start = time.perf_counter()
            can_dataset.generate_dataset(out, executor=args.executor)
            wall = time.perf_counter() - start
            data = can_dataset.load_dataset(out)
            print(
                f"full data set measured: {len(data)} rows in {wall:.0f} s on "
                f"{args.executor or default_spec()} (goal < {GOAL_FULL_SECONDS:.0f} s on 2 cores); "
                f"{int(data.timed_out.sum())} timed out, {int((~data.throwable).sum())} "
                f"unthrowable rows; written to {out}"
            )
    print(f"format 2: {materials.STEPPING}; cap {materials.MAX_SIM_TIME} s")
    print(
        "the 'hit' share and cans thrown off per throw are statistics of the world: a stepping "
        "that changes them changes the world (Table I is the test; see README)"
    )


if __name__ == "__main__":
    main()
