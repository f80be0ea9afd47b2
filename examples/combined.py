"""The paper's combined system (§IV-C): the throw network aims, the can network plans.

Trains the throw network on the robot's throws and the can network on the can data set
(under ``--data-dir``, generated on first use), then plays the paper's three scenarios
(Tables II-IV) with the paper's round planner and with an exact planner
(:mod:`experiments.combined`). Writes ``combined.json`` and ``combined.md`` to ``--out``::

    .venv/bin/python examples/combined.py [--scale full|quick|tiny] [--noise]
        [--proposals can|combined] [--table-z 0.75] [--jitter 0.003]
"""

from __future__ import annotations

import argparse

import torch

from experiments.cans import SCALES
from experiments.combined import PROPOSALS, CombinedConfig, CombinedResult, run_combined
from experiments.config import config_or_exit, run_script
from sim2d.combined import TABLE_TOP_Z


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
    parser.add_argument("--n-throws", type=int, default=29_000, help="throw network's data")
    parser.add_argument("--bins", type=int, default=16, help="throw-network clusters per axis")
    parser.add_argument("--horizon", type=int, default=6, help="throws the exact planner may use")
    parser.add_argument("--episodes", type=int, default=50, help="plays of the exact policy")
    parser.add_argument("--noise", action="store_true", help="release noise (0.5 deg, 2 %%)")
    parser.add_argument(
        "--proposals",
        choices=PROPOSALS,
        default="can",
        help="paper planner's actions: most probable outcome under the can network alone (the "
        "paper's) or under the can and throw networks together",
    )
    parser.add_argument("--table-z", type=float, default=TABLE_TOP_Z, help="table top, m")
    parser.add_argument(
        "--jitter", type=float, default=None, help="aim jitter, m (default: the data set's)"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)
    args.config = config_or_exit(
        parser,
        lambda: CombinedConfig(
            scale=args.scale,
            data_dir=args.data_dir,
            executor=args.executor,
            n_throws=args.n_throws,
            bins=args.bins,
            horizon=args.horizon,
            episodes=args.episodes,
            noise=args.noise,
            proposals=args.proposals,
            table_z=args.table_z,
            jitter=args.jitter,
            seed=args.seed,
            progress=not args.quiet,
        ),
    )
    return args


def main(args: argparse.Namespace) -> CombinedResult:
    torch.set_num_threads(1)
    result = run_combined(args.config)
    result.save(args.out)
    print(result.to_markdown())
    return result


if __name__ == "__main__":
    run_script(main, parse_args())
