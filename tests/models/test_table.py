"""The table kind's lazy gather against pyro's Vindex and torch's Categorical."""

import pyro.distributions as dist
import pytest
import torch
from effect_networks.models.cpds.table import GatheredCategorical, broadcast_shapes, gather
from hypothesis import given, settings
from hypothesis import strategies as st
from pyro.ops.indexing import Vindex


@st.composite
def gathers(draw):
    """A table and one index per axis, each an enumerated axis (arange on its own dim
    left of the rows), one value per row, a single value, or another shape."""
    n_axes = draw(st.integers(1, 4))
    sizes = [draw(st.integers(1, 4)) for _ in range(n_axes)]
    n = draw(st.integers(1, 5))
    g = torch.Generator().manual_seed(draw(st.integers(0, 10_000)))
    table = torch.randn(*sizes, generator=g, dtype=torch.float64)
    dims = iter(range(-2, -2 - n_axes, -1))
    index = []
    for size in sizes:
        kind = draw(st.sampled_from(["whole", "rows", "one", "odd"]))
        if kind == "whole":
            d = next(dims)
            index.append(torch.arange(size).reshape((size,) + (1,) * (-d - 1)))
        elif kind == "rows":
            index.append(torch.randint(0, size, (n,), generator=g))
        elif kind == "one":
            index.append(torch.randint(0, size, (1,), generator=g))
        else:
            index.append(torch.randint(0, size, (1, n), generator=g))
    return table, tuple(index)


@settings(max_examples=200, deadline=None)
@given(case=gathers())
def test_gather_equals_vindex(case):
    table, index = case
    want = Vindex(table)[index]
    got = gather(table, index)
    assert got.shape == want.shape
    assert torch.equal(got, want)


def test_gathered_categorical_is_the_categorical_of_the_gathered_rows():
    g = torch.Generator().manual_seed(0)
    logs = torch.randn(3, 4, 5, generator=g, dtype=torch.float64).log_softmax(-1)
    index = (torch.arange(3).reshape(3, 1, 1), torch.randint(0, 4, (6,), generator=g))
    lazy = GatheredCategorical(logs, index)
    full = dist.Categorical(logits=Vindex(logs)[(*index, slice(None))])
    assert lazy.batch_shape == full.batch_shape == (3, 1, 6)
    value = torch.randint(0, 5, (6,), generator=g)
    torch.testing.assert_close(lazy.log_prob(value), full.log_prob(value))
    support = lazy.enumerate_support(expand=False)
    torch.testing.assert_close(lazy.log_prob(support), full.log_prob(support))
    torch.testing.assert_close(lazy.probs, full.probs)
    wide = lazy.expand((2, 3, 1, 6))
    assert wide.log_prob(value).shape == (2, 3, 1, 6)
    torch.manual_seed(0)
    assert lazy.sample((7,)).shape == (7, 3, 1, 6)
    with pytest.raises(ValueError, match=r"state index outside 0..4"):
        lazy.log_prob(torch.tensor([5]))


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), zeros=st.sampled_from([0.0, 0.3, 1.0]))
def test_the_log_table_is_torch_s_logits_of_the_normalised_table(seed, zeros):
    """Bit for bit ``probs_to_logits(probs / probs.sum(-1))``, zeros and unnormalised rows
    included, computed without a temporary per step."""
    from effect_networks.models.cpds.table import _logits
    from torch.distributions.utils import probs_to_logits

    g = torch.Generator().manual_seed(seed)
    probs = torch.rand(3, 4, 5, generator=g, dtype=torch.float64) * 3
    probs[torch.rand(3, 4, 5, generator=g) < zeros] = 0.0
    probs[..., 0] += 1e-300  # no row entirely zero
    expected = probs_to_logits(probs / probs.sum(-1, keepdim=True))
    assert torch.equal(_logits(probs), expected)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.lists(st.integers(0, 3), max_size=4), min_size=1, max_size=4))
def test_broadcast_shapes_is_torch_s(shapes):
    """The plain-Python broadcast agrees with torch's, refusals included."""
    try:
        expected = torch.broadcast_shapes(*shapes)
    except RuntimeError:
        with pytest.raises(RuntimeError):
            broadcast_shapes(*shapes)
        return
    assert broadcast_shapes(*shapes) == expected
