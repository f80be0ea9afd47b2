"""The active curves: throw targets chosen by a rule, the re-throw error against the budget.

Each curve starts from random targets, then adds batches chosen among random candidates
by its strategy (:data:`~experiments.adaptive_throw.settings.STRATEGIES`) on the grid that
will be fitted at the next budget, and at each budget fits that grid and re-throws. Beside
the curves: the same grid fitted on every training throw (the grid's floor).
"""

from __future__ import annotations

import math

import numpy as np
from effect_networks.experiments.adaptive_throw.aiming import hit_window, rethrow_error
from effect_networks.experiments.adaptive_throw.settings import ROWS_PER_CLUSTER
from effect_networks.experiments.throwing import rms
from effect_networks.inference import fit
from effect_networks.inference.design.active_gaussian import (
    select_by_information,
    select_by_variance,
)
from effect_networks.models.humanoid_throw import TARGET, throw_data, throw_network
from effect_networks.sim2d.analytic_throw import TARGET_AREA, sample_targets, throw
from tqdm.auto import tqdm

__all__ = [
    "active_curve",
    "below_at_every_budget",
    "grid_floor",
    "grid_for",
    "mean_curve",
    "near_edge",
]


def grid_for(n: int) -> int:
    """Clusters per axis of the grid fitted to ``n`` throws: about 30 a cluster, 2..16."""
    return int(min(16, max(2, round(math.sqrt(n / ROWS_PER_CLUSTER)))))


def active_curve(strategy, config, test_hits, window, rng):
    """Re-throw RMS at each budget, the targets chosen by ``strategy`` (one of ``STRATEGIES``).

    ``"variance"`` sums the predictive variance over a fresh uniform sample of the target area
    each round (the targets the inverse model will be asked to reach are hits of such targets).
    Each point also holds ``edge_share``: the share of the targets chosen since the last budget
    that lie within a tenth of a cell's width of an edge of the grid they were chosen for
    (uniform targets: 36 %); None at the first budget.
    """
    targets = sample_targets(config.budgets[0], rng)
    hits = throw(targets).hit
    curve = []
    edge_picks = []
    bar = tqdm(total=config.budgets[-1], desc=f"active ({strategy})", disable=not config.progress)
    bar.update(len(targets))
    for budget in config.budgets:
        while len(targets) < budget:
            k = min(config.batch, budget - len(targets))
            pool = sample_targets(config.pool, rng)
            if strategy == "random":
                chosen = pool[:k]
            else:
                net = throw_network((grid_for(budget),) * 2)  # the grid to be fitted
                candidates = {"action": [net.actions[0]] * len(pool), f"param.{TARGET}": pool}
                data = throw_data(net, targets, hits)
                if strategy == "information":
                    index = select_by_information(net, TARGET, data, candidates, k)
                else:
                    area = sample_targets(config.pool, rng)
                    reference = {"action": [net.actions[0]] * len(area), f"param.{TARGET}": area}
                    index = select_by_variance(
                        net, TARGET, data, candidates, k, reference=reference
                    )
                chosen = pool[index.numpy()]
            edge_picks.append(near_edge(chosen, grid_for(budget)))
            targets = np.concatenate([targets, chosen])
            hits = np.concatenate([hits, throw(chosen).hit])
            bar.update(len(chosen))
        k = grid_for(len(targets))
        net = throw_network((k, k))
        data = throw_data(net, targets, hits)
        params = fit(net, data, pseudo_count=config.pseudo_count).params
        error = rethrow_error((net, params), test_hits, hit_window(window, hits))
        y, z = rms(error)
        share = float(np.concatenate(edge_picks).mean()) if edge_picks else None
        edge_picks = []
        curve.append(
            {"n": len(targets), "bins": k, "rms_y_m": float(y), "rms_z_m": float(z)}
            | {"edge_share": share}
        )
    bar.close()
    return curve


def near_edge(targets: np.ndarray, bins: int) -> np.ndarray:
    """``(n,)`` bool: within a tenth of a cell's width of an edge of the ``bins`` x ``bins`` grid."""
    cell = (targets - TARGET_AREA.low) / (TARGET_AREA.high - TARGET_AREA.low) * bins
    offset = cell - np.floor(cell)
    return (np.abs(offset - 0.5) > 0.4).any(1)


def mean_curve(curves: list[list[dict]]) -> list[dict]:
    """The seeds' curves as one: the mean RMS per budget, with each seed's."""
    out = []
    for rows in zip(*curves, strict=True):
        row = {"n": rows[0]["n"], "bins": rows[0]["bins"]}
        shares = [r["edge_share"] for r in rows if r.get("edge_share") is not None]
        row["edge_share"] = float(np.mean(shares)) if shares else None
        for axis in ("y", "z"):
            values = [r[f"rms_{axis}_m"] for r in rows]
            row[f"rms_{axis}_m"] = float(np.mean(values))
            row[f"seeds_{axis}_m"] = values
        out.append(row)
    return out


def below_at_every_budget(curve: list[dict], other: list[dict]) -> bool:
    """Whether ``curve`` is below ``other`` at every budget on both axes."""
    return all(
        a["rms_y_m"] < b["rms_y_m"] and a["rms_z_m"] < b["rms_z_m"]
        for a, b in zip(curve, other, strict=True)
    )


def grid_floor(budget, train, test_hits, window, config) -> dict:
    """The re-throw RMS of ``budget``'s grid fitted on every training throw."""
    k = grid_for(budget)
    net = throw_network((k, k))
    params = fit(net, throw_data(net, *train), pseudo_count=config.pseudo_count).params
    y, z = rms(rethrow_error((net, params), test_hits, hit_window(window, train[1])))
    return {"n": budget, "bins": k, "rms_y_m": float(y), "rms_z_m": float(z)}
