"""fit_update: a closed-form fit continued with new rows equals one fit on all rows."""

import numpy as np
import pytest
import torch
from effect_networks.inference import K2, BDeu, NormalInverseWishart, fit, fit_update, simulate
from effect_networks.models import (
    Continuous,
    Discrete,
    EffectNetwork,
    Parameter,
    load,
    random_params,
    save,
)
from effect_networks.models.params import NetworkParams
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.networks import README_NET, declared_networks

THROW = EffectNetwork(  # closed form throughout, a parameter's clusters included
    (Discrete("grip", ("loose", "firm")), Continuous("hit", 2, initial=False)),
    ("throw", "drop"),
    (Parameter("target", (0.0, 0.0), (1.0, 1.0), (2, 3), ("throw",), "hit"),),
)


def split(rows: dict, cut: int) -> tuple[dict, dict]:
    return {k: v[:cut] for k, v in rows.items()}, {k: v[cut:] for k, v in rows.items()}


def assert_same(a: NetworkParams, b: NetworkParams, tol: float) -> None:
    for site, cpd in a.cpds.items():
        for name, value in vars(cpd).items():
            if isinstance(value, torch.Tensor):
                other = getattr(b[site], name)
                torch.testing.assert_close(value, other, atol=tol, rtol=tol, msg=f"{site}.{name}")


@settings(max_examples=20, deadline=None)
@given(
    net=declared_networks(),
    seed=st.integers(0, 10_000),
    n=st.integers(2, 80),
    share=st.floats(0.0, 1.0),
    prior=st.sampled_from([None, 0.5, BDeu(3.0), K2()]),
)
def test_discrete_updates_equal_one_fit(net, seed, n, share, prior):
    rows = simulate(net, random_params(net, seed), n, seed=seed)
    first, second = split(rows, max(1, min(n - 1, int(share * n))))
    once = fit(net, rows, prior=prior).params
    updated = fit_update(net, fit(net, first, prior=prior).params, second, prior=prior).params
    assert_same(once, updated, 1e-12)
    for site, counts in once.statistics.items():
        assert torch.equal(counts.counts, updated.statistics[site].counts)


@settings(max_examples=15, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    n=st.integers(4, 300),
    cuts=st.lists(st.floats(0.0, 1.0), min_size=1, max_size=3),
    niw=st.booleans(),
)
def test_gaussian_updates_equal_one_fit_over_several_steps(seed, n, cuts, niw):
    rows = simulate(THROW, random_params(THROW, seed), n, seed=seed)
    prior = {"end.hit": NormalInverseWishart(0.1, 1.0, 0.01)} if niw else None
    edges = sorted({max(1, min(n - 1, int(c * n))) for c in cuts})
    pieces = [
        {k: v[a:b] for k, v in rows.items()} for a, b in zip([0, *edges], [*edges, n], strict=True)
    ]
    params = fit(THROW, pieces[0], prior=prior).params
    for piece in pieces[1:]:
        params = fit_update(THROW, params, piece, prior=prior).params
    once = fit(THROW, rows, prior=prior).params
    # the moments summed piece by piece round differently from one sum, and a regression on
    # throws (small noise beside large offsets) magnifies rounding: the update agrees with
    # one fit as closely as one fit agrees with itself on the rows in another order (and
    # to 1e-10 of the numbers' scale, where a few rows sum alike in any order)
    order = torch.randperm(n, generator=torch.Generator().manual_seed(seed))
    shuffled = fit(THROW, {k: take(v, order) for k, v in rows.items()}, prior=prior).params
    for site, cpd in once.cpds.items():
        for name, value in vars(cpd).items():
            if isinstance(value, torch.Tensor) and value.is_floating_point():
                diff = (value - getattr(shuffled[site], name)).abs()
                spread = float(diff.max()) if value.numel() else 0.0
                scale = float(value.abs().max()) if value.numel() else 0.0
                torch.testing.assert_close(
                    getattr(params[site], name),
                    value,
                    atol=100 * spread + 1e-10 * max(1.0, scale),
                    rtol=0,
                    msg=f"{site}.{name}",
                )


def take(values, order: torch.Tensor):
    """Rows of ``values`` (a tensor or a list of labels) in ``order``."""
    if isinstance(values, torch.Tensor):
        return values[order]
    return [values[i] for i in order.tolist()]


def test_an_update_from_chunks_and_after_a_save_equals_one_fit(tmp_path):
    rows = simulate(THROW, random_params(THROW, 1), 400, seed=1)
    first, second = split(rows, 150)
    params = fit(THROW, first).params
    path = save(tmp_path / "throw.pt", THROW, params)
    net, loaded = load(path)
    for site, s in params.statistics.items():  # bit for bit
        for name, value in vars(s).items():
            assert torch.equal(value, getattr(loaded.statistics[site], name))
            assert value.dtype == getattr(loaded.statistics[site], name).dtype
    chunks = iter(split(second, 100))
    assert_same(fit(THROW, rows).params, fit_update(net, loaded, chunks).params, 1e-12)


def test_a_file_without_statistics_loads_and_is_refused_an_update(tmp_path):
    rows = simulate(THROW, random_params(THROW, 1), 100, seed=1)
    fitted = fit(THROW, rows).params
    bare = NetworkParams(fitted.cpds, fitted.pseudo_count, THROW)
    net, loaded = load(save(tmp_path / "bare.pt", THROW, bare))
    assert loaded.statistics is None
    assert_same(fitted, loaded, 0.0)
    with pytest.raises(ValueError, match="carry no sufficient statistics"):
        fit_update(net, loaded, rows)


def test_updates_are_refused_where_no_sum_determines_the_fit():
    rows = simulate(README_NET, random_params(README_NET, 0), 60, seed=0)
    params = fit(README_NET, rows).params
    with pytest.raises(ValueError, match="softmax CPDs: their fit is iterative"):
        fit_update(README_NET, params, rows)
    throw_rows = simulate(THROW, random_params(THROW, 0), 60, seed=0)
    gappy = dict(throw_rows)
    grip = np.array(throw_rows["end.grip"], dtype=object)
    grip[0] = None
    gappy["end.grip"] = grip
    with pytest.raises(ValueError, match="the new rows miss values"):
        fit_update(THROW, fit(THROW, throw_rows).params, gappy)
    em = fit(THROW, gappy).params  # EM over gaps keeps no statistics
    with pytest.raises(ValueError, match="carry no sufficient statistics"):
        fit_update(THROW, em, throw_rows)
