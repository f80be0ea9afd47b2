"""Time of one budget point of active exploration's learning curve (:mod:`experiments.active`).

At every budget the experiment fits the can network on the throws chosen so far, plainly
and pooled over neighbouring fields, and scores Table I's cases (both protocols, both
tie-break rules) on the held-out replays. This script runs one learner over the can data
set at a scale (generated into the cache on first use, as the experiment does) and times
each budget point's evaluation, beside the goal of under 1 s per point::

    .venv/bin/python benchmarks/active.py                       # quick scale, learner random
    .venv/bin/python benchmarks/active.py --scale full --old    # and the can network itself

The figures are CPU seconds (``time.process_time``) and wall seconds of one evaluation
per budget after one warm-up evaluation, on the threads ``--threads`` allows. ``--old`` also times the same points on
the can network itself, whose end configuration's table (configurations x 11 x 195 x
configurations values) is fitted and compiled though no score reads it, and checks the
scores equal.
"""

from __future__ import annotations

import argparse
import time

import torch
from effect_networks.experiments.active import run as ex
from effect_networks.experiments.active import settings as exs
from effect_networks.experiments.can_tossing.run import table_one_cases
from effect_networks.experiments.can_tossing.settings import ANGLE, PROTOCOLS
from effect_networks.experiments.cans import can_dataset, default_data_dir
from effect_networks.inference import grid_kernel
from effect_networks.inference.design.active import explore
from effect_networks.sim2d import field_throws, geometry
from timing import add_out, print_also_to  # benchmarks/timing.py, beside this script


def timed(fn):
    """``(fn(), CPU seconds, wall seconds)``."""
    cpu, wall = time.process_time(), time.perf_counter()
    out = fn()
    return out, time.process_time() - cpu, time.perf_counter() - wall


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scale", default="quick", choices=("tiny", "quick", "full"))
    parser.add_argument("--learner", default="random", choices=tuple(exs.LEARNERS))
    parser.add_argument("--fractions", type=float, nargs="+", default=None)
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--old", action="store_true", help="also time the can network itself")
    add_out(parser)
    args = parser.parse_args()
    print_also_to(args.out, __file__)
    torch.set_num_threads(args.threads)

    settings = dict(exs.QUICK) if args.scale == "quick" else {"scale": args.scale}
    if args.fractions is not None:
        settings["fractions"] = tuple(args.fractions)
    data_dir = default_data_dir() if args.data_dir is None else args.data_dir
    config = exs.ActiveConfig(**settings, data_dir=data_dir, progress=False)
    data = can_dataset(config.data_dir, config.scale, progress=False)
    replays, configs = ex.replay_counts(config)
    net, pool, oracle, rows = ex.can_pool(data)
    budgets = [max(1, round(f * pool.n_rows)) for f in config.fractions]
    throwable = torch.tensor(
        [field_throws.is_throwable(f, ANGLE) for f in range(geometry.N_FIELDS)]
    )
    cases = {p: table_one_cases(data, p) for p in PROTOCOLS}
    pooling = (
        grid_kernel((geometry.N_ROWS, geometry.N_COLUMNS), config.pool_sigma),
        config.pool_strength,
    )
    strategy, shared = exs.LEARNERS[args.learner]
    learned, cpu, wall = timed(
        lambda: explore(
            net,
            pool,
            oracle,
            budgets[-1],
            batch_size=config.batch_size,
            strategy=strategy,
            prior_strength=config.prior_strength if shared else 0.0,
            sites=config.sites,
            seed=config.seed,
        )
    )
    n_states = len(net.feature("config").states)
    print(
        f"scale {config.scale}: {n_states} configurations, pool {pool.n_rows:,} throws, "
        f"{sum(len(c[0]) for c in cases.values()):,} cases; {args.learner} chose "
        f"{budgets[-1]:,} throws in {cpu:.2f} CPU s ({wall:.2f} s wall)"
    )
    scoring = ex.scoring_network(net)
    first = learned.rows.rows(slice(0, budgets[0]))  # warm-up: imports, first allocations
    ex._scores(scoring, first, pool, throwable, pooling, cases, replays, configs)
    head = "| throws | Table I, CPU s | wall s |"
    if args.old:
        head += " can network, CPU s | wall s | scores equal |"
    print(f"\nTable I per budget point (goal: under {exs.POINT_GOAL_S:g} s)\n\n{head}")
    print("|---:" * (head.count("|") - 1) + "|")
    for b in budgets:
        chosen = learned.rows.rows(slice(0, b))

        def scores(network, chosen=chosen):
            return ex._scores(network, chosen, pool, throwable, pooling, cases, replays, configs)

        new, cpu, wall = timed(lambda: scores(scoring))
        line = f"| {b:,} | {cpu:.3f} | {wall:.3f} |"
        if args.old:
            old, old_cpu, old_wall = timed(lambda: scores(net))
            line += f" {old_cpu:.3f} | {old_wall:.3f} | {new == old} |"
        print(line, flush=True)


if __name__ == "__main__":
    main()
