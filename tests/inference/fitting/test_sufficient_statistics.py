"""Chunked fitting: sufficient statistics merge by addition; chunks fit like one pass."""

import numpy as np
import pytest
import torch
from effect_networks.inference import fit, fit_statistics, params_from_statistics, simulate
from effect_networks.models import (
    Continuous,
    Discrete,
    EffectNetwork,
    Parameter,
    random_params,
    to_frame,
)
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.helpers import discrete_network

THROW = EffectNetwork(  # closed form throughout: no discrete child of a continuous parent
    (Discrete("grip", ("loose", "firm")), Continuous("hit", 2, initial=False)),
    ("throw", "drop"),
    (Parameter("target", (0.0, 0.0), (1.0, 1.0), (2, 3), ("throw",), "hit"),),
)


def chunks(rows: dict, sizes: list[int]):
    start = 0
    for size in sizes:
        yield {k: v[start : start + size] for k, v in rows.items()}
        start += size


def cut(n: int, draw_sizes: list[int]) -> list[int]:
    sizes, left = [], n
    for s in draw_sizes:
        if left <= 0:
            break
        sizes.append(min(s, left))
        left -= sizes[-1]
    if left:
        sizes.append(left)
    return sizes


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 100), sizes=st.lists(st.integers(1, 400), min_size=1, max_size=6))
def test_discrete_tables_from_chunks_are_the_one_pass_tables_bit_for_bit(seed, sizes):
    net = discrete_network([3, 2], 4)
    rows = simulate(net, random_params(net, seed), 600, seed=seed)
    one = fit(net, rows).params
    many = fit(net, chunks(rows, cut(600, sizes))).params
    for site in one.cpds:
        assert torch.equal(one[site].probs, many[site].probs)
        assert torch.equal(one[site].n, many[site].n)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 100), sizes=st.lists(st.integers(1, 700), min_size=1, max_size=6))
def test_gaussians_from_chunks_equal_the_one_pass_fit(seed, sizes):
    rows = simulate(THROW, random_params(THROW, seed), 1500, seed=seed)
    whole = fit_statistics(THROW, [rows])
    parts = fit_statistics(THROW, chunks(rows, cut(1500, sizes)))
    for site, s in whole.sites.items():
        for name, value in vars(s).items():
            # counts exactly; sums of products to float64 rounding (another order of adds)
            got = getattr(parts.sites[site], name)
            scale = float(value.abs().max()) or 1.0
            torch.testing.assert_close(got, value, rtol=1e-12, atol=1e-13 * scale)
    one = fit(THROW, rows).params
    many = fit(THROW, chunks(rows, cut(1500, sizes))).params
    for site, cpd in one.cpds.items():
        for name, value in vars(cpd).items():
            # the least squares of a configuration with few rows is ill-conditioned and
            # magnifies those last-bit differences (a case with 6.5e-7 was found)
            torch.testing.assert_close(getattr(many[site], name), value, rtol=1e-5, atol=1e-5)


def test_partitions_merge_in_any_grouping():
    rows = simulate(THROW, random_params(THROW, 1), 900, seed=2)
    a, b, c = (fit_statistics(THROW, [part]) for part in chunks(rows, [300, 300, 300]))
    left, right = (a + b) + c, a + (b + c)
    shuffled = c + a + b
    for x, y in ((left, right), (left, shuffled)):
        assert x.rows == y.rows == 900
        for site in x.sites:
            for name, value in vars(x.sites[site]).items():
                torch.testing.assert_close(getattr(y.sites[site], name), value, rtol=1e-12, atol=0)
    params = params_from_statistics(THROW, left, 0.01, 1e-6)
    torch.testing.assert_close(params["end.hit"].bias, fit(THROW, rows).params["end.hit"].bias)


def test_one_partition_given_whole_is_one_chunk():
    """A mapping or a DataFrame is one partition's rows, not an iterable of chunks."""
    rows = simulate(THROW, random_params(THROW, 1), 300, seed=2)
    listed = fit_statistics(THROW, [rows])
    pytest.importorskip("pandas")
    for whole in (rows, to_frame(THROW, rows)):
        got = fit_statistics(THROW, whole)
        assert got.rows == listed.rows == 300
        for site in listed.sites:
            for name, value in vars(listed.sites[site]).items():
                torch.testing.assert_close(getattr(got.sites[site], name), value, rtol=0, atol=0)


def test_chunk_limits_are_named():
    net = EffectNetwork((Discrete("door", ("shut", "open")), Continuous("pos", 1)), ("a",))
    rows = simulate(net, random_params(net, 0), 50, seed=0)
    with pytest.raises(ValueError, match=r"\['end.door'\] are softmax CPDs"):
        fit(net, chunks(rows, [25, 25]))
    with pytest.raises(ValueError, match="masks need the rows in memory"):
        fit(net, chunks(rows, [50]), masks={"end.door": np.ones(50, bool)})
    with pytest.raises(ValueError, match="no training rows: the iterable was empty"):
        fit(net, iter([]))
    with pytest.raises(ValueError, match="chunk of type str"):
        fit(net, ["rows"])
    bad = {k: v[:10] for k, v in rows.items()}
    bad["end.door"] = ["ajar"] * 10
    with pytest.raises(ValueError, match="'ajar' is not one of its states"):
        fit_statistics(net, [bad])


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 100))
def test_weighted_rows_count_as_repeated_rows(seed):
    # the statistics an EM step gives: a row of weight k is the row k times, for every
    # kind (tables, linear Gaussians, a parameter's cluster table and Gaussians)
    from effect_networks.inference.fitting.rows import training_rows
    from effect_networks.inference.fitting.sufficient_statistics import statistics

    rows = training_rows(THROW, simulate(THROW, random_params(THROW, seed), 300, seed=seed))
    k = torch.as_tensor(np.random.default_rng(seed).integers(0, 4, rows.n_rows))
    weighted = statistics(THROW, rows, k.to(torch.float64))
    repeated = statistics(THROW, rows.rows(torch.arange(rows.n_rows).repeat_interleave(k)))
    for site, s in weighted.sites.items():
        for name, value in vars(s).items():
            got = getattr(repeated.sites[site], name)
            scale = float(value.abs().max()) or 1.0
            torch.testing.assert_close(got, value, rtol=1e-12, atol=1e-13 * scale)
