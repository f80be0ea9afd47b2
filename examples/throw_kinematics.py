"""The throw kinematics of the paper's throwing experiment (§IV-B), in figures and numbers.

Writes ``target_to_hit.png`` (a grid of targets on the plane x = 2 m and the hits their
throws produce; throws clamped by the arm's joint limits in red) and
``flight_paths.png`` (top and side views of a few throws) to ``--out``, and prints the
clamped share of uniform targets, the share of the target area any throw can hit, the
time for ``--n`` throws and the scatter release noise adds
(:func:`experiments.pictures.draw_throw_kinematics`)::

    .venv/bin/python examples/throw_kinematics.py [--out results/throw] [--grid 15] [--n 30000]
"""

from __future__ import annotations

import argparse

from experiments.config import config_or_exit, run_script
from experiments.pictures import (
    ThrowKinematicsConfig,
    ThrowKinematicsResult,
    draw_throw_kinematics,
)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", default="results/throw")
    parser.add_argument("--grid", type=int, default=15, help="targets per side in the figure")
    parser.add_argument("--n", type=int, default=30_000, help="uniform targets to throw at")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    args.config = config_or_exit(
        parser, lambda: ThrowKinematicsConfig(grid=args.grid, n=args.n, seed=args.seed)
    )
    return args


def main(args: argparse.Namespace) -> ThrowKinematicsResult:
    result = draw_throw_kinematics(args.config, args.out)
    print(result.to_markdown())
    return result


if __name__ == "__main__":
    run_script(main, parse_args())
