"""Evaluation helpers against independent computations: pair counting, hand-made grids,
brute-force tail sums and the network's own imitation check."""

import itertools

import numpy as np
import pytest
import torch
from effect_networks.experiments.evaluation import (
    ACCURACY_BINS,
    accuracy_histogram,
    aim_pooled,
    aim_robust_best,
    best_threshold,
    rates_at,
    roc_auc,
    roc_curve,
    sample_frequencies,
    tail_surprise,
)
from effect_networks.inference.queries import imitation_check, predict
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.helpers import discrete_network, random_params


def brute_force_auc(scores, positive):
    """Every (positive, negative) pair: 1 if the positive scores higher, 1/2 on a tie."""
    pos = [s for s, p in zip(scores, positive, strict=True) if p]
    neg = [s for s, p in zip(scores, positive, strict=True) if not p]
    wins = sum(1.0 if a > b else 0.5 if a == b else 0.0 for a, b in itertools.product(pos, neg))
    return wins / (len(pos) * len(neg))


def scored_rows(top: int):
    """2-30 (score, positive) rows, scores integers 0..top (ties), both classes present."""
    return st.lists(
        st.tuples(st.integers(0, top).map(float), st.booleans()), min_size=2, max_size=30
    ).filter(lambda rows: 0 < sum(p for _, p in rows) < len(rows))


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
@given(scored_rows(5))
def test_roc_auc_equals_pair_counting(rows):
    scores, positive = zip(*rows, strict=True)
    assert roc_auc(scores, positive) == pytest.approx(brute_force_auc(scores, positive))


@settings(max_examples=40, deadline=None)
@given(scored_rows(4))
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


def test_best_threshold_by_hand():
    scores, positive = [0.1, 0.4, 0.35, 0.8], [False, False, True, True]
    # >= 0.8: TPR 1/2, FPR 0; >= 0.35: TPR 1, FPR 1/2 -- tied at J = 1/2: the higher one
    assert best_threshold(scores, positive) == 0.8
    assert rates_at(scores, positive, 0.8) == (0.0, 0.5)
    assert rates_at(scores, positive, 0.35) == (0.5, 1.0)
    with pytest.raises(ValueError, match="both classes"):
        best_threshold([0.1, 0.2], [True, True])


@settings(max_examples=40, deadline=None)
@given(scored_rows(6))
def test_best_threshold_is_the_roc_point_farthest_above_the_diagonal(rows):
    scores, positive = zip(*rows, strict=True)
    fpr, tpr = roc_curve(scores, positive)
    chosen = best_threshold(scores, positive)
    f, t = rates_at(scores, positive, chosen)
    assert t - f == pytest.approx(np.max(tpr - fpr))
    assert any(f == a and t == b for a, b in zip(fpr, tpr, strict=True))  # a point of the curve


def test_sample_frequencies_by_hand():
    freq = sample_frequencies([[0, 0, 0, 1], [2, 2, 2, 2]], 3)
    assert freq.tolist() == [[0.75, 0.25, 0.0], [0.0, 0.0, 1.0]]
    # the surprise under them: 0 for the most frequent outcome, 1 for one never drawn
    surprise = tail_surprise(freq, torch.tensor([1, 0]))
    assert surprise.tolist() == [0.75, 1.0]


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 5), st.integers(1, 9), st.integers(1, 4), st.integers(0, 2**32 - 1))
def test_sample_frequencies_are_the_counts_over_the_draws(k, repeats, rows, seed):
    samples = np.random.default_rng(seed).integers(0, k, (rows, repeats))
    freq = sample_frequencies(samples, k)
    expected = [np.bincount(row, minlength=k) / repeats for row in samples]
    assert np.allclose(freq.numpy(), expected)
    assert np.allclose(freq.sum(-1).numpy(), 1.0)


def test_sample_frequencies_bad_inputs():
    with pytest.raises(ValueError, match="R >= 1"):
        sample_frequencies(np.zeros((2, 0), np.int64), 3)
    with pytest.raises(ValueError, match="integer"):
        sample_frequencies([[0.5]], 3)
    with pytest.raises(ValueError, match=r"lie in 0\.\.2"):
        sample_frequencies([[3]], 3)


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


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_aim_robust_best_respects_allowed_and_matches_hand_average(seed):
    """Rows with one tied action, with several and with all of them, each answered as the hand
    average says, and as the row alone is answered."""
    gen = torch.Generator().manual_seed(seed)
    n = 40
    probs = torch.rand(n, 12, generator=gen, dtype=torch.float64).round(decimals=1)
    probs[:5] = 0.5  # every action tied
    allowed = torch.rand(n, 12, generator=gen) > 0.3
    allowed[:, 0] = True
    sigma = 0.8
    best = aim_robust_best(probs, (3, 4), allowed=allowed, sigma=sigma)
    alone = [
        int(aim_robust_best(probs[r : r + 1], (3, 4), allowed=allowed[r], sigma=sigma))
        for r in range(n)
    ]
    assert best.tolist() == alone
    for row in range(n):
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


def random_predictive(shape, seed):
    """Random rows on the simplex, some outcomes impossible."""
    gen = torch.Generator().manual_seed(seed)
    p = torch.rand(shape, generator=gen, dtype=torch.float64) ** 3
    p = p * (torch.rand(shape, generator=gen) > 0.3)
    p[..., 0] += 1e-3  # no empty row
    return p / p.sum(-1, keepdim=True)


def test_aim_pooled_without_aim_error_is_the_actions_own_row():
    probs = random_predictive((12, 5), 1)
    actions = torch.tensor([0, 7, 11, 7])
    for sigma in (0.0, 1e-3):
        assert torch.allclose(aim_pooled(probs, (3, 4), actions, sigma=sigma), probs[actions])


def test_aim_pooled_hand_computed_three_by_three():
    # Outcome 0 at the centre cell only, outcome 1 everywhere else; the corner (2, 2)
    # cannot be executed. Aiming at the centre with sigma = 1 weighs the centre 1, its
    # four edge neighbours e = exp(-1/2) each and the three allowed corners c = exp(-1).
    probs = torch.zeros(9, 2, dtype=torch.float64)
    probs[:, 1] = 1
    probs[4] = torch.tensor([1.0, 0.0])
    allowed = torch.ones(9, dtype=torch.bool)
    allowed[8] = False
    e, c = np.exp(-0.5), np.exp(-1.0)
    pooled = aim_pooled(probs, (3, 3), [4, 0], allowed=allowed, sigma=1.0)
    centre = 1 / (1 + 4 * e + 3 * c)
    assert pooled[0].tolist() == pytest.approx([centre, 1 - centre])
    # corner (0, 0): itself 1, edges (0, 1), (1, 0) at e, centre at c, (0, 2) and (2, 0)
    # at exp(-2), (1, 2) and (2, 1) at exp(-5/2); (2, 2) not allowed
    den = 1 + 2 * e + c + 2 * np.exp(-2) + 2 * np.exp(-2.5)
    assert pooled[1].tolist() == pytest.approx([c / den, 1 - c / den])


@settings(max_examples=30, deadline=None)
@given(
    rows=st.integers(1, 4),
    cols=st.integers(1, 5),
    k=st.integers(1, 6),
    sigma=st.floats(0.0, 3.0),
    seed=st.integers(0, 10_000),
)
def test_aim_pooled_rows_are_distributions_and_match_the_weighted_sum(rows, cols, k, sigma, seed):
    a = rows * cols
    probs = random_predictive((2, a, k), seed)
    gen = torch.Generator().manual_seed(seed)
    allowed = torch.rand(a, generator=gen) > 0.4
    allowed[seed % a] = True
    actions = allowed.nonzero().flatten()
    pooled = aim_pooled(probs, (rows, cols), actions, allowed=allowed, sigma=sigma)
    assert pooled.shape == (2, len(actions), k)
    assert torch.allclose(pooled.sum(-1), torch.ones((), dtype=torch.float64), atol=1e-12)
    for i, act in enumerate(actions.tolist()):
        r, c = divmod(act, cols)
        total, weight = torch.zeros(2, k, dtype=torch.float64), 0.0
        for b in range(a):
            if not allowed[b]:
                continue
            rb, cb = divmod(b, cols)
            d2 = (r - rb) ** 2 + (c - cb) ** 2
            w = 1.0 if d2 == 0 else 0.0 if sigma**2 == 0 else np.exp(-d2 / (2 * sigma**2))
            total, weight = total + w * probs[:, b], weight + w
        assert torch.allclose(pooled[:, i], total / weight)


def test_aim_pooled_bad_inputs():
    probs = random_predictive((6, 3), 0)
    with pytest.raises(ValueError, match="grid"):
        aim_pooled(probs, (3, 3), [0], sigma=1.0)
    with pytest.raises(ValueError, match="sum to 1"):
        aim_pooled(2 * probs, (2, 3), [0], sigma=1.0)
    with pytest.raises(ValueError, match="0..5"):
        aim_pooled(probs, (2, 3), [6], sigma=1.0)
    allowed = torch.tensor([True, False, True, True, True, True])
    with pytest.raises(ValueError, match="not allowed"):
        aim_pooled(probs, (2, 3), [1], allowed=allowed, sigma=1.0)
    with pytest.raises(ValueError, match="sigma"):
        aim_pooled(probs, (2, 3), [0], sigma=-0.5)


def brute_tail(p, observed):
    """Sum over outcomes whose probability exceeds the observed one's beyond rounding."""
    return sum(q for q in p if q > p[observed] * np.exp(1e-9))


@settings(max_examples=50, deadline=None)
@given(k=st.integers(1, 8), seed=st.integers(0, 10_000), data=st.data())
def test_tail_surprise_equals_a_loop_over_outcomes(k, seed, data):
    probs = random_predictive((3, k), seed)
    probs[0] = torch.full((k,), 1 / k)  # all tied: nothing is strictly more likely
    observed = torch.tensor([data.draw(st.integers(0, k - 1)) for _ in range(3)])
    got = tail_surprise(probs, observed)
    for i in range(3):
        assert float(got[i]) == pytest.approx(brute_tail(probs[i].tolist(), int(observed[i])))
    assert float(got[0]) == 0.0


def test_tail_surprise_of_an_impossible_outcome():
    probs = torch.tensor([[0.5, 0.5, 0.0, 0.0]], dtype=torch.float64)
    assert tail_surprise(probs, torch.tensor([2])).tolist() == [1.0]
    assert tail_surprise(probs, torch.tensor([0])).tolist() == [0.0]


def test_tail_surprise_bad_inputs():
    probs = random_predictive((2, 4), 0)
    with pytest.raises(ValueError, match="leading shape"):
        tail_surprise(probs, torch.tensor([0]))
    with pytest.raises(ValueError, match="0..3"):
        tail_surprise(probs, torch.tensor([0, 4]))
    with pytest.raises(ValueError, match="non-negative"):
        tail_surprise(-probs, torch.tensor([0, 1]))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_unpooled_tail_surprise_is_the_networks_imitation_check(seed):
    # One discrete end feature, six actions on a 2 x 3 grid: the network's predictive per
    # action, pooled with sigma = 0, scored by tail_surprise, against imitation_check.
    net = discrete_network([4], 6)
    params = random_params(net, seed)
    gen = torch.Generator().manual_seed(seed)
    n = 20
    initial = torch.randint(0, 4, (n,), generator=gen)
    action = torch.randint(0, 6, (n,), generator=gen)
    end = torch.randint(0, 4, (n,), generator=gen)
    check = imitation_check(
        net,
        params,
        net.encode_indices({"initial.f0": initial, "action": action, "end.f0": end}),
    ).surprise
    for s in range(4):
        rows = initial == s
        table = predict(
            net, params, {"initial.f0": torch.full((6,), s), "action": list(net.actions)}
        ).discrete["f0"]
        pooled = aim_pooled(table, (2, 3), action[rows], sigma=0.0)
        assert torch.allclose(tail_surprise(pooled, end[rows]), check[rows], atol=1e-12)
