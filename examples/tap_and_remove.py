"""The paper's §III illustration: a "remove" action and a "tap" action with a force.

"remove" is emulated and imitated with a plain network; "tap" is predicted without a
parameter site, with one cluster and with ``--bins`` force clusters
(:mod:`experiments.tap_and_remove`). Writes ``tap_and_remove.json``, ``.md`` and
``.png`` to ``--out``::

    .venv/bin/python examples/tap_and_remove.py --n 2000 --out results/tap_and_remove
"""

from __future__ import annotations

import argparse

import torch

from experiments.config import config_or_exit, run_script
from experiments.tap_and_remove import (
    TapAndRemoveConfig,
    TapAndRemoveResult,
    run_tap_and_remove,
)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--n", type=int, default=2000, help="training rows")
    parser.add_argument("--bins", type=int, default=8, help="force clusters")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="results/tap_and_remove")
    args = parser.parse_args(argv)
    args.config = config_or_exit(
        parser, lambda: TapAndRemoveConfig(n=args.n, bins=args.bins, seed=args.seed)
    )
    return args


def main(args: argparse.Namespace) -> TapAndRemoveResult:
    torch.set_num_threads(1)
    result = run_tap_and_remove(args.config)
    result.save(args.out)
    print(result.to_markdown())
    return result


if __name__ == "__main__":
    run_script(main, parse_args())
