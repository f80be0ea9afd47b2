"""What the physics allows: upper bounds on Table I (both protocols) and the combined scenarios.

No learning: the simulator's own best action, chosen on half of some fresh repeats and
scored on the other half (:mod:`experiments.physics_bounds`). The simulations are saved
under ``--data-dir`` as they finish and resumed when interrupted. Writes
``physics_bounds.json`` and ``physics_bounds.md`` to ``--out``::

    .venv/bin/python examples/physics_bounds.py [--scale full|quick|tiny]
        [--table-z 0.75 0.35 ...] [--executor process:N | dask-local:N | dask://HOST:PORT | ray]
"""

from __future__ import annotations

import argparse

import torch

from experiments.cans import SCALES
from experiments.config import config_or_exit, run_script
from experiments.physics_bounds import (
    PhysicsBoundsConfig,
    PhysicsBoundsResult,
    run_physics_bounds,
)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--scale", choices=tuple(SCALES), default="full")
    parser.add_argument("--data-dir", default="data")
    parser.add_argument("--out", default="results")
    d = PhysicsBoundsConfig()
    parser.add_argument("--repeats", type=int, default=d.repeats, help="Table I: per field")
    parser.add_argument("--table-z", type=float, nargs="+", default=list(d.table_z))
    parser.add_argument("--step", type=float, default=d.step, help="combined: m between heights")
    parser.add_argument(
        "--combined-repeats", type=int, default=d.combined_repeats, help="combined: even"
    )
    parser.add_argument("--horizon", type=int, default=d.horizon, help="combined: throws")
    parser.add_argument(
        "--executor",
        default=None,
        help="process:N | dask-local:N | dask://HOST:PORT | ray (default: every core here)",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)
    args.config = config_or_exit(
        parser,
        lambda: PhysicsBoundsConfig(
            scale=args.scale,
            data_dir=args.data_dir,
            executor=args.executor,
            repeats=args.repeats,
            table_z=tuple(args.table_z),
            step=args.step,
            combined_repeats=args.combined_repeats,
            horizon=args.horizon,
            progress=not args.quiet,
        ),
    )
    return args


def main(args: argparse.Namespace) -> PhysicsBoundsResult:
    torch.set_num_threads(1)
    result = run_physics_bounds(args.config)
    result.save(args.out)
    print(result.to_markdown())
    return result


if __name__ == "__main__":
    run_script(main, parse_args())
