r"""The combined system (the paper's §IV-C): the throw network aims, the can network plans.

Two networks trained apart are chained: the can network (Fig. 2) picks the field to hit,
the throw network (Fig. 4) turns that hit point into the point the robot aims at, and the
robot's throw is played through its kinematics into the can world. Three scenarios
(Tables II-IV), each from the full pyramid: throw off the top three cans, the near flank,
the far flank.

Set-up (:mod:`sim2d.combined`): the pyramid stands on a table ``table_z`` above the
robot's floor with its near face in the throw's target plane; a throw within the can
depth enters the can world with its in-plane velocity, plus the can data set's aim jitter
(``jitter``); intermediate states follow the recorded settle rule. A field's hit point is
where the can network's training throw through that field first meets the cans (the
network was trained on that angle's parabolas). The can network is trained on the angle
whose direction is closest to the robot's measured impact direction.

Planners: the paper's round planner (:mod:`experiments.round_planner`), whose actions in
a round are the fields whose most probable end configuration is the (intermediate) goal;
and an exact planner (:mod:`inference.sequences.dynamic_programming`) that maximises the probability
of reaching the goal within ``horizon`` throws under the learned models, with the
throw's uncertainty (the throw network's predicted hit Gaussian) included and the hit
read among fields whose boundaries are as uncertain as the can data's throws were spread
about them (:func:`hit_gaussians`); its success rate is measured by playing its policy
``episodes`` times. Its first throw from the full pyramid is checked for transfer
(:mod:`experiments.arrival_transfer`): the next state as the models predict it, as the data
set's own throw through that field gives it and as the robot's throw gives it.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import ClassVar

import numpy as np
import torch
from effect_networks.experiments.arrival_transfer import measure_transfer
from effect_networks.experiments.cans import CanDataSettings, CanModel, can_dataset, fit_can_network
from effect_networks.experiments.harness.config import (
    Result,
    check_choice,
    check_float,
    check_int,
    percent,
)
from effect_networks.experiments.harness.registry import Experiment
from effect_networks.experiments.round_planner import paper_planner
from effect_networks.experiments.scenario_tables import TABLES, table_markdown
from effect_networks.experiments.throwing import MAX_BINS, fit_throws, get_data
from effect_networks.inference import GaussianMixture, predict
from effect_networks.inference import compile as compile_queries
from effect_networks.inference.sequences.chaining import BoxPartition, chain, link_probabilities
from effect_networks.inference.sequences.dynamic_programming import exact_plan, policy_value
from effect_networks.models.humanoid_throw import TARGET
from effect_networks.sim2d import geometry, materials
from effect_networks.sim2d.analytic_throw import TARGET_AREA, ReleaseNoise, throw
from effect_networks.sim2d.combined import CAN_BAND, TABLE_TOP_Z, first_contact, play_throw, settle
from effect_networks.sim2d.configurations import stable_configurations
from effect_networks.sim2d.field_throws import aim_offset, launch_state
from tqdm.auto import tqdm

__all__ = [
    "CombinedConfig",
    "CombinedResult",
    "PAPER_RATES",
    "PROPOSALS",
    "SCENARIOS",
    "Robot",
    "World",
    "build_world",
    "face_height_spread",
    "field_link",
    "hit_gaussians",
    "run_combined",
    "run_scenario",
    "transition_model",
]

PROPOSALS = ("can", "combined")  # the paper planner's actions, see CombinedConfig
MAX_HORIZON = 50  # throws
MAX_JITTER = 0.05  # m: beyond a field's height, the aim says nothing
BOUNDARY_SPREADS = ("measured", "none")  # how sharp the fields' boundaries are, see CombinedConfig


@dataclass(frozen=True)
class CombinedConfig(CanDataSettings):
    """Settings of :func:`run_combined`; every field is checked on construction.

    The can data set's: :class:`experiments.cans.CanDataSettings`.

    Attributes
    ----------
    n_throws : int
        Throws that train the throw network.
    bins : int
        Throw-network clusters per axis, ``1..MAX_BINS``.
    horizon : int
        Throws the exact planner may use, ``1..MAX_HORIZON``.
    episodes : int
        Plays of the exact planner's policy.
    noise : bool
        Throw with release noise (0.5 deg, 2 %).
    proposals : str
        The paper planner's actions: ``"can"``, fields whose most probable outcome under
        the can network alone is the goal (the paper's); ``"combined"``, under the can
        and throw networks together (aiming with the robot's scatter).
    table_z : float
        Table top above the robot's floor, m, in ``[0, TARGET_AREA.z_max]``.
    jitter : float or None
        Aim jitter added to every throw's entry height, m, in ``[0, MAX_JITTER]``; None:
        the data set's.
    boundary_spread : str
        How a predicted hit is read as a field (:func:`hit_gaussians`): ``"measured"``,
        among fields whose boundaries are as uncertain as the can data set's throws at
        the chosen angle were spread about their fields' heights
        (:func:`face_height_spread`, measured on the training throws); ``"none"``, sharp
        at the midpoints between the fields' heights.
    transfer_repeats : int
        Throws per physics way in the first throw's transfer check
        (:func:`experiments.arrival_transfer.measure_transfer`), >= 1.
    seed : int
        Seeds the throw network's data and every play (>= 0).
    progress : bool
        Progress bars.
    """

    n_throws: int = 29_000
    bins: int = 16
    horizon: int = 6
    episodes: int = 50
    noise: bool = False
    proposals: str = "can"
    table_z: float = TABLE_TOP_Z
    jitter: float | None = None
    boundary_spread: str = "measured"
    transfer_repeats: int = 24
    seed: int = 0
    progress: bool = True

    def __post_init__(self):
        super().__post_init__()
        check_int("n_throws", self.n_throws, 10)
        check_int("bins", self.bins, 1, MAX_BINS)
        check_int("horizon", self.horizon, 1, MAX_HORIZON)
        check_int("episodes", self.episodes, 1)
        check_choice("noise", self.noise, (False, True))
        check_choice("proposals", self.proposals, PROPOSALS)
        check_float("table_z", self.table_z, 0.0, TARGET_AREA.z_max, unit="m")
        if self.jitter is not None:
            check_float("jitter", self.jitter, 0.0, MAX_JITTER, unit="m")
        check_choice("boundary_spread", self.boundary_spread, BOUNDARY_SPREADS)
        check_int("transfer_repeats", self.transfer_repeats, 1)
        check_int("seed", self.seed, 0)


SCENARIOS = {
    "top_three": geometry.TOP_THREE,
    "near_flank": geometry.NEAR_FLANK,
    "far_flank": geometry.FAR_FLANK,
}
PAPER_RATES = {"top_three": 0.5713, "near_flank": 0.6857, "far_flank": 0.5771}


@dataclass
class Robot:
    """The throw side: the learned inverse (hit -> aim) and the kinematics that throw."""

    queries: object  # the throw network's compiled queries (inference.compile)
    net: object
    params: object
    noise: ReleaseNoise | None
    rng: np.random.Generator

    def aim(self, hits: np.ndarray) -> np.ndarray:
        """The throw network's aims for the desired ``hits``, clipped into the target area.

        Parameters
        ----------
        hits : (n, 2) float
            The points the ball should hit.

        Returns
        -------
        (n, 2) float
            The parameter posterior's mean for each hit, clipped into ``TARGET_AREA``.
        """
        aims = self.queries.infer_parameter(TARGET, {"end.hit": torch.as_tensor(hits)}).mean.numpy()
        return np.clip(aims, TARGET_AREA.low, TARGET_AREA.high)

    def hit_distribution(self, aims: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The throw network's predicted hit for each aim: means ``(n, 2)``, covs ``(n, 2, 2)``."""
        mix = predict(
            self.net, self.params, {"action": ["throw"] * len(aims), "param.target": aims}
        )
        hit = mix.continuous["hit"]
        return hit.mean.numpy(), hit.cov.numpy()


@dataclass
class World:
    """Everything one throw needs: the can model, the robot, and the geometry between them."""

    can: CanModel
    robot: Robot
    stable: frozenset[int]
    table_z: float = TABLE_TOP_Z
    jitter: float = 0.0  # m, the can data set's aim jitter added to every throw's entry height
    boundary_sd: float = 0.0  # m, sd of the fields' boundaries in the hit's height
    _heights: dict = field(default_factory=dict)

    def heights(self, state: int) -> np.ndarray:
        """``(195,)`` near-face heights (can frame) to hit.

        So that the robot's ball meets the cans of ``state`` where the training throw through each
        field does (NaN: unthrowable).

        Solved with the robot's own forward kinematics: a few fixed-point steps of
        "aim, read the velocity at the plane, run it back from the contact point".
        """
        if state not in self._heights:
            fields = np.flatnonzero(self.can.throwable.numpy())
            contact = np.array([first_contact(state, f, self.can.angle) for f in fields])
            z2 = contact[:, 1].copy()
            for _ in range(4):
                aims = self.robot.aim(np.stack([np.zeros_like(z2), z2 + self.table_z], -1))
                v = throw(aims).velocity_at_plane
                t = (contact[:, 0] - geometry.PYRAMID_X) / v[:, 0]
                z2 = contact[:, 1] - v[:, 2] * t + 0.5 * materials.GRAVITY * t * t
            heights = np.full(geometry.N_FIELDS, np.nan)
            heights[fields] = z2
            self._heights[state] = heights
        return self._heights[state]

    def play(self, state: int, field: int) -> int:
        """Aim at ``field`` from ``state``, throw, play the ball into the cans; the next state."""
        desired = np.array([[0.0, self.heights(state)[field] + self.table_z]])
        result = throw(self.robot.aim(desired), rng=self.robot.rng, noise=self.robot.noise)
        seed = int(self.robot.rng.integers(2**32))
        return play_throw(
            state,
            result.hit[0],
            result.velocity_at_plane[0],
            table_z=self.table_z,
            jitter=self.jitter,
            seed=seed,
            stable=self.stable,
        )

    def proposals(self, state: int, goal: int) -> list[int]:
        """The paper's actions: fields whose most probable end configuration is ``goal``."""
        states = self.can.states
        if state not in states or goal not in states:
            return []
        probs = self.can.end_config_probs(state)
        seen = self.can.params["end.config"].n[states.index(state), bin(state).count("1")] > 0
        ok = (probs.argmax(-1) == states.index(goal)) & seen & self.can.throwable
        return ok.nonzero().flatten().tolist()


def build_world(config: CombinedConfig, data) -> tuple[World, dict]:
    """Train both networks; choose the can network's angle by the robot's impact direction."""
    rng = np.random.default_rng(config.seed)
    noise = ReleaseNoise() if config.noise else None
    targets, hits = get_data(config.n_throws, rng, noise)
    net, params, _ = fit_throws((config.bins, config.bins), targets, hits)
    robot = Robot(compile_queries(net, params), net, params, noise, rng)
    # the robot's impact direction at the pyramid, throwing at every field height
    probe = np.linspace(0.05, geometry.PYRAMID_HEIGHT, 12) + config.table_z
    v = throw(robot.aim(np.stack([np.zeros_like(probe), probe], -1))).velocity_at_plane
    impact_deg = float(np.degrees(np.arctan2(v[:, 2], v[:, 0])).mean())
    angle_deg = [math.degrees(math.atan2(vz, vx)) for vx, vz in geometry.ANGLES]
    angle = int(np.argmin([abs(a - impact_deg) for a in angle_deg]))
    can = fit_can_network(data, angle)
    why = {
        "robot_impact_deg_mean": impact_deg,
        "angle_deg": dict(zip(geometry.ANGLE_NAMES, angle_deg, strict=True)),
        "chosen_angle": geometry.ANGLE_NAMES[angle],
        "training_speed": float(np.hypot(*geometry.ANGLES[angle])),
    }
    jitter = data.metadata["jitter"] if config.jitter is None else config.jitter
    spread = face_height_spread(data, angle) if config.boundary_spread == "measured" else 0.0
    stable = frozenset(stable_configurations())
    world = World(can, robot, stable, config.table_z, jitter, boundary_sd=spread)
    return world, why | {"table_z": config.table_z, "jitter": jitter, "boundary_sd": spread}


def face_height_spread(data, angle: int) -> float:
    """How far from its field's height the can data set's throws at ``angle`` crossed the near face.

    The root mean square, over the throwable throws, of the crossing height's offset from the
    jitter-free throw's (m).

    A throw "at field f" in the data set passes ``field centre + offset``, the offset its
    aim jitter (:func:`sim2d.field_throws.aim_offset`, read back from the throw's recorded
    seed and the data set's ``jitter``), with the field's velocity there: the jitter-free
    parabola moved by ``(dx, dz)``, which crosses the near face ``dz - dx * slope`` higher
    to first order. Only the training data enters: no outcome, no play.
    """
    sel = (data.angle == angle) & data.throwable
    if not sel.any():
        raise ValueError(
            f"the data set has no throwable throws at angle {angle} ({geometry.ANGLE_NAMES[angle]})"
        )
    jitter = float(data.metadata["jitter"])
    offsets = np.array([aim_offset(jitter, int(seed)) for seed in data.seed[sel]])
    fields = data.field[sel].astype(np.int64)
    table = np.array([launch_state(f, angle) for f in range(geometry.N_FIELDS)])
    (entry_x, entry_z), (vx, vz) = table[fields, 0].T, table[fields, 1].T

    def crossing(x):  # the jitter-free throw's height at x
        t = (x - entry_x) / vx
        return entry_z + vz * t - 0.5 * materials.GRAVITY * t * t

    shift = (
        crossing(geometry.PYRAMID_X - offsets[:, 0]) + offsets[:, 1] - crossing(geometry.PYRAMID_X)
    )
    return float(np.sqrt(np.mean(shift * shift)))


def hit_gaussians(
    robot: Robot, aims: np.ndarray, table_z: float, boundary_sd: float = 0.0
) -> GaussianMixture:
    """The throw network's predicted hit for each aim as one Gaussian a row, in the can frame.

    Lateral, height above the table; its two coordinates taken as independent: the can band is read
    across and the fields' slices up, one coordinate each.

    ``boundary_sd`` (m) widens the height's sd in quadrature: the boundaries between the
    can network's actions, read as moved together by a normal offset of that sd (equally:
    the hit's height moved by minus it). Why they are uncertain: the can network learned
    what an action does from a few throws (three per state and field at the full scale)
    that crossed the near face about ``boundary_sd`` above or below the action's height
    (their aim jitter; :func:`face_height_spread` measures it on the training throws). An
    action's learned outcome is the physics averaged over that spread, so it cannot change
    faster than it with height: actions closer than it are near-replicates of one another,
    and a hit is read among all of them, not as the one nearest. Without it a robot that
    throws almost deterministically (the throw network's predicted sd is about 1 mm) reads
    each aim as one field's few throws alone, and the planner, maximising over some 180
    such estimates, picks the field whose few throws were luckiest (the maximum of many
    noisy estimates is biased upward). The price: the spread is counted twice (in the
    training throws and here), so the models' predicted success is blurred, too low where
    the heights that succeed form a narrow band.
    """
    mean, cov = robot.hit_distribution(aims)
    mean = torch.as_tensor(mean) - torch.tensor([0.0, table_z], dtype=torch.float64)
    var = torch.diagonal(torch.as_tensor(cov), dim1=-2, dim2=-1).clone()
    var[:, 1] += boundary_sd**2
    return GaussianMixture(
        torch.ones(len(mean), 1, dtype=torch.float64), mean[:, None], torch.diag_embed(var)[:, None]
    )


def field_link(heights: np.ndarray, fields: np.ndarray) -> tuple[BoxPartition, np.ndarray]:
    """A hit in the can band read as the field whose near-face height is nearest.

    Each of ``fields`` owns the heights between the midpoints to its neighbours (the lowest and
    highest open-ended); a hit beside the band hits nothing. Returns the partition (the can
    network's actions: every field) and ``fields`` ordered by height.
    """
    order = fields[np.argsort(heights[fields])]
    edges = np.concatenate([[-np.inf], (heights[order][1:] + heights[order][:-1]) / 2, [np.inf]])
    across = np.tile([-CAN_BAND, CAN_BAND], (len(order), 1))
    link = BoxPartition(
        np.stack([across[:, 0], edges[:-1]], -1),
        np.stack([across[:, 1], edges[1:]], -1),
        labels=order.tolist(),
        actions=range(geometry.N_FIELDS),
    )
    return link, order


def transition_model(world: World, states: list[int]) -> torch.Tensor:
    """``T[s, f, s']``: the learned chance that aiming at field ``f`` from ``s`` gives ``s'``.

    The two networks chained (:func:`inference.sequences.chaining.chain`): the throw
    network's predicted hit (:func:`hit_gaussians`, widened by the fields' boundary
    spread ``World.boundary_sd``) read through each state's :func:`field_link` (the
    fields' matched near-face heights, :meth:`World.heights`),
    and the can network's end configurations settled by the recorded rule; a hit beside
    the cans leaves the state unchanged. States the can network never saw as a start get
    no actions (their rows stay zero).
    """
    index = {s: i for i, s in enumerate(states)}
    can_states = world.can.states
    settled_index = [index.get(settle(end, world.stable), -1) for end in can_states]
    fields = np.flatnonzero(world.can.throwable.numpy())
    lower = torch.zeros(len(states), geometry.N_FIELDS, len(states), dtype=torch.float64)
    links = [None] * len(states)
    for s in states:
        if s not in can_states:
            continue
        link, order = field_link(world.heights(s), fields)
        desired = np.stack([np.zeros(len(order)), world.heights(s)[order] + world.table_z], -1)
        aims = world.robot.aim(desired)
        hits = hit_gaussians(world.robot, aims, world.table_z, world.boundary_sd)
        links[index[s]] = link_probabilities(link, hits).padded(order, geometry.N_FIELDS)
        probs = world.can.end_config_probs(s, order).double()  # (hit field, network state)
        for j, target in enumerate(settled_index):
            if target >= 0:
                lower[index[s], order, target] += probs[:, j]
    return chain(links, lower)


def run_scenario(world: World, name: str, config: CombinedConfig) -> dict:
    """Both planners from the full pyramid to scenario ``name``'s goal, played in the world."""
    removed = SCENARIOS[name]
    start = geometry.FULL_PYRAMID
    goal = start & ~geometry.cans_to_mask(removed)
    to_set = lambda mask: frozenset(geometry.mask_to_cans(mask))  # noqa: E731
    to_mask = geometry.cans_to_mask
    # the learned transitions over every physically possible superset of the goal
    states = sorted(s for s in world.stable if s & goal == goal)
    t = transition_model(world, states)

    def propose(s, g):
        if config.proposals == "can":  # the paper's: the can network alone
            return world.proposals(to_mask(s), to_mask(g))
        # the combined model's most probable outcome of aiming at each field
        s, g = to_mask(s), to_mask(g)
        if s not in states or g not in states:
            return []
        row = t[states.index(s)]
        failure = 1 - row.sum(-1)  # mass on states that lost a goal can
        ok = (
            (row.sum(-1) > 0)
            & (row.argmax(-1) == states.index(g))
            & (row[:, states.index(g)] > failure)
        )
        return ok.nonzero().flatten().tolist()

    rounds, rate = paper_planner(
        to_set(start), to_set(goal), propose, lambda s, f: to_set(world.play(to_mask(s), f))
    )
    names = {r.state: f"round {i + 1}" for i, r in enumerate(rounds)}
    plan = exact_plan(t, states.index(goal), config.horizon, allowed=t.sum(-1) > 0)
    successes = 0
    for _ in range(config.episodes):
        state = start
        for h in range(config.horizon, 0, -1):
            state = world.play(state, int(plan.policy[h, states.index(state)]))
            if state == goal or state & goal != goal:
                break
        successes += state == goal
    # how sure the first throw is: the fields as good under the models, the robot's arrival
    first, here = int(plan.policy[config.horizon, states.index(start)]), states.index(start)
    q = t[here] @ plan.value[config.horizon - 1]
    # the first throw's next state as the models predict and as the physics plays it
    transfer = measure_transfer(
        world, start, first, states, t, plan.value[config.horizon - 1],
        repeats=config.transfer_repeats, seed=config.seed,
    )  # fmt: skip
    # the policy's probability with sharp field boundaries (the spread steers the choice among
    # near-ties and blurs the probability); one (S, F, S) table held at a time
    if world.boundary_sd:
        t = None
        t = transition_model(replace(world, boundary_sd=0.0), states)
    value = policy_value(t, plan.policy, states.index(goal), config.horizon)
    desired = np.array([[0.0, world.heights(start)[first] + world.table_z]])
    v = throw(world.robot.aim(desired)).velocity_at_plane[0]
    return {
        "success_rate": rate,
        "paper_success_rate": PAPER_RATES[name],
        "rounds": [r.as_dict(names) for r in rounds],
        "success_rate_exact_planner": successes / config.episodes,
        "exact_planner_predicted": float(plan.value[config.horizon, states.index(start)]),
        "exact_planner_predicted_sharp": float(value[config.horizon, states.index(start)]),
        "exact_planner_first_field": first,
        "first_field_ties": int((q >= q.max() * (1 - 1e-9)).sum()),
        "first_throw_deg": float(np.degrees(np.arctan2(v[2], v[0]))),
        "first_throw_speed": float(np.hypot(v[0], v[2])),
        "transfer": transfer.as_dict(),
    }


@dataclass
class CombinedResult(Result):
    """What :func:`run_combined` measured.

    ``scenarios``: per scenario name (``SCENARIOS``) the paper planner's ``success_rate``
    and ``rounds`` (the paper's table), the paper's ``paper_success_rate``, and the exact
    planner's measured ``success_rate_exact_planner``, its ``exact_planner_predicted``
    success under the models, ``exact_planner_predicted_sharp`` (the same policy's under the
    models with sharp field boundaries) and its first field, and ``transfer``, that first
    throw's next state four ways (:meth:`experiments.arrival_transfer.ArrivalTransfer.as_dict`:
    frequencies, total-variation distances, the plan's value one throw later; the data
    set's and the robot's throw replayed ``transfer_repeats`` times). ``angle_choice``: the
    robot's impact direction, the angle the can network was trained on, the table height,
    the jitter and the fields' boundary sd (``boundary_sd``, m).
    """

    experiment_name: ClassVar[str] = "combined"

    scenarios: dict[str, dict]
    angle_choice: dict
    release_noise: bool
    proposals: str
    scale: str
    seconds: float

    def to_markdown(self) -> str:
        """The experiment's report, in Markdown (:meth:`~experiments.harness.config.Result.to_markdown`)."""
        tables = [table_markdown(n, s) for n, s in self.scenarios.items()]
        why = self.angle_choice
        lines = [
            "| scenario | paper | ours (paper planner) | ours (exact planner) |",
            "|---|---:|---:|---:|",
        ]
        for n, s in self.scenarios.items():
            lines.append(
                f"| {n} | {100 * s['paper_success_rate']:.2f} % | {100 * s['success_rate']:.2f} % "
                f"| {100 * s['success_rate_exact_planner']:.1f} % |"
            )
        head = (
            f"Robot impact direction {why['robot_impact_deg_mean']:.1f} deg; can network trained "
            f"on {why['chosen_angle']} ({why['angle_deg'][why['chosen_angle']]:.1f} deg), the "
            f"closest"
            + (f", at {why['training_speed']:.2f} m/s" if "training_speed" in why else "")
            + f"; table top {why['table_z']} m, aim jitter {1000 * why['jitter']:.1f} mm; "
            f"fields' boundaries read with sd {1000 * why.get('boundary_sd', 0.0):.2f} mm."
        )
        return "\n\n".join([head, *tables, "\n".join(lines)]) + "\n"

    def summary_rows(self, results) -> list[str]:
        """The paper's three scenarios, each beside its bound at the same table height."""
        table_z = str(self.angle_choice.get("table_z", ""))
        bounds = results["physics_bounds"].combined if "physics_bounds" in results else {}
        bounds = bounds.get(table_z, {})
        rows = []
        for name, table in TABLES.items():
            s, bound = self.scenarios[name], ""
            if name in bounds:
                bound = (
                    f"{percent(bounds[name]['success_bound'], 1)} held out, "
                    f"{percent(bounds[name]['success_in_sample'], 1)} in sample"
                )
            predicted = s.get("exact_planner_predicted")  # older results have none
            predicted = "" if predicted is None else f", predicted {percent(predicted, 1)}"
            rows.append(
                f"| §IV-C combined, {table}, {name.replace('_', ' ')} (table {table_z} m) | "
                f"{percent(s['paper_success_rate'])} | {percent(s['success_rate'])} (paper "
                f"planner); {percent(s['success_rate_exact_planner'], 1)} (exact planner"
                f"{predicted}) | {bound} |"
            )
        return rows


def run_combined(config: CombinedConfig) -> CombinedResult:
    """Train both networks and play the three scenarios with both planners."""
    started = time.perf_counter()
    data = can_dataset(
        config.data_dir, config.scale, progress=config.progress, executor=config.executor
    )
    world, why = build_world(config, data)
    scenarios = {
        name: run_scenario(world, name, config)
        for name in tqdm(SCENARIOS, desc="scenarios", disable=not config.progress)
    }
    return CombinedResult(
        scenarios=scenarios,
        angle_choice=why,
        release_noise=config.noise,
        proposals=config.proposals,
        scale=config.scale,
        seconds=time.perf_counter() - started,
    )


EXPERIMENTS = (
    Experiment(
        CombinedConfig,
        run_combined,
        CombinedResult,
        order=70,
        tiny={
            "scale": "tiny",
            "n_throws": 300,
            "bins": 2,
            "episodes": 1,
            "horizon": 1,
            "transfer_repeats": 2,
        },
        quick={"scale": "quick", "n_throws": 5000, "episodes": 10},
    ),
)
