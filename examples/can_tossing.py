"""The paper's can-tossing experiment (§IV-A): Table I, emulation and imitation.

The can network is fitted on the can data set's 0° throws (generated under ``--data-dir``
on first use, then reused) and judged by throwing again: Table I under both protocols
and both tie-breaks, emulation of demonstrated throws, and the imitation surprise's ROC
(:mod:`experiments.can_tossing`). Writes ``can_tossing.json``, ``can_tossing.md``,
``can_tossing_table1.png`` and ``can_tossing_roc.png`` to ``--out``::

    .venv/bin/python examples/can_tossing.py --scale full
    .venv/bin/python examples/can_tossing.py --scale tiny --n-demos 30 --out /tmp/cans
"""

from __future__ import annotations

import argparse

import torch

from experiments.can_tossing import (
    PROTOCOLS,
    RULES,
    CanTossingConfig,
    CanTossingResult,
    run_can_tossing,
)
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
        help="data set: process:N | dask-local:N | dask://HOST:PORT | ray (default: every core)",
    )
    parser.add_argument("--out", default="results")
    parser.add_argument("--seed", type=int, default=0, help="seed of the evaluation throws")
    parser.add_argument("--rule", choices=RULES, default="aim", help="headline tie-break")
    parser.add_argument("--cases", choices=PROTOCOLS, default="counts", help="headline protocol")
    parser.add_argument("--n-demos", type=int, default=300, help="emulation/imitation throws")
    parser.add_argument("--aim-error", type=float, default=0.03, help="imitation, m per axis")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)
    args.config = config_or_exit(
        parser,
        lambda: CanTossingConfig(
            scale=args.scale,
            data_dir=args.data_dir,
            executor=args.executor,
            seed=args.seed,
            rule=args.rule,
            cases=args.cases,
            n_demos=args.n_demos,
            aim_error=args.aim_error,
            progress=not args.quiet,
        ),
    )
    return args


def main(args: argparse.Namespace) -> CanTossingResult:
    torch.set_num_threads(1)
    result = run_can_tossing(args.config)
    result.save(args.out)
    print(result.to_markdown())
    return result


if __name__ == "__main__":
    run_script(main, parse_args())
