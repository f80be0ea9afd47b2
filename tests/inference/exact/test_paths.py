"""The scaled sums over a chain's steps against log-sum-exp over the gathered tables."""

import pytest
import torch
from effect_networks.inference.exact.paths import GROUPED_KEYS, LogTables, log_matvec, max_matvec
from effect_networks.models.declaration import DTYPE
from hypothesis import given, settings
from hypothesis import strategies as st


def dense(left, tables, key):
    return (left[:, :, None] + tables[key]).logsumexp(1)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    n_keys=st.sampled_from([1, 3, GROUPED_KEYS + 5]),
    spread=st.sampled_from([1.0, 30.0, 2000.0]),
)
def test_log_matvec_is_logsumexp(seed, n_keys, spread):
    """Entries spread over thousands of nats (densities far in a tail) and -inf ones:
    the scaled products, and the rows summed again where they underflow, match the
    log-sum-exp to float64 precision."""
    g = torch.Generator().manual_seed(seed)
    n, j, m = 50, 4, 3
    left = torch.randn(n, j, generator=g, dtype=DTYPE) * spread
    left[torch.rand(n, j, generator=g) < 0.3] = -torch.inf
    left[:, 0] = torch.randn(n, generator=g, dtype=DTYPE)  # every row has some mass
    tables = torch.randn(n_keys, j, m, generator=g, dtype=DTYPE) * spread
    key = torch.randint(n_keys, (n,), generator=g)
    got = log_matvec(left, LogTables(tables), key)
    want = dense(left, tables, key)
    assert torch.allclose(got, want, rtol=1e-12, atol=1e-9)
    total = log_matvec(left, LogTables(tables), key, total=True)
    kept = want - want.logsumexp(-1, keepdim=True) > -150  # the entries that matter
    assert torch.allclose(total[kept], want[kept], rtol=1e-12, atol=1e-9)
    assert torch.allclose(total.logsumexp(-1), want.logsumexp(-1), rtol=1e-12, atol=1e-9)


def test_an_underflowing_row_is_summed_again():
    """A row whose only mass meets a table entry 2000 nats below the table's largest:
    the product underflows to 0, the answer is still the exact -2000."""
    tables = torch.tensor([[[0.0, -2000.0]]], dtype=DTYPE)  # (1, J=1, M=2)
    left = torch.zeros(1, 1, dtype=DTYPE)
    got = log_matvec(left, LogTables(tables), torch.zeros(1, dtype=torch.long))
    assert got[0].tolist() == pytest.approx([0.0, -2000.0])


def test_max_matvec_is_the_maximum_and_its_argument():
    g = torch.Generator().manual_seed(1)
    left = torch.randn(7, 5, generator=g, dtype=DTYPE)
    tables = torch.randn(2, 5, 3, generator=g, dtype=DTYPE)
    key = torch.tensor([0, 1, 1, 0, 1, 0, 0])
    value, arg = max_matvec(left, tables, key)
    for i in range(7):
        scores = left[i, :, None] + tables[key[i]]
        assert torch.equal(value[i], scores.max(0).values)
        assert torch.equal(arg[i], scores.argmax(0))
