"""Sums by elimination: the contraction against the dense joint, max-product against brute
force, and a sparse network whose joint could never be built, against its closed form."""

from __future__ import annotations

import effect_networks.inference.exact.elimination as elimination
import pytest
import torch
from effect_networks.inference import imitation_check, infer_action, predict, simulate
from effect_networks.inference.exact.elimination import (
    contract,
    max_config,
    maximum,
    sample,
    value_at,
)
from effect_networks.inference.exact.enumeration import enumerate_model
from effect_networks.models import Continuous, Discrete, EffectNetwork, random_params
from effect_networks.models.declaration import DTYPE

from tests.networks import closed_form, sparse_network

TOL = 1e-12


def random_factors(seed: int, n: int = 3) -> tuple[list[torch.Tensor], list[int]]:
    """Log-factors over 5 dims (sizes 2-3) and ``n`` rows, each on a random subset of the
    dims, some entries ``-inf``, some rows of size 1."""
    g = torch.Generator().manual_seed(seed)
    sizes = [2, 3, 2, 3, 2]
    factors = []
    for i in range(7):
        shape = [k if torch.rand((), generator=g) < 0.4 else 1 for k in sizes]
        rows = n if i % 3 else 1
        f = torch.randn(*shape, rows, generator=g, dtype=DTYPE) * 5
        f = torch.where(torch.rand(f.shape, generator=g) < 0.1, -torch.inf, f)
        factors.append(f)
    return factors, [-2 - i for i in range(len(sizes))][::-1]


@pytest.mark.parametrize("seed", range(6))
def test_contraction_is_the_dense_sum(seed):
    factors, dims = random_factors(seed)
    dense = sum(factors)  # broadcast: (3, 2, 3, 2, 3?, n) ...
    dense = dense.expand(*dense.shape[:-1], 3)
    for keep in ([], [dims[0]], [dims[1], dims[3]]):
        eliminate = [d for d in dims if d not in keep]
        want = dense.logsumexp([dense.dim() + d for d in eliminate], keepdim=True)
        got = contract(factors, eliminate).expand_as(want)
        finite = torch.isfinite(want)
        assert torch.equal(finite, torch.isfinite(got))
        assert torch.allclose(got[finite], want[finite], rtol=0, atol=TOL)
    top = dense.amax([dense.dim() + d for d in dims], keepdim=True)
    assert torch.allclose(maximum(factors, dims).expand_as(top), top, rtol=0, atol=TOL)


@pytest.mark.parametrize("seed", range(4))
def test_leaves_summed_together_are_each_ones_own_sum(seed):
    """Private latent dims (a prior and a factor with a kept dim each, as a latent initial
    feature under an observed end): their sums, batched as one, equal one sum per dim and
    the dense joint's."""
    g = torch.Generator().manual_seed(seed)
    k, kept = 6, -2  # dims -3 .. -8 private, -2 kept (3 states), rows last
    factors = []
    for i in range(k):
        d = -3 - i
        shape = [1] * (k + 1)
        shape[d + 1] = 2
        factors.append(torch.randn(*shape, 2, generator=g, dtype=DTYPE) * 3)  # its prior
        both = list(shape)
        both[kept + 1] = 3
        factors.append(torch.randn(*both, 2, generator=g, dtype=DTYPE) * 3)  # with the kept dim
    factors[0] = torch.where(factors[0] > 2, -torch.inf, factors[0])
    eliminate = [-3 - i for i in range(k)]
    dense = sum(factors)
    want = dense.logsumexp([dense.dim() + d for d in eliminate], keepdim=True)
    got = contract(factors, eliminate)
    assert torch.allclose(got.expand_as(want), want, rtol=0, atol=TOL)
    one_by_one = sum(
        (factors[2 * i] + factors[2 * i + 1]).logsumexp(-3 - i, keepdim=True) for i in range(k)
    )
    assert torch.allclose(got.expand_as(one_by_one), one_by_one, rtol=0, atol=TOL)


@pytest.mark.parametrize("seed", range(6))
def test_max_product_finds_a_best_configuration(seed):
    factors, dims = random_factors(seed)
    dense = sum(factors)
    dense = dense.expand(*dense.shape[:-1], 3)
    top, best = max_config(factors, dims, 3)
    brute = dense.reshape(-1, 3).amax(0)
    assert torch.allclose(top, brute, rtol=0, atol=TOL)
    assert torch.allclose(value_at(dense, best, 3), brute, rtol=0, atol=TOL)


def test_draws_by_elimination_follow_the_joint():
    """20,000 joint draws (one per row, the same factors in every row) against the dense
    joint: each configuration's share within 5 standard errors."""
    factors, dims = random_factors(1, n=1)
    factors = [torch.where(torch.isfinite(f), f / 5, f) for f in factors]  # flatter
    dense = sum(factors)
    probs = (dense - dense.logsumexp(list(range(dense.dim())), keepdim=True)).exp()[..., 0]
    n = 20_000
    torch.manual_seed(0)
    drawn = sample(factors, dims, n)
    spanned = [d for d in dims if probs.shape[probs.dim() + d + 1] > 1]
    assert sorted(drawn) == sorted(spanned)
    counts = torch.zeros(probs.shape, dtype=DTYPE)
    index = [  # axis i of ``probs`` is dim i - rank - 1 of the factors
        drawn[i - probs.dim() - 1] if k > 1 else torch.zeros(n, dtype=torch.long)
        for i, k in enumerate(probs.shape)
    ]
    counts.index_put_(tuple(index), torch.ones(n, dtype=DTYPE), accumulate=True)
    share = counts / n
    se = (probs * (1 - probs) / n).sqrt()
    assert bool(((share - probs).abs() <= 5 * se + 1e-12).all())


def test_a_sparse_network_of_40_latent_features_answers_in_closed_form():
    """2^40 initial configurations: summed as one tensor, the joint would not fit in any
    memory; by elimination each feature is summed on its own."""
    k, observed, n = 40, 30, 5
    net = sparse_network(k)
    params = random_params(net, 3, unseen=0.2)
    y = torch.randint(0, 2, (n, observed), generator=torch.Generator().manual_seed(4))
    ends = {f"end.f{i}": y[:, i] for i in range(observed)}
    got = infer_action(net, params, net.encode_indices(ends))
    post, unseen, marginals, target_unseen = closed_form(params, k, y, observed)
    assert torch.allclose(got.probs, post, rtol=0, atol=TOL)
    assert torch.allclose(got.unseen, unseen, rtol=0, atol=TOL)
    forward = predict(net, params, net.encode_indices(ends))
    assert set(forward.discrete) == set(marginals)
    for f, m in marginals.items():
        assert torch.allclose(forward.discrete[f], m, rtol=0, atol=TOL), f
    assert torch.allclose(forward.unseen, target_unseen, rtol=0, atol=TOL)


def test_elimination_keeps_the_dense_answers(monkeypatch):
    """The same queries, summed dense and by elimination, on a network with two
    continuous end features observed near their means and far from them (1e150, where
    their densities' optima disagree by far: the factors are centred at the most probable
    configuration): every answer equal."""
    net = EffectNetwork(
        (
            *(Discrete(f"f{i}", (0, 1)) for i in range(4)),
            Continuous("pos", 1),
            Continuous("tilt", 1),
        ),
        ("push", "lift", "wait"),
        parents={
            **{f"end.f{i}": (f"initial.f{i}", "action") for i in range(4)},
            "end.pos": ("initial.f0", "action"),
            "end.tilt": ("initial.f1", "action"),
        },
    )
    params = random_params(net, 5, unseen=0.2)
    n = 4
    y = torch.randint(0, 2, (n, 3), generator=torch.Generator().manual_seed(6))
    rows = {f"end.f{i}": y[:, i] for i in range(3)}
    rows["initial.pos"] = torch.zeros(n, 1, dtype=DTYPE)
    rows["initial.tilt"] = torch.zeros(n, 1, dtype=DTYPE)
    rows["end.pos"] = torch.tensor([[0.3], [-1.0], [1e150], [-3e149]], dtype=DTYPE)
    rows["end.tilt"] = torch.tensor([[0.1], [2.0], [-1e150], [1e148]], dtype=DTYPE)
    with_action = rows | {"action": torch.tensor([0, 1, 2, 0])}

    def answers():
        enc, given = net.encode_indices(rows), net.encode_indices(with_action)
        a = infer_action(net, params, enc)
        p = predict(net, params, enc)
        c = imitation_check(net, params, given.without("end.pos", "end.tilt"))
        e = enumerate_model(net, params, enc)
        return [a.probs, a.unseen, p.discrete["f3"], p.unseen, c.log_likelihood, c.surprise,
                c.unseen, e.log_evidence, e.marginal("initial.f1")]  # fmt: skip

    dense = answers()
    assert not enumerate_model(net, params, net.encode_indices(rows)).contracted
    monkeypatch.setattr(elimination, "DENSE_CONFIGURATIONS", 0)
    monkeypatch.setattr(elimination, "DENSE_RATIO", 0)
    assert enumerate_model(net, params, net.encode_indices(rows)).contracted
    for want, got in zip(dense, answers(), strict=True):
        assert torch.allclose(got, want, rtol=TOL, atol=TOL), (got, want)


def test_the_elimination_order_keeps_sums_small():
    """30 binary dims, each in one factor with a shared 3-state dim: each summed beside
    the shared one, never their joint (3 * 2^30)."""
    scopes = tuple(frozenset({(-2 - i, 2), (-50, 3)}) for i in range(30))
    order, largest = elimination.plan(scopes, frozenset(d for sc in scopes for d, _ in sc))
    assert largest == 6
    assert sorted(order) == sorted({d for sc in scopes for d, _ in sc})


def test_draws_given_the_end_state_on_a_sparse_network_of_40_features():
    """``simulate`` given the end state draws the latent initial state and action jointly
    by elimination: the action's and each initial feature's shares against the closed
    form, within 5 standard errors."""
    k, n = 40, 4000
    net = sparse_network(k)
    params = random_params(net, 1)
    y = torch.randint(0, 2, (1, k), generator=torch.Generator().manual_seed(2))
    out = simulate(net, params, n, {f"end.f{i}": [int(y[0, i])] * n for i in range(k)}, seed=0)
    post, *_ = closed_form(params, k, y, k)
    actions = torch.tensor([net.action_index(a) for a in out["action"]])
    share = torch.bincount(actions, minlength=3).to(DTYPE) / n
    assert bool(((share - post[0]).abs() <= 5 * (post[0] * (1 - post[0]) / n).sqrt() + 1e-9).all())
    for i in (0, 17, 39):
        prior, table = params[f"initial.f{i}"].probs, params[f"end.f{i}"].probs
        like = prior[:, None] * table[:, :, int(y[0, i])]  # (x, a)
        p = float(((like / like.sum(0))[1] * post[0]).sum())
        drawn = float(torch.as_tensor(list(out[f"initial.f{i}"]), dtype=DTYPE).mean())
        assert abs(drawn - p) <= 5 * (p * (1 - p) / n) ** 0.5 + 1e-9, (i, drawn, p)
