"""Choosing parameter values by information and by variance: closed forms against a recount."""

import math

import pytest
import torch
from effect_networks.inference.design.active_gaussian import (
    regression_information,
    select_by_information,
    select_by_variance,
    variance_reduction,
)
from effect_networks.models import Continuous, EffectNetwork, Parameter
from effect_networks.models.declaration import DTYPE

NET = EffectNetwork(
    (Continuous("y", 2, initial=False),),
    ("go",),
    (Parameter("p", (0.0, 0.0), (1.0, 1.0), (2, 2), ("go",), "y"),),
)


def rows(theta):
    theta = torch.as_tensor(theta, dtype=DTYPE)
    y = torch.stack([theta[:, 0] + theta[:, 1] ** 2, theta[:, 1]], -1)
    return {"action": ["go"] * len(theta), "param.p": theta, "end.y": y}


def candidates(theta):
    return {"action": ["go"] * len(theta), "param.p": torch.as_tensor(theta, dtype=DTYPE)}


def brute_gain(train, z_new, cell, lam):
    """d/2 log det(A + z z^T) / det(A), A recounted from the training rows in ``cell``."""
    theta = torch.as_tensor(train, dtype=DTYPE)
    mine = NET.parameters[0].cluster_of(theta) == cell
    z = torch.cat([theta[mine], torch.ones(int(mine.sum()), 1, dtype=DTYPE)], -1)
    a = lam * torch.eye(3, dtype=DTYPE) + z.T @ z
    b = a + z_new[:, None] * z_new[None, :]
    return 0.5 * 2 * (torch.logdet(b) - torch.logdet(a))


def test_information_is_the_determinant_ratio():
    g = torch.Generator().manual_seed(0)
    train = torch.rand(40, 2, generator=g, dtype=DTYPE)
    cand = torch.rand(25, 2, generator=g, dtype=DTYPE)
    gain = regression_information(NET, "p", rows(train), candidates(cand), prior_precision=0.1)
    cells = NET.parameters[0].cluster_of(cand)
    for i in range(len(cand)):
        z = torch.cat([cand[i], torch.ones(1, dtype=DTYPE)])
        expected = brute_gain(train, z, int(cells[i]), 0.1)
        assert float(gain[i]) == pytest.approx(float(expected), rel=1e-9)


def test_greedy_updates_equal_a_recount():
    """After each pick the remaining gains equal those recomputed from the training rows
    plus the picks (their outcomes do not enter the information)."""
    g = torch.Generator().manual_seed(1)
    train = torch.rand(30, 2, generator=g, dtype=DTYPE) * 0.5  # only cell 0 seen
    cand = torch.rand(40, 2, generator=g, dtype=DTYPE)
    chosen = select_by_information(NET, "p", rows(train), candidates(cand), 6)
    assert len(set(chosen.tolist())) == 6
    for j in range(6):
        seen = torch.cat([train, cand[chosen[:j]]])
        gain = regression_information(NET, "p", rows(seen), candidates(cand))
        gain[chosen[:j]] = -math.inf
        assert int(gain.argmax()) == int(chosen[j])
    # the unseen cells are explored first
    cells = NET.parameters[0].cluster_of(cand[chosen[:3]])
    assert 0 not in cells.tolist()


def test_bad_arguments_are_value_errors():
    train, cand = rows(torch.rand(10, 2, dtype=DTYPE)), candidates(torch.rand(5, 2, dtype=DTYPE))
    for k in (0, 6, 1.5, True):
        with pytest.raises(ValueError, match="k"):
            select_by_information(NET, "p", train, cand, k)
    with pytest.raises(ValueError, match="prior_precision"):
        regression_information(NET, "p", train, cand, prior_precision=0.0)
    adaptive = EffectNetwork(
        NET.features,
        NET.actions,
        (Parameter("p", (0.0, 0.0), (1.0, 1.0), (2, 2), ("go",), "y", layout="adaptive"),),
    )
    with pytest.raises(ValueError, match="adaptive"):
        regression_information(adaptive, "p", train, cand)


def brute_variance_sum(train, extra, reference, cell, lam):
    """The cell's residual variance times the sum over its reference rows of ``r^T A^-1 r``.

    ``A`` recounted from the training rows and the rows ``extra`` (no outcomes) in ``cell``;
    the residual variance from the training rows alone: a ridge fit's residual sum of
    squares over the rows beyond the three coefficients (pooled over the cells that have
    such rows where this one has none).
    """
    cluster = NET.parameters[0].cluster_of

    def design(theta):
        return torch.cat([theta, torch.ones(len(theta), 1, dtype=DTYPE)], -1)

    def residual(c):
        mine = cluster(train) == c
        z, y = design(train[mine]), rows(train[mine])["end.y"]
        a = lam * torch.eye(3, dtype=DTYPE) + z.T @ z
        coef = torch.linalg.solve(a, z.T @ y)
        rss = float((y * y).sum() - (coef * (z.T @ y)).sum())
        return rss, int(mine.sum()) - 3

    rss, free = residual(cell)
    if free <= 0:
        parts = [residual(c) for c in range(4)]
        rss = sum(r for r, f in parts if f > 0)
        free = sum(f for _, f in parts if f > 0)
    theta = torch.cat([train, extra])
    z = design(theta[cluster(theta) == cell])
    a = lam * torch.eye(3, dtype=DTYPE) + z.T @ z
    ref = design(reference[cluster(reference) == cell])
    return rss / free * float((ref * torch.linalg.solve(a, ref.T).T).sum())


def test_variance_reduction_is_the_drop_of_the_summed_predictive_variance():
    g = torch.Generator().manual_seed(2)
    train = torch.rand(60, 2, generator=g, dtype=DTYPE) * torch.tensor([1.0, 0.45])  # cells 0, 2
    cand = torch.rand(20, 2, generator=g, dtype=DTYPE)
    ref = torch.rand(50, 2, generator=g, dtype=DTYPE)
    got = variance_reduction(
        NET, "p", rows(train), candidates(cand), candidates(ref), prior_precision=0.1
    )
    cells = NET.parameters[0].cluster_of(cand)
    for i in range(len(cand)):
        c = int(cells[i])
        before = brute_variance_sum(train, cand[:0], ref, c, 0.1)
        after = brute_variance_sum(train, cand[i : i + 1], ref, c, 0.1)
        assert float(got[i]) == pytest.approx(before - after, rel=1e-8, abs=1e-12)
        assert float(got[i]) >= 0


def test_greedy_variance_picks_equal_a_recount():
    """Each pick is the candidate that lowers the summed variance most, given the picks before."""
    g = torch.Generator().manual_seed(3)
    train = torch.rand(50, 2, generator=g, dtype=DTYPE)
    cand = torch.rand(30, 2, generator=g, dtype=DTYPE)
    ref = torch.rand(40, 2, generator=g, dtype=DTYPE)
    chosen = select_by_variance(
        NET, "p", rows(train), candidates(cand), 5, reference=candidates(ref)
    )
    assert len(set(chosen.tolist())) == 5
    cells = NET.parameters[0].cluster_of(cand)
    lam = 1e-3
    for j in range(5):
        picked = cand[chosen[:j]]
        drops = []
        for i in range(len(cand)):
            if i in chosen[:j].tolist():
                drops.append(-math.inf)
                continue
            c = int(cells[i])
            before = brute_variance_sum(train, picked, ref, c, lam)
            after = brute_variance_sum(train, torch.cat([picked, cand[i : i + 1]]), ref, c, lam)
            drops.append(before - after)
        assert int(torch.tensor(drops).argmax()) == int(chosen[j])
    # the reference defaults to the candidates
    default = select_by_variance(NET, "p", rows(train), candidates(cand), 5)
    same = select_by_variance(
        NET, "p", rows(train), candidates(cand), 5, reference=candidates(cand)
    )
    assert torch.equal(default, same)


def test_bad_arguments_to_the_variance_rule_are_value_errors():
    train, cand = rows(torch.rand(10, 2, dtype=DTYPE)), candidates(torch.rand(5, 2, dtype=DTYPE))
    for k in (0, 6, 1.5, True):
        with pytest.raises(ValueError, match="k"):
            select_by_variance(NET, "p", train, cand, k)
    with pytest.raises(ValueError, match="prior_precision"):
        variance_reduction(NET, "p", train, cand, cand, prior_precision=-1.0)
