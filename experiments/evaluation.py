"""Scoring of the can-world experiments: effect networks measured against the simulator.

* :func:`accuracy_histogram` -- desired minus achieved, in the bins of the paper's
  Table I (``-3 or less`` ... ``3 or more``).
* :func:`roc_auc` and :func:`roc_curve` -- how well a score (the surprise of
  :func:`inference.imitation_check`, say) separates failed from successful actions; the
  AUC is the Mann-Whitney statistic, ties counting one half, computed exactly.
* :func:`aim_robust_best` -- the best action when the actions are cells of a grid that is
  aimed at: among the actions tied for the highest posterior, the one whose
  neighbourhood also succeeds (the expected success under a Gaussian aim error of
  ``sigma`` cells), instead of whichever the tie-break by index happens to give.
* :func:`aim_pooled` -- the predictive of an action aimed at a grid cell when the
  executed aim is off by a Gaussian error of ``sigma`` cells: the cells' predictives
  averaged with Gaussian weights. It fills in outcomes that a table estimated from a few
  throws per cell misses but the neighbouring cells produced.
* :func:`tail_surprise` -- the imitation surprise of an observed outcome under a
  discrete predictive: the probability of the outcomes strictly more likely than it.
* :func:`sample_frequencies` -- a discrete predictive estimated from repeated outcomes:
  the simulator's own, from which the surprise's physics bound is computed.
* :func:`best_threshold` and :func:`rates_at` -- a score's operating point: the
  threshold chosen on one draw (the largest true- minus false-positive rate), and the
  rates it gives on another.
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = [
    "ACCURACY_BINS",
    "SURPRISE_LOG_TOLERANCE",
    "accuracy_histogram",
    "aim_pooled",
    "aim_robust_best",
    "best_threshold",
    "rates_at",
    "roc_auc",
    "roc_curve",
    "sample_frequencies",
    "tail_surprise",
]

#: Row labels of the paper's Table I, in order: desired minus achieved count.
ACCURACY_BINS = ("-3 or less", "-2", "-1", "0", "1", "2", "3 or more")


def accuracy_histogram(desired, achieved) -> dict[str, int]:
    """Count ``desired - achieved`` in the paper's bins (``ACCURACY_BINS``).

    Parameters
    ----------
    desired, achieved : (n,) int
        Desired and achieved counts.

    Returns
    -------
    dict
        Bin label -> number of cases, every label present (zero when empty).
    """
    desired = np.asarray(desired, dtype=np.int64)
    achieved = np.asarray(achieved, dtype=np.int64)
    if desired.shape != achieved.shape or desired.ndim != 1:
        raise ValueError(
            f"desired and achieved must be (n,) arrays of one length, got {desired.shape} "
            f"and {achieved.shape}"
        )
    diff = np.clip(desired - achieved, -3, 3)
    counts = np.bincount(diff + 3, minlength=len(ACCURACY_BINS))
    return {label: int(c) for label, c in zip(ACCURACY_BINS, counts, strict=True)}


def _scores_and_labels(scores, positive) -> tuple[np.ndarray, np.ndarray]:
    scores = np.asarray(scores, dtype=float)
    positive = np.asarray(positive, dtype=bool)
    if scores.shape != positive.shape or scores.ndim != 1:
        raise ValueError(
            f"scores and positive must be (n,) arrays of one length, got {scores.shape} "
            f"and {positive.shape}"
        )
    if positive.all() or not positive.any():
        raise ValueError(
            f"the ROC needs both classes; got {int(positive.sum())} positives of {len(positive)}"
        )
    return scores, positive


def roc_auc(scores, positive) -> float:
    """Area under the ROC curve: P(score of a positive > score of a negative), ties 1/2.

    Computed exactly as the Mann-Whitney U statistic from mid-ranks.

    Parameters
    ----------
    scores : (n,) float
        Higher means "more likely positive".
    positive : (n,) bool
        The true class.
    """
    scores, positive = _scores_and_labels(scores, positive)
    order = np.argsort(scores, kind="stable")
    sorted_scores = scores[order]
    ranks = np.empty(len(scores))
    # mid-ranks: every member of a run of equal scores gets the run's mean rank
    starts = np.flatnonzero(np.r_[True, sorted_scores[1:] != sorted_scores[:-1]])
    ends = np.r_[starts[1:], len(scores)]
    for lo, hi in zip(starts, ends, strict=True):
        ranks[order[lo:hi]] = (lo + hi + 1) / 2  # ranks lo+1 .. hi
    n_pos, n_neg = int(positive.sum()), int((~positive).sum())
    u = ranks[positive].sum() - n_pos * (n_pos + 1) / 2
    return float(u / (n_pos * n_neg))


def roc_curve(scores, positive) -> tuple[np.ndarray, np.ndarray]:
    """False- and true-positive rates at every threshold, from (0, 0) to (1, 1).

    Returns
    -------
    fpr, tpr : np.ndarray
        ``(m,)`` each; the trapezoid area under them equals :func:`roc_auc`.
    """
    scores, positive = _scores_and_labels(scores, positive)
    thresholds = np.unique(scores)[::-1]
    tp = np.array([(positive & (scores >= t)).sum() for t in thresholds])
    fp = np.array([(~positive & (scores >= t)).sum() for t in thresholds])
    tpr = np.r_[0.0, tp / positive.sum()]
    fpr = np.r_[0.0, fp / (~positive).sum()]
    return fpr, tpr


def rates_at(scores, positive, threshold: float) -> tuple[float, float]:
    """``(false-positive rate, true-positive rate)`` when a score ``>= threshold`` flags.

    ``scores`` and ``positive`` as in :func:`roc_auc`.
    """
    scores, positive = _scores_and_labels(scores, positive)
    flagged = scores >= threshold
    return float(flagged[~positive].mean()), float(flagged[positive].mean())


def best_threshold(scores, positive) -> float:
    """The score threshold of the largest true- minus false-positive rate (Youden's J).

    A score ``>= threshold`` flags. Candidates are the observed scores; among equally good
    ones, the highest (fewest flags). ``scores`` and ``positive`` as in :func:`roc_auc`.
    """
    scores, positive = _scores_and_labels(scores, positive)
    candidates = np.unique(scores)[::-1]
    j = [np.subtract(*rates_at(scores, positive, t)[::-1]) for t in candidates]
    return float(candidates[int(np.argmax(j))])


def aim_robust_best(
    probs: torch.Tensor,
    grid_shape: tuple[int, int],
    *,
    allowed: torch.Tensor | None = None,
    sigma: float = 1.0,
    rtol: float = 1e-9,
) -> torch.Tensor:
    """Best action per row, ties broken by the expected success under an aim error.

    The actions are the cells of a ``grid_shape = (rows, columns)`` grid in row-major
    order (action ``r * columns + c``), aimed at with some error. The primary criterion is
    the exact posterior ``probs``; among the actions within ``rtol`` (relative) of the
    row's maximum, the one with the highest posterior averaged over its neighbourhood
    with Gaussian weights ``exp(-d^2 / (2 sigma^2))`` (``d`` in cells; only allowed cells
    inside the grid count) wins. A cell in the interior of a region of equally good
    cells keeps succeeding when the aim or the region's border is off; one on the
    border does not. Remaining ties go to the lowest index.

    Parameters
    ----------
    probs : (n, A) float
        Posterior over actions (or any success score), ``A = rows * columns``.
    allowed : (A,) or (n, A) bool, optional
        Actions that may be chosen (and that count in the neighbourhood average).
    sigma : float
        Aim error in cells; ``0`` gives the index tie-break.

    Returns
    -------
    torch.Tensor
        ``(n,)`` long.
    """
    probs = torch.as_tensor(probs, dtype=torch.float64)
    n_rows, n_cols = grid_shape
    if probs.dim() != 2 or probs.shape[-1] != n_rows * n_cols:
        raise ValueError(
            f"probs must be (n, {n_rows * n_cols}) for a {n_rows} x {n_cols} grid, got "
            f"{tuple(probs.shape)}"
        )
    if allowed is None:
        allowed = torch.ones(probs.shape[-1], dtype=torch.bool)
    allowed = torch.as_tensor(allowed, dtype=torch.bool).expand_as(probs)
    if not bool(allowed.any(-1).all()):
        raise ValueError("every row needs at least one allowed action")
    score = probs.masked_fill(~allowed, -1.0)
    top = score.max(-1, keepdim=True).values
    tied = allowed & (score >= top - rtol * top.abs())
    best = tied.to(torch.int8).argmax(-1)
    if sigma <= 0:
        return best
    # a row with one tied action needs no tie-break: only the others are averaged (each
    # row's average is its own, so the subset's values are those of the whole batch)
    rows = torch.nonzero(tied.sum(-1) > 1)[:, 0]
    if len(rows):
        smooth = _grid_average(probs[rows], allowed[rows].to(probs.dtype), grid_shape, sigma)
        best[rows] = smooth.masked_fill(~tied[rows], -1.0).argmax(-1)
    return best


def _grid_average(values, weights, grid_shape, sigma) -> torch.Tensor:
    """Gaussian-weighted average of ``values`` over each cell's neighbourhood, ``(n, A)``."""
    n_rows, n_cols = grid_shape
    reach = int(np.ceil(3 * sigma))
    offsets = torch.arange(-reach, reach + 1, dtype=values.dtype)
    kernel = torch.exp(-(offsets[:, None] ** 2 + offsets[None, :] ** 2) / (2 * sigma**2))
    kernel = kernel[None, None]
    v = (values * weights).reshape(-1, 1, n_rows, n_cols)
    w = weights.reshape(-1, 1, n_rows, n_cols)
    num = torch.nn.functional.conv2d(v, kernel, padding=reach)
    den = torch.nn.functional.conv2d(w, kernel, padding=reach)
    return (num / den.clamp_min(1e-300)).reshape(values.shape)


#: Log-scale margin of :func:`tail_surprise` (as in :func:`inference.imitation_check`):
#: an outcome counts as more likely than the observed one only when its log-probability
#: exceeds the observed one's by more than this, so that rounding does not decide.
SURPRISE_LOG_TOLERANCE = 1e-9


def aim_pooled(
    probs,
    grid_shape: tuple[int, int],
    actions,
    *,
    allowed=None,
    sigma: float,
) -> torch.Tensor:
    """Predictive of each requested action under a Gaussian aim error of ``sigma`` cells.

    The actions are the cells of a ``grid_shape = (rows, columns)`` grid in row-major
    order (action ``r * columns + c``). Aiming at action ``a`` executes cell ``b`` with
    weight ``exp(-d(a, b)^2 / (2 sigma^2))`` (``d`` the Euclidean distance in cells;
    only allowed cells can be executed), so the pooled predictive is::

        pooled[a] = sum_b w(a, b) probs[b] / sum_b w(a, b)

    All cells count, however far (no truncation). ``sigma = 0`` returns ``probs[a]``.

    Parameters
    ----------
    probs : (A, K) or (B, A, K) float
        Predictive over ``K`` outcomes for every action, ``A = rows * columns``; each row
        non-negative and summing to 1. ``B``: a batch (one start state each, say).
    grid_shape : (int, int)
        ``(rows, columns)``.
    actions : (n,) int
        The aimed-at actions; each must be allowed. The same for every batch member.
    allowed : (A,) bool, optional
        Cells that can be executed (all by default).
    sigma : float
        Aim error in cells, ``>= 0``.

    Returns
    -------
    torch.Tensor
        ``(n, K)`` or ``(B, n, K)`` float64, each row summing to 1.
    """
    probs = torch.as_tensor(probs, dtype=torch.float64)
    n_rows, n_cols = grid_shape
    n_actions = n_rows * n_cols
    if probs.dim() not in (2, 3) or probs.shape[-2] != n_actions:
        raise ValueError(
            f"probs must be (A, K) or (B, A, K) with A = {n_actions} for a {n_rows} x "
            f"{n_cols} grid, got {tuple(probs.shape)}"
        )
    if not bool(torch.isfinite(probs).all()) or bool((probs < 0).any()):
        raise ValueError("probs must be finite and non-negative")
    if not torch.allclose(probs.sum(-1), torch.ones((), dtype=probs.dtype), atol=1e-6):
        raise ValueError("every row of probs must sum to 1 (a predictive distribution)")
    actions = torch.as_tensor(actions)
    if actions.dim() != 1 or actions.is_floating_point():
        raise ValueError(f"actions must be an (n,) integer array, got {tuple(actions.shape)}")
    if len(actions) and not bool(((actions >= 0) & (actions < n_actions)).all()):
        raise ValueError(f"actions must lie in 0..{n_actions - 1}, got {actions.tolist()}")
    if allowed is None:
        allowed = torch.ones(n_actions, dtype=torch.bool)
    allowed = torch.as_tensor(allowed, dtype=torch.bool)
    if allowed.shape != (n_actions,):
        raise ValueError(f"allowed must be ({n_actions},) bool, got {tuple(allowed.shape)}")
    if not bool(allowed[actions].all()):
        bad = actions[~allowed[actions]].tolist()
        raise ValueError(f"actions {bad} are not allowed: aim only at allowed cells")
    if not (np.isfinite(sigma) and sigma >= 0):
        raise ValueError(f"sigma must be a finite number of cells >= 0, got {sigma}")
    if sigma == 0:
        return probs[..., actions, :]
    row, col = torch.arange(n_actions) // n_cols, torch.arange(n_actions) % n_cols
    d2 = (row[actions, None] - row[None]) ** 2 + (col[actions, None] - col[None]) ** 2
    # the aimed-at cell weighs 1 even where sigma**2 underflows (0 / 0)
    gauss = torch.exp(-d2.to(torch.float64) / (2 * sigma**2))
    weights = torch.where(d2 == 0, 1.0, gauss) * allowed  # (n, A)
    return weights @ probs / weights.sum(-1, keepdim=True)


def tail_surprise(probs, observed) -> torch.Tensor:
    """Probability of the outcomes strictly more likely than the observed one.

    The surprise of :func:`inference.imitation_check` for a discrete predictive given as
    a table: near 1, the observed outcome is among the action's rare ones; an outcome of
    probability 0 has surprise 1 (up to the mass of the other zero-probability outcomes).
    "More likely" means a log-probability above the observed one's by more than
    ``SURPRISE_LOG_TOLERANCE`` (``1e-9``), so outcomes equal up to rounding tie and do
    not count.

    Parameters
    ----------
    probs : (..., K) float
        Predictive over ``K`` outcomes, non-negative.
    observed : (...) int
        Index of the observed outcome in ``0..K-1``, one per predictive.

    Returns
    -------
    torch.Tensor
        ``(...)`` float64 in [0, 1].
    """
    probs = torch.as_tensor(probs, dtype=torch.float64)
    observed = torch.as_tensor(observed)
    if probs.dim() < 1 or observed.shape != probs.shape[:-1]:
        raise ValueError(
            f"probs must be (..., K) and observed (...) with the same leading shape, got "
            f"{tuple(probs.shape)} and {tuple(observed.shape)}"
        )
    if observed.is_floating_point():
        raise ValueError("observed must hold integer outcome indices")
    k = probs.shape[-1]
    if observed.numel() and not bool(((observed >= 0) & (observed < k)).all()):
        raise ValueError(f"observed outcomes must lie in 0..{k - 1}")
    if not bool(torch.isfinite(probs).all()) or bool((probs < 0).any()):
        raise ValueError("probs must be finite and non-negative")
    log_p = probs.log()
    log_obs = torch.gather(log_p, -1, observed[..., None])
    more_likely = log_p > log_obs + SURPRISE_LOG_TOLERANCE
    return (probs * more_likely).sum(-1).clamp(0, 1)


def sample_frequencies(samples, n_outcomes: int) -> torch.Tensor:
    """The outcomes' relative frequencies among repeated draws, a predictive per row.

    Parameters
    ----------
    samples : (..., R) int
        ``R >= 1`` observed outcomes per row, indices in ``0..n_outcomes-1``.
    n_outcomes : int
        ``K``, the number of outcomes.

    Returns
    -------
    torch.Tensor
        ``(..., K)`` float64, each row summing to 1; an outcome never drawn has 0.
    """
    samples = torch.as_tensor(np.asarray(samples))
    if samples.dim() < 1 or samples.shape[-1] < 1 or samples.is_floating_point():
        raise ValueError(
            f"samples must be a (..., R) integer array with R >= 1, got {tuple(samples.shape)}"
        )
    if samples.numel() and not bool(((samples >= 0) & (samples < n_outcomes)).all()):
        raise ValueError(f"samples must lie in 0..{n_outcomes - 1}")
    counts = torch.zeros(*samples.shape[:-1], n_outcomes, dtype=torch.float64)
    counts.scatter_add_(-1, samples.long(), torch.ones(samples.shape, dtype=torch.float64))
    return counts / samples.shape[-1]
