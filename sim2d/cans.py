"""The can world: a 4-3-2-1 pyramid of cans in the vertical throwing plane (pymunk).

The world is the plane of the throw: x points from the thrower towards the cans, z up,
gravity -9.81 m/s², SI units throughout (metres, seconds, kilograms). Ten cans, each a
box 0.12 m wide (the can's diameter) and 0.16 m tall, stand 4-3-2-1 on a table top at
z = 0; neighbours in a row are 0.02 m apart and each upper can is centred over the gap
between the two below it. The pyramid's near face (the side the ball comes from) is at
x = ``PYRAMID_X`` = 2 m, where the combined experiment puts it (DESIGN.md)::

        z
        ^           thrower --> ball flies towards +x
   0.64 +                 +----+
        |                 |  9 |                      row 3
   0.48 +            +----+----+----+
        |            |  7 |    |  8 |                 row 2
   0.32 +       +----+----+----+----+----+
        |       |  4 |    |  5 |    |  6 |            row 1
   0.16 +  +----+----+----+----+----+----+----+
        |  |  0 |    |  1 |    |  2 |    |  3 |       row 0
   0.00 +==+====+====+====+====+====+====+====+====== table top
           x = 2.00 (near face)            x = 2.54 (far face)

Can indices run row by row from the bottom, and within a row from the near side
(small x, towards the thrower) to the far side (large x). Can i of row r rests on cans
``SUPPORTERS[i]``. Named groups used by the combined experiment (paper §IV-C):

- ``TOP_THREE = (7, 8, 9)``: the top can and the two below it,
- ``NEAR_FLANK = (0, 4, 7, 9)``: the near diagonal edge, bottom to top,
- ``FAR_FLANK = (3, 6, 8, 9)``: the far diagonal edge, bottom to top.

A configuration is a subset of the ten cans, written as a 10-bit int mask (bit i set:
can i stands at its standard position). Which subsets are physically possible is
decided by simulation in :mod:`sim2d.configurations`.

An action is a field and an angle. The fields are a grid of 15 columns x 13 rows over
the pyramid's bounding box (0.54 m x 0.64 m); field index = row * 15 + column, row 0 at
the bottom, column 0 at the near side. A throw at (field, angle) is a 2 kg ball whose
centre passes through the field's centre with velocity ``ANGLES[angle]`` unless it hits
something first. The ball flies under gravity from the entry line x = ``ENTRY_X``; its
launch state there is found by running the parabola backwards from the field centre,
so every field (not only every row) is a different throw. A throw whose parabola would
touch the table top between the entry line and the field cannot be thrown
(:func:`is_throwable`).

A simulation ends when everything is at rest (pymunk's sleeping), when the ball has
passed every can without touching one (nothing can change any more), or at the time
cap ``MAX_SIM_TIME`` (reported as ``timed_out``). A can is thrown off when, at the end,
it moved more than 1 cm vertically or more than 10 cm horizontally from its start, or
left the table.

The step size (1 ms), the solver iterations and the sleeping thresholds are part of the
model: outcomes change with them (DESIGN.md, "Findings from a quick trial").
"""

from __future__ import annotations

import math
import operator
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import pymunk

__all__ = [
    "ANGLES",
    "ANGLE_NAMES",
    "BALL_MASS",
    "BALL_RADIUS",
    "CAN_HEIGHT",
    "CAN_MASS",
    "CAN_WIDTH",
    "ENTRY_X",
    "FAR_FLANK",
    "FIELD_HEIGHT",
    "FIELD_WIDTH",
    "FULL_PYRAMID",
    "GAP",
    "GRAVITY",
    "MAX_SIM_TIME",
    "NEAR_FLANK",
    "N_CANS",
    "N_COLUMNS",
    "N_FIELDS",
    "N_ROWS",
    "PYRAMID_HEIGHT",
    "PYRAMID_WIDTH",
    "PYRAMID_X",
    "ROW_OF",
    "ROW_SIZES",
    "SUPPORTERS",
    "TIME_STEP",
    "TOP_THREE",
    "ThrowOutcome",
    "ThrowTrace",
    "can_positions",
    "cans_to_mask",
    "count",
    "field_centres",
    "is_throwable",
    "launch_state",
    "mask_to_cans",
    "physical_constants",
    "play_ball",
    "throw",
    "throw_seed",
    "trace_throw",
]

# --- geometry (DESIGN.md, "The can world"; paper §IV-A) -----------------------------------
N_CANS = 10
ROW_SIZES = (4, 3, 2, 1)  # bottom row first
CAN_WIDTH = 0.12  # m, the can's diameter
CAN_HEIGHT = 0.16  # m
GAP = 0.02  # m, between neighbours in a row
PYRAMID_X = 2.0  # m, near face; the combined experiment's pyramid stands at x = 2 m
PYRAMID_WIDTH = ROW_SIZES[0] * CAN_WIDTH + (ROW_SIZES[0] - 1) * GAP  # 0.54 m
PYRAMID_HEIGHT = len(ROW_SIZES) * CAN_HEIGHT  # 0.64 m
FULL_PYRAMID = (1 << N_CANS) - 1

# Row of each can and the two cans each upper can rests on (None for the bottom row).
ROW_OF = tuple(r for r, n in enumerate(ROW_SIZES) for _ in range(n))
_ROW_START = tuple(sum(ROW_SIZES[:r]) for r in range(len(ROW_SIZES)))
SUPPORTERS: tuple[tuple[int, int] | None, ...] = tuple(
    None if r == 0 else (_ROW_START[r - 1] + k, _ROW_START[r - 1] + k + 1)
    for r, n in enumerate(ROW_SIZES)
    for k in range(n)
)
TOP_THREE = (7, 8, 9)
NEAR_FLANK = (0, 4, 7, 9)
FAR_FLANK = (3, 6, 8, 9)

# --- actions (DESIGN.md; the paper's 195 fields x 3 angles) -------------------------------
N_COLUMNS = 15
N_ROWS = 13
N_FIELDS = N_COLUMNS * N_ROWS  # 195
FIELD_WIDTH = PYRAMID_WIDTH / N_COLUMNS  # 0.036 m
FIELD_HEIGHT = PYRAMID_HEIGHT / N_ROWS  # ~0.0492 m
# Ball velocity (vx, vz) in m/s as its centre passes the field centre. The names follow
# the paper's three throwing angles; ours lie in the plane: "30deg" descends
# (atan(4/7) = 29.7 degrees below horizontal), "-30deg" ascends.
ANGLES = ((7.0, 0.0), (7.0, -4.0), (7.0, 4.0))
ANGLE_NAMES = ("0deg", "30deg", "-30deg")

# --- bodies --------------------------------------------------------------------------------
GRAVITY = 9.81  # m/s², acting along -z
BALL_MASS = 2.0  # kg (DESIGN.md)
# m; a 2 kg ball 12 cm across (density ~2200 kg/m³, a small medicine ball). The radius
# must lie between the bottom field row's centre height (0.025 m) and the second row's
# (0.074 m) so that exactly the bottom row is too low to throw at flat (DESIGN.md).
BALL_RADIUS = 0.06
CAN_MASS = 0.1  # kg; an empty steel food tin of 12 cm x 16 cm weighs about 0.1 kg
# Coulomb friction and restitution of each pair of materials (engineering tables: dry
# steel on steel ~0.4-0.6, steel on wood ~0.2-0.6; a tin can bounces little). pymunk
# multiplies the two shapes' values, so the shape values are derived from these below.
FRICTION_CAN_CAN = 0.4
FRICTION_CAN_TABLE = 0.4
FRICTION_BALL_CAN = 0.4
ELASTICITY_CAN_CAN = 0.2
ELASTICITY_CAN_TABLE = 0.2
ELASTICITY_BALL_CAN = 0.4
TABLE_MARGIN = 1.5  # m, the table top reaches this far past both faces of the pyramid
TABLE_THICKNESS = 0.1  # m

# --- simulation (part of the model: outcomes depend on them) ------------------------------
TIME_STEP = 0.001  # s, fixed; 1 ms showed no tunnelling at 7 m/s (DESIGN.md trial)
SOLVER_ITERATIONS = 10  # pymunk's default
COLLISION_SLOP = 0.0005  # m; pymunk's default 0.1 assumes pixels
SLEEP_TIME = 0.2  # s a body must stay idle before it sleeps (counts as at rest)
IDLE_SPEED = 0.01  # m/s below which a body counts as idle
MAX_SIM_TIME = 5.0  # s, the cap on every simulation
CHECK_EVERY = 10  # steps between checks of the stopping rules
ENTRY_X = PYRAMID_X - 0.1  # m; the entry line where a field throw's ball starts
TABLE_CLEARANCE = 0.01  # m; a throwable parabola keeps the ball this far above the table
# A can at rest is thrown off when it moved more than this (DESIGN.md).
THROWN_OFF_VERTICAL = 0.01  # m
THROWN_OFF_HORIZONTAL = 0.10  # m
# Bodies beyond this distance from the pyramid and moving away, or below the table top
# by more than FALLEN_DEPTH, have left the scene for good: they are removed (a can so
# removed counts as thrown off), which bounds the simulated time.
SCENE_MARGIN = 0.5  # m
FALLEN_DEPTH = 0.2  # m
_TOLERANCE = 1e-9  # m, for overlap checks of user ball states

# Shape values whose pairwise products are the pair values above.
_CAN_FRICTION = math.sqrt(FRICTION_CAN_CAN)
_TABLE_FRICTION = FRICTION_CAN_TABLE / _CAN_FRICTION
_BALL_FRICTION = FRICTION_BALL_CAN / _CAN_FRICTION
_CAN_ELASTICITY = math.sqrt(ELASTICITY_CAN_CAN)
_TABLE_ELASTICITY = ELASTICITY_CAN_TABLE / _CAN_ELASTICITY
_BALL_ELASTICITY = ELASTICITY_BALL_CAN / _CAN_ELASTICITY

_BALL_TYPE, _CAN_TYPE = 1, 2


def physical_constants() -> dict[str, float | int | str | list]:
    """Every constant that changes what the simulation does, for metadata and cache keys.

    Returns
    -------
    dict
        Plain JSON-serialisable values, including the pymunk version.
    """
    return {
        "n_cans": N_CANS,
        "row_sizes": list(ROW_SIZES),
        "can_width": CAN_WIDTH,
        "can_height": CAN_HEIGHT,
        "gap": GAP,
        "pyramid_x": PYRAMID_X,
        "n_columns": N_COLUMNS,
        "n_rows": N_ROWS,
        "angles": [list(a) for a in ANGLES],
        "angle_names": list(ANGLE_NAMES),
        "gravity": GRAVITY,
        "ball_mass": BALL_MASS,
        "ball_radius": BALL_RADIUS,
        "can_mass": CAN_MASS,
        "friction_can_can": FRICTION_CAN_CAN,
        "friction_can_table": FRICTION_CAN_TABLE,
        "friction_ball_can": FRICTION_BALL_CAN,
        "friction_ball_table": _BALL_FRICTION * _TABLE_FRICTION,
        "elasticity_can_can": ELASTICITY_CAN_CAN,
        "elasticity_can_table": ELASTICITY_CAN_TABLE,
        "elasticity_ball_can": ELASTICITY_BALL_CAN,
        "elasticity_ball_table": _BALL_ELASTICITY * _TABLE_ELASTICITY,
        "table_margin": TABLE_MARGIN,
        "time_step": TIME_STEP,
        "solver_iterations": SOLVER_ITERATIONS,
        "collision_slop": COLLISION_SLOP,
        "sleep_time": SLEEP_TIME,
        "idle_speed": IDLE_SPEED,
        "max_sim_time": MAX_SIM_TIME,
        "check_every": CHECK_EVERY,
        "entry_x": ENTRY_X,
        "table_clearance": TABLE_CLEARANCE,
        "thrown_off_vertical": THROWN_OFF_VERTICAL,
        "thrown_off_horizontal": THROWN_OFF_HORIZONTAL,
        "scene_margin": SCENE_MARGIN,
        "fallen_depth": FALLEN_DEPTH,
        "pymunk_version": pymunk.version,
    }


# --- geometry helpers -------------------------------------------------------------------


@lru_cache(maxsize=1)
def _can_positions() -> np.ndarray:
    pitch = CAN_WIDTH + GAP
    rows = [
        (PYRAMID_X + r * pitch / 2 + k * pitch + CAN_WIDTH / 2, r * CAN_HEIGHT + CAN_HEIGHT / 2)
        for r, n in enumerate(ROW_SIZES)
        for k in range(n)
    ]
    out = np.array(rows, dtype=float)
    out.setflags(write=False)
    return out


def can_positions() -> np.ndarray:
    """Standard centres of the ten cans.

    Returns
    -------
    np.ndarray
        ``(10, 2)`` float, metres: ``(x, z)`` of can i's centre in row i. Order: bottom
        row near to far (0-3), then 4-6, 7-8, and the top can 9 (see the module sketch).
    """
    return _can_positions().copy()


@lru_cache(maxsize=1)
def _field_centres() -> np.ndarray:
    column = np.arange(N_FIELDS) % N_COLUMNS
    row = np.arange(N_FIELDS) // N_COLUMNS
    out = np.stack([PYRAMID_X + (column + 0.5) * FIELD_WIDTH, (row + 0.5) * FIELD_HEIGHT], axis=1)
    out.setflags(write=False)
    return out


def field_centres() -> np.ndarray:
    """Centres of the 195 fields.

    Returns
    -------
    np.ndarray
        ``(195, 2)`` float, metres: ``(x, z)`` of field ``row * 15 + column``; row 0 is
        the bottom, column 0 the near side (smallest x).
    """
    return _field_centres().copy()


def mask_to_cans(mask: int) -> tuple[int, ...]:
    """Indices of the cans in a configuration mask, ascending."""
    mask = _check_mask(mask, "mask")
    return tuple(i for i in range(N_CANS) if mask >> i & 1)


def cans_to_mask(cans) -> int:
    """Configuration mask of an iterable of can indices (0-9)."""
    mask = 0
    for can in cans:
        i = _check_index(can, "cans", N_CANS, "a can index")
        mask |= 1 << i
    return mask


def count(mask: int) -> int:
    """Number of cans in a configuration mask."""
    return _check_mask(mask, "mask").bit_count()


# --- validation -----------------------------------------------------------------------------


def _as_int(value, name: str) -> int:
    if isinstance(value, bool):
        raise ValueError(f"{name}={value!r} is a bool; expected an int")
    try:
        return operator.index(value)
    except TypeError:
        raise ValueError(f"{name}={value!r} is a {type(value).__name__}; expected an int") from None


def _check_index(value, name: str, size: int, what: str) -> int:
    i = _as_int(value, name)
    if not 0 <= i < size:
        raise ValueError(f"{name}={value!r} is out of range; expected {what} in 0..{size - 1}")
    return i


def _check_mask(mask, name: str) -> int:
    return _check_index(mask, name, 1 << N_CANS, "a 10-bit configuration mask")


def _check_config(config, name: str = "config") -> int:
    from sim2d.configurations import is_stable  # local: configurations imports this module

    mask = _check_mask(config, name)
    if not is_stable(mask):
        raise ValueError(
            f"{name}={mask} (cans {mask_to_cans(mask)}) is not a physically possible "
            "configuration; expected one of sim2d.configurations.stable_configurations()"
        )
    return mask


def _check_vector(value, name: str) -> np.ndarray:
    try:
        vec = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name}={value!r} is not numeric; expected (x, z) in SI units") from None
    if vec.shape != (2,):
        raise ValueError(f"{name}={value!r} has shape {vec.shape}; expected shape (2,): (x, z)")
    if not np.all(np.isfinite(vec)):
        raise ValueError(f"{name}={value!r} is not finite; expected two finite numbers")
    return vec


def _check_ball_position(config: int, position: np.ndarray) -> None:
    x, z = position
    if z - BALL_RADIUS < -_TOLERANCE:
        raise ValueError(
            f"position={tuple(position)} puts the ball (radius {BALL_RADIUS} m) into the "
            f"table top; expected z >= {BALL_RADIUS}"
        )
    lo, hi = PYRAMID_X - TABLE_MARGIN, PYRAMID_X + PYRAMID_WIDTH + TABLE_MARGIN
    if not lo <= x <= hi:
        raise ValueError(f"position={tuple(position)} is off the table; expected x in [{lo}, {hi}]")
    centres = _can_positions()
    for i in mask_to_cans(config):
        # distance from the ball's centre to the can's box
        dx = max(abs(x - centres[i, 0]) - CAN_WIDTH / 2, 0.0)
        dz = max(abs(z - centres[i, 1]) - CAN_HEIGHT / 2, 0.0)
        if math.hypot(dx, dz) < BALL_RADIUS - _TOLERANCE:
            raise ValueError(
                f"position={tuple(position)} puts the ball (radius {BALL_RADIUS} m) inside "
                f"can {i}; expected a ball state clear of every can, e.g. at the entry line "
                f"x = {ENTRY_X}"
            )


# --- throws -----------------------------------------------------------------------------


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
    field = _check_index(field, "field", N_FIELDS, "a field index")
    angle = _check_index(angle, "angle", len(ANGLES), "an angle index")
    target = _field_centres()[field] + np.asarray(offset, dtype=float)
    vx, vz = ANGLES[angle]
    s = (ENTRY_X - target[0]) / vx  # time from the field back to the entry line, < 0
    position = np.array([ENTRY_X, target[1] + vz * s - 0.5 * GRAVITY * s * s])
    velocity = np.array([vx, vz - GRAVITY * s])
    return position, velocity


def is_throwable(field: int, angle: int) -> bool:
    """Whether a (field, angle) throw reaches the field without touching the table.

    The ball's centre runs on a parabola (concave) from the entry line to the field
    centre, so its lowest point is one of the two ends; the throw is possible when both
    keep the ball ``TABLE_CLEARANCE`` above the table top. This excludes the bottom
    field row at every angle and low fields far from the thrower at 0 and -30 degrees.
    """
    position, _ = launch_state(field, angle)
    lowest = min(position[1], _field_centres()[field, 1])
    return bool(lowest >= BALL_RADIUS + TABLE_CLEARANCE)


def throw_seed(seed: int, config: int, field: int, angle: int, repeat: int) -> int:
    """Seed of one throw of a data set, derived from the data set's seed (documented)."""
    sequence = np.random.SeedSequence([seed, config, field, angle, repeat])
    return int(sequence.generate_state(1, dtype=np.uint32)[0])


def _aim_offset(jitter: float, seed: int | None) -> np.ndarray:
    if jitter == 0.0:
        return np.zeros(2)
    # A normal aim error per axis, clipped at 3 standard deviations so that a throwable
    # parabola (TABLE_CLEARANCE = 1 cm) never starts inside the table for jitter <= 3 mm.
    offset = np.random.default_rng(seed).normal(0.0, jitter, size=2)
    return np.clip(offset, -3 * jitter, 3 * jitter)


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


@dataclass(frozen=True)
class ThrowTrace:
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


def _new_space() -> pymunk.Space:
    space = pymunk.Space()
    space.gravity = (0.0, -GRAVITY)
    space.iterations = SOLVER_ITERATIONS
    space.collision_slop = COLLISION_SLOP
    space.sleep_time_threshold = SLEEP_TIME
    space.idle_speed_threshold = IDLE_SPEED
    lo, hi = PYRAMID_X - TABLE_MARGIN, PYRAMID_X + PYRAMID_WIDTH + TABLE_MARGIN
    table = pymunk.Poly(
        space.static_body, [(lo, -TABLE_THICKNESS), (hi, -TABLE_THICKNESS), (hi, 0.0), (lo, 0.0)]
    )
    table.friction = _TABLE_FRICTION
    table.elasticity = _TABLE_ELASTICITY
    space.add(table)
    return space


def _add_cans(space: pymunk.Space, config: int) -> dict[int, pymunk.Body]:
    moment = pymunk.moment_for_box(CAN_MASS, (CAN_WIDTH, CAN_HEIGHT))
    bodies = {}
    for i in mask_to_cans(config):
        body = pymunk.Body(CAN_MASS, moment)
        body.position = tuple(_can_positions()[i])
        shape = pymunk.Poly.create_box(body, (CAN_WIDTH, CAN_HEIGHT))
        shape.friction = _CAN_FRICTION
        shape.elasticity = _CAN_ELASTICITY
        shape.collision_type = _CAN_TYPE
        space.add(body, shape)
        bodies[i] = body
    return bodies


def _leaving(body: pymunk.Body, lo: float, hi: float) -> bool:
    """Whether a body has left the scene for good (fell off the table or flies away)."""
    x, z = body.position
    vx = body.velocity.x
    return z < -FALLEN_DEPTH or (x < lo and vx <= 0.0) or (x > hi and vx >= 0.0)


def _play(config: int, position: np.ndarray, velocity: np.ndarray, frame_every: int = 0):
    """Run one ball state against a configuration; the single simulation loop."""
    space = _new_space()
    cans = _add_cans(space, config)
    start = {i: tuple(_can_positions()[i]) for i in cans}

    ball = pymunk.Body(BALL_MASS, pymunk.moment_for_circle(BALL_MASS, 0.0, BALL_RADIUS))
    ball.position = tuple(position)
    # pymunk moves each body with its current velocity, then adds gravity. Starting with
    # the mean velocity of the first step (half a step of gravity later) puts the
    # positions at the step times exactly on the parabola of (position, velocity).
    ball.velocity = (velocity[0], velocity[1] - 0.5 * GRAVITY * TIME_STEP)
    ball_shape = pymunk.Circle(ball, BALL_RADIUS)
    ball_shape.friction = _BALL_FRICTION
    ball_shape.elasticity = _BALL_ELASTICITY
    ball_shape.collision_type = _BALL_TYPE
    space.add(ball, ball_shape)

    can_of_shape = {next(iter(body.shapes)): i for i, body in cans.items()}
    touched = [0]

    def on_touch(arbiter, space, data):
        for shape in arbiter.shapes:
            if shape in can_of_shape:
                touched[0] |= 1 << can_of_shape[shape]

    space.on_collision(_BALL_TYPE, _CAN_TYPE, begin=on_touch)

    lo, hi = PYRAMID_X - SCENE_MARGIN, PYRAMID_X + PYRAMID_WIDTH + SCENE_MARGIN
    max_steps = round(MAX_SIM_TIME / TIME_STEP)
    removed = 0
    ball_in = True
    frames: list[tuple[float, np.ndarray, np.ndarray]] = []

    def record(step: int) -> None:
        poses = np.full((N_CANS, 3), np.nan)
        for i, body in cans.items():
            poses[i] = (body.position.x, body.position.y, body.angle)
        where = np.array(ball.position) if ball_in else np.full(2, np.nan)
        frames.append((step * TIME_STEP, poses, where))

    step = 0
    timed_out = True
    if frame_every:
        record(0)
    while step < max_steps:
        for _ in range(CHECK_EVERY):
            space.step(TIME_STEP)
            step += 1
            if frame_every and step % frame_every == 0:
                record(step)
        for i in list(cans):
            if _leaving(cans[i], lo, hi):
                space.remove(cans[i], *cans[i].shapes)
                del cans[i]
                removed |= 1 << i
        if ball_in and _leaving(ball, lo, hi):
            space.remove(ball, ball_shape)
            ball_in = False
        if not touched[0] and _passed_every_can(ball, ball_in, config):
            timed_out = False
            break
        if (
            touched[0]
            and all(b.is_sleeping for b in cans.values())
            and _ball_done(ball, ball_in, cans)
        ):
            timed_out = False
            break
    if frame_every and frames[-1][0] != step * TIME_STEP:
        record(step)

    thrown_off = removed
    for i, body in cans.items():
        dx = abs(body.position.x - start[i][0])
        dz = abs(body.position.y - start[i][1])
        if dz > THROWN_OFF_VERTICAL or dx > THROWN_OFF_HORIZONTAL:
            thrown_off |= 1 << i
    end_config = config & ~thrown_off
    outcome = ThrowOutcome(
        start_config=config,
        end_config=end_config,
        thrown_off=thrown_off,
        count_before=config.bit_count(),
        count_after=end_config.bit_count(),
        hit_any_can=bool(touched[0]),
        touched=touched[0],
        sim_time=step * TIME_STEP,
        timed_out=timed_out,
    )
    return outcome, frames


def _passed_every_can(ball: pymunk.Body, ball_in: bool, config: int) -> bool:
    """Before any contact the cans stand still: can the ball no longer reach any of them?"""
    if not ball_in or config == 0 or ball.is_sleeping:
        return True
    right = max(_can_positions()[i, 0] for i in mask_to_cans(config)) + CAN_WIDTH / 2
    return ball.position.x - BALL_RADIUS > right and ball.velocity.x >= 0.0


def _ball_done(ball: pymunk.Body, ball_in: bool, cans: dict[int, pymunk.Body]) -> bool:
    """The ball can change nothing more: gone, asleep, or moving away beyond every can.

    Needed because a rolling circle never stops in pymunk (no rolling resistance).
    """
    if not ball_in or ball.is_sleeping or not cans:
        return True
    reach = math.hypot(CAN_WIDTH, CAN_HEIGHT) / 2 + BALL_RADIUS
    xs = [body.position.x for body in cans.values()]
    x, vx = ball.position.x, ball.velocity.x
    return (vx >= 0.0 and x > max(xs) + reach) or (vx <= 0.0 and x < min(xs) - reach)


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
    config = _check_config(config)
    position = _check_vector(position, "position")
    velocity = _check_vector(velocity, "velocity")
    _check_ball_position(config, position)
    outcome, _ = _play(config, position, velocity)
    return outcome


def _throw_state(config, field, angle, jitter, seed):
    config = _check_config(config)
    field = _check_index(field, "field", N_FIELDS, "a field index")
    angle = _check_index(angle, "angle", len(ANGLES), "an angle index")
    try:
        jitter = float(jitter)
    except (TypeError, ValueError):
        raise ValueError(f"jitter={jitter!r} is not a number; expected metres >= 0") from None
    if not (math.isfinite(jitter) and jitter >= 0.0):
        raise ValueError(f"jitter={jitter!r} is invalid; expected finite metres >= 0")
    if seed is not None:
        seed = _as_int(seed, "seed")
    if not is_throwable(field, angle):
        raise ValueError(
            f"(field={field}, angle={angle}) cannot be thrown: the ball's parabola touches "
            "the table top before it reaches the field; expected an action with "
            "is_throwable(field, angle) True"
        )
    position, velocity = launch_state(field, angle, offset=_aim_offset(jitter, seed))
    return config, position, velocity


def throw(
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
    config, position, velocity = _throw_state(config, field, angle, jitter, seed)
    _check_ball_position(config, position)
    outcome, _ = _play(config, position, velocity)
    return outcome


def trace_throw(
    config: int,
    field: int,
    angle: int,
    *,
    jitter: float = 0.0,
    seed: int | None = None,
    frame_interval: float = 0.02,
) -> ThrowTrace:
    """:func:`throw`, recording the scene every ``frame_interval`` seconds for pictures."""
    config, position, velocity = _throw_state(config, field, angle, jitter, seed)
    _check_ball_position(config, position)
    every = max(1, round(frame_interval / TIME_STEP))
    outcome, frames = _play(config, position, velocity, frame_every=every)
    return ThrowTrace(
        outcome=outcome,
        times=np.array([f[0] for f in frames]),
        cans=np.stack([f[1] for f in frames]),
        ball=np.stack([f[2] for f in frames]),
    )
