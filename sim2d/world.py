"""The pymunk world of the cans and its stepping: table, cans, ball, stopping rules.

:func:`new_space` builds the table top, :func:`add_cans` a configuration's cans at their
standard positions and :func:`add_ball` the ball; :func:`run_ball` runs one ball state
against a configuration with the fixed step until a stopping rule fires and returns
what is left (:class:`Run`). It is the only simulation loop of a ball in the can world.

How it steps is :class:`sim2d.materials.Stepping` (default :data:`sim2d.materials.STEPPING`).
With the cans asleep until touched (``start_asleep``), a throw costs next to nothing until
the ball reaches a can, and a ball that passes clear of every can and the table top is
not simulated at all (:func:`clear_miss`, the same run bit for bit).

Stopping rules, checked every ``CHECK_EVERY`` steps:

- a body beyond ``scene_margin`` from the pyramid and moving away, or more than
  ``FALLEN_DEPTH`` below the table top, has left the scene for good and is removed;
- before the ball touched any can the cans stand still, so the run ends as soon as the
  ball can no longer reach any of them (or is gone or asleep);
- after a touch, the run ends when every can sleeps (pymunk's sleeping: idle for
  ``sleep_time``) and the ball can change nothing more: it is gone, asleep, or moving
  away beyond every can (a rolling circle never stops in pymunk: no rolling resistance);
- otherwise the run ends at ``MAX_SIM_TIME`` and reports ``timed_out``.

``scene_margin`` and ``sleep_time`` are :class:`sim2d.materials.StoppingRules`; the
default is :data:`sim2d.materials.STOPPING`.

Speed: pymunk's public ``Space.step`` spends more time in Python bookkeeping (deferred
additions and removals, post-step callbacks) than in the C step for this small world.
Between checks nothing is added or removed and no callback changes the space, so the
loop calls pymunk's C step (``cpSpaceStep`` through pymunk's cffi binding) and reads
body states through the same binding. The results are the same numbers, bit for bit:
``run_ball(..., reference=True)`` runs the same loop through the public API, and the
tests compare the two.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pymunk
from effect_networks.sim2d import materials as m
from effect_networks.sim2d.clock import simulation
from effect_networks.sim2d.geometry import (
    CAN_HEIGHT,
    CAN_WIDTH,
    N_CANS,
    PYRAMID_WIDTH,
    PYRAMID_X,
    can_positions,
    mask_to_cans,
)

# pymunk's cffi binding of Chipmunk: the C step and body getters without the Python
# wrappers' bookkeeping (see the module docstring; tested equal to the public API).
from pymunk._chipmunk import lib as _cp

__all__ = [
    "BALL_TYPE",
    "CAN_TYPE",
    "CLEAR_MARGIN",
    "Run",
    "add_ball",
    "add_cans",
    "clear_miss",
    "new_space",
    "run_ball",
]

BALL_TYPE, CAN_TYPE = 1, 2  # pymunk collision types

#: ``on_frame(step, cans, ball)``: ``cans`` ``(10, 3)`` x, z, rotation (NaN: not in the
#: scene), ``ball`` ``(2,)`` (NaN once it left the scene).
FrameCallback = Callable[[int, np.ndarray, np.ndarray], None]


@dataclass(frozen=True)
class Run:
    """What one run of :func:`run_ball` left behind.

    Attributes
    ----------
    end_positions : np.ndarray
        ``(10, 2)`` float, metres: ``(x, z)`` of each can still in the scene at the end;
        NaN for cans not in the configuration or removed.
    removed : int
        Mask of the cans that left the scene (removed by the stopping rules).
    touched : int
        Mask of the cans the ball touched.
    steps : int
        Steps simulated.
    timed_out : bool
        The run reached ``MAX_SIM_TIME`` before a stopping rule fired.
    time_step : float
        Seconds per step.
    """

    end_positions: np.ndarray
    removed: int
    touched: int
    steps: int
    timed_out: bool
    time_step: float

    @property
    def sim_time(self) -> float:
        """Simulated seconds, ``steps * time_step``."""
        return self.steps * self.time_step


def new_space(
    *, sleep_time: float = m.STOPPING.sleep_time, iterations: int = m.SOLVER_ITERATIONS
) -> pymunk.Space:
    """A pymunk space with gravity, the solver settings and the table top (z <= 0)."""
    space = pymunk.Space()
    space.gravity = (0.0, -m.GRAVITY)
    space.iterations = iterations
    space.collision_slop = m.COLLISION_SLOP
    space.sleep_time_threshold = sleep_time
    space.idle_speed_threshold = m.IDLE_SPEED
    lo, hi = PYRAMID_X - m.TABLE_MARGIN, PYRAMID_X + PYRAMID_WIDTH + m.TABLE_MARGIN
    table = pymunk.Poly(
        space.static_body,
        [(lo, -m.TABLE_THICKNESS), (hi, -m.TABLE_THICKNESS), (hi, 0.0), (lo, 0.0)],
    )
    table.friction = m.TABLE_FRICTION_SHAPE
    table.elasticity = m.TABLE_ELASTICITY_SHAPE
    space.add(table)
    return space


def add_cans(space: pymunk.Space, config: int, *, asleep: bool = False) -> dict[int, pymunk.Body]:
    """Add the cans of ``config`` at their standard positions; ``{can index: body}``.

    With ``asleep``, the cans are put to sleep as one group (the space must allow
    sleeping): they stay exactly where they are until a body touches one of them, which
    wakes them all.
    """
    moment = pymunk.moment_for_box(m.CAN_MASS, (CAN_WIDTH, CAN_HEIGHT))
    positions = can_positions()
    bodies = {}
    for i in mask_to_cans(config):
        body = pymunk.Body(m.CAN_MASS, moment)
        body.position = tuple(positions[i])
        shape = pymunk.Poly.create_box(body, (CAN_WIDTH, CAN_HEIGHT))
        shape.friction = m.CAN_FRICTION_SHAPE
        shape.elasticity = m.CAN_ELASTICITY_SHAPE
        shape.collision_type = CAN_TYPE
        space.add(body, shape)
        bodies[i] = body
    if asleep:
        first = None
        for body in bodies.values():
            if first is None:
                body.sleep()
                first = body
            else:
                body.sleep_with_group(first)
    return bodies


def add_ball(
    space: pymunk.Space, position, velocity, *, time_step: float = m.TIME_STEP
) -> tuple[pymunk.Body, pymunk.Circle]:
    """Add the ball with centre ``position`` and velocity ``velocity`` (SI, ``(x, z)``).

    ``time_step`` is the step the space will be stepped with (see below).
    """
    ball = pymunk.Body(m.BALL_MASS, pymunk.moment_for_circle(m.BALL_MASS, 0.0, m.BALL_RADIUS))
    ball.position = (float(position[0]), float(position[1]))
    # pymunk moves each body with its current velocity, then adds gravity. Starting with
    # the mean velocity of the first step (half a step of gravity later) puts the
    # positions at the step times exactly on the parabola of (position, velocity).
    ball.velocity = (float(velocity[0]), float(velocity[1]) - 0.5 * m.GRAVITY * time_step)
    shape = pymunk.Circle(ball, m.BALL_RADIUS)
    shape.friction = m.BALL_FRICTION_SHAPE
    shape.elasticity = m.BALL_ELASTICITY_SHAPE
    shape.collision_type = BALL_TYPE
    space.add(ball, shape)
    return ball, shape


#: How close (m) the ball may come to a can or the table top, at a step, for
#: :func:`clear_miss` to answer without pymunk; pymunk finds contacts only at overlap.
CLEAR_MARGIN = 0.01


def clear_miss(
    config: int,
    position,
    velocity,
    *,
    stopping: m.StoppingRules = m.STOPPING,
    stepping: m.Stepping = m.STEPPING,
) -> Run | None:
    """The run of a ball that touches nothing, without pymunk; None if it may touch something.

    With the cans asleep until touched (``stepping.start_asleep``), a ball that never
    comes near a can or the table top flies alone under gravity: pymunk moves it with
    semi-implicit Euler (each step the position moves by the velocity times the step, then
    gravity is added to the velocity), which is repeated here with the same floating-point
    operations in the same order, so the positions, the step at which a stopping rule
    fires and hence the :class:`Run` are those :func:`run_ball` would step to, bit for bit
    (tested against the public API). The answer is None when at any step up to the end
    the ball comes within ``CLEAR_MARGIN`` of a can of ``config`` or of the table top.
    """
    if not stepping.start_asleep:
        raise ValueError(
            f"stepping={stepping!r} starts the cans awake; clear_miss needs cans that stand "
            "exactly still until touched (start_asleep=True)"
        )
    dt, every = stepping.time_step, m.CHECK_EVERY
    max_steps = round(m.MAX_SIM_TIME / dt)
    checks = -(-max_steps // every)  # run_ball checks every `every` steps from `every` on
    n = checks * every
    # pymunk's integration: x_{k+1} = x_k + vx dt, vz_{k+1} = vz_k + (-g) dt, z_{k+1} =
    # z_k + vz_k dt; np.add.accumulate adds left to right, one addition at a time.
    vx = float(velocity[0])
    vz0 = float(velocity[1]) - 0.5 * m.GRAVITY * dt  # as add_ball sets it
    gdt = -m.GRAVITY * dt
    vz = np.add.accumulate(np.concatenate(([vz0], np.full(n, gdt))))  # vz after k steps
    xs = np.add.accumulate(np.concatenate(([float(position[0])], np.full(n, vx * dt))))
    zs = np.add.accumulate(np.concatenate(([float(position[1])], vz[:-1] * dt)))
    # the stopping rules at the checks (steps every, 2 every, ...)
    at = np.arange(1, checks + 1) * every
    x, z = xs[at], zs[at]
    lo = PYRAMID_X - stopping.scene_margin
    hi = PYRAMID_X + PYRAMID_WIDTH + stopping.scene_margin
    leaving = (z < -m.FALLEN_DEPTH) | ((x < lo) & (vx <= 0.0)) | ((x > hi) & (vx >= 0.0))
    centres = can_positions()[list(mask_to_cans(config))]
    right = centres[:, 0].max() + CAN_WIDTH / 2 if len(centres) else -math.inf
    ends = leaving | ((x - m.BALL_RADIUS > right) & (vx >= 0.0))
    if config == 0:
        ends[:] = True
    fired = np.flatnonzero(ends)
    stop = int(at[fired[0]]) if len(fired) else n
    # clear of the cans and the table top at every step until then
    px, pz = xs[: stop + 1], zs[: stop + 1]
    near = m.BALL_RADIUS + CLEAR_MARGIN
    table_lo, table_hi = PYRAMID_X - m.TABLE_MARGIN, PYRAMID_X + PYRAMID_WIDTH + m.TABLE_MARGIN
    over_table = (px > table_lo - near) & (px < table_hi + near)
    if np.any(over_table & (pz < near) & (pz > -m.TABLE_THICKNESS - near)):
        return None
    for cx, cz in centres:
        dx = np.maximum(np.abs(px - cx) - CAN_WIDTH / 2, 0.0)
        dz = np.maximum(np.abs(pz - cz) - CAN_HEIGHT / 2, 0.0)
        if np.any(dx * dx + dz * dz < near * near):
            return None
    end_positions = np.full((N_CANS, 2), np.nan)
    end_positions[list(mask_to_cans(config))] = centres
    return Run(end_positions, 0, 0, stop, not len(fired), dt)


def _public_api(space: pymunk.Space):
    """Step and body getters through pymunk's public API (the reference)."""
    return (
        lambda handle, dt: space.step(dt),
        space,
        lambda body: body,
        lambda body: body.position,
        lambda body: body.velocity,
        lambda body: body.is_sleeping,
    )


def _binding_api(space: pymunk.Space):
    """The same through pymunk's cffi binding: the same numbers, less Python."""
    return (
        _cp.cpSpaceStep,
        space._space,
        lambda body: body._body,
        _cp.cpBodyGetPosition,
        _cp.cpBodyGetVelocity,
        _cp.cpBodyIsSleeping,
    )


@simulation
def run_ball(
    config: int,
    position,
    velocity,
    *,
    frame_every: int = 0,
    on_frame: FrameCallback | None = None,
    stopping: m.StoppingRules = m.STOPPING,
    stepping: m.Stepping = m.STEPPING,
    reference: bool = False,
) -> Run:
    """Run one ball state against a configuration until a stopping rule fires.

    Parameters
    ----------
    config : int
        Configuration mask (checked by the caller).
    position, velocity : (2,) float
        The ball's centre (m) and velocity (m/s), ``(x, z)``; checked by the caller.
    frame_every : int
        With ``on_frame``, call it at step 0, every ``frame_every`` steps and at the end.
    on_frame : callable, optional
        ``on_frame(step, cans, ball)``, see :data:`FrameCallback`.
    stopping : sim2d.materials.StoppingRules
        When the run is over.
    stepping : sim2d.materials.Stepping
        How the world is stepped.
    reference : bool
        Step and read bodies through pymunk's public API (slower, same numbers).

    Returns
    -------
    Run
    """
    if stepping.start_asleep and not reference and not (frame_every and on_frame):
        run = clear_miss(config, position, velocity, stopping=stopping, stepping=stepping)
        if run is not None:
            return run
    space = new_space(sleep_time=stopping.sleep_time, iterations=stepping.solver_iterations)
    cans = add_cans(space, config, asleep=stepping.start_asleep)
    ball, ball_shape = add_ball(space, position, velocity, time_step=stepping.time_step)
    step_space, space_handle, handle, pos, vel, sleeping = (
        _public_api if reference else _binding_api
    )(space)
    # body handles for the getters, by can index (removed cans are dropped from both)
    can_handles = {i: handle(body) for i, body in cans.items()}
    ball_handle = handle(ball)

    can_of_shape = {next(iter(body.shapes)): i for i, body in cans.items()}
    touched = 0

    def on_touch(arbiter, space, data):
        nonlocal touched
        for shape in arbiter.shapes:
            if shape in can_of_shape:
                touched |= 1 << can_of_shape[shape]

    space.on_collision(BALL_TYPE, CAN_TYPE, begin=on_touch)

    lo = PYRAMID_X - stopping.scene_margin
    hi = PYRAMID_X + PYRAMID_WIDTH + stopping.scene_margin
    fallen = -m.FALLEN_DEPTH
    # the far face of the configuration's rightmost can, for the no-touch rule
    right = max((can_positions()[i, 0] for i in cans), default=-math.inf) + CAN_WIDTH / 2
    reach = math.hypot(CAN_WIDTH, CAN_HEIGHT) / 2 + m.BALL_RADIUS
    radius, dt, every = m.BALL_RADIUS, stepping.time_step, m.CHECK_EVERY
    max_steps = round(m.MAX_SIM_TIME / dt)

    def leaving(body) -> bool:
        p = pos(body)
        if p.y < fallen:
            return True
        if p.x < lo:
            return vel(body).x <= 0.0
        if p.x > hi:
            return vel(body).x >= 0.0
        return False

    def record(step: int) -> None:
        poses = np.full((N_CANS, 3), np.nan)
        for i, body in cans.items():
            poses[i] = (body.position.x, body.position.y, body.angle)
        where = np.array(ball.position) if ball_in else np.full(2, np.nan)
        on_frame(step, poses, where)

    recording = bool(frame_every) and on_frame is not None
    removed = 0
    ball_in = True
    step = 0
    last_frame = -1
    timed_out = True
    if recording:
        record(0)
        last_frame = 0
    while step < max_steps:
        if recording:
            for _ in range(every):
                step_space(space_handle, dt)
                step += 1
                if step % frame_every == 0:
                    record(step)
                    last_frame = step
        else:
            for _ in range(every):
                step_space(space_handle, dt)
            step += every
        # Untouched cans that started asleep still stand exactly at their standard
        # positions, inside the scene: only cans that may have moved are checked.
        moved = touched or not stepping.start_asleep
        for i in [i for i, h in can_handles.items() if leaving(h)] if moved else ():
            space.remove(cans[i], *cans[i].shapes)
            del cans[i], can_handles[i]
            removed |= 1 << i
        if ball_in and leaving(ball_handle):
            space.remove(ball, ball_shape)
            ball_in = False
        if not touched:
            # Before any contact the cans stand still: can the ball still reach one?
            if not ball_in or config == 0 or sleeping(ball_handle):
                timed_out = False
                break
            p, v = pos(ball_handle), vel(ball_handle)
            if p.x - radius > right and v.x >= 0.0:
                timed_out = False
                break
        elif all(sleeping(h) for h in can_handles.values()):
            if not ball_in or sleeping(ball_handle) or not cans:
                timed_out = False
                break
            p, v = pos(ball_handle), vel(ball_handle)
            xs = [pos(h).x for h in can_handles.values()]
            if (v.x >= 0.0 and p.x > max(xs) + reach) or (v.x <= 0.0 and p.x < min(xs) - reach):
                timed_out = False
                break
    if recording and last_frame != step:
        record(step)

    end_positions = np.full((N_CANS, 2), np.nan)
    for i, h in can_handles.items():
        p = pos(h)
        end_positions[i] = (p.x, p.y)
    return Run(end_positions, removed, touched, step, timed_out, dt)
