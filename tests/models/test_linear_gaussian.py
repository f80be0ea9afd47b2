"""The linear Gaussian kind's density against mpmath, near a large mean: a value a few
noise scales from ``W x + b`` with ``x`` up to the accepted magnitude (a position far
from the origin, moved a little)."""

import math

import torch
from effect_networks.models.cpds.linear_gaussian import LinearGaussianCPD, LinearGaussianParams
from effect_networks.models.declaration import DTYPE
from effect_networks.models.evidence import MAX_MAGNITUDE
from hypothesis import given, settings
from hypothesis import strategies as st
from mpmath import mp, mpf


def exact_log_density(params: LinearGaussianParams, g: int, x, y) -> float:
    """log N(y; W x + b, L L^T) of configuration ``g`` with every float64 number read
    exactly, in 2 * 150 + 60 digits (the mean's terms reach 1e150 and the residual is
    of order 1)."""
    with mp.workdps(2 * int(math.log10(MAX_MAGNITUDE)) + 60):
        w, b, tril = params.weight[g].tolist(), params.bias[g].tolist(), params.scale_tril[g]
        d = len(b)
        r = [
            mpf(y[i]) - mp.fsum([mpf(w[i][j]) * mpf(x[j]) for j in range(len(x))]) - mpf(b[i])
            for i in range(d)
        ]
        L = mp.matrix(tril.tolist())
        z = mp.lu_solve(L, mp.matrix(r))  # L lower triangular: z = L^-1 r
        quad = mp.fsum([z[i] ** 2 for i in range(d)])
        log_det = mp.fsum([mp.log(L[i, i]) for i in range(d)])
        return float(-quad / 2 - log_det - d * mp.log(2 * mp.pi) / 2)


@settings(max_examples=60, deadline=None)
@given(
    d=st.integers(1, 2),
    p=st.integers(1, 3),
    seed=st.integers(0, 2**16),
    scale=st.sampled_from([1.0, 1e6, 1e13, 1e17, 1e60, MAX_MAGNITUDE]),
)
def test_density_near_a_large_mean_is_exact(d, p, seed, scale):
    g = torch.Generator().manual_seed(seed)
    cpd = LinearGaussianCPD("end.x", ("a",), (3,), d, ("initial.x",), p)
    a = torch.randn(3, d, d, generator=g, dtype=DTYPE)
    cov = a @ a.mT / d + 0.01 * torch.eye(d, dtype=DTYPE)
    params = LinearGaussianParams(
        torch.randn(3, d, p, generator=g, dtype=DTYPE),
        torch.randn(3, d, generator=g, dtype=DTYPE),
        torch.linalg.cholesky(cov),
        torch.ones(3, dtype=DTYPE),
    )
    x = torch.randn(4, p, generator=g, dtype=DTYPE) * scale
    config = torch.tensor([0, 1, 2, 1])
    mean = (params.weight[config] @ x[..., None])[..., 0] + params.bias[config]
    # a value a few noise scales from the mean (the rounded mean, moved)
    y = mean + (params.scale_tril[config] @ torch.randn(4, d, 1, generator=g, dtype=DTYPE))[..., 0]
    got = cpd.distribution(params, [config], x, {}).log_prob(y)
    for r in range(4):
        want = exact_log_density(params, int(config[r]), x[r].tolist(), y[r].tolist())
        assert abs(float(got[r]) - want) <= 1e-12 * max(1.0, abs(want)), (r, got[r], want)


def test_density_broadcasts_over_enumerated_parents():
    """The density of one value under every configuration at once (an enumerated parent),
    the same as configuration by configuration."""
    g = torch.Generator().manual_seed(0)
    cpd = LinearGaussianCPD("end.x", ("a",), (3,), 1, ("initial.x",), 1)
    params = LinearGaussianParams(
        torch.ones(3, 1, 1, dtype=DTYPE),
        torch.randn(3, 1, generator=g, dtype=DTYPE),
        torch.full((3, 1, 1), 0.5, dtype=DTYPE),
        torch.ones(3, dtype=DTYPE),
    )
    x = torch.tensor([[1e15], [2.0]], dtype=DTYPE)
    y = x + 0.25
    enumerated = torch.arange(3)[:, None]  # (3, 1) against 2 rows
    fn = cpd.distribution(params, [enumerated], x, {}).expand((3, 2))
    both = fn.log_prob(y)
    for c in range(3):
        one = cpd.distribution(params, [torch.full((2,), c)], x, {}).log_prob(y)
        assert torch.equal(both[c], one)
