"""Beyond the paper: learn the can network from a fraction of the throws (active exploration).

A learner chooses which 0° throws of the can data set to make, by expected information
gain about the network's tables (or at random, or by uncertainty), and Table I is
measured on held-out replays at each budget beside the network fitted on every throw
(:mod:`experiments.active`), each network fitted plainly and pooled over neighbouring
fields (:func:`inference.fit_pooled`). Writes ``active.json``, ``active.md`` and ``active.png`` to
``--out``::

    .venv/bin/python examples/active.py                  # full scale
    .venv/bin/python examples/active.py --quick          # the quick data set, about a minute
"""

from __future__ import annotations

import argparse

import torch

from experiments.active import LEARNERS, QUICK, ActiveConfig, ActiveResult, run_active
from experiments.cans import SCALES
from experiments.config import config_or_exit, run_script


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--scale", choices=tuple(SCALES), default="full")
    parser.add_argument("--data-dir", default="data")
    parser.add_argument(
        "--executor",
        default=None,
        help="simulations, if needed: process:N | dask-local:N | dask://HOST:PORT | ray",
    )
    parser.add_argument("--out", default="results")
    parser.add_argument("--repeats", type=int, default=16, help="held-out replays per pair")
    parser.add_argument(
        "--fractions",
        type=float,
        nargs="+",
        default=[0.02, 0.05, 0.1, 0.2, 0.5],
        help="budgets, as fractions of the 0° throws",
    )
    parser.add_argument("--learners", nargs="+", choices=tuple(LEARNERS), default=list(LEARNERS))
    parser.add_argument("--batch-size", type=int, default=100)
    parser.add_argument("--prior-strength", type=float, default=1.0, help="eig_shared's prior")
    parser.add_argument(
        "--pool-sigma", type=float, default=0.7, help="pooled fit: kernel width in fields"
    )
    parser.add_argument(
        "--pool-strength", type=float, default=0.5, help="pooled fit: neighbours' pseudo-throws"
    )
    parser.add_argument(
        "--sites", nargs="+", default=["end.count"], help="end sites the gains are about"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--n-seeds", type=int, default=1, help="runs per learner, averaged")
    parser.add_argument("--checkpoint-dir", default=None, help="save and resume the learners")
    parser.add_argument(
        "--quick",
        action="store_true",
        help="quick data set, 8 replays, budgets 5-50 %%, batches of 20",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)
    settings = {
        "scale": args.scale,
        "repeats": args.repeats,
        "fractions": tuple(args.fractions),
        "batch_size": args.batch_size,
    }
    if args.quick:
        settings |= QUICK
    args.config = config_or_exit(
        parser,
        lambda: ActiveConfig(
            **settings,
            data_dir=args.data_dir,
            executor=args.executor,
            learners=tuple(args.learners),
            prior_strength=args.prior_strength,
            pool_sigma=args.pool_sigma,
            pool_strength=args.pool_strength,
            sites=tuple(args.sites),
            seed=args.seed,
            n_seeds=args.n_seeds,
            checkpoint_dir=args.checkpoint_dir,
            progress=not args.quiet,
        ),
    )
    return args


def main(args: argparse.Namespace) -> ActiveResult:
    torch.set_num_threads(1)
    result = run_active(args.config)
    result.save(args.out)
    print(result.to_markdown())
    return result


if __name__ == "__main__":
    run_script(main, parse_args())
