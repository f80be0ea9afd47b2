"""Adaptive target clusters (EM) against the paper's grid, and active throw targets.

Beyond the paper's §IV-B (:mod:`experiments.adaptive_throw`): for each grid size the
grid layout and the EM-refined adaptive layout side by side (cluster count, fit time on
one torch thread, re-throw RMS) queried both as the paper does (the posterior) and with
the inverse model (``parameter_for_effect``), the largest also with release noise beside
the noise's own scatter and the exact inverse of the noise-free throw, a local-fit floor
of what the throws support, the best of the inverse model's candidates, what one best
plane per cell leaves of the map's curvature, and re-throw RMS against the number of
throws for actively chosen and random targets. Writes
``adaptive_throw.json``, ``adaptive_throw.md`` and ``adaptive_throw.png`` to ``--out``::

    .venv/bin/python examples/adaptive_throw.py [--n-train 29000] [--bins 4 8 12 16 20]
    .venv/bin/python examples/adaptive_throw.py --quick          # small sizes, seconds
"""

from __future__ import annotations

import argparse

import torch

from experiments.adaptive_throw import (
    QUICK,
    AdaptiveThrowConfig,
    AdaptiveThrowResult,
    run_adaptive_throw,
)
from experiments.config import check_threads, config_or_exit, run_script


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--n-train", type=int, default=29_000)
    parser.add_argument("--n-test", type=int, default=1_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--bins", type=int, nargs="+", default=[4, 8, 12, 16, 20])
    parser.add_argument(
        "--noisy-bins", type=int, default=16, help="clusters per axis with release noise"
    )
    parser.add_argument(
        "--em-steps", type=int, nargs="+", default=[5, 20], help="EM checkpoints to measure"
    )
    parser.add_argument("--budgets", type=int, nargs="+", default=[250, 500, 1000, 2000, 4000])
    parser.add_argument("--batch", type=int, default=50)
    parser.add_argument("--pool", type=int, default=2000)
    parser.add_argument(
        "--noise-repeats", type=int, default=10, help="re-throws per hit with release noise"
    )
    parser.add_argument(
        "--pseudo-count",
        type=float,
        default=0.0,
        help="every fit's pseudo-count (the library's default is 0.01)",
    )
    parser.add_argument("--out", default="results")
    parser.add_argument("--quick", action="store_true", help="2000 + 200 throws, small grids")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (timings: 1)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)
    config_or_exit(parser, lambda: check_threads("threads", args.threads))
    sizes = {
        "n_train": args.n_train,
        "n_test": args.n_test,
        "bins": tuple(args.bins),
        "noisy_bins": args.noisy_bins,
        "em_steps": tuple(args.em_steps),
        "budgets": tuple(args.budgets),
        "batch": args.batch,
        "pool": args.pool,
        "noise_repeats": args.noise_repeats,
    }
    if args.quick:
        sizes |= QUICK
    args.config = config_or_exit(
        parser,
        lambda: AdaptiveThrowConfig(
            **sizes, seed=args.seed, pseudo_count=args.pseudo_count, progress=not args.quiet
        ),
    )
    return args


def main(args: argparse.Namespace) -> AdaptiveThrowResult:
    threads = torch.get_num_threads()
    torch.set_num_threads(args.threads)
    try:
        result = run_adaptive_throw(args.config)
    finally:
        torch.set_num_threads(threads)
    result.save(args.out)
    print(result.to_markdown())
    return result


if __name__ == "__main__":
    run_script(main, parse_args())
