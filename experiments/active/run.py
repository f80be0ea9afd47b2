"""The active-exploration experiment's run: the pool, the learners' curves, the bound.

The experiment is described in :mod:`experiments.active`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch
from effect_networks.experiments.active.settings import (
    GOAL_POINTS,
    LEARNERS,
    SCORES,
    ActiveConfig,
)
from effect_networks.experiments.can_tossing.run import start_evidence, table_one_cases
from effect_networks.experiments.can_tossing.settings import (
    ANGLE,
    PROTOCOLS,
    RULES,
)
from effect_networks.experiments.cans import (
    CanModel,
    can_dataset,
    choose,
    replays,
)
from effect_networks.experiments.harness.config import Result
from effect_networks.experiments.harness.parallel import forks, run_tasks
from effect_networks.experiments.physics_bounds import held_out_best
from effect_networks.inference import compile as compile_queries
from effect_networks.inference import fit, fit_pooled, grid_kernel
from effect_networks.inference.design.active import explore, with_pool_prior
from effect_networks.models.can_pyramid import can_network, can_rows, config_index
from effect_networks.models.declaration import EffectNetwork
from effect_networks.sim2d import field_throws, geometry
from effect_networks.sim2d.executors import open_executor
from tqdm.auto import tqdm

__all__ = [
    "ActiveResult",
    "bound_by_repeats",
    "can_pool",
    "cases_seen",
    "replay_counts",
    "run_active",
    "scoring_network",
    "table_one_on_replays",
]


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
    sims = replays(
        config.data_dir, config.scale, config.repeats, executor=executor, progress=config.progress
    )
    return sims.count_after, list(sims.configs)


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
    bit (tests/experiments/active/test_active.py).
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
