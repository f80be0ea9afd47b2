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
   (:func:`experiments.physics_bounds.cross_fitted_bound`). A goal is *reachable* when that held-out success is
   above zero.
3. **The learned system.** The can network (configuration before, aim height as the
   action, configuration after) is fitted by maximum likelihood on the robot's
   experience; the throw network on ``n_throws`` random throws. Aiming at a height means:
   the throw network's inverse gives the aim, its forward model the predicted hit (a
   Gaussian), which spreads the aim over the heights the can network knows, read among
   bins whose boundaries are as uncertain as the training throws were spread (their
   jitter; ``boundary_spread``); a hit beside the cans or outside the face changes nothing. That chain gives the learned transition
   ``P(next | state, aimed height)``.
4. **Planners, played in the world.** The exact planner maximises the learned probability
   of the goal within ``horizon`` throws and is played ``episodes`` times (fresh seeds);
   the paper's round planner takes, per round, every aim whose most probable outcome is
   the goal (or an intermediate goal) and plays each once.

Reported per goal: the bound, the exact planner's measured and predicted success, the
paper planner's success; overall, the mean of success / bound over reachable goals.

**Calibration.** The exact planner's predicted success is the value of its policy under
the learned transition. Beside it, the same policy's value under the learned transition
with sharp bins (no boundary spread: the spread steers the choice among near-ties, and
blurs the probability) and under the physics' own transition (the bound's throws, both
halves: what the world gives that policy, measured on throws neither the learned system
nor the plays used). Each is compared with the measured success over the goals
(:func:`experiments.calibration.reliability`: the reliability diagram and its expected
calibration error), so that the gap between prediction and measurement is split into what
the learned transition gets wrong and what the plays' own scatter leaves.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch
from effect_networks.experiments.aimed_heights import (
    can_model,
    impact_angle,
    learned_transition,
    train_robot,
)
from effect_networks.experiments.calibration import plot_reliability, reliability
from effect_networks.experiments.cans import SimulationSettings
from effect_networks.experiments.combined import Robot
from effect_networks.experiments.harness.config import (
    ConfigError,
    Result,
    check_choice,
    check_float,
    check_int,
    percent,
)
from effect_networks.experiments.harness.registry import Experiment
from effect_networks.experiments.physics_bounds import (
    BOUND_SEED,
    cross_fitted_bound,
    empirical_transition,
    robot_throws,
)
from effect_networks.experiments.round_planner import paper_planner
from effect_networks.experiments.throwing import MAX_BINS
from effect_networks.inference.sequences.dynamic_programming import exact_plan, policy_value
from effect_networks.sim2d import geometry
from effect_networks.sim2d.analytic_throw import TARGET_AREA, ReleaseNoise, throw
from effect_networks.sim2d.clock import simulating
from effect_networks.sim2d.combined import (
    TABLE_TOP_Z,
    exact_throws,
    play_policy,
    play_throw,
)
from effect_networks.sim2d.configurations import stable_configurations
from effect_networks.sim2d.executors import open_executor

__all__ = [
    "AllGoalsConfig",
    "AllGoalsResult",
    "plot",
    "run_all_goals",
]

TRAIN_SEED = 2  # the robot's experience; the physics bound's uses seed 1, the can data set 0
PLAY_SEED = 3
#: the goal: the exact planner's success over the bound, averaged over goals
GOAL_RATIO = 0.90
#: The exact planner's success predictions compared with the measured one, by their key per goal.
PREDICTIONS = {
    "learned model": "exact_predicted",
    "learned model, sharp bins": "exact_predicted_sharp",
    "physics' own transitions": "exact_physics",
}
MAX_STEP = 0.1  # m between aim heights: coarser says little about a 6.4 cm can
MAX_HORIZON = 20  # throws
MAX_JITTER = 0.05  # m
BOUNDARY_SPREADS = ("jitter", "none")  # how sharp the aim heights' bins are, see AllGoalsConfig


@dataclass(frozen=True)
class AllGoalsConfig(SimulationSettings):
    """Settings of :func:`run_all_goals`; every field is checked on construction.

    Where the simulations are saved and run: :class:`experiments.cans.SimulationSettings`.

    Attributes
    ----------
    table_z : tuple of float
        Table-top heights above the robot's floor, m; one experiment each.
    step : float
        m between the aim heights on the pyramid's face (the can network's actions).
    train_repeats : int
        The robot's experience: throws per state and aim height.
    bound_repeats : int
        The physics bound's throws per state and aim height (even: half plan, half score).
    horizon : int
        Throws allowed per goal.
    episodes : int
        Plays of the exact planner's policy per goal.
    n_throws, bins : int
        The throw network's training throws and clusters per axis.
    jitter : float
        The can world's aim jitter added to every throw's entry height, m.
    boundary_spread : str
        How a predicted hit is read as an aim height's bin
        (:func:`experiments.combined.hit_gaussians`): ``"jitter"``, among bins with
        boundaries as uncertain as the robot's training throws were spread about their
        aim height (sd ``jitter``: the world moves each throw's entry height by its aim
        jitter); ``"none"``, sharp half a step either side of each height.
    noise : bool
        Throw with release noise.
    seed : int
        Seeds the throw network's data.
    progress : bool
        Progress bars.
    """

    table_z: tuple[float, ...] = (TABLE_TOP_Z, 0.35)
    step: float = 0.005
    train_repeats: int = 6
    bound_repeats: int = 24
    horizon: int = 6
    episodes: int = 50
    n_throws: int = 29_000
    bins: int = 16
    jitter: float = 0.003
    boundary_spread: str = "jitter"
    noise: bool = False
    seed: int = 0
    progress: bool = True

    def __post_init__(self) -> None:
        super().__post_init__()
        heights = tuple(self.table_z) if isinstance(self.table_z, (list, tuple)) else None
        if not heights:
            raise ConfigError("table_z", f"{self.table_z!r}: expected one or more heights, m")
        object.__setattr__(
            self,
            "table_z",
            tuple(
                check_float("table_z", z, 0.0, TARGET_AREA.z_max, low_open=True, unit="m")
                for z in heights
            ),
        )
        check_float("step", self.step, 0.0, MAX_STEP, low_open=True, unit="m")
        check_int("train_repeats", self.train_repeats, 1)
        check_int("bound_repeats", self.bound_repeats, 2)
        if self.bound_repeats % 2:
            raise ConfigError(
                "bound_repeats", f"{self.bound_repeats} is odd; expected an even number"
            )
        check_int("horizon", self.horizon, 1, MAX_HORIZON)
        check_int("episodes", self.episodes, 1)
        check_int("n_throws", self.n_throws, 10)
        check_int("bins", self.bins, 1, MAX_BINS)
        check_float("jitter", self.jitter, 0.0, MAX_JITTER, unit="m")
        check_choice("boundary_spread", self.boundary_spread, BOUNDARY_SPREADS)
        check_choice("noise", self.noise, (False, True))
        check_int("seed", self.seed, 0)

    def to_dict(self) -> dict:
        """The settings as JSON values."""
        return asdict(self) | {"data_dir": str(self.data_dir), "table_z": list(self.table_z)}


@dataclass
class AllGoalsResult(Result):
    """What :func:`run_all_goals` measured.

    ``tables``: per table height, ``table_z``, the robot's ``impact_deg``, ``n_heights``
    (aim heights), ``n_goals`` and ``reachable`` goals, the overall figures
    ``exact_over_bound`` and ``paper_over_bound`` (means over reachable goals of each
    planner's measured success over the held-out bound), ``exact_over_bound_in_sample``,
    ``exact_total_over_bound_total`` and ``seconds``; and ``goals``, one dict per
    reachable goal: ``goal`` (mask), ``removed`` (cans), ``bound`` (held out),
    ``bound_in_sample``, ``exact_measured``, ``exact_predicted``, ``exact_predicted_sharp``
    and ``exact_physics`` (the policy's value with sharp bins and under the physics' own
    transitions), ``exact_throws`` (mean throws used), ``paper_measured``, ``paper_plays``;
    and ``calibration``, per prediction of ``PREDICTIONS`` its
    :func:`~experiments.calibration.reliability` against the measured success. Success
    figures are fractions.
    """

    experiment_name: ClassVar[str] = "all_goals"

    settings: dict
    tables: list[dict]
    goal_ratio: float
    seconds: float

    def to_markdown(self) -> str:
        """The experiment's report, in Markdown (:meth:`~experiments.harness.config.Result.to_markdown`)."""
        c = self.settings
        lines = [
            f"**Every reachable goal** (within {c['horizon']} throws; bound: the best plan on "
            f"half of {c['bound_repeats']} simulated repeats per aim height, scored on the "
            f"other half, both ways round; learned system trained on {c['train_repeats']} "
            f"other repeats; exact planner played {c['episodes']} times per goal)",
            "",
            "| table top (m) | robot impact (deg) | reachable goals "
            "| exact planner / bound | paper planner / bound | goal "
            "| exact planner / in-sample bound |",
            "|---|---|---|---|---|---|---|",
        ]
        for t in self.tables:
            met = "met" if t["exact_over_bound"] >= self.goal_ratio else "missed"
            lines.append(
                f"| {t['table_z']} | {t['impact_deg']:.1f} | {t['reachable']} of {t['n_goals']} "
                f"| {100 * t['exact_over_bound']:.1f} % | {100 * t['paper_over_bound']:.1f} % "
                f"| >= {100 * self.goal_ratio:.0f} %: {met} "
                f"| {100 * t['exact_over_bound_in_sample']:.1f} % |"
            )
        for t in self.tables:
            lines += [
                "",
                f"Table top {t['table_z']} m, per goal (cans removed; success in %):",
                "",
                "| cans removed | bound (in sample) | exact planner (predicted) | throws "
                "| paper planner |",
                "|---|---|---|---|---|",
            ]
            for g in sorted(t["goals"], key=lambda g: (len(g["removed"]), g["removed"])):
                lines.append(
                    f"| {' '.join(map(str, g['removed']))} | {100 * g['bound']:.1f} "
                    f"({100 * g['bound_in_sample']:.1f}) "
                    f"| {100 * g['exact_measured']:.1f} ({100 * g['exact_predicted']:.1f}) "
                    f"| {g['exact_throws']:.2f} | {100 * g['paper_measured']:.1f} |"
                )
        lines += self._calibration_lines()
        return "\n".join(lines) + "\n"

    def _calibration_lines(self) -> list[str]:
        """Per table height, each success prediction against the measured success."""
        tables = [t for t in self.tables if t.get("calibration")]
        if not tables:
            return []
        lines = [
            "",
            "**Calibration**: the exact planner's success predicted for its own policy, against "
            "the success measured by playing it, over the reachable goals (ECE: the expected "
            "calibration error over 10 bins of the prediction; reliability diagram "
            "`all_goals_reliability.png`). Beside the learned model's prediction, the same "
            "policy's value with sharp bins (no boundary spread) and under the physics' own "
            "transitions (the bound's throws): what is left between the last and the "
            "measurement is the plays' own scatter; between the first and the last, the "
            "learned transitions' error.",
            "",
            "| table top (m) | prediction | ECE (points) | mean gap per goal (points) "
            "| goals within 5 points | mean predicted | mean measured |",
            "|---|---|---:|---:|---:|---:|---:|",
        ]
        for t in tables:
            for name, r in t["calibration"].items():
                if not r["n"]:
                    continue
                lines.append(
                    f"| {t['table_z']} | {name} | {100 * r['ece']:.1f} | {100 * r['mean_abs']:.1f} "
                    f"| {100 * r['within']:.0f} % | {100 * r['mean_predicted']:.1f} % "
                    f"| {100 * r['mean_measured']:.1f} % |"
                )
        return lines

    def figures(self, out: Path) -> list[Path]:
        """Draw the goals' figure, ``all_goals.png``, and the reliability diagrams into ``out``."""
        plot(self, out / "all_goals.png")
        panels = [
            (f"table top {t['table_z']} m, {t['reachable']} goals", t["calibration"])
            for t in self.tables
            if t.get("calibration")
        ]
        if not panels:
            return [out / "all_goals.png"]
        return [out / "all_goals.png", plot_reliability(panels, out / "all_goals_reliability.png")]

    def summary_rows(self, results) -> list[str]:
        """Per table height, every goal the bound reaches: both planners beside the bound."""
        rows = []
        for t in self.tables:

            def mean(key, goals=t["goals"]):
                return sum(g[key] for g in goals) / len(goals) if goals else None

            rows.append(
                f"| combined, beyond the paper: every goal reachable within "
                f"{self.settings['horizon']} throws (table {t['table_z']} m, {t['reachable']} "
                f"goals) | - | exact planner {percent(mean('exact_measured'), 1)} mean success, "
                f"{percent(t['exact_over_bound'], 1)} of the bound per goal on average "
                f"(goal {percent(self.goal_ratio, 0)}); paper planner "
                f"{percent(mean('paper_measured'), 1)}, {percent(t['paper_over_bound'], 1)} | "
                f"{percent(mean('bound'), 1)} mean held out, "
                f"{percent(mean('bound_in_sample'), 1)} in sample |"
            )
        return rows


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


def run_table(config: AllGoalsConfig, table_z: float, robot: Robot, executor) -> dict:
    """One table height's entry of ``AllGoalsResult.tables``."""
    started = time.perf_counter()
    states = sorted(stable_configurations())
    full = geometry.FULL_PYRAMID
    heights = exact_throws(config.step, table_z=table_z)[0]
    common = dict(
        table_z=table_z, step=config.step, jitter=config.jitter, horizon=config.horizon,
        executor=executor, progress=config.progress,
    )  # fmt: skip
    train = robot_throws(config.data_dir, repeats=config.train_repeats, seed=TRAIN_SEED, **common)
    bound = robot_throws(config.data_dir, repeats=config.bound_repeats, seed=BOUND_SEED, **common)
    half = config.bound_repeats // 2
    halves = (
        empirical_transition(states, bound, slice(None, half)),
        empirical_transition(states, bound, slice(half, None)),
    )
    spread = config.jitter if config.boundary_spread == "jitter" else 0.0
    can = can_model(states, heights, train)
    t_learned, aims = learned_transition(can, robot, heights, table_z, spread)
    t_sharp = learned_transition(can, robot, heights, table_z)[0] if spread else t_learned
    t_physics = (halves[0] + halves[1]) / 2
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

        def value_under(transition, policy=learned.policy, goal=index[g]):
            return float(policy_value(transition, policy, goal, h)[h, index[full]])

        rows[g] = dict(
            bound=held,
            bound_in_sample=in_sample,
            exact_predicted=float(learned.value[h, index[full]]),
            exact_predicted_sharp=value_under(t_sharp),
            exact_physics=value_under(t_physics),
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
        with simulating():  # the workers play the episodes
            episodes, paper = exact_f.result(), paper_f.result()
        bar.update(1)
        results.append(
            rows[g]
            | dict(
                goal=g,
                removed=sorted(set(range(geometry.N_CANS)) - set(geometry.mask_to_cans(g))),
                exact_measured=float(np.mean(episodes["end"] == g)),
                exact_throws=float(episodes["throws"].mean()),
                paper_measured=paper["rate"],
                paper_plays=paper["plays"],
            )
        )
    bar.close()

    def mean_ratio(key: str, over: str) -> float:
        if not results:
            return math.nan
        return float(np.mean([r[key] / r[over] for r in results]))

    return dict(
        table_z=table_z,
        impact_deg=impact_angle(robot, heights, table_z),
        n_heights=len(heights),
        n_goals=len(goals),
        reachable=len(results),
        exact_over_bound=mean_ratio("exact_measured", "bound"),
        paper_over_bound=mean_ratio("paper_measured", "bound"),
        exact_over_bound_in_sample=mean_ratio("exact_measured", "bound_in_sample"),
        exact_total_over_bound_total=(
            sum(r["exact_measured"] for r in results) / sum(r["bound"] for r in results)
            if results
            else math.nan
        ),
        seconds=time.perf_counter() - started,
        goals=results,
        calibration={
            name: reliability([r[key] for r in results], [r["exact_measured"] for r in results])
            for name, key in PREDICTIONS.items()
        },
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
    return AllGoalsResult(
        settings=config.to_dict(),
        tables=tables,
        goal_ratio=GOAL_RATIO,
        seconds=time.perf_counter() - started,
    )


def plot(result: AllGoalsResult, path) -> None:
    """Per goal and table height: the bound, the exact planner and the paper planner.

    The exact planner measured and predicted; goals ordered by their bound.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(result.tables)
    fig, axes = plt.subplots(n, 1, figsize=(12.5, 3.4 * n), squeeze=False)
    for ax, t in zip(axes[:, 0], result.tables, strict=True):
        goals = sorted(t["goals"], key=lambda g: (-g["bound"], len(g["removed"]), g["removed"]))
        x = np.arange(len(goals))

        def percent(key, goals=goals):
            return [100 * g[key] for g in goals]

        ax.bar(x, percent("bound"), color="0.85", label="physics bound (held out)")
        ax.plot(x, percent("bound_in_sample"), "_", color="0.4", ms=9,
                label="physics bound (in sample)")  # fmt: skip
        ax.plot(x, percent("exact_measured"), "o", color="C0",
                label=f"exact planner, measured ({100 * t['exact_over_bound']:.0f} % of bound)")  # fmt: skip
        ax.plot(x, percent("exact_predicted"), "o", mfc="none", color="C0",
                label="exact planner, predicted by the models")  # fmt: skip
        ax.plot(x, percent("paper_measured"), "x", color="C3",
                label=f"paper planner ({100 * t['paper_over_bound']:.0f} % of bound)")  # fmt: skip
        labels = [" ".join(map(str, g["removed"])) for g in goals]
        ax.set_xticks(x, labels, rotation=70, fontsize=7)
        ax.set_ylabel("success (%)")
        ax.set_ylim(0, 105)
        ax.set_title(
            f"table top {t['table_z']} m (ball descends at {-t['impact_deg']:.0f} deg): "
            f"{t['reachable']} reachable goals, cans removed below"
        )
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


#: A first look: the standard table only, coarser heights, fewer repeats and plays.
QUICK = {
    "table_z": (TABLE_TOP_Z,),
    "step": 0.01,
    "train_repeats": 2,
    "bound_repeats": 4,
    "episodes": 10,
    "n_throws": 5000,
    "bins": 8,
}

EXPERIMENTS = (
    Experiment(
        AllGoalsConfig,
        run_all_goals,
        AllGoalsResult,
        order=90,
        tiny={
            "table_z": (TABLE_TOP_Z,),
            "step": 0.05,
            "train_repeats": 1,
            "bound_repeats": 2,
            "horizon": 1,
            "episodes": 1,
            "n_throws": 300,
            "bins": 2,
        },
        quick=QUICK,
    ),
)
