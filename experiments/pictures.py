"""Pictures of the two worlds: the can pyramid with one throw, and the robot's throw.

* :func:`draw_can_world`: the pyramid with its 195 fields and three angles, one recorded
  throw before and after, and the throw as an animated GIF (:mod:`sim2d.render`).
* :func:`draw_throw_kinematics`: the humanoid's target-to-hit mapping and a few flight
  paths (:mod:`sim2d.throw_plot`), with the numbers that characterise the throw: the
  share of uniform targets the joint limits clamp, the share of the target area any
  throw can hit, and the scatter release noise adds at the target plane.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
from effect_networks.experiments.harness.config import ConfigError, Result, check_float, check_int
from effect_networks.experiments.harness.registry import Experiment
from effect_networks.sim2d import geometry, recording, render
from effect_networks.sim2d.analytic_throw import (
    TARGET_AREA,
    ReleaseNoise,
    is_reachable_hit,
    sample_targets,
    throw,
)
from effect_networks.sim2d.configurations import check_config
from effect_networks.sim2d.field_throws import check_throwable
from effect_networks.sim2d.throw_plot import plot_flight_paths, plot_target_to_hit

__all__ = [
    "CanWorldConfig",
    "CanWorldPictures",
    "ThrowKinematicsConfig",
    "ThrowKinematicsResult",
    "draw_can_world",
    "draw_throw_kinematics",
]

#: A descending throw at the top row's middle, which takes the top three cans.
DEFAULT_FIELD = 12 * geometry.N_COLUMNS + 7
MAX_JITTER = 0.0033  # m: the largest aim jitter that keeps every throwable parabola clear
MAX_FRAME_INTERVAL = 1.0  # s


@dataclass(frozen=True)
class CanWorldConfig:
    """Settings of :func:`draw_can_world`; every field is checked on construction.

    Attributes
    ----------
    config : int
        The start configuration, a physically possible mask of the cans.
    field, angle : int
        The throw: a field (0..194) and an angle (0: flat, 1: descending, 2: ascending)
        that can throw at it.
    jitter : float
        Aim error sd, m, in ``[0, MAX_JITTER]``.
    seed : int
        Seeds the aim error (>= 0).
    frame_interval : float
        Seconds between GIF frames, in ``(0, MAX_FRAME_INTERVAL]``.
    fps : int
        GIF frames per second (1..100).
    """

    config: int = geometry.FULL_PYRAMID
    field: int = DEFAULT_FIELD
    angle: int = 1
    jitter: float = 0.003
    seed: int = 0
    frame_interval: float = 0.02
    fps: int = 25

    def __post_init__(self):
        check_int("config", self.config, 0, geometry.FULL_PYRAMID)
        check_int("field", self.field, 0, geometry.N_FIELDS - 1)
        check_int("angle", self.angle, 0, len(geometry.ANGLES) - 1)
        for name, check in (
            ("config", lambda: check_config(self.config)),
            ("field", lambda: check_throwable(self.field, self.angle)),
        ):
            try:
                check()
            except ValueError as error:
                raise ConfigError(name, str(error)) from None
        check_float("jitter", self.jitter, 0.0, MAX_JITTER, unit="m")
        check_int("seed", self.seed, 0)
        check_float(
            "frame_interval",
            self.frame_interval,
            0.0,
            MAX_FRAME_INTERVAL,
            low_open=True,
            unit="s",
        )
        check_int("fps", self.fps, 1, 100)


@dataclass
class CanWorldPictures(Result):
    """The recorded throw's outcome (``outcome``: text) and the pictures' paths by name."""

    experiment_name: ClassVar[str] = "can_world"

    outcome: str
    files: dict[str, str]

    def to_markdown(self) -> str:
        """The experiment's report, in Markdown (:meth:`~experiments.harness.config.Result.to_markdown`)."""
        return "\n".join([self.outcome, *(f"- {k}: {v}" for k, v in self.files.items())]) + "\n"

    def figures(self, out: Path) -> list[Path]:
        """The pictures :func:`draw_can_world` drew."""
        return [Path(path) for path in self.files.values()]


def draw_can_world(config: CanWorldConfig, out) -> CanWorldPictures:
    """Record the throw and save ``pyramid.png``, ``throw.png`` and ``throw.gif`` to ``out``."""
    out = Path(out)
    trace = recording.record_throw(
        config.config,
        config.field,
        config.angle,
        jitter=config.jitter,
        seed=config.seed,
        frame_interval=config.frame_interval,
    )
    o = trace.outcome
    files = {
        "pyramid": render.plot_pyramid(out / "pyramid.png", config.config),
        "throw": render.plot_throw(out / "throw.png", trace, config.field, config.angle),
        "gif": render.animate_throw(
            out / "throw.gif", trace, config.field, config.angle, fps=config.fps
        ),
    }
    outcome = (
        f"field {config.field}, angle {geometry.ANGLE_NAMES[config.angle]}: {o.count_before} -> "
        f"{o.count_after} cans, thrown off {list(geometry.mask_to_cans(o.thrown_off))}, "
        f"ball touched {list(geometry.mask_to_cans(o.touched))}, {o.sim_time:.2f} s simulated"
    )
    return CanWorldPictures(outcome, {k: str(v) for k, v in files.items()})


#: A few targets [y, z] (m) for the flight-path views: straight ahead of the shoulder, one
#: on the robot's centre line, and some beyond the joint limits.
FLIGHT_TARGETS = np.array(
    [[-0.2, 1.4], [0.0, 1.0], [0.9, 2.3], [-0.9, 0.5], [0.3, 0.9], [-0.6, 2.1]]
)


@dataclass(frozen=True)
class ThrowKinematicsConfig:
    """Settings of :func:`draw_throw_kinematics`; every field is checked on construction.

    Attributes
    ----------
    grid : int
        Targets per side in the figure (2..100).
    n : int
        Uniform targets to throw at (>= 1).
    seed : int
        Seeds the targets and the release noise (>= 0).
    """

    grid: int = 15
    n: int = 30_000
    seed: int = 0

    def __post_init__(self):
        check_int("grid", self.grid, 2, 100)
        check_int("n", self.n, 1)
        check_int("seed", self.seed, 0)


@dataclass
class ThrowKinematicsResult(Result):
    """The throw's numbers and the figures' paths.

    Shares in [0, 1], the time of ``n`` throws (s), the release noise's scatter at the plane (m, sd
    per axis), and the figures' paths.
    """

    experiment_name: ClassVar[str] = "throw_kinematics"

    n: int
    clamped_share: float
    reachable_area_share: float
    seconds: float
    noise_scatter_y_m: float
    noise_scatter_z_m: float
    files: dict[str, str]

    def to_markdown(self) -> str:
        """The experiment's report, in Markdown (:meth:`~experiments.harness.config.Result.to_markdown`)."""
        return (
            f"- {self.n} throws in {1e3 * self.seconds:.1f} ms\n"
            f"- clamped by the joint limits: {self.clamped_share:.1%} of uniform targets\n"
            f"- target area any throw can hit: {self.reachable_area_share:.1%}\n"
            f"- release noise {ReleaseNoise()} scatters the hit by "
            f"{100 * self.noise_scatter_y_m:.2f} cm (y), {100 * self.noise_scatter_z_m:.2f} cm "
            "(z) sd\n"
        )

    def figures(self, out: Path) -> list[Path]:
        """The figures :func:`draw_throw_kinematics` drew."""
        return [Path(path) for path in self.files.values()]


def draw_throw_kinematics(config: ThrowKinematicsConfig, out) -> ThrowKinematicsResult:
    """Throw at ``n`` uniform targets; save ``target_to_hit.png`` and ``flight_paths.png``."""
    out = Path(out)
    rng = np.random.default_rng(config.seed)
    targets = sample_targets(config.n, rng)
    start = time.perf_counter()
    exact = throw(targets)
    seconds = time.perf_counter() - start
    noisy = throw(targets, noise=ReleaseNoise(), rng=rng)
    scatter = (noisy.hit - exact.hit).std(axis=0)
    side = np.linspace(0.0, 1.0, 201)
    area_grid = TARGET_AREA.low + np.stack(np.meshgrid(side, side), -1).reshape(-1, 2) * (
        TARGET_AREA.high - TARGET_AREA.low
    )
    files = {
        "target_to_hit": plot_target_to_hit(out / "target_to_hit.png", grid=config.grid),
        "flight_paths": plot_flight_paths(out / "flight_paths.png", FLIGHT_TARGETS),
    }
    return ThrowKinematicsResult(
        n=config.n,
        clamped_share=float(exact.clamped.mean()),
        reachable_area_share=float(is_reachable_hit(area_grid).mean()),
        seconds=seconds,
        noise_scatter_y_m=float(scatter[0]),
        noise_scatter_z_m=float(scatter[1]),
        files={k: str(v) for k, v in files.items()},
    )


EXPERIMENTS = (
    Experiment(
        CanWorldConfig,
        draw_can_world,
        CanWorldPictures,
        order=20,
        tiny={"frame_interval": 0.5},
        quick={"frame_interval": 0.04, "fps": 12},  # fewer GIF frames, the same throw
        folder="can_world",
        draws=True,
    ),
    Experiment(
        ThrowKinematicsConfig,
        draw_throw_kinematics,
        ThrowKinematicsResult,
        order=30,
        tiny={"grid": 2, "n": 10},
        folder="throw",
        draws=True,
    ),
)
