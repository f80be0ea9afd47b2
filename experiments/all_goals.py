"""The combined system judged on every goal the physics can reach, beside the physics bound.

Goals are the stable sub-configurations of the full pyramid. For each table height:

1. **Simulation.** From every stable state the robot throws, with exact inverse kinematics,
   at every reachable height of the pyramid's near face (``step`` apart), each throw with
   the can world's aim jitter: ``train_repeats`` times with one seed (the robot's
   experience, which the learned system trains on) and ``bound_repeats`` times with
   another (the physics bound's, never seen by the learned system).
2. **Physics bound.** The empirical transitions of one half of the bound's repeats give
   the best plan within ``horizon`` throws (finite-horizon dynamic programming); its
   success is scored on the other half (held out), both ways round and averaged
   (:func:`cross_fitted_bound`). A goal is *reachable* when that held-out success is
   above zero.
3. **The learned system.** The can network (configuration before, aim height as the
   action, configuration after) is fitted by maximum likelihood on the robot's
   experience; the throw network on ``n_throws`` random throws. Aiming at a height means:
   the throw network's inverse gives the aim, its forward model the predicted hit (a
   Gaussian), which spreads the aim over the heights the can network knows; a hit beside
   the cans or outside the face changes nothing. That chain gives the learned transition
   ``P(next | state, aimed height)``.
4. **Planners, played in the world.** The exact planner maximises the learned probability
   of the goal within ``horizon`` throws and is played ``episodes`` times (fresh seeds);
   the paper's round planner takes, per round, every aim whose most probable outcome is
   the goal (or an intermediate goal) and plays each once.

Reported per goal: the bound, the exact planner's measured and predicted success, the
paper planner's success; overall, the mean of success / bound over reachable goals.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from inference import fit, predict
from inference.compiled import compile_parameter_query
from inference.planning import exact_plan, paper_planner, policy_value
from models.can_network import can_network, can_rows
from models.throw_network import TARGET, throw_data, throw_network
from sim2d import geometry
from sim2d.combined import CAN_BAND, exact_throws, explore, play_policy, play_throw
from sim2d.configurations import stable_configurations
from sim2d.executors import open_executor, parse_spec
from sim2d.throw import TARGET_AREA, ReleaseNoise, sample_targets, throw

__all__ = [
    "AllGoalsConfig",
    "AllGoalsResult",
    "GoalResult",
    "TableResult",
    "cross_fitted_bound",
    "plot",
    "run_all_goals",
]

TRAIN_SEED = 2  # the robot's experience; the physics bound uses seed 1, the can data set 0
BOUND_SEED = 1
PLAY_SEED = 3
#: the issue's goal: the exact planner's success over the bound, averaged over goals
GOAL_RATIO = 0.90


@dataclass(frozen=True)
class AllGoalsConfig:
    """What to simulate and how hard to test. Every number is checked on creation."""

    data_dir: str = "data"
    table_z: tuple[float, ...] = (0.75, 0.35)
    step: float = 0.005
    train_repeats: int = 6
    bound_repeats: int = 24
    horizon: int = 6
    episodes: int = 50
    n_throws: int = 29_000
    bins: int = 16
    jitter: float = 0.003
    noise: bool = False
    seed: int = 0
    executor: str | None = None
    progress: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "table_z", tuple(float(z) for z in self.table_z))
        checks = {
            "table_z": bool(self.table_z) and all(0.0 < z < 2.0 for z in self.table_z),
            "step": 0.0 < self.step <= 0.1,
            "train_repeats": self.train_repeats >= 1,
            "bound_repeats": self.bound_repeats >= 2 and self.bound_repeats % 2 == 0,
            "horizon": 1 <= self.horizon <= 20,
            "episodes": self.episodes >= 1,
            "n_throws": self.n_throws >= 100,
            "bins": 1 <= self.bins <= 64,
            "jitter": 0.0 <= self.jitter <= 0.05,
            "seed": self.seed >= 0,
        }
        bad = [name for name, ok in checks.items() if not ok]
        if bad:
            expected = {
                "table_z": "heights in (0, 2) m, at least one",
                "step": "in (0, 0.1] m",
                "train_repeats": ">= 1",
                "bound_repeats": "an even number >= 2 (half plan, half score)",
                "horizon": "in 1..20",
                "episodes": ">= 1",
                "n_throws": ">= 100",
                "bins": "in 1..64",
                "jitter": "in [0, 0.05] m",
                "seed": ">= 0",
            }
            raise ValueError(
                "; ".join(f"{b} = {getattr(self, b)!r}: expected {expected[b]}" for b in bad)
            )
        if self.executor is not None:
            parse_spec(self.executor)


@dataclass
class GoalResult:
    """One goal at one table height (success rates are fractions)."""

    goal: int
    removed: list[int]
    bound: float
    bound_in_sample: float
    exact_measured: float
    exact_predicted: float
    exact_throws: float
    paper_measured: float
    paper_plays: int


@dataclass
class TableResult:
    """Every reachable goal at one table height, and the overall figures."""

    table_z: float
    impact_deg: float
    n_heights: int
    n_goals: int
    goals: list[GoalResult]
    exact_over_bound: float
    paper_over_bound: float
    exact_total_over_bound_total: float
    exact_over_bound_in_sample: float
    seconds: float

    @property
    def reachable(self) -> int:
        return len(self.goals)


@dataclass
class AllGoalsResult:
    config: AllGoalsConfig
    tables: list[TableResult]
    seconds: float = 0.0
    goal_ratio: float = GOAL_RATIO
    extra: dict = field(default_factory=dict)

    def to_json(self) -> str:
        data = asdict(self)
        data["config"]["table_z"] = list(self.config.table_z)
        return json.dumps(data, indent=2)

    @classmethod
    def from_json(cls, text: str) -> AllGoalsResult:
        data = json.loads(text)
        config = AllGoalsConfig(**data.pop("config"))
        tables = [
            TableResult(**(t | {"goals": [GoalResult(**g) for g in t["goals"]]}))
            for t in data.pop("tables")
        ]
        return cls(config, tables, **data)

    def to_markdown(self) -> str:
        c = self.config
        lines = [
            f"**Every reachable goal** (within {c.horizon} throws; bound: the best plan on "
            f"half of {c.bound_repeats} simulated repeats per aim height, scored on the other "
            f"half, both ways round; learned system trained on "
            f"{c.train_repeats} other repeats; exact planner played {c.episodes} times per goal)",
            "",
            "| table top (m) | robot impact (deg) | reachable goals "
            "| exact planner / bound | paper planner / bound | goal "
            "| exact planner / in-sample bound |",
            "|---|---|---|---|---|---|---|",
        ]
        for t in self.tables:
            met = "met" if t.exact_over_bound >= self.goal_ratio else "missed"
            lines.append(
                f"| {t.table_z} | {t.impact_deg:.1f} | {t.reachable} of {t.n_goals} "
                f"| {100 * t.exact_over_bound:.1f} % | {100 * t.paper_over_bound:.1f} % "
                f"| >= {100 * self.goal_ratio:.0f} %: {met} "
                f"| {100 * t.exact_over_bound_in_sample:.1f} % |"
            )
        for t in self.tables:
            lines += [
                "",
                f"Table top {t.table_z} m, per goal (cans removed; success in %):",
                "",
                "| cans removed | bound (in sample) | exact planner (predicted) | throws "
                "| paper planner |",
                "|---|---|---|---|---|",
            ]
            for g in sorted(t.goals, key=lambda g: (len(g.removed), g.removed)):
                lines.append(
                    f"| {' '.join(map(str, g.removed))} | {100 * g.bound:.1f} "
                    f"({100 * g.bound_in_sample:.1f}) "
                    f"| {100 * g.exact_measured:.1f} ({100 * g.exact_predicted:.1f}) "
                    f"| {g.exact_throws:.2f} | {100 * g.paper_measured:.1f} |"
                )
        return "\n".join(lines) + "\n"


# --- the learned side --------------------------------------------------------------------


@dataclass(frozen=True)
class Robot:
    """The throw network: aims for desired hits and the hits it predicts for aims."""

    net: object
    params: object
    query: object

    def aim(self, hits: np.ndarray) -> np.ndarray:
        aims = self.query.infer({"end.hit": torch.as_tensor(hits)}).mean.numpy()
        return np.clip(aims, TARGET_AREA.low, TARGET_AREA.high)

    def hit_distribution(self, aims: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        mix = predict(
            self.net, self.params, {"action": ["throw"] * len(aims), "param.target": aims}
        )
        return mix.continuous["hit"].mean.numpy(), mix.continuous["hit"].cov.numpy()


def train_robot(n_throws: int, bins: int, seed: int, noise: ReleaseNoise | None) -> Robot:
    """The throw network fitted on ``n_throws`` random throws."""
    rng = np.random.default_rng(seed)
    targets = sample_targets(n_throws, rng)
    hits = throw(targets, rng=rng, noise=noise).hit
    net = throw_network((bins, bins))
    params = fit(net, throw_data(net, targets, hits)).params
    return Robot(net, params, compile_parameter_query(net, params, TARGET))


def can_model(states: list[int], heights: np.ndarray, outcomes: dict[int, np.ndarray]):
    """The can network with aim heights as actions, fitted on the robot's experience.

    Returns ``P[s, b, s']``: the predicted next state for each state and height bin.
    """
    net = can_network(states, len(heights))
    starts, actions, ends = [], [], []
    for s, nxt in outcomes.items():
        starts.append(np.full(nxt.size, s))
        actions.append(np.repeat(np.arange(nxt.shape[0]), nxt.shape[1]))
        ends.append(nxt.reshape(-1))
    rows = can_rows(net, np.concatenate(starts), np.concatenate(actions), np.concatenate(ends))
    params = fit(net, rows).params
    n_a = len(heights)
    probs = torch.zeros(len(states), n_a, len(states), dtype=torch.float64)
    for i, s in enumerate(states):
        ev = {
            "initial.config": np.full(n_a, s),
            "initial.count": np.full(n_a, bin(s).count("1")),
            "action": list(net.actions),
        }
        probs[i] = predict(net, params, ev).discrete["config"].double()
    return probs


def learned_transition(
    can_probs: torch.Tensor, robot: Robot, heights: np.ndarray, table_z: float
) -> tuple[torch.Tensor, np.ndarray]:
    """``T[s, a, s']`` of aiming at ``heights[a]``, and the robot's aims ``(A, 2)``."""
    desired = np.stack([np.zeros_like(heights), heights + table_z], -1)
    aims = robot.aim(desired)
    mean, cov = robot.hit_distribution(aims)
    half = np.diff(heights).mean() / 2 if len(heights) > 1 else 0.01
    edges = torch.as_tensor(np.concatenate([heights - half, [heights[-1] + half]]))
    z = torch.distributions.Normal(
        torch.as_tensor(mean[:, 1] - table_z)[:, None],
        torch.as_tensor(np.sqrt(cov[:, 1, 1]))[:, None],
    )
    cdf = z.cdf(edges[None, :])
    p_bin = cdf[:, 1:] - cdf[:, :-1]  # (aimed, hit bin); the rest falls off the face
    y = torch.distributions.Normal(
        torch.as_tensor(mean[:, 0]), torch.as_tensor(np.sqrt(cov[:, 0, 0]))
    )
    p_band = y.cdf(torch.tensor(CAN_BAND)) - y.cdf(torch.tensor(-CAN_BAND))
    p_hit = p_band[:, None] * p_bin  # (A, B)
    t = torch.einsum("ab,sbt->sat", p_hit, can_probs)
    stay = (1 - p_hit.sum(-1)).clamp_min(0.0)  # (A,)
    idx = torch.arange(can_probs.shape[0])
    t[idx, :, idx] += stay[None, :]
    return t, aims


def empirical_transition(
    states: list[int], outcomes: dict[int, np.ndarray], cols: slice
) -> torch.Tensor:
    """``T[s, a, s']`` counted from the simulated outcomes' repeats ``cols``."""
    index = {s: i for i, s in enumerate(states)}
    n_a = next(iter(outcomes.values())).shape[0]
    t = torch.zeros(len(states), n_a, len(states), dtype=torch.float64)
    for s in states:
        if s not in outcomes:  # never reached within the horizon, or no cans: stays
            t[index[s], :, index[s]] = 1.0
            continue
        nxt = outcomes[s][:, cols]
        for a in range(n_a):
            values, counts = np.unique(nxt[a], return_counts=True)
            t[index[s], a, [index[int(v)] for v in values]] = torch.as_tensor(
                counts / counts.sum(), dtype=torch.float64
            )
    return t


def cross_fitted_bound(
    halves: tuple[torch.Tensor, torch.Tensor], goal: int, start: int, horizon: int
) -> tuple[float, float]:
    """The best plan's success from ``start``: planned on one half of the simulations and
    scored on the other, both ways round, averaged (held out); and the plans' own values
    on the halves they were made on, averaged (in sample).

    The held-out figure is low by the luck the plan's choice fitted in its half, the
    in-sample one high by the same luck; the true best lies between them.
    """
    held, in_sample = 0.0, 0.0
    for made, scored in ((0, 1), (1, 0)):
        plan = exact_plan(halves[made], goal, horizon)
        value = policy_value(halves[scored], plan.policy, goal, horizon)
        held += float(value[horizon, start]) / 2
        in_sample += float(plan.value[horizon, start]) / 2
    return held, in_sample


def _paper_task(start, goal, most_probable, states, aims, table_z, jitter, noise, seed):
    """The paper planner towards ``goal``, playing in the world; an executor task."""
    index = {s: i for i, s in enumerate(states)}
    to_set = lambda mask: frozenset(geometry.mask_to_cans(mask))  # noqa: E731
    rng = np.random.default_rng(np.random.SeedSequence([seed, goal]))
    stable = frozenset(states)

    def propose(s, g):
        s, g = geometry.cans_to_mask(s), geometry.cans_to_mask(g)
        if s not in index or g not in index:
            return []
        return np.flatnonzero(most_probable[index[s]] == index[g]).tolist()

    def play(s, a):
        result = throw(aims[a : a + 1], rng=rng, noise=noise)
        nxt = play_throw(
            geometry.cans_to_mask(s), result.hit[0], result.velocity_at_plane[0],
            table_z=table_z, jitter=jitter, seed=int(rng.integers(2**32)), stable=stable,
        )  # fmt: skip
        return to_set(nxt)

    rounds, rate = paper_planner(to_set(start), to_set(goal), propose, play, max_rounds=200)
    return {"rate": float(rate), "plays": sum(len(r.actions) for r in rounds)}


def impact_angle(robot: Robot, heights: np.ndarray, table_z: float) -> float:
    """Mean descent angle (degrees, negative: downwards) of the robot's ball at the face."""
    aims = robot.aim(np.stack([np.zeros_like(heights), heights + table_z], -1))
    v = throw(aims).velocity_at_plane
    return float(np.degrees(np.arctan2(v[:, 2], v[:, 0])).mean())


def run_table(config: AllGoalsConfig, table_z: float, robot: Robot, executor) -> TableResult:
    started = time.perf_counter()
    states = sorted(stable_configurations())
    full = geometry.FULL_PYRAMID
    heights = exact_throws(config.step, table_z=table_z)[0]
    base = Path(config.data_dir)
    common = dict(
        depth=config.horizon, table_z=table_z, step=config.step, jitter=config.jitter,
        executor=executor, progress=config.progress,
    )  # fmt: skip
    name = f"robot_throws_{table_z}_{config.step}_{config.jitter}"
    train = explore(
        base / f"{name}_{config.train_repeats}_seed{TRAIN_SEED}", full,
        repeats=config.train_repeats, seed=TRAIN_SEED, **common,
    )  # fmt: skip
    bound = explore(
        base / f"{name}_{config.bound_repeats}_seed{BOUND_SEED}", full,
        repeats=config.bound_repeats, seed=BOUND_SEED, **common,
    )  # fmt: skip
    half = config.bound_repeats // 2
    halves = (
        empirical_transition(states, bound, slice(None, half)),
        empirical_transition(states, bound, slice(half, None)),
    )
    t_learned, aims = learned_transition(can_model(states, heights, train), robot, heights, table_z)
    most_probable = t_learned.argmax(-1).numpy()
    index = {s: i for i, s in enumerate(states)}
    h = config.horizon
    goals = [g for g in states if g != full]
    rows, futures = {}, {}
    for g in goals:
        held, in_sample = cross_fitted_bound(halves, index[g], index[full], h)
        if held <= 0:
            continue
        learned = exact_plan(t_learned, index[g], h)
        rows[g] = dict(
            bound=held,
            bound_in_sample=in_sample,
            exact_predicted=float(learned.value[h, index[full]]),
        )
        play = dict(
            episodes=config.episodes, table_z=table_z, jitter=config.jitter,
            noise=ReleaseNoise() if config.noise else None, seed=PLAY_SEED * 1_000_003 + g,
        )  # fmt: skip
        futures[g] = (
            executor.submit(play_policy, full, g, learned.policy.numpy(), states, aims, **play),
            executor.submit(
                _paper_task, full, g, most_probable, states, aims, table_z, config.jitter,
                play["noise"], PLAY_SEED,
            ),
        )  # fmt: skip
    results = []
    bar = _bar(len(futures), f"goals (table {table_z} m)", config.progress)
    for g, (exact_f, paper_f) in futures.items():
        episodes, paper = exact_f.result(), paper_f.result()
        bar.update(1)
        results.append(
            GoalResult(
                goal=g,
                removed=sorted(set(range(geometry.N_CANS)) - set(geometry.mask_to_cans(g))),
                exact_measured=float(np.mean(episodes["end"] == g)),
                exact_throws=float(episodes["throws"].mean()),
                paper_measured=paper["rate"],
                paper_plays=paper["plays"],
                **rows[g],
            )
        )
    bar.close()
    bounds = np.array([r.bound for r in results])
    in_sample = np.array([r.bound_in_sample for r in results])
    exact = np.array([r.exact_measured for r in results])
    paper = np.array([r.paper_measured for r in results])
    return TableResult(
        table_z=table_z,
        impact_deg=impact_angle(robot, heights, table_z),
        n_heights=len(heights),
        n_goals=len(goals),
        goals=results,
        exact_over_bound=float(np.mean(exact / bounds)) if len(results) else math.nan,
        paper_over_bound=float(np.mean(paper / bounds)) if len(results) else math.nan,
        exact_over_bound_in_sample=float(np.mean(exact / in_sample)) if len(results) else math.nan,
        exact_total_over_bound_total=float(exact.sum() / bounds.sum())
        if len(results)
        else math.nan,
        seconds=time.perf_counter() - started,
    )


def _bar(total: int, desc: str, progress: bool):
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, disable=not progress)


def run_all_goals(config: AllGoalsConfig) -> AllGoalsResult:
    """Measure the bound and both planners on every reachable goal at each table height."""
    started = time.perf_counter()
    noise = ReleaseNoise() if config.noise else None
    torch.set_num_threads(1)
    robot = train_robot(config.n_throws, config.bins, config.seed, noise)
    with open_executor(config.executor) as executor:
        tables = [run_table(config, z, robot, executor) for z in config.table_z]
    return AllGoalsResult(config, tables, time.perf_counter() - started)


def plot(result: AllGoalsResult, path) -> None:
    """Per goal and table height: the bound, the exact planner (measured and predicted) and
    the paper planner, goals ordered by their bound."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(result.tables)
    fig, axes = plt.subplots(n, 1, figsize=(12.5, 3.4 * n), squeeze=False)
    for ax, t in zip(axes[:, 0], result.tables, strict=True):
        goals = sorted(t.goals, key=lambda g: (-g.bound, len(g.removed), g.removed))
        x = np.arange(len(goals))
        ax.bar(x, [100 * g.bound for g in goals], color="0.85", label="physics bound (held out)")
        ax.plot(x, [100 * g.bound_in_sample for g in goals], "_", color="0.4", ms=9,
                label="physics bound (in sample)")  # fmt: skip
        ax.plot(x, [100 * g.exact_measured for g in goals], "o", color="C0",
                label=f"exact planner, measured ({100 * t.exact_over_bound:.0f} % of bound)")  # fmt: skip
        ax.plot(x, [100 * g.exact_predicted for g in goals], "o", mfc="none", color="C0",
                label="exact planner, predicted by the models")  # fmt: skip
        ax.plot(x, [100 * g.paper_measured for g in goals], "x", color="C3",
                label=f"paper planner ({100 * t.paper_over_bound:.0f} % of bound)")  # fmt: skip
        ax.set_xticks(x, [" ".join(map(str, g.removed)) for g in goals], rotation=70, fontsize=7)
        ax.set_ylabel("success (%)")
        ax.set_ylim(0, 105)
        ax.set_title(
            f"table top {t.table_z} m (ball descends at {-t.impact_deg:.0f} deg): "
            f"{t.reachable} reachable goals, cans removed below"
        )
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
