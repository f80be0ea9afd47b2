"""Throws into the can world and the outcome rules: what a throw at a field does.

A throw at (field, angle) is the 2 kg ball whose centre passes through the field's
centre with velocity ``ANGLES[angle]`` unless it hits something first
(:mod:`sim2d.geometry`). The ball flies under gravity from the entry line
x = ``ENTRY_X``; its launch state there is found by running the parabola backwards
from the field centre (:func:`launch_state`), so every field (not only every row) is a
different throw. A throw whose parabola would touch the table top between the entry
line and the field cannot be thrown (:func:`is_throwable`). An aim error (the jitter)
moves the field centre by a seeded, clipped normal offset (:func:`aim_offset`).

:func:`play_ball` plays any ball state into a configuration; :func:`throw_at_field` is
the throw at a field. Both simulate with :func:`sim2d.world.run_ball` and read the
outcome off the end state with the outcome rule: a can is thrown off when, at the end,
it moved more than ``THROWN_OFF_VERTICAL`` (1 cm) vertically or more than
``THROWN_OFF_HORIZONTAL`` (10 cm) horizontally from its start, or left the scene. The
same throw with the same seed gives the same outcome, bit for bit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from effect_networks.sim2d import materials as m
from effect_networks.sim2d.configurations import check_config
from effect_networks.sim2d.geometry import (
    ANGLES,
    CAN_HEIGHT,
    CAN_WIDTH,
    ENTRY_X,
    N_FIELDS,
    PYRAMID_WIDTH,
    PYRAMID_X,
    can_positions,
    field_centres,
    mask_to_cans,
)
from effect_networks.sim2d.validation import as_int, check_index, check_vector
from effect_networks.sim2d.world import Run, run_ball

__all__ = [
    "ThrowOutcome",
    "aim_offset",
    "aim_seed",
    "check_ball_position",
    "check_jitter",
    "check_throwable",
    "field_launch",
    "is_throwable",
    "launch_state",
    "outcome_of",
    "play_ball",
    "throw_at_field",
]

_TOLERANCE = 1e-9  # m, for overlap checks of user ball states


@dataclass(frozen=True)
class ThrowOutcome:
    """What one throw did.

    Attributes
    ----------
    start_config, end_config, thrown_off : int
        Configuration masks: the cans before, the cans not thrown off, the cans thrown
        off (``start_config & ~end_config``).
    count_before, count_after : int
        Number of cans before and after.
    hit_any_can : bool
        Whether the ball touched a can.
    touched : int
        Mask of the cans the ball touched.
    sim_time : float
        Simulated seconds until the stopping rule fired.
    timed_out : bool
        True when the simulation hit ``MAX_SIM_TIME`` before everything was at rest; the
        outcome is then read off the state at the cap.
    """

    start_config: int
    end_config: int
    thrown_off: int
    count_before: int
    count_after: int
    hit_any_can: bool
    touched: int
    sim_time: float
    timed_out: bool


def launch_state(field: int, angle: int, *, offset=(0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Ball state at the entry line for a throw whose centre passes a field's centre.

    Parameters
    ----------
    field : int
        Field index, 0..194 (``row * 15 + column``).
    angle : int
        Index into ``ANGLES``, 0..2.
    offset : (2,) float, metres
        Aim offset added to the field centre (the jitter).

    Returns
    -------
    position, velocity : np.ndarray
        ``(2,)`` each, metres and m/s, at x = ``ENTRY_X``: the parabola through
        ``field centre + offset`` with velocity ``ANGLES[angle]`` there, run backwards.
    """
    field = check_index(field, "field", N_FIELDS, "a field index")
    angle = check_index(angle, "angle", len(ANGLES), "an angle index")
    target = field_centres()[field] + np.asarray(offset, dtype=float)
    vx, vz = ANGLES[angle]
    s = (ENTRY_X - target[0]) / vx  # time from the field back to the entry line, < 0
    position = np.array([ENTRY_X, target[1] + vz * s - 0.5 * m.GRAVITY * s * s])
    velocity = np.array([vx, vz - m.GRAVITY * s])
    return position, velocity


def is_throwable(field: int, angle: int) -> bool:
    """Whether a (field, angle) throw reaches the field without touching the table.

    The ball's centre runs on a parabola (concave) from the entry line to the field
    centre, so its lowest point is one of the two ends; the throw is possible when both
    keep the ball ``TABLE_CLEARANCE`` above the table top. This excludes the bottom
    field row at every angle and low fields far from the thrower at 0 and -30 degrees.
    """
    position, _ = launch_state(field, angle)
    lowest = min(position[1], field_centres()[field, 1])
    return bool(lowest >= m.BALL_RADIUS + m.TABLE_CLEARANCE)


def aim_seed(seed: int, config: int, field: int, angle: int, repeat: int) -> int:
    """Seed of the aim error of one throw of a data set, derived from the data set's seed.

    The rule: the first 32-bit word of ``numpy.random.SeedSequence([seed, config, field,
    angle, repeat])``.
    """
    sequence = np.random.SeedSequence([seed, config, field, angle, repeat])
    return int(sequence.generate_state(1, dtype=np.uint32)[0])


def aim_offset(jitter: float, seed: int | None) -> np.ndarray:
    """The aim error: ``(2,)`` metres, normal with sd ``jitter`` per axis, clipped at 3 sd.

    Drawn from ``numpy.random.default_rng(seed)``; zero when ``jitter`` is 0. The clip
    keeps a throwable parabola (``TABLE_CLEARANCE`` = 1 cm) from starting inside the
    table for jitter <= 3.3 mm.
    """
    if jitter == 0.0:
        return np.zeros(2)
    offset = np.random.default_rng(seed).normal(0.0, jitter, size=2)
    return np.clip(offset, -3 * jitter, 3 * jitter)


def check_jitter(jitter, name: str = "jitter") -> float:
    """``jitter`` as a finite float >= 0 (metres)."""
    try:
        value = float(jitter)
    except (TypeError, ValueError):
        raise ValueError(f"{name}={jitter!r} is not a number; expected metres >= 0") from None
    if not (math.isfinite(value) and value >= 0.0):
        raise ValueError(f"{name}={jitter!r} is invalid; expected finite metres >= 0")
    return value


def check_throwable(field: int, angle: int) -> tuple[int, int]:
    """``(field, angle)`` as ints, refused unless :func:`is_throwable`."""
    field = check_index(field, "field", N_FIELDS, "a field index")
    angle = check_index(angle, "angle", len(ANGLES), "an angle index")
    if not is_throwable(field, angle):
        raise ValueError(
            f"(field={field}, angle={angle}) cannot be thrown: the ball's parabola touches "
            "the table top before it reaches the field; expected an action with "
            "is_throwable(field, angle) True"
        )
    return field, angle


def check_ball_position(config: int, position: np.ndarray) -> None:
    """Refuse a ball centre inside the table top, off the table, or overlapping a can."""
    x, z = position
    if z - m.BALL_RADIUS < -_TOLERANCE:
        raise ValueError(
            f"position={tuple(position)} puts the ball (radius {m.BALL_RADIUS} m) into the "
            f"table top; expected z >= {m.BALL_RADIUS}"
        )
    lo, hi = PYRAMID_X - m.TABLE_MARGIN, PYRAMID_X + PYRAMID_WIDTH + m.TABLE_MARGIN
    if not lo <= x <= hi:
        raise ValueError(f"position={tuple(position)} is off the table; expected x in [{lo}, {hi}]")
    centres = can_positions()
    for i in mask_to_cans(config):
        # distance from the ball's centre to the can's box
        dx = max(abs(x - centres[i, 0]) - CAN_WIDTH / 2, 0.0)
        dz = max(abs(z - centres[i, 1]) - CAN_HEIGHT / 2, 0.0)
        if math.hypot(dx, dz) < m.BALL_RADIUS - _TOLERANCE:
            raise ValueError(
                f"position={tuple(position)} puts the ball (radius {m.BALL_RADIUS} m) inside "
                f"can {i}; expected a ball state clear of every can, e.g. at the entry line "
                f"x = {ENTRY_X}"
            )


def outcome_of(config: int, run: Run) -> ThrowOutcome:
    """The outcome rule: which cans of ``config`` a finished run threw off."""
    start = can_positions()
    thrown_off = run.removed
    for i in mask_to_cans(config & ~run.removed):
        dx = abs(run.end_positions[i, 0] - start[i, 0])
        dz = abs(run.end_positions[i, 1] - start[i, 1])
        if dz > m.THROWN_OFF_VERTICAL or dx > m.THROWN_OFF_HORIZONTAL:
            thrown_off |= 1 << i
    end_config = config & ~thrown_off
    return ThrowOutcome(
        start_config=config,
        end_config=end_config,
        thrown_off=thrown_off,
        count_before=config.bit_count(),
        count_after=end_config.bit_count(),
        hit_any_can=bool(run.touched),
        touched=run.touched,
        sim_time=run.sim_time,
        timed_out=run.timed_out,
    )


def play_ball(config: int, position, velocity) -> ThrowOutcome:
    """Play any ball state into a configuration.

    Parameters
    ----------
    config : int
        A physically possible configuration mask (see
        :func:`sim2d.configurations.stable_configurations`).
    position : (2,) float, metres
        Ball centre ``(x, z)``: on the table's extent, not in the table top, clear of
        every can of ``config``; typically at the entry line x = ``ENTRY_X``.
    velocity : (2,) float, m/s
        Ball velocity ``(vx, vz)`` at ``position``.

    Returns
    -------
    ThrowOutcome

    Raises
    ------
    ValueError
        For a configuration that is not physically possible, a non-finite or misshapen
        state, or a ball overlapping a can or the table.
    """
    config = check_config(config)
    position = check_vector(position, "position")
    velocity = check_vector(velocity, "velocity")
    check_ball_position(config, position)
    return outcome_of(config, run_ball(config, position, velocity))


def field_launch(config, field, angle, jitter, seed) -> tuple[int, np.ndarray, np.ndarray]:
    """Checked ``(config, position, velocity)`` of a throw at a field with its aim error."""
    config = check_config(config)
    field, angle = check_throwable(field, angle)
    jitter = check_jitter(jitter)
    if seed is not None:
        seed = as_int(seed, "seed")
    position, velocity = launch_state(field, angle, offset=aim_offset(jitter, seed))
    check_ball_position(config, position)
    return config, position, velocity


def throw_at_field(
    config: int, field: int, angle: int, *, jitter: float = 0.0, seed: int | None = None
) -> ThrowOutcome:
    """Throw the ball at a field with one of the three angles.

    Parameters
    ----------
    config : int
        A physically possible configuration mask.
    field : int
        Field index 0..194 (``row * 15 + column``).
    angle : int
        Index into ``ANGLES`` (0: flat, 1: descending "30deg", 2: ascending "-30deg").
    jitter : float, metres
        Standard deviation of a normal aim error added to the field centre in x and z
        (clipped at 3 standard deviations); 0 for the nominal throw.
    seed : int, optional
        Seed of the aim error; the same (throw, seed) gives the same outcome bit for bit.

    Returns
    -------
    ThrowOutcome

    Raises
    ------
    ValueError
        For an unknown field or angle, a configuration that is not physically possible,
        an unthrowable action (:func:`is_throwable`), or a negative or non-finite jitter.
    """
    config, position, velocity = field_launch(config, field, angle, jitter, seed)
    return outcome_of(config, run_ball(config, position, velocity))
