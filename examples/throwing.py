"""The paper's throwing experiment (§IV-B): learn where to aim to hit a point, and re-throw.

The throw network's inverse query answers "where to aim to hit this point"; the robot
throws there and the new hit's RMS error against the desired one is reported per axis,
without and with release noise (:mod:`experiments.throwing`). Writes ``throwing.json``,
``throwing.md`` and ``throwing_errors.png`` to ``--out``::

    .venv/bin/python examples/throwing.py [--n-train 29000] [--n-test 1000] [--seed 0]
    .venv/bin/python examples/throwing.py --quick          # small sizes, seconds
"""

from __future__ import annotations

import argparse

import torch

from experiments.config import check_threads, config_or_exit, run_script
from experiments.throwing import (
    BIN_CANDIDATES,
    QUICK,
    ThrowingConfig,
    ThrowingResult,
    run_throwing,
)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--n-train", type=int, default=29_000)
    parser.add_argument("--n-test", type=int, default=1_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="results")
    parser.add_argument(
        "--bins", type=int, nargs="+", default=list(BIN_CANDIDATES), help="grid sizes to try"
    )
    parser.add_argument("--quick", action="store_true", help="1500 + 200 throws, 3 grid sizes")
    parser.add_argument(
        "--threads", type=int, default=1, help="torch threads (small tensors: 1 is fastest)"
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)
    config_or_exit(parser, lambda: check_threads("threads", args.threads))
    sizes = QUICK if args.quick else {"n_train": args.n_train, "n_test": args.n_test}
    sizes = {"bins": tuple(args.bins)} | sizes
    args.config = config_or_exit(
        parser, lambda: ThrowingConfig(**sizes, seed=args.seed, progress=not args.quiet)
    )
    return args


def main(args: argparse.Namespace) -> ThrowingResult:
    threads = torch.get_num_threads()
    torch.set_num_threads(args.threads)
    try:
        result = run_throwing(args.config)
    finally:
        torch.set_num_threads(threads)
    result.save(args.out)
    print(result.to_markdown())
    return result


if __name__ == "__main__":
    run_script(main, parse_args())
