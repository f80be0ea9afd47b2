"""A throw at a field recorded frame by frame, for pictures (:mod:`sim2d.render`).

:func:`record_throw` runs the same simulation as :func:`sim2d.field_throws.throw_at_field`
and in addition samples the scene every ``frame_interval`` seconds; its outcome equals
that function's, bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from effect_networks.sim2d import materials as m
from effect_networks.sim2d.field_throws import ThrowOutcome, field_launch, outcome_of
from effect_networks.sim2d.world import run_ball

__all__ = ["ThrowRecording", "record_throw"]


@dataclass(frozen=True)
class ThrowRecording:
    """A throw recorded for pictures.

    Attributes
    ----------
    outcome : ThrowOutcome
    times : np.ndarray
        ``(n,)`` float, seconds.
    cans : np.ndarray
        ``(n, 10, 3)`` float: x (m), z (m), rotation (rad) of each can; NaN for cans not
        in the start configuration or removed from the scene.
    ball : np.ndarray
        ``(n, 2)`` float, metres; NaN once the ball left the scene.
    """

    outcome: ThrowOutcome
    times: np.ndarray
    cans: np.ndarray
    ball: np.ndarray


def record_throw(
    config: int,
    field: int,
    angle: int,
    *,
    jitter: float = 0.0,
    seed: int | None = None,
    frame_interval: float = 0.02,
) -> ThrowRecording:
    """:func:`sim2d.field_throws.throw_at_field`, sampling the scene every ``frame_interval`` s.

    Raises
    ------
    ValueError
        As :func:`sim2d.field_throws.throw_at_field`, or for a ``frame_interval`` that is
        not a positive number of seconds.
    """
    try:
        interval = float(frame_interval)
    except (TypeError, ValueError):
        interval = float("nan")
    if not interval > 0.0:
        raise ValueError(f"frame_interval={frame_interval!r} is invalid; expected seconds > 0")
    config, position, velocity = field_launch(config, field, angle, jitter, seed)
    frames: list[tuple[int, np.ndarray, np.ndarray]] = []
    run = run_ball(
        config,
        position,
        velocity,
        frame_every=max(1, round(interval / m.TIME_STEP)),
        on_frame=lambda step, poses, ball: frames.append((step, poses, ball)),
    )
    return ThrowRecording(
        outcome=outcome_of(config, run),
        times=np.array([step * m.TIME_STEP for step, _, _ in frames]),
        cans=np.stack([poses for _, poses, _ in frames]),
        ball=np.stack([ball for _, _, ball in frames]),
    )
