"""Beyond the paper: learn the can network from a fraction of the throws (active exploration).

Table I's can network is fitted on every 0° throw of the can data set (every stable
configuration x every throwable field x its repeats). Here a learner chooses which
throws to make (:func:`inference.design.active.explore`) and the learning curve of Table I's
exact fraction against the number of throws used is measured for each strategy, beside
the network fitted on every throw.

* **Pool and oracle.** The pool is the 0° throwable throws
  :func:`experiments.cans.fit_can_network` fits on: one candidate per recorded throw,
  so each (configuration, field) pair is listed once per recorded repeat and can be played at most that often.
  Playing candidate ``i`` returns the end configuration and count that recorded throw
  reached. The oracle is fair: every recorded throw is an independent draw of the world
  (its own seeded aim jitter), the learner sees only the throws it asks for, and the
  full-data network is fitted on exactly the same throws, so the curves and the
  full-data figure share one source and no simulation noise between them.
* **Scoring on held-out replays.** Table I's cases
  (:func:`experiments.can_tossing.table_one_cases`, both protocols, from the full data
  set so that every curve point answers the same cases) get their best field from the learned network exactly as
  Table I does (:func:`experiments.cans.choose`, both tie-break rules). The field
  is scored on ``repeats`` fresh throws of (start, field) that no network was fitted on
  (the physics bound's replays, :mod:`experiments.physics_bounds`, seed
  ``BOUND_SEED``): the case's success is the fraction of replays that reach the desired
  count, its expectation over the aim jitter rather than one throw's luck. The simulator's
  own best field, chosen on half of the replays and scored on the other half, is the
  bound (:func:`experiments.physics_bounds.held_out_best`).
* **Fits.** Every curve point's network is fitted on the chosen throws twice: plainly
  (:func:`inference.fit`, scored with both tie-break rules) and with each row's prior
  pooled from the neighbouring fields' throws (:func:`inference.fit_pooled`, kernel
  width ``pool_sigma`` fields, ``pool_strength`` pseudo-throws; score ``pooled``). Either
  way the start and field priors are the pool's
  (:func:`inference.design.active.with_pool_prior`), not the learner's play
  frequencies, which would otherwise steer the choice towards often-played fields. The full data is fitted the same two ways, and the
  goal is measured against its best score. The fits are of :func:`scoring_network`, the
  can network with the end configuration parentless (its large table, which no score
  reads, is never fitted; the same answers, bit for bit, at a fraction of the cost); the compiled tables of each fit
  answer both protocols, one field per distinct (start, desired count). Each budget's
  evaluation time is in the result (``point_time_s``; goal under ``POINT_GOAL_S``).
* **Strategies.** ``eig`` (plain Dirichlet information gain with the fit's pseudo-count
  as prior), ``eig_shared`` (the same with a prior shared by a start configuration's
  fields, weight ``prior_strength``), ``uncertainty`` (predictive entropy) and
  ``random``; every gain is about ``sites`` (default ``end.count``, the site Table I's
  query reads).

The goal: within one point of the full data's exact fraction with at most 10 % of its
throws (the 0° throws Table I fits on).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch
from effect_networks.experiments.can_tossing import (
    ANGLE,
    PROTOCOLS,
    RULES,
    choose,
    start_evidence,
    table_one_cases,
)
from effect_networks.experiments.can_tossing_report import TABLE_I_PROTOCOLS
from effect_networks.experiments.cans import (
    SCALES,
    CanDataSettings,
    CanModel,
    can_dataset,
    start_configurations,
)
from effect_networks.experiments.harness.config import (
    ConfigError,
    Result,
    check_choice,
    check_float,
    check_int,
    percent,
)
from effect_networks.experiments.harness.parallel import forks, run_tasks
from effect_networks.experiments.harness.registry import Experiment
from effect_networks.experiments.physics_bounds import BOUND_SEED, held_out_best
from effect_networks.inference import compile as compile_queries
from effect_networks.inference import fit, fit_pooled, grid_kernel
from effect_networks.inference.design.active import explore, with_pool_prior
from effect_networks.models.can_network import can_network, can_rows, config_index
from effect_networks.models.declaration import EffectNetwork
from effect_networks.sim2d import field_throws, geometry
from effect_networks.sim2d.can_dataset import generate_dataset, load_dataset
from effect_networks.sim2d.executors import open_executor
from tqdm.auto import tqdm

__all__ = [
    "LEARNERS",
    "QUICK",
    "SCORES",
    "ActiveConfig",
    "ActiveResult",
    "can_pool",
    "bound_by_repeats",
    "cases_seen",
    "replay_counts",
    "run_active",
    "scoring_network",
    "table_one_on_replays",
]

#: The strategies compared: ``{name: (inference.design.active strategy, shared prior?)}``.
LEARNERS = {
    "eig": ("eig", False),
    "eig_shared": ("eig", True),
    "uncertainty": ("uncertainty", False),
    "random": ("random", False),
}
#: How each curve point's network is fitted and its field chosen: the plain fit with the
#: ``aim`` or ``index`` tie-break (:data:`experiments.can_tossing.RULES`), or the tables
#: pooled over neighbouring fields (:func:`inference.fit_pooled`) with the ``aim`` rule.
SCORES = ("aim", "index", "pooled")
GOAL_FRACTION = 0.10  # of the full data's throws
GOAL_POINTS = 0.01  # within one point of the full data's exact fraction
#: Goal of one budget point's Table I evaluation (fits and scores), CPU seconds.
POINT_GOAL_S = 1.0
#: The quick scale's settings (examples/active.py --quick).
QUICK = {"scale": "quick", "repeats": 8, "fractions": (0.05, 0.1, 0.2, 0.5), "batch_size": 20}


@dataclass(frozen=True)
class ActiveConfig(CanDataSettings):
    """Settings of :func:`run_active`; every field is checked on construction.

    The can data set's, and where the replays are simulated if they are not under ``data_dir`` yet:
    :class:`experiments.cans.CanDataSettings`.

    Attributes
    ----------
    repeats : int
        Held-out replays per (start, field), >= 2 (the physics bound's file at this
        count is reused).
    fractions : tuple of float
        Budgets, as fractions of the pool (the 0° throws), each in ``(0, 1]``; increasing.
    learners : tuple of str
        Keys of ``LEARNERS``.
    batch_size : int
        Throws chosen before they are played.
    prior_strength : float
        Weight of the shared prior of ``eig_shared`` (> 0).
    pool_sigma, pool_strength : float
        The ``pooled`` score's fit (:func:`inference.fit_pooled`): Gaussian weights between
        fields ``pool_sigma`` cells apart (> 0) and ``pool_strength`` pseudo-throws of the
        neighbouring fields' outcomes in each row's prior (> 0).
    sites : tuple of str
        End sites the gains are about: ``end.count``, ``end.config`` or both.
    seed, n_seeds : int
        The learners run with seeds ``seed .. seed + n_seeds - 1`` (ties, random
        choices); the curves are their means.
    checkpoint_dir : Path or None
        Where each learner's state is saved after every batch (and resumed from); None:
        not saved.
    workers : int
        Processes for the learners (each learner and seed one task, its choices and its
        curve's fits: :func:`experiments.harness.parallel.run_tasks`); 0: one per core. The results
        do not depend on it.
    progress : bool
        Progress bars.
    """

    repeats: int = 16
    fractions: tuple[float, ...] = (0.02, 0.05, 0.1, 0.2, 0.5)
    learners: tuple[str, ...] = tuple(LEARNERS)
    batch_size: int = 100
    prior_strength: float = 1.0
    pool_sigma: float = 0.7
    pool_strength: float = 0.5
    sites: tuple[str, ...] = ("end.count",)
    seed: int = 0
    n_seeds: int = 1
    checkpoint_dir: Path | None = None
    workers: int = 0
    progress: bool = True

    def __post_init__(self):
        super().__post_init__()
        check_int("repeats", self.repeats, 2)
        object.__setattr__(self, "fractions", tuple(self.fractions))
        if not self.fractions:
            raise ConfigError("fractions", "no budget given; expected at least one")
        for f in self.fractions:
            check_float("fractions", f, 0.0, 1.0, low_open=True)
        if list(self.fractions) != sorted(set(self.fractions)):
            raise ConfigError("fractions", f"{self.fractions} must increase strictly")
        object.__setattr__(self, "learners", tuple(self.learners))
        if not self.learners:
            raise ConfigError("learners", "no learner given; expected at least one")
        for name in self.learners:
            check_choice("learners", name, LEARNERS)
        check_int("batch_size", self.batch_size, 1)
        check_float("prior_strength", self.prior_strength, 0.0, 1e6, low_open=True)
        check_float("pool_sigma", self.pool_sigma, 0.0, 1e3, low_open=True)
        check_float("pool_strength", self.pool_strength, 0.0, 1e6, low_open=True)
        object.__setattr__(self, "sites", tuple(self.sites))
        if not self.sites:
            raise ConfigError("sites", "no site given; expected end.count and/or end.config")
        for s in self.sites:
            check_choice("sites", s, ("end.count", "end.config"))
        check_int("seed", self.seed, 0)
        check_int("n_seeds", self.n_seeds, 1)
        check_int("workers", self.workers, 0)
        if self.checkpoint_dir is not None:
            object.__setattr__(self, "checkpoint_dir", Path(self.checkpoint_dir))


def can_pool(data):
    """The can network over the data set's configurations and the pool of its 0° throwable throws.

    ``(net, pool rows (encoded initial sites and action), oracle, end configs)``.

    ``oracle(index)`` returns the recorded end configuration and count of the throws
    ``index`` of the pool.
    """
    sel = (data.angle == ANGLE) & data.throwable
    states = sorted(set(data.start_config.tolist()) | set(data.end_config[sel].tolist()))
    net = can_network(states)
    rows = can_rows(net, data.start_config[sel], data.field[sel], data.end_config[sel])
    pool = rows.without("end.config", "end.count")
    ends = rows.rows(slice(None)).without("initial.config", "initial.count", "action")

    def oracle(index: np.ndarray):
        return ends.rows(torch.as_tensor(index))

    return net, pool, oracle, rows


def replay_counts(config: ActiveConfig, executor=None) -> tuple[np.ndarray, list[int]]:
    """``(configs, 195, repeats)`` end counts of the held-out replays, and their configurations.

    The replays of every non-empty start configuration's 0° fields (sorted configurations), and
    those configurations.
    """
    configs = [c for c in start_configurations(SCALES[config.scale]["n_configs"]) if c]
    path = generate_dataset(
        config.data_dir / f"can_bound_{config.scale}_{config.repeats}.npz",
        configs=configs,
        angles=(ANGLE,),
        repeats=config.repeats,
        seed=BOUND_SEED,
        executor=executor,
        progress=config.progress,
    )
    sims = load_dataset(path)
    order = np.lexsort((sims.repeat, sims.field, sims.start_config))
    counts = sims.count_after[order].reshape(len(configs), geometry.N_FIELDS, config.repeats)
    return counts.astype(np.int64), sorted(configs)


def table_one_on_replays(
    model: CanModel, cases: dict, replays, configs, rules: tuple[str, ...] = RULES
) -> dict:
    """Table I's exact fraction per protocol and rule (of ``rules``).

    Each case's chosen field is scored by the fraction of its replays that reach the desired count.

    ``cases``: ``{protocol: (start masks, desired counts)}``; ``replays``: as
    :func:`replay_counts` returns. A field is chosen once per distinct (start, desired
    count) of all the protocols' cases (:func:`experiments.cans.choose`, row by
    row: the same field whichever protocol asks).
    """
    row = {c: i for i, c in enumerate(configs)}
    pairs = np.concatenate([np.stack([start, desired], 1) for start, desired in cases.values()])
    distinct, inverse = np.unique(pairs.astype(np.int64), axis=0, return_inverse=True)
    evidence = start_evidence(model, distinct[:, 0]) | {
        "end.count": torch.as_tensor(distinct[:, 1])
    }
    fields = {rule: choose(model, evidence, rule)[inverse.reshape(-1)] for rule in rules}
    out, at = {}, 0
    for protocol, (start, desired) in cases.items():
        index = np.array([row[int(s)] for s in start])
        part = slice(at, at + len(start))
        at += len(start)
        out[protocol] = {}
        for rule in rules:
            success = replays[index, fields[rule][part]] == desired[:, None]
            out[protocol][rule] = float(success.mean())
    return out


def bound_by_repeats(replays, configs, cases, throwable) -> dict[str, list[float]]:
    """How many throws per pair a chooser that knows the simulator needs.

    Per protocol, the exact fraction when each case's field is the one that succeeded most often on
    the first ``m`` replays of every throwable field (``m = 1 .. repeats // 2``), scored on the
    second half of the replays (:func:`experiments.physics_bounds.held_out_best` at ``m`` = half).
    Choosing with ``m`` throws of every pair costs ``m`` throws per pair.
    """
    half = replays.shape[-1] // 2
    out = {}
    for p, (start, desired) in cases.items():
        success, case = _replay_success(replays, configs, start, desired, throwable)
        held = success[..., half:].mean(-1)
        out[p] = []
        for m in range(1, half + 1):
            chosen = success[..., :m].mean(-1).argmax(-1)
            out[p].append(float(np.take_along_axis(held, chosen[:, None], -1)[case].mean()))
    return out


def _replay_success(replays, configs, start, desired, fields) -> tuple[np.ndarray, np.ndarray]:
    """``(success, case)``: whether each replay reached the desired count, and each case's row.

    Per distinct (start, desired count) of the cases ``(start masks, desired counts)``, whether each
    replay of each of ``fields`` reached the desired count, ``(distinct, fields, repeats)`` bool;
    and each case's distinct row. Many cases share a start and a desired count: every per-row figure
    of ``success`` indexed by ``case`` is the per-case figure, element for element.
    """
    row = {c: i for i, c in enumerate(configs)}
    pairs = np.stack([np.asarray(start), np.asarray(desired)], 1).astype(np.int64)
    distinct, case = np.unique(pairs, axis=0, return_inverse=True)
    index = [row[int(s)] for s in distinct[:, 0]]
    return replays[index][:, fields] == distinct[:, 1, None, None], case.reshape(-1)


def cases_seen(rows, cases) -> float:
    """The fraction of cases whose desired count some row of ``rows`` reached from the case's start.

    Cases are ``(start state indices, desired counts)``; without such a row the network can only
    guess a field for the case.
    """
    played = set(zip(rows["initial.config"].tolist(), rows["end.count"].tolist(), strict=True))
    start, desired = cases
    hit = [(s, d) in played for s, d in zip(start.tolist(), desired.tolist(), strict=True)]
    return float(np.mean(hit))


def scoring_network(net: EffectNetwork) -> EffectNetwork:
    """The can network as Table I's query reads it: ``net`` with the end configuration parentless.

    Table I's query observes the start (configuration and count) and the desired end
    count and infers the field. The end configuration is neither observed nor a parent
    of the end count, so its table sums to one in every answer: the query never reads it.
    In ``net`` that table has ``configurations x 11 x 195 x configurations`` values (24.5
    million at full scale), and fitting, tracing and compiling it was most of a curve
    point's cost. Declared parentless it has ``configurations`` values; fitted on the
    same rows, every table the query reads is the same, and so is every answer, bit for
    bit (tests/experiments/test_active.py).
    """
    parents = dict(net.parents) | {"end.config": ()}
    return EffectNetwork(net.features, net.actions, net.parameters, parents, net.kinds)


def _model(net, rows, pool, throwable, pooling=None) -> CanModel:
    """The can model fitted on ``rows``: plainly, or pooled with ``pooling = (kernel, strength)``.

    The start and field priors are the pool's (design-free:
    :func:`inference.design.active.with_pool_prior`). Pooled, only the end count's table is pooled:
    the one Table I's query reads. ``net`` is :func:`scoring_network`'s (the end configuration's
    table, read by no score, is not fitted).
    """
    if pooling is None:
        params = fit(net, rows).params
    else:
        kernel, strength = pooling
        params = fit_pooled(net, rows, kernel, strength=strength, sites=("end.count",)).params
    params = with_pool_prior(net, params, pool)
    return CanModel(ANGLE, net, params, compile_queries(net, params), throwable)


def _scores(net, rows, pool, throwable, pooling, cases, replays, configs) -> dict:
    """``{protocol: {score: exact fraction}}`` for every one of ``SCORES``.

    ``net``: :func:`scoring_network`'s.
    """
    plain = table_one_on_replays(_model(net, rows, pool, throwable), cases, replays, configs)
    pooled = table_one_on_replays(
        _model(net, rows, pool, throwable, pooling), cases, replays, configs, ("aim",)
    )
    return {p: plain[p] | {"pooled": pooled[p]["aim"]} for p in plain}


@dataclass
class ActiveResult(Result):
    """What :func:`run_active` measured (fractions in [0, 1]).

    ``n_pool`` the 0° throws (the full data Table I fits on), ``n_dataset`` every throw
    of the data set, ``n_pairs`` distinct (configuration, field) pairs in the pool;
    ``budgets`` the throws of each curve point; ``curves[learner][protocol][rule]`` the
    exact fraction at each budget; ``full[protocol][rule]`` the network fitted on the
    whole pool; ``bound[protocol]`` the simulator's held-out best; ``bound_by_repeats[protocol]`` the same chosen on
    ``1 .. repeats // 2`` replays of every pair (:func:`bound_by_repeats`); ``pairs_covered
    [learner]`` distinct pairs played at each budget, per seed; ``cases_seen[learner][protocol]`` the fraction of
    cases whose desired count some chosen throw reached from their start (mean over seeds;
    :func:`cases_seen`); ``goal[learner][protocol][rule]``
    the fewest throws (of the budgets) within one point of the full data's best score
    (the largest of ``full[protocol]``), or None;
    ``seconds[learner]`` the learner's choosing time; ``point_time_s[learner]`` the CPU
    seconds of each budget's Table I evaluation (both fits, both protocols; mean over
    seeds; goal under ``POINT_GOAL_S``); ``settings`` the config.
    """

    experiment_name: ClassVar[str] = "active"

    scale: str
    n_pool: int
    n_dataset: int
    n_pairs: int
    n_cases: dict
    repeats: int
    budgets: list
    fractions: list
    curves: dict
    full: dict
    bound: dict
    bound_by_repeats: dict
    pairs_covered: dict
    cases_seen: dict
    curves_by_seed: dict
    goal: dict
    seconds: dict
    point_time_s: dict
    settings: dict

    def to_markdown(self) -> str:
        """Per protocol and rule, each learner's exact fraction at every budget.

        See :func:`experiments.active_report.markdown`.
        """
        from effect_networks.experiments.active_report import markdown

        return markdown(self)

    def figures(self, out: Path) -> list[Path]:
        """Draw the learning curves, ``active.png``, into the folder ``out``; its path."""
        from effect_networks.experiments.active_report import plot_curves

        return [plot_curves(self, out / "active.png")]

    def summary_rows(self, results) -> list[str]:
        """Per protocol, each learner at the budget nearest its goal.

        The goal is ``GOAL_FRACTION`` of the full data's throws; plain fit with tie-break ``aim``,
        and pooled, beside the bound.
        """
        k = min(range(len(self.fractions)), key=lambda i: abs(self.fractions[i] - GOAL_FRACTION))
        rows = []
        for protocol, words in TABLE_I_PROTOCOLS.items():
            learners = ", ".join(
                f"{name} {percent(c[protocol]['aim'][k])} "
                f"(pooled {percent(c[protocol]['pooled'][k])})"
                for name, c in self.curves.items()
            )
            reached = [
                name
                for name, g in self.goal.items()
                if any(v is not None and v <= self.budgets[k] for v in g[protocol].values())
            ]
            full = self.full[protocol]
            rows.append(
                f"| cans, beyond the paper: Table I ({words}) learned by active exploration "
                f"from {percent(self.fractions[k], 0)} of the {self.n_pool:,} 0° throws, exact "
                f"on {self.repeats} held-out replays | - | {learners}; full data "
                f"{percent(full['aim'])} (pooled {percent(full['pooled'])}) (goal: within 1 "
                "point of the full data's best: "
                + (", ".join(reached) if reached else "not reached")
                + f") | {percent(self.bound[protocol])} held out |"
            )
        return rows


def run_active(config: ActiveConfig) -> ActiveResult:
    """Learning curves of Table I against the throws used, per learner, beside the full data."""
    with open_executor(config.executor) as executor:
        data = can_dataset(
            config.data_dir, config.scale, executor=executor, progress=config.progress
        )
        replays, configs = replay_counts(config, executor)
    net, pool, oracle, rows = can_pool(data)
    n = pool.n_rows
    budgets = [max(1, round(f * n)) for f in config.fractions]
    throwable = torch.tensor(
        [field_throws.is_throwable(f, ANGLE) for f in range(geometry.N_FIELDS)]
    )
    cases = {p: table_one_cases(data, p) for p in PROTOCOLS}
    pair = (pool["initial.config"] * geometry.N_FIELDS + pool["action"]).numpy()

    pooling = (
        grid_kernel((geometry.N_ROWS, geometry.N_COLUMNS), config.pool_sigma),
        config.pool_strength,
    )
    scoring = scoring_network(net)
    full = _scores(scoring, rows, pool, throwable, pooling, cases, replays, configs)
    bound = {}
    for p, (start, desired) in cases.items():
        success, case = _replay_success(replays, configs, start, desired, throwable.numpy())
        bound[p] = float(held_out_best(success)[case].mean())

    by_repeats = bound_by_repeats(replays, configs, cases, throwable.numpy())
    curves, by_seed, covered, seen, seconds, point_time = {}, {}, {}, {}, {}, {}
    cases_rows = {
        p: (config_index(net, start), torch.as_tensor(desired))
        for p, (start, desired) in cases.items()
    }
    # every learner and seed is a task of its own, on every core (workers); forked
    # workers' bars would mix: one bar over the tasks instead
    keys = [
        (name, seed)
        for name in config.learners
        for seed in range(config.seed, config.seed + config.n_seeds)
    ]
    forked = forks(config.workers, len(keys))
    alone = config.progress and not forked

    def learner_task(name: str, seed: int):
        """One learner's run with one seed, as a task.

        Its choosing time, its curve points and their evaluation times, the pairs it covered
        and the cases it saw, per budget.
        """

        def task():
            strategy, shared = LEARNERS[name]
            checkpoint = None
            if config.checkpoint_dir is not None:
                checkpoint = config.checkpoint_dir / f"active_{config.scale}_{name}_{seed}.pt"
            start_time = time.process_time()
            learned = explore(
                net,
                pool,
                oracle,
                budgets[-1],
                batch_size=config.batch_size,
                strategy=strategy,
                prior_strength=config.prior_strength if shared else 0.0,
                sites=config.sites,
                seed=seed,
                checkpoint=checkpoint,
                progress=alone,
            )
            seconds = time.process_time() - start_time
            points, times = [], []
            for b in tqdm(budgets, desc=f"Table I ({name})", disable=not alone):
                start_time = time.process_time()
                chosen = learned.rows.rows(slice(0, b))
                points.append(
                    _scores(scoring, chosen, pool, throwable, pooling, cases, replays, configs)
                )
                times.append(time.process_time() - start_time)
            covered = [len(np.unique(pair[learned.chosen[:b]])) for b in budgets]
            seen = {
                p: [cases_seen(learned.rows.rows(slice(0, b)), c) for b in budgets]
                for p, c in cases_rows.items()
            }
            return seconds, points, times, covered, seen

        return task

    done = dict(
        zip(
            keys,
            run_tasks(
                [learner_task(*key) for key in keys],
                config.workers,
                desc="learners",
                progress=config.progress and forked,
            ),
            strict=True,
        )
    )
    for name in config.learners:
        runs, seen_runs, covered[name], seconds[name], point_times = [], [], [], 0.0, []
        for seed in range(config.seed, config.seed + config.n_seeds):
            spent, points, times, pairs, seen_run = done[name, seed]
            seconds[name] += spent
            runs.append(points)
            point_times.append(times)
            covered[name].append(pairs)
            seen_runs.append(seen_run)
        by_seed[name] = {
            p: {rule: [[pt[p][rule] for pt in points] for points in runs] for rule in SCORES}
            for p in PROTOCOLS
        }
        curves[name] = {
            p: {rule: np.mean(by_seed[name][p][rule], 0).tolist() for rule in SCORES}
            for p in PROTOCOLS
        }
        seen[name] = {p: np.mean([r[p] for r in seen_runs], 0).tolist() for p in PROTOCOLS}
        point_time[name] = np.mean(point_times, 0).tolist()

    goal = {
        name: {
            p: {
                rule: next(
                    (
                        b
                        for b, v in zip(budgets, curves[name][p][rule], strict=True)
                        if v >= max(full[p].values()) - GOAL_POINTS
                    ),
                    None,
                )
                for rule in SCORES
            }
            for p in PROTOCOLS
        }
        for name in curves
    }
    settings = {  # but the workers: how the work is spread, not what it computes
        k: (str(v) if isinstance(v, Path) else list(v) if isinstance(v, tuple) else v)
        for k, v in vars(config).items()
        if k != "workers"
    }
    return ActiveResult(
        scale=config.scale,
        n_pool=n,
        n_dataset=len(data.angle),
        n_pairs=len(np.unique(pair)),
        n_cases={p: len(c[0]) for p, c in cases.items()},
        repeats=config.repeats,
        budgets=budgets,
        fractions=list(config.fractions),
        curves=curves,
        full=full,
        bound=bound,
        bound_by_repeats=by_repeats,
        pairs_covered=covered,
        cases_seen=seen,
        curves_by_seed=by_seed,
        goal=goal,
        seconds=seconds,
        point_time_s=point_time,
        settings=settings,
    )


EXPERIMENTS = (
    Experiment(
        ActiveConfig,
        run_active,
        ActiveResult,
        order=100,
        tiny={"scale": "tiny", "repeats": 2, "fractions": (0.3, 1.0), "batch_size": 20},
        quick=QUICK,
    ),
)
