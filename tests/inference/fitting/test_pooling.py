"""fit_pooled: against a per-row recount of the documented formula, against fit where the
pooling is off, and the exact queries on its tables against brute-force enumeration."""

import itertools
from unittest import mock

import numpy as np
import pytest
import torch
from effect_networks.inference import fit, fit_pooled, grid_kernel, infer_action
from effect_networks.inference.fitting import pooling
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.helpers import brute_joint, discrete_network

NET = discrete_network([3, 2], 4)  # features f0 (3 states), f1 (2), four actions


def random_rows(seed, n):
    rng = np.random.default_rng(seed)
    cols = {
        "initial.f0": rng.integers(0, 3, n),
        "initial.f1": rng.integers(0, 2, n),
        "action": rng.integers(0, 4, n),
        "end.f0": rng.integers(0, 3, n),
        "end.f1": rng.integers(0, 2, n),
    }
    return NET.encode_indices({k: torch.as_tensor(v) for k, v in cols.items()}), cols


def recount(cols, site, kernel, strength, alpha):
    """The module's formula, one row at a time, from the raw rows."""
    card = 3 if site == "end.f0" else 2
    out = np.zeros((3, 2, 4, card))
    n_eff = np.zeros((3, 2, 4))
    y = cols[site]
    for f0, f1, a in itertools.product(range(3), range(2), range(4)):

        def counts(b, f0=f0, f1=f1):
            sel = (cols["initial.f0"] == f0) & (cols["initial.f1"] == f1) & (cols["action"] == b)
            return np.bincount(y[sel], minlength=card).astype(float)

        own = counts(a)
        neigh = sum(kernel[a, b] * counts(b) for b in range(4) if b != a)
        t = neigh.sum()
        m = neigh / t if t > 0 else np.zeros(card)
        w = strength * min(1.0, t)
        total = own.sum() + card * alpha + w
        out[f0, f1, a] = (own + alpha + w * m) / total if total > 0 else 1.0 / card
        n_eff[f0, f1, a] = own.sum() + w
    return out, n_eff


@settings(max_examples=30, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    n=st.integers(1, 60),
    strength=st.sampled_from([0.0, 0.5, 2.0]),
    alpha=st.sampled_from([0.0, 0.01, 1.0]),
    sigma=st.sampled_from([0.0, 0.7, 1.5]),
)
def test_pooled_tables_equal_a_per_row_recount(seed, n, strength, alpha, sigma):
    enc, cols = random_rows(seed, n)
    kernel = grid_kernel((2, 2), sigma)
    params = fit_pooled(NET, enc, kernel, strength=strength, pseudo_count=alpha).params
    for site in ("end.f0", "end.f1"):
        want, n_eff = recount(cols, site, kernel.numpy(), strength, alpha)
        got = params[site]
        assert torch.isfinite(got.probs).all()
        np.testing.assert_allclose(got.probs.sum(-1).numpy(), 1.0, atol=1e-12)
        seen = (n_eff > 0) | (alpha > 0)  # with alpha = 0, an unseen row is uniform
        np.testing.assert_allclose(got.probs.numpy()[seen], want[seen], atol=1e-12)
        np.testing.assert_allclose(got.probs.numpy()[~seen], 1.0 / want.shape[-1])
        np.testing.assert_allclose(got.n.numpy(), n_eff, atol=1e-12)
    plain = fit(NET, enc, pseudo_count=alpha).params
    for site in ("initial.f0", "initial.f1", "action"):  # not pooled: the plain fit
        torch.testing.assert_close(params[site].probs, plain[site].probs, rtol=0, atol=0)


@pytest.mark.parametrize("kernel", [grid_kernel((2, 2), 1.0), torch.ones(4, 4)])
def test_no_pooling_is_the_plain_fit(kernel):
    enc, _ = random_rows(3, 40)
    plain = fit(NET, enc).params
    for params in (
        fit_pooled(NET, enc, kernel, strength=0.0).params,
        fit_pooled(NET, enc, torch.eye(4) * 5.0).params,  # no off-diagonal weight
    ):
        for site in plain.cpds:
            torch.testing.assert_close(params[site].probs, plain[site].probs, rtol=1e-14, atol=0)
            torch.testing.assert_close(
                params[site].n.to(torch.float64), plain[site].n.to(torch.float64)
            )


def test_an_unplayed_action_takes_its_neighbours_distribution():
    """Action 3 never played from (0, 0); its neighbours 1 and 2 always ended in f0 = 2."""
    rows = {
        "initial.f0": [0, 0, 0, 0],
        "initial.f1": [0, 0, 0, 0],
        "action": [1, 2, 1, 2],
        "end.f0": [2, 2, 2, 2],
        "end.f1": [0, 1, 0, 1],
    }
    enc = NET.encode_indices({k: torch.tensor(v) for k, v in rows.items()})
    params = fit_pooled(NET, enc, grid_kernel((2, 2), 1.0), strength=1.0).params
    row = params["end.f0"].probs[0, 0, 3]
    assert int(row.argmax()) == 2 and float(row[2]) > 0.95
    assert float(params["end.f0"].n[0, 0, 3]) == pytest.approx(1.0)  # capped weight
    # another initial state is untouched: uniform, unseen
    torch.testing.assert_close(params["end.f0"].probs[1, 0, 3], torch.full((3,), 1 / 3).double())
    assert float(params["end.f0"].n[1, 0, 3]) == 0.0
    # the plain fit knows nothing of action 3 from (0, 0)
    plain = fit(NET, enc).params
    assert float(plain["end.f0"].n[0, 0, 3]) == 0.0


def test_queries_on_pooled_tables_are_exact():
    enc, _ = random_rows(5, 50)
    params = fit_pooled(NET, enc, grid_kernel((2, 2), 0.8), strength=1.5).params
    joint = brute_joint(NET, params)
    post = infer_action(
        NET, params, {"initial.f0": [1], "initial.f1": [0], "end.f0": [2]}, avoid_unseen=False
    )
    want = np.zeros(4)
    for (init, a, end), p in joint.items():
        if init == (1, 0) and end[0] == 2:
            want[a] += p
    np.testing.assert_allclose(post.probs[0].numpy(), want / want.sum(), atol=1e-9)


def test_grid_kernel():
    k = grid_kernel((2, 3), 1.0)
    assert k.shape == (6, 6)
    torch.testing.assert_close(k, k.T)
    assert float(k[0, 0]) == 1.0
    assert float(k[0, 1]) == pytest.approx(np.exp(-0.5))  # one column apart
    assert float(k[0, 3]) == pytest.approx(np.exp(-0.5))  # one row apart
    assert float(k[0, 4]) == pytest.approx(np.exp(-1.0))  # diagonal neighbour
    torch.testing.assert_close(grid_kernel((2, 3), 0), torch.eye(6, dtype=torch.float64))


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda enc: fit_pooled(NET, enc, torch.ones(3, 3)), "kernel must be"),
        (lambda enc: fit_pooled(NET, enc, -torch.ones(4, 4)), "non-negative"),
        (lambda enc: fit_pooled(NET, enc, torch.full((4, 4), float("nan"))), "non-negative"),
        (lambda enc: fit_pooled(NET, enc, torch.ones(4, 4), strength=-1), "strength"),
        (lambda enc: fit_pooled(NET, enc, torch.ones(4, 4), strength=float("inf")), "strength"),
        (lambda enc: fit_pooled(NET, enc, torch.ones(4, 4), pseudo_count=-1), "pseudo_count"),
        (lambda enc: grid_kernel((0, 3), 1.0), "grid_shape"),
        (lambda enc: grid_kernel((2, 3), -1.0), "sigma"),
    ],
)
def test_bad_input_is_refused(call, match):
    enc, _ = random_rows(0, 10)
    with pytest.raises(ValueError, match=match):
        call(enc)


def _pooled_whole(counts, off, strength, alpha):
    """The pooled table computed on the whole table at once (every parent configuration,
    played or not): the formula of the module, written out."""
    k = counts.shape[-1]
    neighbours = torch.einsum("ab,...bk->...ak", off, counts)
    weight = neighbours.sum(-1, keepdim=True)
    m = torch.where(weight > 0, neighbours / weight.clamp_min(1e-300), 0.0)
    w = strength * weight.clamp(max=1.0)
    n = counts.sum(-1, keepdim=True)
    total = n + k * alpha + w
    probs = torch.where(total > 0, (counts + alpha + w * m) / total.clamp_min(1e-300), 1.0 / k)
    return probs, (n + w)[..., 0]


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    played=st.sampled_from([0.0, 0.1, 0.5, 1.0]),
    alpha=st.sampled_from([0.0, 0.01, 1.0]),
    strength=st.sampled_from([0.0, 0.5, 3.0]),
)
def test_unplayed_configurations_are_computed_once_with_the_same_bits(
    seed, played, alpha, strength
):
    """Parent configurations that no row reached share one computed row: the table is
    bit for bit the table computed everywhere."""
    g = torch.Generator().manual_seed(seed)
    counts = torch.randint(0, 3, (4, 6, 9, 5), generator=g).to(torch.float64)
    counts *= torch.rand(4, 6, generator=g)[..., None, None] < played  # unplayed groups
    off = grid_kernel((3, 3), 0.8)
    off.fill_diagonal_(0.0)
    probs, n = _pooled_whole(counts, off, strength, alpha)
    computed = []
    rows = pooling._pooled_rows

    def counting(c, *args):
        computed.append(c.shape[0])
        return rows(c, *args)

    with mock.patch.object(pooling, "_pooled_rows", counting):
        table = pooling._pooled(counts, off, strength, alpha, axis=2)
    assert torch.equal(table.probs, probs) and torch.equal(table.n, n)
    reached = int((counts.sum((-2, -1)) > 0).sum())
    assert computed == [reached + (reached < 24)]  # the reached ones and one other


def test_only_the_named_sites_are_pooled():
    """``sites`` names the end tables that are pooled; every other CPD is the plain fit's,
    bit for bit, and the pooled one is the one pooled with every site."""
    net = discrete_network([3, 2], 6)
    g = torch.Generator().manual_seed(3)
    rows = net.encode_indices(
        {s.name: torch.randint(0, s.size, (40,), generator=g) for s in net.sites}
    )
    kernel = grid_kernel((2, 3), 1.0)
    every = fit_pooled(net, rows, kernel).params
    plain = fit(net, rows).params
    one = fit_pooled(net, rows, kernel, sites=["end.f0"]).params
    assert torch.equal(one["end.f0"].probs, every["end.f0"].probs)
    assert torch.equal(one["end.f1"].probs, plain["end.f1"].probs)
    assert not torch.equal(every["end.f1"].probs, plain["end.f1"].probs)
    assert torch.equal(
        fit_pooled(net, rows, kernel, sites="end.f0").params["end.f1"].probs, plain["end.f1"].probs
    )
    with pytest.raises(ValueError, match=r"\['initial.f0'\] cannot be pooled"):
        fit_pooled(net, rows, kernel, sites=["end.f0", "initial.f0"])
