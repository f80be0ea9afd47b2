"""Evaluation helpers against independent computations: pair counting, hand-made grids."""

import itertools

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from inference.evaluation import (
    ACCURACY_BINS,
    accuracy_histogram,
    aim_robust_best,
    roc_auc,
    roc_curve,
)


def brute_force_auc(scores, positive):
    """Every (positive, negative) pair: 1 if the positive scores higher, 1/2 on a tie."""
    pos = [s for s, p in zip(scores, positive, strict=True) if p]
    neg = [s for s, p in zip(scores, positive, strict=True) if not p]
    wins = sum(1.0 if a > b else 0.5 if a == b else 0.0 for a, b in itertools.product(pos, neg))
    return wins / (len(pos) * len(neg))


def test_accuracy_histogram_bins():
    desired = np.array([5, 5, 5, 5, 5, 5, 5, 5, 5, 0])
    achieved = np.array([10, 8, 7, 6, 5, 4, 3, 2, 0, 0])  # diffs -5 -3 -2 -1 0 1 2 3 5 0
    hist = accuracy_histogram(desired, achieved)
    assert tuple(hist) == ACCURACY_BINS
    assert hist == {"-3 or less": 2, "-2": 1, "-1": 1, "0": 2, "1": 1, "2": 1, "3 or more": 2}
    assert sum(hist.values()) == len(desired)


def test_accuracy_histogram_rejects_mismatched_lengths():
    with pytest.raises(ValueError, match="one length"):
        accuracy_histogram([1, 2], [1])


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(st.integers(0, 5).map(float), st.booleans()), min_size=2, max_size=30
    ).filter(lambda rows: 0 < sum(p for _, p in rows) < len(rows))
)
def test_roc_auc_equals_pair_counting(rows):
    scores, positive = zip(*rows, strict=True)
    assert roc_auc(scores, positive) == pytest.approx(brute_force_auc(scores, positive))


@settings(max_examples=40, deadline=None)
@given(
    st.lists(
        st.tuples(st.integers(0, 4).map(float), st.booleans()), min_size=2, max_size=30
    ).filter(lambda rows: 0 < sum(p for _, p in rows) < len(rows))
)
def test_roc_curve_area_is_the_auc(rows):
    scores, positive = zip(*rows, strict=True)
    fpr, tpr = roc_curve(scores, positive)
    assert (fpr[0], tpr[0], fpr[-1], tpr[-1]) == (0.0, 0.0, 1.0, 1.0)
    assert np.all(np.diff(fpr) >= 0) and np.all(np.diff(tpr) >= 0)
    area = float(np.sum(np.diff(fpr) * (tpr[1:] + tpr[:-1]) / 2))
    assert area == pytest.approx(roc_auc(scores, positive))


def test_roc_auc_extremes_and_one_class():
    assert roc_auc([0.1, 0.2, 0.9, 0.95], [False, False, True, True]) == 1.0
    assert roc_auc([0.9, 0.95, 0.1, 0.2], [False, False, True, True]) == 0.0
    assert roc_auc([0.5, 0.5, 0.5], [True, False, False]) == 0.5
    with pytest.raises(ValueError, match="both classes"):
        roc_auc([0.1, 0.2], [True, True])


def test_aim_robust_best_prefers_the_interior_of_a_tied_region():
    # 5 x 7 grid: a 3 x 3 block of top cells (rows 1-3, columns 3-5) amid failing cells,
    # and an isolated top cell at (0, 0). The index tie-break takes (0, 0); the aim rule
    # the block's centre, the one tied cell whose whole neighbourhood succeeds.
    p = torch.full((5, 7), 0.01, dtype=torch.float64)
    p[1:4, 3:6] = 0.3
    p[0, 0] = 0.3
    probs = p.reshape(1, -1)
    assert int(aim_robust_best(probs, (5, 7), sigma=0)) == 0
    assert divmod(int(aim_robust_best(probs, (5, 7), sigma=1.0)), 7) == (2, 4)
    p[4, 6] = 0.31  # a unique maximum wins whatever its neighbours
    assert int(aim_robust_best(p.reshape(1, -1), (5, 7))) == 34


def test_aim_robust_best_respects_allowed_and_matches_hand_average():
    gen = torch.Generator().manual_seed(0)
    probs = torch.rand(4, 12, generator=gen, dtype=torch.float64).round(decimals=1)
    allowed = torch.rand(4, 12, generator=gen) > 0.3
    allowed[:, 0] = True
    sigma = 0.8
    best = aim_robust_best(probs, (3, 4), allowed=allowed, sigma=sigma)
    for row in range(4):
        score = probs[row].masked_fill(~allowed[row], -1)
        tied = [a for a in range(12) if allowed[row, a] and score[a] >= score.max() * (1 - 1e-9)]

        def average(a, row=row):
            r, c = divmod(a, 4)
            num = den = 0.0
            for b in range(12):
                if not allowed[row, b]:
                    continue
                rb, cb = divmod(b, 4)
                w = np.exp(-((r - rb) ** 2 + (c - cb) ** 2) / (2 * sigma**2))
                num, den = num + w * float(probs[row, b]), den + w
            return num / den

        expected = max(tied, key=lambda a: (average(a), -a))
        assert int(best[row]) == expected


def test_aim_robust_best_bad_shapes():
    with pytest.raises(ValueError, match="grid"):
        aim_robust_best(torch.ones(2, 10), (3, 4))
    with pytest.raises(ValueError, match="allowed"):
        aim_robust_best(torch.ones(1, 4), (2, 2), allowed=torch.zeros(4, dtype=torch.bool))
