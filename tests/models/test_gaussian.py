"""The error-free float64 operations of ``models.gaussian`` against exact rational
arithmetic (``fractions``): every float64 number is a rational, so the exact sums and
products are known."""

from fractions import Fraction

import numpy as np
import torch
from effect_networks.models.declaration import DTYPE
from effect_networks.models.gaussian import affine_pair, lstsq_rows, two_product, two_sum
from hypothesis import given, settings
from hypothesis import strategies as st

#: float64 numbers over the magnitudes the toolkit accepts, zero and subnormal-free
magnitudes = st.floats(-1e150, 1e150, allow_nan=False, allow_subnormal=False).filter(
    lambda v: v == 0 or abs(v) > 1e-140
)


def exact(t: torch.Tensor) -> list[Fraction]:
    return [Fraction(v) for v in t.reshape(-1).tolist()]


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(magnitudes, magnitudes), min_size=1, max_size=20))
def test_two_sum_and_two_product_are_exact(pairs):
    a = torch.tensor([p[0] for p in pairs], dtype=DTYPE)
    b = torch.tensor([p[1] for p in pairs], dtype=DTYPE)
    s, e = two_sum(a, b)
    p, f = two_product(a, b)
    for x, y, s_, e_, p_, f_ in zip(*map(exact, (a, b, s, e, p, f)), strict=True):
        assert s_ + e_ == x + y
        assert p_ + f_ == x * y


@settings(max_examples=100, deadline=None)
@given(
    d=st.integers(1, 3),
    p=st.integers(1, 4),
    seed=st.integers(0, 2**16),
    scale=st.sampled_from([1.0, 1e8, 1e13, 1e60, 1e150]),
    near=st.booleans(),
)
def test_affine_pair_is_the_sum_to_twice_float64s_precision(d, p, seed, scale, near):
    """``hi + lo`` within ``p * 2^-104`` of the terms' magnitudes of the exact ``W x + b``
    (where ``near``, the bias nearly cancels the products: the sum is small against its
    terms, as a mean near a large observed value is), and ``hi`` is ``hi + lo`` rounded."""
    g = torch.Generator().manual_seed(seed)
    weight = torch.randn(5, d, p, generator=g, dtype=DTYPE)
    x = torch.randn(5, p, generator=g, dtype=DTYPE) * scale
    bias = torch.randn(5, d, generator=g, dtype=DTYPE)
    if near:
        bias = bias - (weight @ x[..., None])[..., 0]
    hi, lo = affine_pair(weight, x, bias)
    for r in range(5):
        for i in range(d):
            terms = [Fraction(float(weight[r, i, j])) * Fraction(float(x[r, j])) for j in range(p)]
            terms.append(Fraction(float(bias[r, i])))
            want = sum(terms)
            got = Fraction(float(hi[r, i])) + Fraction(float(lo[r, i]))
            assert abs(got - want) <= (p + 1) * 2**-104 * sum(abs(t) for t in terms)
            assert float(hi[r, i]) == float(got)


def test_affine_pair_keeps_what_is_not_finite():
    weight = torch.ones(3, 1, 1, dtype=DTYPE)
    x = torch.tensor([[torch.inf], [torch.nan], [1e305]], dtype=DTYPE)
    hi, lo = affine_pair(weight, x, torch.ones(3, 1, dtype=DTYPE))
    assert hi[0, 0] == torch.inf and torch.isnan(hi[1, 0]) and hi[2, 0] == 1e305
    assert (lo == 0).all()


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(0, 12),
    batch=st.integers(1, 5),
    d=st.integers(1, 3),
    k=st.integers(1, 3),
    designs=st.integers(1, 4),
    free=st.booleans(),
    seed=st.integers(0, 2**16),
)
def test_lstsq_rows_is_each_rows_minimum_norm_solution(n, batch, d, k, designs, free, seed):
    """Rows sharing a design (a few distinct ones among them) solved together equal numpy's
    pseudo-inverse solution of each problem alone, and LAPACK's one problem at a time to
    rounding (the blocked solver with several right-hand sides may round differently from
    one at a time); a direction no row constrains (a zero column) stays at 0."""
    g = torch.Generator().manual_seed(seed)
    distinct = torch.randn(designs, batch, d, k, generator=g, dtype=DTYPE)
    if free:
        distinct[..., -1] = 0.0
    pick = torch.randint(designs, (n,), generator=g)
    design = distinct[pick]
    rhs = torch.randn(n, batch, d, generator=g, dtype=DTYPE)
    z = lstsq_rows(design, rhs)
    assert z.shape == (n, batch, k)
    reference = np.einsum("...kd,...d->...k", np.linalg.pinv(design.numpy()), rhs.numpy())
    np.testing.assert_allclose(z.numpy(), reference, rtol=1e-9, atol=1e-9)
    alone = torch.linalg.lstsq(design, rhs[..., None], driver="gelsd").solution[..., 0]
    torch.testing.assert_close(z, alone, rtol=1e-12, atol=1e-12)
    if free and n:
        assert bool((z[..., -1] == 0).all())


def test_lstsq_rows_takes_one_design_broadcast_over_the_rows():
    """A design expanded over the rows (stride 0) is solved once, with every row as a column."""
    g = torch.Generator().manual_seed(3)
    design = torch.randn(1, 4, 2, 2, generator=g, dtype=DTYPE).expand(50, -1, -1, -1)
    rhs = torch.randn(50, 4, 2, generator=g, dtype=DTYPE)
    z = lstsq_rows(design, rhs)
    assert torch.allclose(design @ z[..., None], rhs[..., None], rtol=1e-12, atol=1e-12)
