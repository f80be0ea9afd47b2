"""Aiming by the inverse model: its aims, their re-throws and where their error lies.

The adaptive-throw experiment (:mod:`experiments.adaptive_throw`) scores every fitted throw
network by re-throwing at the aims it infers for desired hits; these are the aims, the
re-throws and the error's causes and tail.
"""

from __future__ import annotations

import math

import numpy as np
from effect_networks.experiments.adaptive_throw.settings import CAUSES
from effect_networks.experiments.throwing import HIT_MARGIN_M, rms
from effect_networks.inference import infer_parameter, parameter_for_effect
from effect_networks.models.humanoid_throw import TARGET, hit_evidence
from effect_networks.sim2d.analytic_throw import TARGET_AREA, throw

__all__ = [
    "NEGLIGIBLE_M",
    "aims_for",
    "best_candidate_error",
    "error_causes",
    "error_tail",
    "hit_window",
    "inferred_aims",
    "rethrow_error",
]


def inferred_aims(model, desired, window, query="posterior"):
    """The inferred aims ``(n, 2)`` for the desired hits, clipped into the area.

    And for the inverse model its answer (:class:`inference.ParameterForEffect`: every cluster's
    candidate, the chosen cluster, whether the value lies outside the area; None for the
    posterior query).
    """
    net, params = model
    evidence = hit_evidence(desired, low=window[0], high=window[1])
    if query == "posterior":
        aim, answer = infer_parameter(net, params, TARGET, evidence).mean, None
    else:
        answer = parameter_for_effect(net, params, TARGET, evidence)
        aim = answer.value
    return np.clip(aim.numpy(), TARGET_AREA.low, TARGET_AREA.high), answer


def aims_for(model, desired, window, query="posterior"):
    """The inferred aims ``(n, 2)`` for the desired hits, clipped into the area."""
    return inferred_aims(model, desired, window, query)[0]


def best_candidate_error(candidates, desired):
    """Errors ``(n, 2)`` of re-throwing at the candidate that the throw itself says misses least.

    How well a perfect choice among the model's per-cluster answers would do; ``candidates``
    ``(n, C, 2)``, clipped into the area.
    """
    n, c, _ = candidates.shape
    hits = throw(candidates.reshape(n * c, 2)).hit.reshape(n, c, 2)
    best = np.linalg.norm(hits - desired[:, None], axis=-1).argmin(1)
    return hits[np.arange(n), best] - desired


#: An RMS below this (m; a tenth of the report's last digit) is rounding: its shares mean nothing.
NEGLIGIBLE_M = 1e-7


def error_causes(error, best_error, outside, clamped) -> np.ndarray:
    """``(n,)`` index into ``CAUSES`` of what each hit's re-throw error is put down to.

    ``error``, ``best_error`` ``(n, 2)``: the re-throw errors at the inverse model's aim and at
    its best candidate (:func:`best_candidate_error`); ``outside`` ``(n,)``: its answer lay outside the
    target area (clipped into it); ``clamped`` ``(n,)``: the arm clamps at the aim (where the map
    has a kink). The first that applies: ``clipped``, ``clamped``, ``choice`` (another cluster's
    candidate misses by less than half as much), else ``curvature`` (what the chosen linear
    piece leaves of the map).
    """
    length, best = np.linalg.norm(error, axis=1), np.linalg.norm(best_error, axis=1)
    cause = np.full(len(length), CAUSES.index("curvature"))
    cause[best < length / 2] = CAUSES.index("choice")
    cause[clamped] = CAUSES.index("clamped")
    cause[outside] = CAUSES.index("clipped")
    return cause


def error_tail(error, cause, desired, worst: float = 0.01, shown: int = 5) -> dict:
    """Where a re-throw error's sum of squares lies, per axis.

    ``worst_share_*``: the share carried by the ``worst`` fraction of the hits (by the error's
    length, at least one hit); ``share_*``: the share of each of ``CAUSES``
    (:func:`error_causes`); None where an axis has no error to speak of (RMS under
    ``NEGLIGIBLE_M``, rounding). ``worst_hits``: the ``shown``
    largest errors, each with its desired hit and error (m) and its cause.
    """
    squares = error**2
    total, rms_ = squares.sum(0), rms(error)
    order = np.argsort(-np.linalg.norm(error, axis=1), kind="stable")
    top = order[: max(1, math.ceil(worst * len(order)))]

    def share(rows) -> list[float | None]:
        return [
            float(squares[rows, a].sum() / total[a]) if rms_[a] >= NEGLIGIBLE_M else None
            for a in (0, 1)
        ]

    out = {"worst_fraction": worst, "n_worst": len(top)}
    out |= dict(zip(("worst_share_y", "worst_share_z"), share(top), strict=True))
    for k, name in enumerate(CAUSES):
        out |= dict(zip((f"share_y_{name}", f"share_z_{name}"), share(cause == k), strict=True))
    out["worst_hits"] = [
        {
            "desired_y_m": float(desired[i, 0]),
            "desired_z_m": float(desired[i, 1]),
            "error_y_m": float(error[i, 0]),
            "error_z_m": float(error[i, 1]),
            "cause": CAUSES[cause[i]],
        }
        for i in order[:shown]
    ]
    return out


def rethrow_error(model, desired, window, rng=None, noise=None, query="posterior"):
    """Errors ``(n, 2)`` of re-throwing at the inferred aims."""
    return throw(aims_for(model, desired, window, query), rng=rng, noise=noise).hit - desired


def hit_window(*hits):
    """The box ``(low, high)`` around every hit given, widened by ``HIT_MARGIN_M``."""
    every = np.concatenate(hits)
    return every.min(0) - HIT_MARGIN_M, every.max(0) + HIT_MARGIN_M
