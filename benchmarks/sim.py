"""Speed of the can world: throws per second per core, today's simulation beside the new one.

    python benchmarks/sim.py                 # a sample of 600 data-set rows, one core
    python benchmarks/sim.py --full          # also generate the whole data set, timed
    python benchmarks/sim.py --full --executor dask-local:2

The sample draws rows of the full data set (every stable configuration x 195 fields x
3 angles x 3 repeats) uniformly at random and simulates them on this core with three
simulations, interleaved and repeated (median of the repeats):

- format 1 (the peer): data-set format 1's stopping rules, stepped through pymunk's
  public API: the simulation as it was before the can world was split;
- format 1, binding: the same rules and numbers, stepped through pymunk's C binding
  (bit for bit the peer's outcomes);
- format 2 (new): the current stopping rules (:data:`sim2d.materials.STOPPING`) through
  the binding: what ``generate_dataset`` runs.

It prints each one's simulated throws/s and data-set rows/s per core, the speed-up over
the peer beside the goal (3x), how many sample throws end in a different configuration
than under the peer, and the full data set's wall time on this machine's cores estimated
from the rows/s, beside the goal (90 s on 2 cores). ``--full`` measures that wall time.
Unthrowable rows cost nothing (they are not simulated).
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from sim2d import can_dataset, materials
from sim2d.configurations import stable_configurations
from sim2d.executors import default_spec
from sim2d.field_throws import aim_offset, aim_seed, is_throwable, launch_state, outcome_of
from sim2d.world import simulate

GOAL_SPEEDUP = 3.0
GOAL_FULL_SECONDS = 90.0  # on 2 cores
VARIANTS = {
    "format 1 (peer)": {"stopping": materials.STOPPING_FORMAT_1, "reference": True},
    "format 1, binding": {"stopping": materials.STOPPING_FORMAT_1, "reference": False},
    "format 2 (new)": {"stopping": materials.STOPPING, "reference": False},
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


def run(throws, variant: dict) -> tuple[float, list[int]]:
    """Seconds to simulate ``throws`` and their end configurations."""
    start = time.perf_counter()
    ends = [outcome_of(c, simulate(c, p, v, **variant)).end_config for c, p, v in throws]
    return time.perf_counter() - start, ends


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
        f"throws; median of {args.repeats} interleaved runs on one core (shared machine)"
    )
    seconds = {name: [] for name in VARIANTS}
    ends = {}
    for _ in range(args.repeats):
        for name, variant in VARIANTS.items():
            elapsed, ends[name] = run(throws, variant)
            seconds[name].append(elapsed)
    peer = statistics.median(seconds["format 1 (peer)"])
    print(f"{'simulation':<20} {'throws/s':>9} {'rows/s':>8} {'speed-up':>9}  goal   differ")
    for name in VARIANTS:
        s = statistics.median(seconds[name])
        differ = sum(a != b for a, b in zip(ends[name], ends["format 1 (peer)"], strict=True))
        print(
            f"{name:<20} {len(throws) / s:>9.0f} {n_rows / s:>8.0f} {peer / s:>8.2f}x"
            f"  {'-' if name.endswith('(peer)') else f'{GOAL_SPEEDUP:.0f}x':>4}"
            f"   {differ} of {len(throws)} end configurations"
        )
    new_rows_per_s = n_rows / statistics.median(seconds["format 2 (new)"])
    print(
        f"full data set: {total} rows; estimated on 2 free cores {total / (2 * new_rows_per_s):.0f} s "
        f"(goal < {GOAL_FULL_SECONDS:.0f} s; format 1 peer: "
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
    print(f"time step {materials.TIME_STEP} s, cap {materials.MAX_SIM_TIME} s")


if __name__ == "__main__":
    main()
