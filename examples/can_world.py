"""The can world at a glance: the pyramid and its fields, one throw before/after, a GIF.

Writes ``pyramid.png``, ``throw.png`` and ``throw.gif`` to ``--out`` and prints the
throw's outcome (:func:`experiments.pictures.draw_can_world`)::

    .venv/bin/python examples/can_world.py --field 15 --angle 0   # low, flat, at the near can
"""

from __future__ import annotations

import argparse

from experiments.config import config_or_exit, run_script
from experiments.pictures import DEFAULT_FIELD, CanWorldConfig, CanWorldPictures, draw_can_world
from sim2d import geometry


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", default="results/can_world")
    parser.add_argument("--config", type=int, default=geometry.FULL_PYRAMID, help="start mask")
    parser.add_argument("--field", type=int, default=DEFAULT_FIELD, help="0..194")
    parser.add_argument("--angle", type=int, default=1, help="0: 0deg, 1: 30deg, 2: -30deg")
    parser.add_argument("--jitter", type=float, default=0.003, help="aim error sd, metres")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--frame-interval", type=float, default=0.02, help="GIF frame, s")
    parser.add_argument("--fps", type=int, default=25, help="GIF frames per second")
    args = parser.parse_args(argv)
    args.config = config_or_exit(
        parser,
        lambda: CanWorldConfig(
            config=args.config,
            field=args.field,
            angle=args.angle,
            jitter=args.jitter,
            seed=args.seed,
            frame_interval=args.frame_interval,
            fps=args.fps,
        ),
    )
    return args


def main(args: argparse.Namespace) -> CanWorldPictures:
    pictures = draw_can_world(args.config, args.out)
    print(pictures.to_markdown())
    return pictures


if __name__ == "__main__":
    run_script(main, parse_args())
