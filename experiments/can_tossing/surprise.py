"""The imitation surprise's scores: under whose predictive, how well, and its physics bound.

A throw's surprise is that of its observed end configuration under the intended field's
predictive (:func:`surprise_under`), from either source of predictives: the network's
tables (:func:`network_tables`) or the simulator's own outcome frequencies over repeated
jittered throws of every field (:func:`replay_tables`). The second gives the physics
bound (:func:`surprise_bound`): the ROC AUC the surprise reaches when the predictive is
the world's own, estimated from replays that the scored throws and their labels are not
part of. An estimate from a few replays per aim is not the world's own predictive yet, so
:func:`bound_curve` measures how the bound moves as fresh replays of each scored throw's
own aim grow. The experiment is described in :mod:`experiments.can_tossing`.
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
    "bound_curve",
    "curve_counts",
    "own_replay_surprise",
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


def own_replay_surprise(ends, observed) -> np.ndarray:
    """``(n,)`` surprise of each observed end configuration under its own replays' frequencies.

    ``ends``: ``(n, R)`` end configurations of ``R`` replays of row ``i``'s intended throw;
    ``observed``: ``(n,)`` what row ``i``'s throw did. The surprise is
    :func:`experiments.evaluation.tail_surprise` of the replays' outcome frequencies: the
    share of replays whose outcome was strictly more frequent than the observed one; an
    outcome none of the replays gave has surprise 1.
    """
    ends, observed = np.asarray(ends), np.asarray(observed)
    if ends.ndim != 2 or ends.shape[1] < 1 or observed.shape != ends.shape[:1]:
        raise ValueError(
            f"ends must be (n, R) with R >= 1 and observed (n,), got {ends.shape} and "
            f"{observed.shape}"
        )
    surprise = np.ones(len(observed))
    for i, (row, seen) in enumerate(zip(ends, observed, strict=True)):
        states = np.unique(row)
        if seen in states:
            freq = sample_frequencies(np.searchsorted(states, row)[None], len(states))
            surprise[i] = float(tail_surprise(freq, np.searchsorted(states, [seen]))[0])
    return surprise


def curve_counts(repeats: int) -> list[int]:
    """The replay counts :func:`bound_curve` measures at: 2, 4, 8, ... below ``repeats``, and it."""
    if repeats < 2:
        raise ValueError(f"repeats must be at least 2, got {repeats}")
    counts = [2**k for k in range(1, repeats.bit_length()) if 2**k < repeats]
    return [*counts, repeats]


def bound_curve(ends, throws: dict) -> list[dict]:
    """The surprise's physics bound from the first ``R`` replays of each scored throw's own aim.

    ``ends``: ``(n, repeats)`` end configurations of fresh replays of each of the ``n`` scored
    throws' intended (start, field), seeds disjoint from the data set's, the throws' and
    their labels'. For each ``R`` of :func:`curve_counts`, ``{repeats, auc,
    auc_ordinary}``: the ROC AUCs of :func:`own_replay_surprise` from the first ``R``
    replays against the throws' two failure labels. Where the AUCs stop moving as ``R``
    doubles, the estimate has reached the bound a detector that knew the world's outcome
    distribution per aim would reach.
    """
    ends = np.asarray(ends)
    curve = []
    for r in curve_counts(ends.shape[1]):
        scores = own_replay_surprise(ends[:, :r], throws["observed"])
        curve.append(
            {
                "repeats": r,
                "auc": auc_or_none(scores, throws["failed"]),
                "auc_ordinary": auc_or_none(scores, throws["failed_ordinary"]),
            }
        )
    return curve
