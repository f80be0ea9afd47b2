"""The adaptive-throw experiment's run: both layouts, the noisy rows, the active curves.

The experiment is described in :mod:`experiments.adaptive_throw`.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch
from effect_networks.experiments.adaptive_throw.active_curves import (
    active_curve,
    below_at_every_budget,
    grid_floor,
    mean_curve,
)
from effect_networks.experiments.adaptive_throw.aiming import (
    aims_for,
    best_candidate_error,
    error_causes,
    error_tail,
    hit_window,
    inferred_aims,
)
from effect_networks.experiments.adaptive_throw.settings import (
    GOAL_FIT_S,
    GOAL_NOISE_RATIO,
    GOAL_RMS_M,
    QUERIES,
    STRATEGIES,
    AdaptiveThrowConfig,
)
from effect_networks.experiments.harness.config import Result
from effect_networks.experiments.harness.parallel import forks, run_tasks
from effect_networks.experiments.throwing import get_data, rms
from effect_networks.inference import fit, fit_em
from effect_networks.models.declaration import EffectNetwork
from effect_networks.models.humanoid_throw import TARGET, throw_data, throw_network
from effect_networks.sim2d.analytic_throw import TARGET_AREA, ReleaseNoise, throw

__all__ = [
    "AdaptiveThrowResult",
    "adaptive_throw_network",
    "local_inverse",
    "plane_residuals",
    "run_adaptive_throw",
]


def adaptive_throw_network(bins) -> EffectNetwork:
    """The throw network with adaptive target clusters seeded by the ``bins`` grid.

    See :func:`models.humanoid_throw.throw_network`.
    """
    net = throw_network(bins)
    target = dataclasses.replace(net.parameters[0], layout="adaptive")
    return EffectNetwork(net.features, net.actions, (target,))


def _fit(layout, k, train, config):
    """Fit one layout with ``k x k`` clusters.

    ``(model, seconds, EM curve)`` per EM checkpoint (one for the grid); the seconds and the curve
    accumulate.
    """
    targets, hits = train
    start = time.perf_counter()
    if layout == "grid":
        net = throw_network((k, k))
        data = throw_data(net, targets, hits)
        params = fit(net, data, pseudo_count=config.pseudo_count).params
        return [((net, params), time.perf_counter() - start, [])]
    net = adaptive_throw_network((k, k))
    data = throw_data(net, targets, hits)
    out, params, curve, done = [], None, [], 0
    for steps in config.em_steps:
        result = fit_em(
            net,
            data,
            init=params,
            steps=steps - done,
            tol=config.tol,
            pseudo_count=config.pseudo_count,
        )
        params, done = result.params, steps
        curve += list(result.log_likelihoods[1:] if curve else result.log_likelihoods)
        out.append(((net, params), time.perf_counter() - start, list(curve)))
    return out


def plane_residuals(targets, hits, bins, use=None):
    """Residuals ``(n, 2)`` of one least-squares plane ``hit ~ A target + b`` per cell.

    Per equidistant cell of the target area (``bins x bins``, the throw network's grid), fitted to
    the rows ``use`` (default: all) of each cell; NaN for the other rows and for cells with fewer
    than four rows to fit.

    An inverse that answers with one linear piece's solution re-throws with exactly that
    piece's residual at the aim (the piece maps the aim onto the desired hit; the throw
    maps it onto the piece's prediction plus the residual). So on unclamped throws, where
    the map is smooth, these residuals are what the best planes over the cells leave of
    the map's curvature: the scale below which a piecewise-linear model with that many
    equal cells does not re-throw.
    """
    targets, hits = np.asarray(targets, dtype=float), np.asarray(hits, dtype=float)
    if targets.ndim != 2 or targets.shape[1] != 2 or hits.shape != targets.shape:
        raise ValueError(
            f"targets {targets.shape} and hits {hits.shape}: expected two (n, 2) arrays of "
            "[y, z] in metres, one row per throw"
        )
    use = np.ones(len(targets), dtype=bool) if use is None else np.asarray(use)
    if use.shape != (len(targets),) or use.dtype != bool:
        raise ValueError(f"use: expected a boolean mask of shape ({len(targets)},)")
    m = throw_network((bins, bins)).mixture(TARGET)
    action = torch.zeros(len(targets), dtype=torch.long)
    cell = m.cells(torch.as_tensor(targets), action).numpy()
    residual = np.full_like(hits, np.nan)
    for c in np.unique(cell[use]):
        rows = np.flatnonzero((cell == c) & use)
        if len(rows) < 4:
            continue
        design = np.column_stack([targets[rows], np.ones(len(rows))])
        coef = np.linalg.lstsq(design, hits[rows], rcond=None)[0]
        residual[rows] = hits[rows] - design @ coef
    return residual


def _noisy_spread(aims, desired, repeats, rng, noise) -> dict[str, float]:
    """RMS per axis of ``repeats`` noisy re-throws at ``aims`` against the desired hits.

    And of the same throws about their noise-free hits (the noise's own scatter).
    """
    clean = throw(aims).hit
    hits = np.concatenate([throw(aims, rng=rng, noise=noise).hit for _ in range(repeats)])
    error = rms(hits - np.tile(desired, (repeats, 1)))
    scatter = rms(hits - np.tile(clean, (repeats, 1)))
    return {
        "rms_y_m": float(error[0]),
        "rms_z_m": float(error[1]),
        "scatter_y_m": float(scatter[0]),
        "scatter_z_m": float(scatter[1]),
        "ratio_y": float(error[0] / scatter[0]),
        "ratio_z": float(error[1] / scatter[1]),
    }


def local_inverse(train_targets, train_hits, desired, start, neighbours, iterations=4):
    """Aims ``(n, 2)`` by damped Newton steps on a local quadratic forward model.

    Per desired hit, from ``start``, fit ``hit ~ quadratic(target - aim)`` to the ``neighbours``
    training throws nearest the aim, step towards the target its model says hits the desired point
    (least squares, so a clamped, flat direction takes no step; at most the neighbourhood's radius),
    and keep the aim whose local model misses least. Only the training throws are used.
    """
    aims = np.clip(np.array(start, dtype=np.float64), TARGET_AREA.low, TARGET_AREA.high)
    # the squared distances as two columns' sum: the same additions as ``.sum(-1)`` over
    # the pair, without numpy's slow reduction over a short last axis
    y, z = (np.ascontiguousarray(c) for c in np.asarray(train_targets).T)
    for i, goal in enumerate(desired):
        aim, best, best_miss = aims[i].copy(), aims[i].copy(), np.inf
        for _ in range(iterations + 1):
            d2 = (y - aim[0]) ** 2 + (z - aim[1]) ** 2
            rows = np.argpartition(d2, neighbours - 1)[:neighbours]
            u = train_targets[rows] - aim
            design = np.column_stack(
                [np.ones(len(u)), u, u[:, 0] ** 2, u[:, 0] * u[:, 1], u[:, 1] ** 2]
            )
            coef = np.linalg.lstsq(design, train_hits[rows], rcond=None)[0]  # (6, 2)
            miss = float(np.linalg.norm(goal - coef[0]))
            if miss < best_miss:
                best, best_miss = aim.copy(), miss
            jacobian = coef[1:3].T  # d hit / d target at the aim
            step = np.linalg.lstsq(jacobian, goal - coef[0], rcond=1e-3)[0]
            radius = float(np.sqrt(d2[rows].max()))
            norm = float(np.linalg.norm(step))
            if norm > radius:
                step *= radius / norm
            aim = np.clip(aim + step, TARGET_AREA.low, TARGET_AREA.high)
        aims[i] = best
    return aims


def _spread(error) -> dict[str, float]:
    """RMS per axis, and the median and 99th percentile of the error's length, metres."""
    y, z = rms(error)
    length = np.linalg.norm(error, axis=1)
    return {
        "rms_y_m": float(y),
        "rms_z_m": float(z),
        "median_m": float(np.median(length)),
        "p99_m": float(np.quantile(length, 0.99)),
    }


@dataclass
class AdaptiveThrowResult(Result):
    """What :func:`run_adaptive_throw` measured; RMS in metres per axis, times in s.

    ``layouts``: per grid size, layout (``"grid"``, ``"adaptive"``, one per EM
    checkpoint) and query (``QUERIES``) the cluster count, fit time, EM steps, noise-free
    re-throw RMS per axis and the median and 99th percentile of the error's length
    (``median_m``, ``p99_m``). ``noisy``: both layouts and queries at ``noisy_bins`` with
    release noise: RMS, the noise's own scatter and their ratio per axis
    (``rms_*``, ``scatter_*``, ``ratio_*``); ``noisy_bound``: the same for the exact
    inverse of the noise-free throw, with the median and 90th percentile of its
    noise-free miss (``miss_median_m``, ``miss_p90_m``: how far the desired hits lie
    beyond what a noise-free throw reaches). ``em_log_likelihoods``: the
    largest adaptive fit's curve (mean per-row). ``floor``: the local Newton inverse (a reference).
    The inverse model's rows also hold ``best_rms_*``: the re-throw RMS had each row
    taken the cluster candidate that the throw itself says misses least (a perfect
    choice among the model's answers), and ``tail``: where the squared error lies
    (:func:`error_tail`: the worst hits' share and each cause's, :func:`error_causes`). ``pieces``: per grid size, the RMS residual of one
    least-squares plane per equidistant cell through the unclamped training throws
    (:func:`plane_residuals`): the curvature that linear pieces of that size leave.
    ``active``: per strategy (``STRATEGIES``) the curve of ``{n, bins, rms_y_m, rms_z_m,
    seeds_y_m, seeds_z_m}``: the mean RMS over the seeds' curves, and each seed's.
    ``active_floor``: per budget the RMS of that budget's grid fitted on all ``n_train``
    training throws (``{n, bins, rms_y_m, rms_z_m}``): what the grid itself leaves, whichever
    targets were thrown. ``goals``: each goal's verdict.
    """

    experiment_name: ClassVar[str] = "adaptive_throw"

    n_train: int
    n_test: int
    seed: int
    pseudo_count: float
    layouts: list[dict]
    noisy: list[dict]
    noisy_bound: dict
    em_log_likelihoods: list[float]
    floor: dict
    pieces: list[dict]
    active: dict[str, list[dict]]
    goals: dict[str, bool]
    active_floor: list[dict] | None = None


def _layout_rows(k, layout, train, test_hits, window, config):
    """One grid size's rows of one layout: each checkpoint's fit scored by both queries.

    ``(rows, EM curve of the last checkpoint, floor aims)``: the floor aims (the local Newton
    inverse from this fit's posterior answers, :func:`local_inverse`) for the grid layout at the
    largest grid size only, else None.
    """
    rows, curve, floor = [], [], None
    for model, seconds, ll in _fit(layout, k, train, config):
        for query in QUERIES:
            aims, answer = inferred_aims(model, test_hits, window, query)
            if (layout, query, k) == ("grid", "posterior", config.bins[-1]):
                floor = local_inverse(*train, test_hits, aims, config.neighbours)
            thrown = throw(aims)
            row = {
                "layout": layout,
                "query": query,
                "bins": k,
                "n_clusters": k * k,
                "fit_s": seconds,
                "em_steps": max(0, len(ll) - 1),
            } | _spread(thrown.hit - test_hits)
            if answer is not None:
                candidates = answer.candidates.numpy()
                candidates = np.clip(candidates, TARGET_AREA.low, TARGET_AREA.high)
                best = best_candidate_error(candidates, test_hits)
                y, z = rms(best)
                row |= {"best_rms_y_m": float(y), "best_rms_z_m": float(z)}
                error = thrown.hit - test_hits
                cause = error_causes(error, best, answer.outside.numpy(), thrown.clamped)
                row["tail"] = error_tail(error, cause, test_hits)
            rows.append(row)
        curve = ll
    return rows, curve, floor


def _noisy_aims(layout, train, test_hits, window, config):
    """The noisy comparison's fit of one layout and its aims per query.

    ``(fit seconds, {query: aims}, bound aims)``: for the grid layout the bound's aims (the
    noise-free throws inverted from this fit's posterior answers, :func:`local_inverse`), else None.
    """
    model, seconds, _ = _fit(layout, config.noisy_bins, train[1], config)[-1]
    aims = {query: aims_for(model, test_hits, window, query) for query in QUERIES}
    bound = None
    if layout == "grid":
        bound = local_inverse(*train[0], test_hits, aims["posterior"], config.neighbours)
    return seconds, aims, bound


def _longest_first(config):
    """A task key's sort key, for the longest task first.

    The adaptive fits first (EM and the inverse query grow with the clusters), the most clusters
    first, then the rest.
    """

    def key(task):
        if task[0] == "active":
            return (False, 0)
        k = task[1] if task[0] == "layout" else config.noisy_bins
        return (task[-1] == "adaptive", k)

    return key


def run_adaptive_throw(config: AdaptiveThrowConfig) -> AdaptiveThrowResult:
    """Both layouts per grid size, the noisy comparison, the references and the active curves."""
    n = config.n_train + config.n_test
    seeds = np.random.SeedSequence(config.seed).spawn(5)
    exact = get_data(n, np.random.default_rng(seeds[0]), None)
    noise, noise_rng = ReleaseNoise(), np.random.default_rng(seeds[1])
    noisy = get_data(n, np.random.default_rng(seeds[2]), noise)
    train = [(t[: config.n_train], h[: config.n_train]) for t, h in (exact, noisy)]
    test = [(t[config.n_train :], h[config.n_train :]) for t, h in (exact, noisy)]
    window = [hit_window(tr[1], te[1]) for tr, te in zip(train, test, strict=True)]

    # the model work: independent tasks (longest first), on every core (workers); the
    # release noise is drawn here afterwards, in the order of the rows
    keys = [("layout", k, layout) for k in config.bins for layout in ("grid", "adaptive")]
    keys += [("noisy", layout) for layout in ("grid", "adaptive")]
    curves = seeds[3].spawn(config.active_seeds)  # per seed, the same first targets
    keys += [("active", strategy, i) for strategy in STRATEGIES for i in range(len(curves))]
    forked = forks(config.workers, len(keys))
    # forked workers' bars would mix: one bar over the tasks instead
    quiet = dataclasses.replace(config, progress=False) if forked else config

    def layout_task(k, layout):
        return lambda: _layout_rows(k, layout, train[0], test[0][1], window[0], quiet)

    def noisy_task(layout):
        return lambda: _noisy_aims(layout, train, test[1][1], window[1], quiet)

    def active_task(strategy, i):
        rng = np.random.default_rng(curves[i])
        return lambda: active_curve(strategy, quiet, test[0][1], window[0], rng)

    make = {"layout": layout_task, "noisy": noisy_task, "active": active_task}
    tasks = {key: make[key[0]](*key[1:]) for key in keys}
    order = sorted(keys, key=_longest_first(config), reverse=True)
    done = dict(
        zip(
            order,
            run_tasks(
                [tasks[key] for key in order],
                config.workers,
                desc="adaptive_throw",
                progress=config.progress and forked,
            ),
            strict=True,
        )
    )

    layouts, curve = [], []
    for k in config.bins:
        for layout in ("grid", "adaptive"):
            rows, ll, _ = done["layout", k, layout]
            layouts += rows
            curve = ll if layout == "adaptive" and k == config.bins[-1] else curve
    floor_aims = done["layout", config.bins[-1], "grid"][2]
    noisy_rows = []
    for layout in ("grid", "adaptive"):
        seconds, aims, _ = done["noisy", layout]
        for query in QUERIES:
            noisy_rows.append(
                {"layout": layout, "query": query, "bins": config.noisy_bins}
                | {"n_clusters": config.noisy_bins**2, "fit_s": seconds}
                | _noisy_spread(aims[query], test[1][1], config.noise_repeats, noise_rng, noise)
            )
    # the physics' bound: the noise-free throw inverted (to ~0.1 cm) at each desired hit
    aims = done["noisy", "grid"][2]
    reach = np.linalg.norm(throw(aims).hit - test[1][1], axis=1)  # beyond the arm's reach
    bound = {"repeats": config.noise_repeats} | _noisy_spread(
        aims, test[1][1], config.noise_repeats, noise_rng, noise
    )
    bound |= {
        "miss_median_m": float(np.median(reach)),
        "miss_p90_m": float(np.quantile(reach, 0.9)),
    }

    # Newton from the largest grid's posterior answers
    floor = {"neighbours": config.neighbours} | _spread(throw(floor_aims).hit - test[0][1])
    free = ~throw(train[0][0]).clamped  # where the map is smooth
    pieces = []
    for k in config.bins:
        residual = plane_residuals(*train[0], k, use=free)
        y, z = rms(residual[~np.isnan(residual[:, 0])])
        pieces.append({"bins": k, "n_clusters": k * k, "rms_y_m": float(y), "rms_z_m": float(z)})

    active = {
        strategy: mean_curve([done["active", strategy, i] for i in range(len(curves))])
        for strategy in STRATEGIES
    }
    active_floor = [
        grid_floor(budget, train[0], test[0][1], window[0], config) for budget in config.budgets
    ]
    adaptive = [r for r in layouts if r["layout"] == "adaptive"]
    worst_axis = [max(r["rms_y_m"], r["rms_z_m"]) for r in adaptive]
    fast = [e for e, r in zip(worst_axis, adaptive, strict=True) if r["fit_s"] < GOAL_FIT_S]
    adaptive_noisy = [r for r in noisy_rows if r["layout"] == "adaptive"]
    goals = {
        "adaptive re-throw RMS <= 0.01 cm on both axes, noise-free (any row)": min(worst_axis)
        <= GOAL_RMS_M,
        f"... with the fit under {GOAL_FIT_S:g} s on one core": bool(fast)
        and min(fast) <= GOAL_RMS_M,
        "adaptive with release noise within 5 % of the noise's scatter (either query)": any(
            max(r["ratio_y"], r["ratio_z"]) <= GOAL_NOISE_RATIO for r in adaptive_noisy
        ),
        "active targets (variance) below random at every budget after the first (thrown at "
        "random by both), both axes, mean of the seeds": below_at_every_budget(
            active["variance"][1:], active["random"][1:]
        ),
    }
    return AdaptiveThrowResult(
        n_train=config.n_train,
        n_test=config.n_test,
        seed=config.seed,
        pseudo_count=config.pseudo_count,
        layouts=layouts,
        noisy=noisy_rows,
        noisy_bound=bound,
        em_log_likelihoods=curve,
        floor=floor,
        pieces=pieces,
        active=active,
        goals={name: bool(ok) for name, ok in goals.items()},
        active_floor=active_floor,
    )
