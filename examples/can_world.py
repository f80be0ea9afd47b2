"""The can world at a glance: the pyramid and its fields, one throw before/after, a GIF.

Writes ``pyramid.png``, ``throw.png`` and ``throw.gif`` to ``--out`` (default
``results/can_world``) and prints the throw's outcome. The world is fixed in
``sim2d`` (geometry, materials, world); the paper's experiment is Rudolph et al., §IV-A.

    python examples/can_world.py --field 15 --angle 0     # low, flat, at the near can
"""

from __future__ import annotations

import argparse
from pathlib import Path

from sim2d import geometry, recording, render


def main(argv=None) -> dict[str, Path]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("results/can_world"))
    parser.add_argument("--config", type=int, default=geometry.FULL_PYRAMID, help="start mask")
    # default: a descending throw at the top row's middle, which takes the top three cans
    parser.add_argument("--field", type=int, default=12 * geometry.N_COLUMNS + 7, help="0..194")
    parser.add_argument("--angle", type=int, default=1, help="0: 0deg, 1: 30deg, 2: -30deg")
    parser.add_argument("--jitter", type=float, default=0.003, help="aim error sd, metres")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--frame-interval", type=float, default=0.02, help="GIF frame, s")
    args = parser.parse_args(argv)

    trace = recording.record_throw(
        args.config,
        args.field,
        args.angle,
        jitter=args.jitter,
        seed=args.seed,
        frame_interval=args.frame_interval,
    )
    o = trace.outcome
    print(
        f"field {args.field}, angle {geometry.ANGLE_NAMES[args.angle]}: {o.count_before} -> "
        f"{o.count_after} cans, thrown off {list(geometry.mask_to_cans(o.thrown_off))}, "
        f"ball touched {list(geometry.mask_to_cans(o.touched))}, {o.sim_time:.2f} s simulated"
    )
    files = {
        "pyramid": render.plot_pyramid(args.out / "pyramid.png", args.config),
        "throw": render.plot_throw(args.out / "throw.png", trace, args.field, args.angle),
        "gif": render.animate_throw(args.out / "throw.gif", trace, args.field, args.angle),
    }
    for name, path in files.items():
        print(f"{name}: {path}")
    return files


if __name__ == "__main__":
    main()
