"""The imitation surprise's scores: under whose predictive, how well, and its physics bound.

A throw's surprise is that of its observed end configuration under the intended field's
predictive (:func:`surprise_under`), from either source of predictives: the network's
tables (:func:`network_tables`) or the simulator's own outcome frequencies over repeated
jittered throws of every field (:func:`replay_tables`). The second gives the physics
bound (:func:`surprise_bound`): the ROC AUC the surprise reaches when the predictive is
the world's own, estimated from replays that the scored throws and their labels are not
part of. The experiment is described in :mod:`experiments.can_tossing`.
"""

from __future__ import annotations

import numpy as np
from effect_networks.experiments.can_tossing.settings import AIM_SIGMAS, FAILURE_LABELS
from effect_networks.experiments.cans import CanModel, Replays
from effect_networks.experiments.evaluation import (
    aim_pooled,
    best_threshold,
    rates_at,
    roc_auc,
    sample_frequencies,
    tail_surprise,
)
from effect_networks.sim2d import geometry

__all__ = [
    "auc_or_none",
    "network_tables",
    "operating_points",
    "replay_tables",
    "surprise_bound",
    "surprise_under",
    "validated_sigma",
]


def surprise_under(table_of, throws: dict, sigma: float, allowed) -> np.ndarray:
    """``(n,)`` surprise of each observed end configuration under the intended field's predictive.

    ``table_of(start)`` gives ``(probs, states)``: ``(195, K)`` predictive end configurations of
    every field from ``start`` and their ``(K,)`` masks, ascending. The predictive is pooled over an
    aim error of ``sigma`` fields among the ``allowed`` ones (:func:`aim_pooled`); an end
    configuration outside ``states`` has surprise 1.
    """
    start, observed = throws["start"], throws["observed"]
    surprise = np.ones(len(start))
    for s in np.unique(start):
        probs, states = table_of(int(s))
        rows = (start == s) & np.isin(observed, states)
        if not rows.any():
            continue
        pooled = aim_pooled(
            probs,
            (geometry.N_ROWS, geometry.N_COLUMNS),
            throws["field"][rows],
            allowed=allowed,
            sigma=sigma,
        )
        surprise[rows] = tail_surprise(pooled, np.searchsorted(states, observed[rows])).numpy()
    return surprise


def network_tables(model: CanModel):
    """:func:`surprise_under`'s ``table_of`` for the network, each start's table computed once."""
    tables: dict[int, tuple] = {}
    states = np.asarray(model.states)
    assert np.all(np.diff(states) > 0)  # the network's states are the masks in order

    def table_of(start: int):
        if start not in tables:
            tables[start] = (model.end_config_probs(start), states)
        return tables[start]

    return table_of


def replay_tables(sims: Replays):
    """:func:`surprise_under`'s ``table_of`` for the simulator: its replays' outcome frequencies."""

    def table_of(start: int):
        ends = sims.end_config[sims.row(start)]  # (195, repeats)
        states = np.unique(ends)
        return sample_frequencies(np.searchsorted(states, ends), len(states)), states

    return table_of


def auc_or_none(scores, positive) -> float | None:
    """ROC AUC, or None where one class is empty."""
    return roc_auc(scores, positive) if 0 < np.sum(positive) < len(positive) else None


def validated_sigma(table_of, held_out: dict, allowed) -> tuple[float, list[dict]]:
    """The aim error of ``AIM_SIGMAS`` with the best ``failed_ordinary`` AUC on ``held_out``.

    Ties to the smaller; with one class only, the first. Returns it and every aim error's AUCs.
    """
    validation = []
    for sigma in AIM_SIGMAS:
        scores = surprise_under(table_of, held_out, sigma, allowed)
        validation.append(
            {
                "sigma": sigma,
                "auc": auc_or_none(scores, held_out["failed"]),
                "auc_ordinary": auc_or_none(scores, held_out["failed_ordinary"]),
            }
        )
    scored = [v for v in validation if v["auc_ordinary"] is not None]
    sigma = max(scored, key=lambda v: v["auc_ordinary"])["sigma"] if scored else AIM_SIGMAS[0]
    return sigma, validation


def surprise_bound(sims: Replays, throws: dict, held_out: dict, allowed) -> dict:
    """The surprise's physics bound: the AUCs reached under the simulator's own outcome frequencies.

    Each throw's surprise is computed as the network's (:func:`surprise_under`), but from the
    frequencies of the intended field's replays (``sims``: the data set's jitter, seeds disjoint
    from the scored throws' and from their labels'), exact per aim and aim-pooled (aim error
    chosen on ``held_out`` by :func:`validated_sigma`). ``half_repeats``: the same from the first
    half of the replays, to show how far the estimate still moves with their number.
    """
    table_of = replay_tables(sims)
    sigma, by_sigma = validated_sigma(table_of, held_out, allowed)
    exact = surprise_under(table_of, throws, 0.0, allowed)
    pooled = surprise_under(table_of, throws, sigma, allowed)
    half = surprise_under(replay_tables(sims.head(sims.repeats // 2)), throws, 0.0, allowed)
    return {
        "repeats": sims.repeats,
        "auc": auc_or_none(exact, throws["failed"]),
        "auc_ordinary": auc_or_none(exact, throws["failed_ordinary"]),
        "aim_sigma": sigma,
        "auc_pooled": auc_or_none(pooled, throws["failed"]),
        "auc_ordinary_pooled": auc_or_none(pooled, throws["failed_ordinary"]),
        "half_repeats": {
            "repeats": sims.repeats // 2,
            "auc": auc_or_none(half, throws["failed"]),
            "auc_ordinary": auc_or_none(half, throws["failed_ordinary"]),
        },
        "by_sigma": by_sigma,
        "surprise": exact.tolist(),
        "pooled_surprise": pooled.tolist(),
    }


def operating_points(held_surprise, held_out: dict, surprise, throws: dict) -> dict:
    """Per failure label, the threshold chosen on ``held_out`` and its rates on ``throws``.

    :func:`best_threshold` of the held-out surprise; ``{label: {threshold, fpr, tpr}}`` (None
    where a draw has one class only).
    """
    points = {}
    for label in FAILURE_LABELS:
        if auc_or_none(held_surprise, held_out[label]) is None:
            points[label] = None
            continue
        t = best_threshold(held_surprise, held_out[label])
        rates = (None, None)
        if auc_or_none(surprise, throws[label]) is not None:
            rates = rates_at(surprise, throws[label], t)
        points[label] = {"threshold": t, "fpr": rates[0], "tpr": rates[1]}
    return points
