"""The throw kinematics of the paper's "throw"-experiment (§IV-B), in figures and numbers.

Writes to ``--out`` (default ``results/throw/``):

- ``target_to_hit.png``: a grid of targets on the plane x = 2 m and the hit points
  their throws produce; throws clamped by the arm's joint limits in red.
- ``flight_paths.png``: top and side views of a few throws.

and prints the clamped share of uniform targets, the share of the target area that
any throw can hit, the time for ``--n`` throws, and the scatter that release noise
adds at the plane. See :mod:`sim2d.throw` for the model.

    python examples/throw_kinematics.py [--out results/throw] [--grid 15] [--n 30000]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from sim2d.throw import (
    TARGET_AREA,
    ReleaseNoise,
    is_reachable_hit,
    sample_targets,
    throw,
)
from sim2d.throw_plot import plot_flight_paths, plot_target_to_hit

#: A few targets [y, z] (m) for the flight-path views: straight ahead of the
#: shoulder, one on the robot's centre line, and some beyond the joint limits.
FLIGHT_TARGETS = np.array(
    [[-0.2, 1.4], [0.0, 1.0], [0.9, 2.3], [-0.9, 0.5], [0.3, 0.9], [-0.6, 2.1]]
)


def main(argv: list[str] | None = None) -> dict[str, float]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("results/throw"))
    parser.add_argument("--grid", type=int, default=15, help="targets per side in the figure")
    parser.add_argument("--n", type=int, default=30_000, help="uniform targets to throw at")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    rng = np.random.default_rng(args.seed)
    targets = sample_targets(args.n, rng)
    start = time.perf_counter()
    exact = throw(targets)
    seconds = time.perf_counter() - start
    noisy = throw(targets, noise=ReleaseNoise(), rng=rng)
    scatter = (noisy.hit - exact.hit).std(axis=0)

    side = np.linspace(0.0, 1.0, 201)
    area_grid = TARGET_AREA.low + np.stack(np.meshgrid(side, side), -1).reshape(-1, 2) * (
        TARGET_AREA.high - TARGET_AREA.low
    )
    summary = {
        "n": args.n,
        "clamped_share": float(exact.clamped.mean()),
        "reachable_area_share": float(is_reachable_hit(area_grid).mean()),
        "seconds": seconds,
        "noise_scatter_y_m": float(scatter[0]),
        "noise_scatter_z_m": float(scatter[1]),
    }
    print(f"{args.n} throws in {1e3 * seconds:.1f} ms")
    print(f"clamped by the joint limits: {summary['clamped_share']:.1%} of uniform targets")
    print(f"target area any throw can hit: {summary['reachable_area_share']:.1%}")
    print(
        f"release noise {ReleaseNoise()} scatters the hit by "
        f"{100 * scatter[0]:.2f} cm (y), {100 * scatter[1]:.2f} cm (z) std"
    )
    for path in (
        plot_target_to_hit(args.out / "target_to_hit.png", grid=args.grid),
        plot_flight_paths(args.out / "flight_paths.png", FLIGHT_TARGETS),
    ):
        print(f"wrote {path}")
    return summary


if __name__ == "__main__":
    main()
