"""Choosing parameter values by information: closed form against a brute-force recount."""

import math

import pytest
import torch
from effect_networks.inference.design.active_gaussian import (
    regression_information,
    select_by_information,
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
