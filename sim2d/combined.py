r"""The combined scene (paper §IV-C): the robot's throw played into the can pyramid.

The pyramid's near face stands at x = 2 m (the throw's target
plane) in the plane y = 0, on a table whose top is ``table_z`` above the robot's floor. A
throw whose hit point lies within the can depth (``|y| <= CAN_BAND``) enters the can world
at its hit height with its in-plane velocity; otherwise it hits no can. The ball is run
back ballistically from the plane to the can world's entry line (0.1 m in front of the
near face) and played from there.

Intermediate states (the recorded rule): after a throw the remaining cans are
put back at their standard positions; if that set is not physically possible, the cans
that cannot stand fall too: the state is the largest physically possible subset of the
remaining cans (ties: the smallest mask).

Everything here is physics and geometry; nothing is learned.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
from effect_networks.sim2d import geometry, materials
from effect_networks.sim2d.analytic_throw import (
    ReleaseNoise,
    exact_target_for_hit,
    is_reachable_hit,
    throw,
)
from effect_networks.sim2d.chunks import locked, read_npz, run_chunks
from effect_networks.sim2d.configurations import stable_configurations
from effect_networks.sim2d.field_throws import aim_offset, launch_state, play_ball

#: m, the table top above the robot's floor: a standard table. The pyramid then spans
#: 0.75-1.39 m, inside the throw's reachable hits (0.35-1.63 m near y = 0).
TABLE_TOP_Z = 0.75
#: m, the largest ``|y|`` of a hit at which the ball still meets a can (half a can + ball radius)
CAN_BAND = geometry.CAN_WIDTH / 2 + materials.BALL_RADIUS


def settle(mask: int, stable: Iterable[int] | None = None) -> int:
    """The recorded intermediate-state rule: the largest physically possible subset of ``mask``.

    ``stable`` defaults to :func:`sim2d.configurations.stable_configurations`.
    """
    stable = frozenset(stable_configurations() if stable is None else stable)
    if mask in stable:
        return mask
    subsets = [s for s in stable if s & ~mask == 0]
    return min(subsets, key=lambda s: (-bin(s).count("1"), s))


def first_contact(state: int, field: int, angle: int) -> tuple[float, float]:
    """Where the training throw through ``field`` first meets a can of ``state`` (can frame).

    The ball's centre path is sampled every millimetre of x up to the field centre; a can
    is met when the centre enters the can's box grown by the ball's radius. A path that
    meets no can is matched at the field centre.
    """
    (x0, z0), (vx, vz) = launch_state(field, angle)
    x_end, z_end = geometry.field_centres()[field]
    radius = materials.BALL_RADIUS
    x = np.arange(geometry.PYRAMID_X - radius, x_end, 1e-3)
    t = (x - x0) / vx
    z = z0 + vz * t - 0.5 * materials.GRAVITY * t * t
    inside = np.zeros(len(x), dtype=bool)
    for cx, cz in geometry.can_positions()[list(geometry.mask_to_cans(state))]:
        inside |= (np.abs(x - cx) <= geometry.CAN_WIDTH / 2 + radius) & (
            np.abs(z - cz) <= geometry.CAN_HEIGHT / 2 + radius
        )
    if inside.any():
        i = int(np.argmax(inside))
        return float(x[i]), float(z[i])
    return float(x_end), float(z_end)


def entry_state(hit, velocity, *, table_z: float = TABLE_TOP_Z):
    """The can world's ball state for a throw crossing the plane x = 2 m, or None if it misses.

    Parameters
    ----------
    hit : (2,) float
        ``[y, z]`` where the ball crosses the plane, robot frame (metres).
    velocity : (3,) float
        ``(vx, vy, vz)`` there (m/s).
    table_z : float
        Height of the table top in the robot frame.

    Returns
    -------
    ((x, z), (vx, vz)) or None
        Position and velocity at the entry line in the can frame; None when the ball passes
        beside the pyramid (``|y| > CAN_BAND``) or would have struck the table top in front
        of it.
    """
    (y, z), (vx, _, vz) = np.asarray(hit, float), np.asarray(velocity, float)
    if abs(y) > CAN_BAND:
        return None
    dt = (geometry.PYRAMID_X - geometry.ENTRY_X) / vx  # back to the entry line
    z_entry = z - table_z - vz * dt - 0.5 * materials.GRAVITY * dt * dt
    if z_entry < materials.BALL_RADIUS + 1e-3:
        return None
    return (geometry.ENTRY_X, z_entry), (vx, vz + materials.GRAVITY * dt)


def play_throw(
    state: int,
    hit,
    velocity,
    *,
    table_z: float = TABLE_TOP_Z,
    jitter: float = 0.0,
    seed: int | None = None,
    stable: Iterable[int] | None = None,
) -> int:
    """Play one robot throw into ``state``; the next state (after :func:`settle`).

    ``jitter`` (metres) adds the can data set's aim jitter to the entry height (normal,
    clipped at 3 sd, seeded by ``seed``), standing in for the paper's simulation deviations.
    """
    entry = entry_state(hit, velocity, table_z=table_z)
    if entry is None:
        return state
    (x, z), v = entry
    if jitter:  # the can world's own aim error (normal, clipped at 3 sd); its first axis
        z = max(z + float(aim_offset(jitter, seed)[0]), materials.BALL_RADIUS + 1e-3)
    outcome = play_ball(state, (x, z), v)
    return settle(outcome.end_config, stable)


def exact_throws(step: float = 0.002, *, table_z: float = TABLE_TOP_Z):
    """The robot's noise-free throws at every reachable height of the pyramid's face.

    Aimed with the exact inverse kinematics (:func:`sim2d.analytic_throw.exact_target_for_hit`) at
    ``y = 0`` and heights from the table top to a ball radius above the pyramid, every
    ``step`` metres; heights the arm cannot reach are left out.

    Returns
    -------
    heights : (n,) float
        Hit heights above the table top (can frame).
    result : sim2d.analytic_throw.ThrowResult
        The throws (``hit``, ``velocity_at_plane``, ...).
    """
    if not step > 0:
        raise ValueError(f"step = {step!r}: expected a positive number of metres")
    heights = np.arange(0.0, geometry.PYRAMID_HEIGHT + materials.BALL_RADIUS, step)
    hits = np.stack([np.zeros_like(heights), heights + table_z], -1)
    ok = is_reachable_hit(hits)
    if not ok.any():
        raise ValueError(f"table_z = {table_z}: the robot reaches no height of the pyramid")
    return heights[ok], throw(exact_target_for_hit(hits[ok]))


def throws_from(
    state: int,
    table_z: float = TABLE_TOP_Z,
    step: float = 0.002,
    repeats: int = 8,
    jitter: float = 0.0,
    seed: int = 0,
) -> dict[str, np.ndarray]:
    """Every exact robot throw (:func:`exact_throws`) played into ``state``, ``repeats`` times.

    Each throw gets the can world's aim jitter with its own seed: the seeds are the
    words of ``numpy.random.SeedSequence([seed, state])``, in order of height and repeat.
    An executor task (returns arrays; see :func:`sim2d.chunks.run_chunks`).

    Returns
    -------
    dict
        ``heights`` ``(n,)`` float (m above the table top) and ``next_states``
        ``(n, repeats)`` int: the state after each throw (:func:`play_throw`).
    """
    heights, result = exact_throws(step, table_z=table_z)
    seeds = np.random.SeedSequence([seed, state]).generate_state(len(result.hit) * repeats)
    seeds = seeds.reshape(len(result.hit), repeats)
    stable = frozenset(stable_configurations())
    next_states = np.array(
        [
            [
                play_throw(state, h, v, table_z=table_z, jitter=jitter, seed=int(k), stable=stable)
                for k in ks
            ]
            for h, v, ks in zip(result.hit, result.velocity_at_plane, seeds, strict=True)
        ],
        dtype=np.int64,
    ).reshape(len(result.hit), repeats)
    return {"heights": heights, "next_states": next_states}


def reachable_throws(
    folder,
    start: int,
    *,
    depth: int,
    table_z: float = TABLE_TOP_Z,
    step: float = 0.002,
    repeats: int = 8,
    jitter: float = 0.0,
    seed: int = 0,
    executor=None,
    progress: bool = True,
) -> dict[int, np.ndarray]:
    """:func:`throws_from` for every state that these throws reach from ``start``.

    Within ``depth - 1`` throws: the states a plan of ``depth`` throws may act in.

    Breadth first: layer 0 is ``start``; layer k + 1 holds the states that layer k's
    throws produced and no earlier layer holds (the empty state has nothing to throw at).
    Each layer is saved in its own parts folder under ``folder`` (one task per state, on
    ``executor``; :func:`sim2d.chunks.run_chunks`), so an interrupted run resumes; the
    layers follow from the seeds, so a resumed run finds the same ones.

    Returns
    -------
    dict
        ``{state: (n_heights, repeats) int}`` next states; the heights are
        :func:`exact_throws`'s for ``step`` and ``table_z``.
    """
    if depth < 1:
        raise ValueError(f"depth = {depth!r}: expected at least 1")
    if repeats < 1:
        raise ValueError(f"repeats = {repeats!r}: expected at least 1")
    if start not in stable_configurations():
        raise ValueError(f"start {start} is not a physically possible configuration")
    n_heights = len(exact_throws(step, table_z=table_z)[0])

    def check(k: int, arrays: dict[str, np.ndarray]) -> str | None:
        shape = arrays["next_states"].shape if "next_states" in arrays else None
        if shape != (n_heights, repeats):
            return f"has next_states of shape {shape}, expected {(n_heights, repeats)}"
        return None

    folder = Path(folder)
    outcomes: dict[int, np.ndarray] = {}
    layer = [int(start)] if start else []
    with locked(folder, or_read_only=True):  # a finished run is usable in a read-only folder
        for k in range(depth):
            if not layer:
                break
            tasks = [
                (s, float(table_z), float(step), int(repeats), float(jitter), int(seed))
                for s in layer
            ]
            protocol = {
                "producer": "sim2d.combined.throws_from",
                "tasks": [list(t) for t in tasks],
                "constants": materials.physical_constants(),
            }
            files = run_chunks(
                folder / f"layer-{k}", protocol, throws_from, tasks, executor=executor,
                check=check, sizes=[n_heights * repeats] * len(tasks), progress=progress,
                desc=f"throws, table {table_z} m, seed {seed}, layer {k}",
            )  # fmt: skip
            for s, f in zip(layer, files, strict=True):
                outcomes[s] = read_npz(f)["next_states"]
            reached = set(np.unique(np.concatenate([outcomes[s].ravel() for s in layer])).tolist())
            layer = sorted(s for s in reached if s and s not in outcomes)
    return outcomes


def play_policy(
    start: int,
    goal: int,
    policy: np.ndarray,
    states: Sequence[int],
    aims: np.ndarray,
    *,
    episodes: int,
    table_z: float = TABLE_TOP_Z,
    jitter: float = 0.0,
    noise: ReleaseNoise | None = None,
    seed: int = 0,
) -> dict[str, np.ndarray]:
    """Play a state-to-action table from ``start`` ``episodes`` times; an executor task.

    An episode ends at the goal, when a goal can is lost, when the policy stops, or after
    ``H`` throws. Every throw gets its own seeds from ``SeedSequence([seed, episode])``.

    Parameters
    ----------
    policy : (H + 1, S) int
        ``policy[h, i]``: the action to take in ``states[i]`` with ``h`` throws left
        (``-1``: stop). Row 0 is unused.
    states : sequence of int
        The masks indexing the policy's columns; a state not among them ends the episode.
    aims : (A, 2) float
        The robot's aim ``[y, z]`` for each action (thrown with :func:`sim2d.analytic_throw.throw`,
        with ``noise`` if given).

    Returns
    -------
    dict
        ``end`` ``(episodes,)`` int: the state each episode ended in; ``throws``
        ``(episodes,)`` int: the throws it used.
    """
    policy = np.asarray(policy, dtype=np.int64)
    aims = np.asarray(aims, dtype=float)
    index = {int(s): i for i, s in enumerate(states)}
    if policy.ndim != 2 or policy.shape[1] != len(index):
        raise ValueError(f"policy must be (H + 1, {len(index)}), got {policy.shape}")
    if aims.ndim != 2 or aims.shape[1] != 2:
        raise ValueError(f"aims must be (A, 2), got {aims.shape}")
    if episodes < 1:
        raise ValueError(f"episodes = {episodes!r}: expected at least 1")
    horizon = policy.shape[0] - 1
    stable = frozenset(stable_configurations())
    end = np.zeros(episodes, dtype=np.int64)
    used = np.zeros(episodes, dtype=np.int64)
    for e in range(episodes):
        rng = np.random.default_rng(np.random.SeedSequence([seed, e]))
        state = int(start)
        for h in range(horizon, 0, -1):
            if state == goal or state & goal != goal or state not in index:
                break
            action = int(policy[h, index[state]])
            if action < 0:
                break
            result = throw(aims[action : action + 1], rng=rng, noise=noise)
            state = play_throw(
                state,
                result.hit[0],
                result.velocity_at_plane[0],
                table_z=table_z,
                jitter=jitter,
                seed=int(rng.integers(2**32)),
                stable=stable,
            )
            used[e] += 1
        end[e] = state
    return {"end": end, "throws": used}
