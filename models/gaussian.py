"""Closed-form Gaussian identities the model and the queries share.

For ``theta ~ N(m, S)`` and ``y = W theta + b + e`` with ``e ~ N(0, R)``:

* marginal: ``y ~ N(W m + b, W S W^T + R)``
* posterior: ``theta | y ~ N(m + K (y - W m - b), S - K W S)``, ``K = S W^T (W S W^T + R)^-1``

A ``y`` with NaN in some dimensions is observed in the others only
(:func:`mask_unobserved`): the marginal of the observed dimensions, its rows and
columns of the covariance, is what conditions.

A mean ``W x + b`` near a large observed ``y`` (a position far from the origin, moved a
little) rounds to float64's spacing at its size, which may not be small against the
noise's scale; :func:`affine_pair` keeps it as two float64 numbers whose sum is the mean to
about twice float64's precision (error-free products and sums), so that the residual
``(y - hi) - lo`` keeps its digits.

All functions broadcast over leading batch dims.
"""

from __future__ import annotations

import math

import torch


def two_sum(a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(s, e)``: the float64 sum ``a + b`` and its rounding error.

    ``s + e == a + b`` exactly wherever ``a + b`` is finite (Knuth's TwoSum, no branch).
    """
    s = a + b
    v = s - a
    return s, (a - (s - v)) + (b - v)


#: Dekker's splitting constant for float64: ``2^27 + 1``.
_SPLITTER = 134217729.0


def two_product(a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(p, e)``: the float64 product ``a * b`` and its rounding error.

    ``p + e == a * b`` exactly (Dekker's product of split halves, no fused multiply-add), for
    factors below about 1e300 and products above about 1e-290 in magnitude.
    """
    p = a * b
    ca, cb = _SPLITTER * a, _SPLITTER * b
    a_hi, b_hi = ca - (ca - a), cb - (cb - b)
    a_lo, b_lo = a - a_hi, b - b_hi
    return p, ((a_hi * b_hi - p) + a_hi * b_lo + a_lo * b_hi) + a_lo * b_lo


def affine_pair(
    weight: torch.Tensor, x: torch.Tensor, bias: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """``W x + b`` as ``(hi, lo)``: ``hi`` its float64 rounding, ``lo`` the rest.

    ``weight`` ``(..., d, p)``, ``x`` ``(..., p)``, ``bias`` ``(..., d)``; together within about ``p
    * 2^-104`` of the sum of the terms' magnitudes (the products and sums error-free, their errors
    summed once: Ogita, Rump and Oishi's Dot2). Where a term is not finite (or a factor beyond
    two_product's range) ``lo`` is 0 and ``hi`` the plain sum.
    """
    products, errors = two_product(weight, x.unsqueeze(-2))  # (..., d, p)
    hi = bias.expand(torch.broadcast_shapes(bias.shape, products.shape[:-1]))
    lo = torch.zeros_like(hi)
    for j in range(products.shape[-1]):
        hi, e = two_sum(hi, products[..., j])
        lo = lo + (e + errors[..., j])
    exact = torch.isfinite(lo)
    s, e = two_sum(hi, torch.where(exact, lo, 0.0))
    return torch.where(exact, s, hi), torch.where(exact, e, 0.0)


#: The plain mean's rounding, relative to the smallest noise scale, above which a mean
#: ``W x + b`` is kept as a pair: below it a residual's error moves a log-density by
#: less than ``|z| 2^-40`` (``z`` the standardised residual).
MEAN_ROUNDING = 2.0**-40


def sum_rounds_off(
    largest_weight: float, largest_bias: float, x: torch.Tensor, noise_scale: float
) -> bool:
    """Whether ``W x + b`` summed in float64 may be off by more than ``MEAN_ROUNDING`` noise scales.

    ``noise_scale`` is the smallest noise scale it is compared with. The rounding bound ``(p + 1)
    2^-52 (p max|W| max|x| + max|b|)`` comes from the largest entries (``x`` ``(..., p)``; cheap:
    never the joint's shape). NaN inputs count as rounding off (the pair keeps them NaN).
    """
    p = x.shape[-1]
    if not p or not x.numel():
        return False
    bound = (p + 1) * 2.0**-52 * (p * largest_weight * float(x.abs().max()) + largest_bias)
    return not bound <= MEAN_ROUNDING * noise_scale


def linear_gaussian_marginal(
    mean: torch.Tensor,
    cov: torch.Tensor,
    weight: torch.Tensor,
    offset: torch.Tensor,
    noise_cov: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean ``(..., d)`` and covariance ``(..., d, d)`` of ``y = W theta + b + e``."""
    loc = (weight @ mean.unsqueeze(-1)).squeeze(-1) + offset
    return loc, weight @ cov @ weight.mT + noise_cov


def condition_linear_gaussian(
    mean: torch.Tensor,
    cov: torch.Tensor,
    weight: torch.Tensor,
    offset: torch.Tensor,
    noise_cov: torch.Tensor,
    y: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Posterior mean ``(..., k)`` and covariance ``(..., k, k)`` of ``theta`` given ``y``.

    Given its dimensions that are not NaN, where some are.
    """
    y_loc, y_cov = linear_gaussian_marginal(mean, cov, weight, offset, noise_cov)
    if bool(torch.isnan(y).any()):
        y, y_loc, y_cov, seen = mask_unobserved(y, y_loc, y_cov)
        weight = torch.where(seen[..., None], weight, 0.0)
    cross = cov @ weight.mT  # (..., k, d)
    chol = torch.linalg.cholesky(y_cov)
    gain = torch.cholesky_solve(cross.mT, chol).mT  # S W^T (W S W^T + R)^-1
    post_mean = mean + (gain @ (y - y_loc).unsqueeze(-1)).squeeze(-1)
    post_cov = cov - gain @ weight @ cov
    return post_mean, 0.5 * (post_cov + post_cov.mT)


def mask_unobserved(
    y: torch.Tensor, loc: torch.Tensor, cov: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """A partly observed ``y``'s Gaussian, its unobserved dimensions carrying no information.

    A Gaussian ``N(loc, cov)`` of ``y`` ``(..., d)`` observed where ``y`` is not NaN, rewritten so
    that the unobserved dimensions carry no information: there ``y`` and ``loc`` are 0 and ``cov``
    has 1 on the diagonal and 0 elsewhere in their rows and columns. Then ``N(y'; loc', cov') =
    N(y_o; loc_o, cov_oo) N(0; 0, 1)^u`` (the observed dimensions' marginal, a Gaussian's rows and
    columns dropped, times a constant) and conditioning on ``y'`` is conditioning on ``y_o``.
    Returns ``y'``, ``loc'``, ``cov'`` (broadcast together) and the observed mask ``(..., d)``.
    """
    seen = ~torch.isnan(y)
    shape = torch.broadcast_shapes(y.shape[:-1], loc.shape[:-1], cov.shape[:-2])
    d = y.shape[-1]
    seen = seen.expand(*shape, d)
    y = torch.where(seen, y.nan_to_num(), 0.0)
    loc = torch.where(seen, loc, 0.0)
    both = seen[..., :, None] & seen[..., None, :]
    eye = torch.eye(d, dtype=cov.dtype)
    cov = torch.where(both, cov, eye)
    return y, loc, cov, seen


def partial_log_density(
    y: torch.Tensor, loc: torch.Tensor, scale_tril: torch.Tensor
) -> torch.Tensor:
    """``log N(y_o; loc_o, cov_oo)`` over the dimensions ``o`` where ``y`` is not NaN.

    0 where none is; ``cov = scale_tril scale_tril^T``; batch-shaped.
    """
    y, loc, cov, seen = mask_unobserved(y, loc, scale_tril @ scale_tril.mT)
    tril = torch.linalg.cholesky(cov)
    z = torch.linalg.solve_triangular(tril, (y - loc)[..., None], upper=False).squeeze(-1)
    log_det = tril.diagonal(dim1=-2, dim2=-1).log().sum(-1)
    k = seen.sum(-1).to(y.dtype)
    return -0.5 * z.square().sum(-1) - log_det - 0.5 * k * math.log(2 * math.pi)


def condition_on_observed(
    y: torch.Tensor, loc: torch.Tensor, cov: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """``N(loc, cov)`` of ``y`` ``(..., d)`` conditioned on its dimensions that are not NaN.

    The unobserved dimensions get ``loc_u + S_uo S_oo^-1 (y_o - loc_o)`` and ``S_uu - S_uo S_oo^-1
    S_ou``; the observed ones their value, with zero variance.
    """
    seen = ~torch.isnan(y)
    eye = torch.eye(y.shape[-1], dtype=cov.dtype)
    noise = torch.zeros_like(eye)
    mean, post = condition_linear_gaussian(loc, cov, eye, torch.zeros_like(y), noise, y)
    both = seen[..., :, None] | seen[..., None, :]
    return torch.where(seen, y.nan_to_num(), mean), torch.where(both, 0.0, post)


def residual_of(fn, value: torch.Tensor) -> torch.Tensor:
    """``value - mean`` of the Gaussian ``fn``, batch-shaped.

    A mean held as a pair (``fn.loc_low``, :func:`affine_pair`) is subtracted in its order, ``(value
    - loc) - loc_low``.
    """
    diff = value - fn.loc
    low = getattr(fn, "loc_low", None)
    return diff if low is None else diff - low


def mahalanobis(fn, value: torch.Tensor) -> torch.Tensor:
    """Squared Mahalanobis distance of ``value`` under the Gaussian ``fn``, batch-shaped.

    ``fn`` is a distribution with ``loc`` and ``scale_tril``. A value with NaN dimensions (partial
    evidence) is measured in its observed dimensions' marginal. A mean held as a pair
    (``fn.loc_low``, :func:`affine_pair`) gives the residual ``(value - loc) - loc_low``.
    """
    diff = residual_of(fn, value)
    tril = fn.scale_tril
    if bool(torch.isnan(value).any()):  # the observed dimensions' marginal
        value, loc, cov, _ = mask_unobserved(value, fn.loc, tril @ tril.mT)
        diff, tril = value - loc, torch.linalg.cholesky(cov)
    shape = torch.broadcast_shapes(diff.shape[:-1], tril.shape[:-2])
    z = torch.linalg.solve_triangular(
        tril.expand(*shape, *tril.shape[-2:]),
        diff.expand(*shape, diff.shape[-1])[..., None],
        upper=False,
    )
    return z.squeeze(-1).square().sum(-1)


def chi_square_tail(dof: int, x: float) -> float:
    """``P(X > x)`` for ``X`` chi-square with ``dof >= 1`` degrees of freedom.

    The regularised ``gammaincc(dof / 2, x / 2)`` in closed form, from ``Q(1, h) = e^-h`` (even
    ``dof``) or ``Q(1/2, h) = erfc(sqrt h)`` (odd) up by ``Q(a + 1, h) = Q(a, h) + h^a e^-h /
    Gamma(a + 1)``.
    """
    h = x / 2
    if h == math.inf:
        return 0.0
    a, tail = (0.5, math.erfc(math.sqrt(h))) if dof % 2 else (1.0, math.exp(-h))
    if h == 0 or a >= dof / 2:
        return tail
    # the terms relative to the first, h^a e^-h / Gamma(a + 1), whose log is log_first
    # (the first term itself may be subnormal where the sum is not)
    log_first = a * math.log(h) - h - math.lgamma(a + 1)
    total, term = 0.0, 1.0
    while a < dof / 2:
        total += term
        a += 1
        term *= h / a
        if total > 1e280:  # keep the sum finite: move a factor into log_first
            total, term, log_first = total * 1e-280, term * 1e-280, log_first + 280 * math.log(10)
    return tail + math.exp(math.log(total) + log_first)


def quadratic_features(y: torch.Tensor) -> torch.Tensor:
    """``(n, F)``: ``y_i y_j`` for ``i <= j`` (row-major), ``y_i``, and 1, of ``y`` ``(n, d)``."""
    i, j = torch.triu_indices(y.shape[-1], y.shape[-1])
    return torch.cat([y[:, i] * y[:, j], y, torch.ones_like(y[:, :1])], -1)


def lstsq_rows(design: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
    """Minimum-norm least-squares solutions ``z`` ``(n, ..., k)`` of ``design z = rhs``, per row.

    ``design`` ``(n, ..., D, k)`` and ``rhs`` ``(n, ..., D)``, the first axis the rows. Rows whose
    designs are equal bit for bit (a query's rows under one action, say) share one factorisation:
    their right-hand sides are solved together as columns (``gelsd``, the SVD solver, which treats
    each column alone), instead of one small problem per row and batch entry.
    """
    n, shape = design.shape[0], design.shape[1:]
    if n <= 1 or design.stride(0) == 0:  # one design for every row
        groups = [(design[0], torch.arange(n))] if n else []
    else:
        bits = {8: torch.int64, 4: torch.int32, 2: torch.int16}[design.element_size()]
        flat = design.reshape(n, -1).contiguous().view(bits)
        _, inverse = torch.unique(flat, dim=0, return_inverse=True)
        order = torch.argsort(inverse, stable=True)
        counts = torch.bincount(inverse).tolist()
        groups = [(design[rows[0]], rows) for rows in order.split(counts)]
    out = rhs.new_empty(n, *shape[:-2], shape[-1])
    for a, rows in groups:
        columns = rhs[rows].movedim(0, -1)  # (..., D, m): the rows as right-hand sides
        z = torch.linalg.lstsq(a, columns, driver="gelsd").solution
        out[rows] = z.movedim(-1, 0)
    return out
