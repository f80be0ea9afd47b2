r"""Whether a field's learned outcome transfers to the robot's throw at it.

The can network learned what a field does from the can data set's throws through it, which
all arrive with the velocity of one angle (``sim2d.geometry.ANGLES``); the robot's ball is
aimed to meet the cans where that throw first does (:meth:`experiments.combined.World.heights`)
but arrives with its own velocity. :func:`measure_transfer` measures, for one start state and
one field, the next state four ways::

    planner        the chained models' row T[s, f, :] (experiments.combined.transition_model)
    can_network    the can network's row for field f alone, settled
    dataset_throw  the physics: the data set's throw through f (its angle, its aim jitter)
    robot_throw    the physics: the robot's throw aimed at f (World.play)

The two model rows differ by the throw network's hit and the fields' boundary spread (the
planner reads an aim as a blend of neighbouring fields). Each row is scored by the value the
exact planner's own value function expects after the throw, ``sum_s' P(s') V_{h-1}(s')``:
for the planner's row this is the plan's predicted success when ``f`` is its first field, so
the physics rows say what the same value function expects after the real first throw.

Next states outside the plan's states (``states``; in the combined experiment every
superset of the goal, so the rest have lost a goal can) are pooled as one outcome,
``OTHER``, of value 0: the rows are compared on the outcomes the plan tells apart, and the
total-variation distances are those of the pooled distributions.

Seeds: the data set's throws drew their aim jitter from the first word of
``numpy.random.SeedSequence([data set seed, config, field, angle, repeat])``
(:func:`sim2d.field_throws.aim_seed`); the replayed throw ``k`` draws it from word ``k`` of
``numpy.random.SeedSequence([TRANSFER_SEED_BASE, seed, state, field, angle])``, a sequence
that begins with a fixed base instead of the data set's seed, so the replays are fresh
throws, not the training ones (for any data set whose seed is not the base). The robot's
throws draw from their own ``numpy.random.default_rng([seed, state, field])``, so the
experiment's other plays are unchanged. Both physics ways use the world's aim jitter
(``World.jitter``: the data set's unless the experiment overrides it): the data set's throw
moves its field centre by it in x and z, the robot's its entry height
(:func:`sim2d.combined.play_throw`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch
from effect_networks.sim2d import geometry, materials
from effect_networks.sim2d.combined import settle
from effect_networks.sim2d.field_throws import launch_state, throw_at_field

__all__ = [
    "OTHER",
    "TRANSFER_SEED_BASE",
    "WAYS",
    "ArrivalTransfer",
    "measure_transfer",
    "transfer_markdown",
]

#: the pooled outcome: a next state outside the plan's states
OTHER = -1
#: the first word of the data set's replayed throws' seed sequence (see the module docstring)
TRANSFER_SEED_BASE = 0x7EA5F3E1
WAYS = ("planner", "can_network", "dataset_throw", "robot_throw")
MODELS = ("planner", "can_network")


@dataclass(frozen=True)
class ArrivalTransfer:
    """One field's next state from one state, four ways (:func:`measure_transfer`).

    Attributes
    ----------
    state, field, angle, repeats, seed : int
        What was measured (``angle``: the can network's, into ``ANGLES``); ``repeats``
        throws per physics way.
    frequencies : dict
        Per way (``WAYS``) ``{next state: probability}``, next states outside the plan's
        pooled as ``OTHER``; each sums to 1.
    values : dict
        Per way ``sum_s' P(s') V(s')``, the plan's value one throw later.
    kept : dict
        Per way the probability that the next state is one of the plan's (not ``OTHER``).
    tv : dict
        ``tv[model][way]``: total-variation distance between a model row (``"planner"``,
        ``"can_network"``) and each way's frequencies, in ``[0, 1]``.
    dataset_arrival : (float, float)
        The data set's (jitter-free) throw at the near face: direction (deg) and speed (m/s).
    """

    state: int
    field: int
    angle: int
    repeats: int
    seed: int
    frequencies: dict[str, dict[int, float]]
    values: dict[str, float]
    kept: dict[str, float]
    tv: dict[str, dict[str, float]]
    dataset_arrival: tuple[float, float]

    def as_dict(self) -> dict:
        """JSON-ready (next states as strings)."""
        return {
            "state": self.state,
            "field": self.field,
            "angle": geometry.ANGLE_NAMES[self.angle],
            "repeats": self.repeats,
            "seed": self.seed,
            "frequencies": {
                w: {str(s): p for s, p in f.items()} for w, f in self.frequencies.items()
            },
            "values": dict(self.values),
            "kept": dict(self.kept),
            "tv": {m: dict(d) for m, d in self.tv.items()},
            "dataset_throw_deg": self.dataset_arrival[0],
            "dataset_throw_speed": self.dataset_arrival[1],
        }


def total_variation(p: dict[int, float], q: dict[int, float]) -> float:
    """``1/2 sum |p - q|`` over both supports."""
    return 0.5 * sum(abs(p.get(s, 0.0) - q.get(s, 0.0)) for s in set(p) | set(q))


def frequencies_of(next_states: list[int], index: dict[int, int]) -> dict[int, float]:
    """The share of each next state, those outside ``index`` pooled as ``OTHER``."""
    pooled = [s if s in index else OTHER for s in next_states]
    values, counts = np.unique(pooled, return_counts=True)
    return {int(s): float(c) / len(pooled) for s, c in zip(values, counts, strict=True)}


def dataset_arrival(field: int, angle: int) -> tuple[float, float]:
    """The data set's jitter-free throw through ``field`` where it crosses the near face."""
    (x0, _), (vx, vz) = launch_state(field, angle)
    vz = vz - materials.GRAVITY * (geometry.PYRAMID_X - x0) / vx
    return float(np.degrees(np.arctan2(vz, vx))), float(np.hypot(vx, vz))


def measure_transfer(
    world,
    state: int,
    field: int,
    states: list[int],
    transitions: torch.Tensor,
    value: torch.Tensor,
    *,
    repeats: int,
    seed: int = 0,
) -> ArrivalTransfer:
    """The next state after a throw at ``field`` from ``state``: the models against the physics.

    Parameters
    ----------
    world : experiments.combined.World
        The can network, the robot and the geometry between them.
    state : int
        The start configuration's mask; one of ``states`` and a start the can network saw.
    field : int
        A field the can network's angle can throw at (``world.can.throwable``).
    states : list of int
        The plan's states (masks), indexing ``transitions`` and ``value``.
    transitions : (S, 195, S) float tensor
        The planner's chained model (:func:`experiments.combined.transition_model`).
    value : (S,) float tensor
        The plan's value with one throw fewer left (``plan.value[h - 1]``).
    repeats : int
        Throws played per physics way (>= 1).
    seed : int
        Seeds both physics ways (>= 0).

    Returns
    -------
    ArrivalTransfer
    """
    if not (isinstance(repeats, (int, np.integer)) and repeats >= 1):
        raise ValueError(f"repeats = {repeats!r}: expected an int >= 1 throws per physics way")
    if not (isinstance(seed, (int, np.integer)) and seed >= 0):
        raise ValueError(f"seed = {seed!r}: expected an int >= 0")
    if not (isinstance(field, (int, np.integer)) and 0 <= field < geometry.N_FIELDS):
        raise ValueError(f"field = {field!r}: expected a field index in 0..{geometry.N_FIELDS - 1}")
    state, field, repeats, seed = int(state), int(field), int(repeats), int(seed)
    angle = world.can.angle
    if not bool(world.can.throwable[field]):
        raise ValueError(
            f"field {field} cannot be thrown at the can network's angle "
            f"({geometry.ANGLE_NAMES[angle]}); expected a field with world.can.throwable True"
        )
    index = {int(s): i for i, s in enumerate(states)}
    if state not in index or state not in world.can.states:
        raise ValueError(
            f"state {state}: expected one of the plan's states that the can network has as a start"
        )
    if transitions.shape != (len(states), geometry.N_FIELDS, len(states)):
        raise ValueError(
            f"transitions: shape {tuple(transitions.shape)}; expected "
            f"({len(states)}, {geometry.N_FIELDS}, {len(states)}) over the plan's states"
        )
    if value.shape != (len(states),):
        raise ValueError(f"value: shape {tuple(value.shape)}; expected ({len(states)},)")

    row = transitions[index[state], field].double()
    planner = {s: float(row[i]) for s, i in index.items() if row[i] > 0}
    planner[OTHER] = max(0.0, 1.0 - float(row.sum()))

    can_network: dict[int, float] = {}
    probs = world.can.end_config_probs(state, np.array([field]))[0].double()
    for end, p in zip(world.can.states, probs.tolist(), strict=True):
        s = settle(end, world.stable)
        key = s if s in index else OTHER
        can_network[key] = can_network.get(key, 0.0) + p

    words = np.random.SeedSequence([TRANSFER_SEED_BASE, seed, state, field, angle])
    dataset = [
        settle(throw_at_field(state, field, angle, jitter=world.jitter, seed=int(k)).end_config,
               world.stable)
        for k in words.generate_state(repeats, dtype=np.uint32)
    ]  # fmt: skip

    robot = replace(world.robot, rng=np.random.default_rng([seed, state, field]))
    player = replace(world, robot=robot)
    played = [player.play(state, field) for _ in range(repeats)]

    frequencies = {
        "planner": planner,
        "can_network": can_network,
        "dataset_throw": frequencies_of(dataset, index),
        "robot_throw": frequencies_of(played, index),
    }
    v = value.double().tolist()
    return ArrivalTransfer(
        state=state,
        field=field,
        angle=angle,
        repeats=repeats,
        seed=seed,
        frequencies=frequencies,
        values={
            w: sum(p * v[index[s]] for s, p in f.items() if s != OTHER)
            for w, f in frequencies.items()
        },
        kept={w: 1.0 - f.get(OTHER, 0.0) for w, f in frequencies.items()},
        tv={
            m: {w: total_variation(frequencies[m], f) for w, f in frequencies.items()}
            for m in MODELS
        },
        dataset_arrival=dataset_arrival(field, angle),
    )


def transfer_markdown(transfer: dict, robot_arrival: tuple[float, float] | None = None) -> str:
    """:meth:`ArrivalTransfer.as_dict` as a small Markdown table, one row per way.

    ``robot_arrival``: the robot's throw at the near face, direction (deg) and speed (m/s).
    """
    robot = (
        ""
        if robot_arrival is None
        else f" ({robot_arrival[0]:.1f} deg, {robot_arrival[1]:.2f} m/s)"
    )
    n, field = transfer["repeats"], transfer["field"]
    rows = {
        "planner": ("the planner's models predict (throw and can networks)", "-"),
        "can_network": (f"the can network predicts for field {field} alone", "-"),
        "dataset_throw": (
            f"the data set's throw does ({transfer['angle']}: "
            f"{transfer['dataset_throw_deg']:.1f} deg, {transfer['dataset_throw_speed']:.2f} m/s)",
            str(n),
        ),
        "robot_throw": (f"the robot's throw does{robot}", str(n)),
    }
    lines = [
        f"First throw at field {field}: the next state as ... (value: the plan's chance of "
        "success after this throw; TV: total-variation distance between next-state "
        "distributions, the states that lost a goal can pooled)",
        "",
        "| next state as | throws | goal cans kept | value | TV to the can network | "
        "TV to the planner's models |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for way, (label, throws) in rows.items():
        lines.append(
            f"| {label} | {throws} | {100 * transfer['kept'][way]:.1f} % | "
            f"{100 * transfer['values'][way]:.1f} % | {transfer['tv']['can_network'][way]:.3f} | "
            f"{transfer['tv']['planner'][way]:.3f} |"
        )
    return "\n".join(lines)
