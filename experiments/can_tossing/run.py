"""Can tossing's run: Table I, emulation and imitation measured, and their result.

The experiment is described in :mod:`experiments.can_tossing`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch
from effect_networks.experiments.can_tossing.settings import (
    ANGLE,
    CHUNK,
    CONVERGE,
    DEMO,
    PAPER_CASES,
    PAPER_PERCENT,
    PAPER_TABLE_I,
    PERTURB,
    PICK,
    PROTOCOLS,
    REPLAY,
    RULES,
    TABLE_I,
    VALIDATE,
    CanTossingConfig,
)
from effect_networks.experiments.can_tossing.surprise import (
    auc_or_none,
    bound_curve,
    network_tables,
    operating_points,
    surprise_bound,
    surprise_under,
    validated_sigma,
)
from effect_networks.experiments.cans import (
    CanModel,
    Replays,
    can_dataset,
    choose,
    fit_can_network,
    fit_on_replays,
    replays,
)
from effect_networks.experiments.evaluation import accuracy_histogram
from effect_networks.experiments.harness.config import Result, check_choice
from effect_networks.inference import imitation_check
from effect_networks.models.can_pyramid import n_cans
from effect_networks.sim2d import field_throws, geometry, materials
from effect_networks.sim2d.clock import simulation
from effect_networks.sim2d.executors import open_executor
from tqdm.auto import tqdm

__all__ = [
    "CanTossingResult",
    "PAPER",
    "ball_ends",
    "demonstrations",
    "emulation",
    "field_throw_ends",
    "fresh_seeds",
    "imitation",
    "network_surprise",
    "perturbed_aims",
    "perturbed_throws",
    "play",
    "imitation_draws",
    "play_table_one",
    "replay_network",
    "run_can_tossing",
    "start_evidence",
    "summarise",
    "table_one",
    "table_one_cases",
]


def fresh_seeds(seed: int, purpose: int, n: int) -> np.ndarray:
    """``(n,)`` uint32 throw seeds for one purpose, disjoint from the training seeds'."""
    return np.random.SeedSequence([seed, purpose]).generate_state(max(n, 1))[:n]


def table_one_cases(data, mode: str = "counts") -> tuple[np.ndarray, np.ndarray]:
    """Table I's cases from the 0° training throws: ``(start masks, desired counts)``.

    ``counts``: every distinct count reached from a start, plus the unchanged one.
    ``actions``: one case per (start, field) whose first throw changed the count, plus
    one unchanged case per start.
    """
    check_choice("mode", mode, PROTOCOLS)
    sel = (data.angle == ANGLE) & data.throwable & (data.start_config != 0)
    if mode == "actions":
        sel &= (data.repeat == 0) & (data.count_after != data.count_before)
        start, desired = data.start_config[sel], data.count_after[sel]
    else:
        pairs = np.unique(np.stack([data.start_config[sel], data.count_after[sel]], 1), axis=0)
        start, desired = pairs[:, 0], pairs[:, 1]
    starts = np.unique(data.start_config[(data.angle == ANGLE) & (data.start_config != 0)])
    unchanged = n_cans(starts)
    if mode == "counts":  # only where the unchanged count is not already a case
        have = {(int(s), int(c)) for s, c in zip(start, desired, strict=True)}
        keep = [(int(s), int(c)) not in have for s, c in zip(starts, unchanged, strict=True)]
        starts, unchanged = starts[keep], unchanged[keep]
    start = np.r_[start, starts].astype(np.int64)
    desired = np.r_[desired, unchanged].astype(np.int64)
    order = np.lexsort((desired, start))
    return start[order], desired[order]


def start_evidence(model: CanModel, start: np.ndarray) -> dict:
    """Query evidence of the start configurations ``(n,)`` masks: configuration and count."""
    return {
        "initial.config": start,
        "initial.count": n_cans(start),
    }


def field_throw_ends(start, fields, seeds, jitter: float) -> np.ndarray:
    """``(n,)`` end configurations of the 0° throws ``(start[i], fields[i])`` with seeded jitter.

    An executor task: arrays in, an array out.
    """
    return np.array(
        [
            field_throws.throw_at_field(
                int(s), int(f), ANGLE, jitter=jitter, seed=int(k)
            ).end_config
            for s, f, k in zip(start, fields, seeds, strict=True)
        ],
        dtype=np.int64,
    )


def ball_ends(start, positions, velocities) -> np.ndarray:
    """``(n,)`` end configurations of the ball states ``(positions[i], velocities[i])``.

    ``(n, 2)`` each, m and m/s at the entry line, played into ``start[i]`` (an executor task).
    """
    return np.array(
        [
            field_throws.play_ball(int(s), p, v).end_config
            for s, p, v in zip(start, positions, velocities, strict=True)
        ],
        dtype=np.int64,
    )


@simulation
def _in_chunks(task, columns, extra, desc: str, progress: bool, executor) -> np.ndarray:
    """``task(*columns, *extra)`` over the rows of ``columns``, in chunks of ``CHUNK`` rows.

    On ``executor`` (None: here, row by row); the results in row order, the same on every executor.
    """
    n = len(columns[0])
    if executor is None:
        rows = tqdm(range(n), desc=desc, leave=False, disable=not progress)
        parts = [task(*(c[i : i + 1] for c in columns), *extra) for i in rows]
        return np.concatenate(parts or [np.zeros(0, np.int64)])
    futures = [
        executor.submit(task, *(c[i : i + CHUNK] for c in columns), *extra)
        for i in range(0, n, CHUNK)
    ]
    done = tqdm(futures, desc=desc, leave=False, disable=not progress, unit="chunk")
    return np.concatenate([f.result() for f in done] or [np.zeros(0, np.int64)])


def play(
    start, fields, jitter: float, seeds, desc: str, progress: bool = True, executor=None
) -> np.ndarray:
    """End configurations of the 0° throws ``(start[i], fields[i])`` with seeded jitter.

    Simulated on ``executor`` (an object with ``submit``; None: in this process).
    """
    columns = [np.asarray(start), np.asarray(fields), np.asarray(seeds)]
    return _in_chunks(field_throw_ends, columns, (jitter,), desc, progress, executor)


def play_table_one(
    model: CanModel,
    data,
    mode: str,
    seed: int,
    rule: str,
    *,
    progress: bool = True,
    executor=None,
) -> dict[str, np.ndarray]:
    """Table I's cases played.

    Per case ``start``, ``desired``, ``field``, ``seed``, ``achieved`` (count) and ``reachable``
    (some 0° training throw reached ``desired``).
    """
    start, desired = table_one_cases(data, mode)
    sel = (data.angle == ANGLE) & data.throwable
    seen = np.unique(data.start_config[sel] * 16 + data.count_after[sel])
    evidence = start_evidence(model, start) | {"end.count": torch.as_tensor(desired)}
    fields = choose(model, evidence, rule)
    seeds = fresh_seeds(seed, TABLE_I, len(start))  # the same for both rules
    desc = f"Table I ({mode}, {rule})"
    end = play(start, fields, data.metadata["jitter"], seeds, desc, progress, executor)
    return {
        "start": start,
        "desired": desired,
        "field": fields,
        "seed": seeds,
        "achieved": n_cans(end),
        "reachable": np.isin(start * 16 + desired, seen),
    }


def summarise(cases: dict[str, np.ndarray]) -> dict:
    """Table I's numbers from :func:`play_table_one`'s cases."""
    exact = cases["desired"] == cases["achieved"]
    reachable = cases["reachable"]
    return {
        "n_cases": len(exact),
        "histogram": accuracy_histogram(cases["desired"], cases["achieved"]),
        "exact_fraction": float(exact.mean()),
        "n_unreachable": int((~reachable).sum()),
        "exact_fraction_reachable": float(exact[reachable].mean()) if reachable.any() else None,
    }


def table_one(
    model: CanModel, data, mode: str, seed: int, *, progress: bool = True, executor=None
) -> dict:
    """Table I for both tie-break rules, on the same cases and the same seeds."""
    return {
        rule: summarise(
            play_table_one(model, data, mode, seed, rule, progress=progress, executor=executor)
        )
        for rule in RULES
    }


def demonstrations(data, n: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """``n`` random (non-empty start, throwable 0° field) pairs from the data set."""
    starts = np.unique(data.start_config[(data.angle == ANGLE) & (data.start_config != 0)])
    throwable = np.flatnonzero(
        [field_throws.is_throwable(f, ANGLE) for f in range(geometry.N_FIELDS)]
    )
    return rng.choice(starts, n), rng.choice(throwable, n)


def emulation(
    model: CanModel, data, n: int, seed: int, rule: str, *, progress: bool = True, executor=None
) -> dict:
    """Infer a field that causes a demonstrated effect, throw it, compare the effects."""
    jitter = data.metadata["jitter"]
    start, field = demonstrations(data, n, np.random.default_rng([seed, PICK]))
    shown = play(
        start, field, jitter, fresh_seeds(seed, DEMO, n), "demonstrations", progress, executor
    )
    known = np.isin(shown, model.states)  # end configurations the network has a state for
    ev = start_evidence(model, start) | {"end.count": torch.as_tensor(n_cans(shown))}
    fields = choose(model, ev, rule)  # count only: the fallback for unknown configurations
    if known.any():
        ev_known = model.net.encode(ev).rows(torch.as_tensor(known))
        ev_known = ev_known | {"end.config": shown[known]}
        fields[known] = choose(model, ev_known, rule)
    seeds = fresh_seeds(seed, REPLAY, 2 * n)
    copied = play(start, fields, jitter, seeds[:n], "emulation", progress, executor)
    again = play(start, field, jitter, seeds[n:], "demonstrated field again", progress, executor)

    return {
        "n_demonstrations": n,
        "n_unknown_end_config": int((~known).sum()),
        "same_end_config": float(np.mean(copied == shown)),
        "same_count": float(np.mean(n_cans(copied) == n_cans(shown))),
        "same_field_chosen": float(np.mean(fields == field)),
        "reference_same_end_config": float(np.mean(again == shown)),
        "reference_same_count": float(np.mean(n_cans(again) == n_cans(shown))),
    }


def perturbed_aims(start, field, aim_error: float, rng) -> list[tuple[np.ndarray, np.ndarray]]:
    """Ball states at the entry line for aims ``aim_error`` off (redrawn until throwable)."""
    states = []
    for f in field:
        while True:
            offset = rng.normal(0.0, aim_error, 2)
            position, velocity = field_throws.launch_state(int(f), ANGLE, offset=offset)
            target_z = geometry.field_centres()[f, 1] + offset[1]
            if min(position[1], target_z) >= materials.BALL_RADIUS + materials.TABLE_CLEARANCE:
                states.append((position, velocity))
                break
    return states


def perturbed_throws(
    data,
    n: int,
    aim_error: float,
    seed: int,
    purpose: int,
    n_ordinary: int = 8,
    *,
    progress: bool = True,
    executor=None,
) -> dict[str, np.ndarray]:
    """``n`` throws aimed ``aim_error`` m off, with their failure labels, ``(n,)`` each.

    ``start``, ``field`` (intended), ``observed`` (end configuration) and two labels:
    ``failed``: the end configuration differs from the unperturbed intended throw's;
    ``failed_ordinary``: it differs from every outcome of the intended throw executed as
    usual (unperturbed, and ``n_ordinary`` times with the data set's aim jitter) -- the
    world is chaotic enough at a 3 mm jitter that the unperturbed throw's outcome is often
    not the intended action's usual one. ``purpose`` seeds the draw (``PERTURB``: test).
    """
    rng = np.random.default_rng([seed, purpose])
    start, field = demonstrations(data, n, rng)
    aims = perturbed_aims(start, field, aim_error, rng)
    positions = np.array([p for p, _ in aims]).reshape(-1, 2)
    velocities = np.array([v for _, v in aims]).reshape(-1, 2)
    nominal = play(start, field, 0.0, np.zeros(n, np.uint32), "intended throws", progress, executor)
    observed = _in_chunks(
        ball_ends, [start, positions, velocities], (), "perturbed throws", progress, executor
    )
    failed = observed != nominal
    seeds = fresh_seeds(seed, purpose, n * n_ordinary).reshape(n_ordinary, n)
    jitter = data.metadata["jitter"]
    usual = [
        play(start, field, jitter, k, f"ordinary throws {j + 1}/{n_ordinary}", progress, executor)
        for j, k in enumerate(seeds)
    ]
    failed_ordinary = failed & np.all([observed != u for u in usual], axis=0)
    return {
        "start": start,
        "field": field,
        "observed": observed,
        "failed": failed,
        "failed_ordinary": failed_ordinary,
    }


def network_surprise(model: CanModel, throws: dict) -> np.ndarray:
    """``(n,)`` surprise of each observed end state under the intended field, exact.

    :func:`inference.imitation_check` on the observed end configuration and count; an end
    configuration the network has no state for was never seen: 1.
    """
    start, field, observed = throws["start"], throws["field"], throws["observed"]
    known = np.isin(observed, model.states)
    surprise = np.ones(len(start))
    if known.any():
        ev = start_evidence(model, start[known]) | {
            "action": [model.net.actions[f] for f in field[known]],
            "end.config": observed[known],
            "end.count": n_cans(observed[known]),
        }
        surprise[known] = imitation_check(model.net, model.params, ev).surprise.numpy()
    return surprise


def imitation_draws(
    data, n: int, aim_error: float, seed: int, n_ordinary: int, *, progress=True, executor=None
) -> tuple[dict, dict]:
    """Imitation's two draws of :func:`perturbed_throws`: the scored one and the validation one."""
    run = {"progress": progress, "executor": executor}
    return (
        perturbed_throws(data, n, aim_error, seed, PERTURB, n_ordinary, **run),
        perturbed_throws(data, n, aim_error, seed, VALIDATE, n_ordinary, **run),
    )


def replay_network(sims: Replays, draws: tuple[dict, dict], angle: int = ANGLE) -> dict:
    """Imitation's AUCs under a network fitted on the replays ``sims`` instead of the data set.

    The network is :func:`experiments.cans.fit_on_replays`'s (every replay a training
    throw: ``sims.repeats`` throws per aim); its surprise, and its pooled surprise with the
    aim error chosen on the validation draw as the data set's network's is
    (:func:`validated_sigma`), scored on ``draws`` (:func:`imitation_draws`). Only numbers
    are returned, so the network is freed on return.
    """
    throws, held_out = draws
    more = fit_on_replays(sims, angle)
    table_of = network_tables(more)
    sigma, _ = validated_sigma(table_of, held_out, more.throwable)
    surprise = network_surprise(more, throws)
    pooled = surprise_under(table_of, throws, sigma, more.throwable)
    failed, failed_ordinary = throws["failed"], throws["failed_ordinary"]
    return {
        "throws_per_aim": sims.repeats,
        "aim_sigma": sigma,
        "auc": auc_or_none(surprise, failed),
        "auc_ordinary": auc_or_none(surprise, failed_ordinary),
        "auc_pooled": auc_or_none(pooled, failed),
        "auc_ordinary_pooled": auc_or_none(pooled, failed_ordinary),
    }


def imitation(
    model: CanModel,
    data,
    n: int,
    aim_error: float,
    seed: int,
    n_ordinary: int,
    sims: Replays,
    curve_repeats: int = 2,
    *,
    draws: tuple[dict, dict] | None = None,
    more_data: dict | None = None,
    progress: bool = True,
    executor=None,
) -> dict:
    """Surprise of perturbed throws' effects under the intended field, its ROC and its bound.

    Labels: :func:`perturbed_throws`. Scores: the network's surprise
    (:func:`network_surprise`), and the pooled surprise (:func:`surprise_under` of the
    network's tables) with the aim error from ``AIM_SIGMAS`` that has the best
    ``failed_ordinary`` AUC on a validation draw (seed purpose ``VALIDATE``; ties to the
    smaller aim error). ``threshold``: the surprise's operating point chosen on the
    validation draw (:func:`operating_points`). ``bound``: :func:`surprise_bound` from the
    simulator's replays ``sims``. ``bound_curve``: :func:`bound_curve` from
    ``curve_repeats`` fresh replays of each scored throw's intended throw (seed purpose
    ``CONVERGE``), to show where the bound settles. ``more_data``: the surprise of a network
    fitted on the replays ``sims`` (:func:`experiments.cans.fit_on_replays`; ``sims.repeats``
    throws per aim where the data set has a few; :func:`replay_network`), to show how much
    of the gap to the bound is the data set's size. ``draws`` and ``more_data``, when given,
    are :func:`imitation_draws`' and :func:`replay_network`'s for these settings, computed
    before ``model`` was fitted so that two networks are never in memory together.
    """
    run = {"progress": progress, "executor": executor}
    if draws is None:
        draws = imitation_draws(data, n, aim_error, seed, n_ordinary, **run)
    if more_data is None:
        more_data = replay_network(sims, draws, model.angle)
    throws, held_out = draws
    failed, failed_ordinary = throws["failed"], throws["failed_ordinary"]
    known = np.isin(throws["observed"], model.states)
    surprise = network_surprise(model, throws)
    table_of = network_tables(model)
    sigma, validation = validated_sigma(table_of, held_out, model.throwable)
    pooled = surprise_under(table_of, throws, sigma, model.throwable)
    held_surprise = network_surprise(model, held_out)
    n = len(throws["start"])
    ends = play(
        np.repeat(throws["start"], curve_repeats),
        np.repeat(throws["field"], curve_repeats),
        data.metadata["jitter"],
        fresh_seeds(seed, CONVERGE, n * curve_repeats),
        "bound's convergence replays",
        **run,
    ).reshape(n, curve_repeats)
    return {
        "n_throws": n,
        "aim_error_m": aim_error,
        "n_failed": int(failed.sum()),
        "n_unknown_end_config": int((~known).sum()),
        "auc": auc_or_none(surprise, failed),
        "n_failed_ordinary": int(failed_ordinary.sum()),
        "auc_ordinary": auc_or_none(surprise, failed_ordinary),
        "aim_sigma": sigma,
        "auc_pooled": auc_or_none(pooled, failed),
        "auc_ordinary_pooled": auc_or_none(pooled, failed_ordinary),
        "validation": {
            "n_throws": n,
            "n_failed": int(held_out["failed"].sum()),
            "n_failed_ordinary": int(held_out["failed_ordinary"].sum()),
            "by_sigma": validation,
        },
        "threshold": operating_points(held_surprise, held_out, surprise, throws),
        "bound": surprise_bound(sims, throws, held_out, model.throwable),
        "bound_curve": bound_curve(ends, throws),
        "more_data": more_data,
        "surprise": surprise.tolist(),
        "pooled_surprise": pooled.tolist(),
        "failed": failed.tolist(),
        "failed_ordinary": failed_ordinary.tolist(),
    }


PAPER = {
    "n_cases": PAPER_CASES,
    "histogram": PAPER_TABLE_I,
    "percent": PAPER_PERCENT,
    "exact_fraction": 0.9043,
}


@dataclass
class CanTossingResult(Result):
    """What :func:`run_can_tossing` measured (fractions in [0, 1]).

    The headline Table I (protocol ``cases``, tie-break ``rule``) is spread into
    ``n_cases``, ``histogram`` (bin label of ``ACCURACY_BINS`` -> cases),
    ``exact_fraction``, ``n_unreachable`` (cases asking for a count no 0° training
    throw reached from their start) and ``exact_fraction_reachable``; ``table_one``
    holds all four as ``{protocol: {rule: {...}}}``. ``paper`` holds the paper's Table I;
    ``emulation`` and ``imitation`` are :func:`emulation`'s and :func:`imitation`'s.
    """

    experiment_name: ClassVar[str] = "can_tossing"

    scale: str
    cases: str
    rule: str
    n_cases: int
    histogram: dict[str, int]
    exact_fraction: float
    n_unreachable: int
    exact_fraction_reachable: float | None
    table_one: dict[str, dict[str, dict]]
    paper: dict
    emulation: dict
    imitation: dict


def run_can_tossing(config: CanTossingConfig) -> CanTossingResult:
    """Fit the can network on the 0° throws and measure Table I, emulation and imitation.

    Every simulation (the data set, then the evaluation throws in chunks) runs on
    ``config.executor``; the numbers do not depend on where.
    """
    progress = config.progress
    with open_executor(config.executor) as executor:
        data = can_dataset(config.data_dir, config.scale, executor=executor, progress=progress)
        run = {"progress": progress, "executor": executor}
        sims = replays(config.data_dir, config.scale, config.bound_repeats, angle=ANGLE, **run)
        settings = (config.n_demos, config.aim_error, config.seed, config.n_ordinary)
        draws = imitation_draws(data, *settings, **run)
        # the replays' network on a worker, or here before the data set's and freed: the two
        # networks' tables are never in one process together
        if executor is None:
            more_data = replay_network(sims, draws)
        else:
            more_data = executor.submit(replay_network, sims, draws).result()
        model = fit_can_network(data, ANGLE)
        tables = {mode: table_one(model, data, mode, config.seed, **run) for mode in PROTOCOLS}
        emulated = emulation(model, data, config.n_demos, config.seed, config.rule, **run)
        imitated = imitation(
            model,
            data,
            *settings,
            sims,
            config.curve_repeats,
            draws=draws,
            more_data=more_data,
            **run,
        )
    return CanTossingResult(
        scale=config.scale,
        cases=config.cases,
        rule=config.rule,
        **tables[config.cases][config.rule],
        table_one=tables,
        paper=PAPER,
        emulation=emulated,
        imitation=imitated,
    )
