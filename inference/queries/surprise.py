"""The imitation surprise of an observed end state with a continuous part.

Definition (the one :func:`inference.imitation_check` reports). Let ``E`` be a row's
evidence other than its observed end sites (the initial state, the executed action, any
parameter given) and ``o*`` the observed end state: the observed discrete end features'
states and the observed continuous end features' values in their observed dimensions.
The model's predictive ``p(o | E)`` is a probability over discrete outcomes, a density
over continuous ones, their product over both. The surprise is

    surprise(o*) = P_{O ~ p(. | E)}( p(O | E) > p(o* | E) ),

the predictive probability of the outcomes strictly more likely than the one observed:
0 at the most likely outcome, near 1 far out in the tails.

Computing it. Given every enumerated site (the latent discrete sites: clusters, unknown
initial states, latent discrete end parents; and the discrete outcome), the continuous
outcome is one Gaussian, unknown parameters integrated out in closed form. So
``p(o | E)`` is a sum over these configurations ("components") ``c`` of
``P(c | E) N(y; mu_c, S_c)``, ``d`` the observed continuous dimensions of the row.

* **One component per discrete outcome** (a given action and parameter, say): the
  outcomes of component ``c`` that are more likely than ``o*`` form the ellipsoid
  ``D_c^2(Y) < r_c^2``, ``r_c^2 = D_c^2(y*) + 2 (log p(c, y*, E) - log p(o*, E))``
  (``D_c^2`` the squared Mahalanobis distance under ``c``), and under ``c`` the distance
  is chi-square with ``d`` degrees of freedom. The surprise is exact:
  ``sum_c P(c | E) P(chi2_d < r_c^2)``; with a single component it is
  ``P(chi2_d < D^2(y*))``.
* **Several components for one discrete outcome** (an unknown parameter's clusters, an
  unknown initial state): the set of more likely outcomes has no closed form. Each
  component's share is integrated in its own whitened coordinates ``Y = mu_c + L_c r u``:
  over fixed directions ``u`` (``+-1`` in one dimension, equally spaced angles in two, a
  fixed scrambled Sobol set with antithetic pairs beyond) and, along each ray, over the
  chi-distributed radius ``r``: the radii where the outcome is more likely are bracketed
  on a grid, their ends found by regula falsi in ``r^2`` (the Illinois variant, started
  from the linear interpolation, which is exact where one component dominates: its
  log-density is linear in ``r^2``), and their chi-square probability summed in closed
  form. In one dimension (the directions +-1) this is exact to rounding. On each component's ball only the components whose density
  can matter there are weighed (a bound per pair). Deterministic: the same row gets the
  same surprise wherever it sits in the batch. Rows observing some dimensions of a
  feature are integrated over those dimensions' marginal.

The joint Gaussian of several continuous end features that share an unknown parameter
(the model samples them in turn, each given the value's Gaussian conditioned on those
before it) is read off the model itself: each feature's mean is affine in the features
before it, and the slopes are the model's means at the observation moved by a step in
each observed dimension. Nothing here is sampled.
"""

from __future__ import annotations

import math

import torch
from effect_networks.inference.exact.enumeration import (
    enumerate_model,
    log_ratio,
    over_row_chunks,
    row_chunks,
)
from effect_networks.inference.exact.traced import Enumerated
from effect_networks.models.declaration import DTYPE, EffectNetwork
from effect_networks.models.evidence import Evidence, observed_dims
from effect_networks.models.gaussian import mahalanobis, mask_unobserved
from effect_networks.models.params import NetworkParams

LOG_2PI = math.log(2 * math.pi)

#: Default quadrature points per component where a discrete outcome has several
#: components (directions x radii).
QUADRATURE_POINTS = 256

#: Elements of one row chunk's quadrature tensor.
_QUADRATURE_CHUNK = 1 << 21

#: Log-scale margin under which two outcomes count as equally likely (as for discrete ones).
_TIE = 1e-9


def continuous_surprise(
    net: EffectNetwork,
    params: NetworkParams,
    evidence: Evidence,
    observed: list[str],
    *,
    n_points: int = QUADRATURE_POINTS,
    seed: int = 0,
) -> torch.Tensor:
    """``(n,)`` surprise of the observed end sites ``observed`` of every row.

    At least one of ``observed`` is continuous; rows of encoded ``evidence`` (at least one row).

    ``n_points``: quadrature points per component (directions times radii) for rows where a discrete
    outcome has several components; ``seed`` fixes the scrambled Sobol directions used
    beyond two continuous dimensions.
    """
    discrete = [s for s in observed if net.site(s).discrete]
    continuous = [s for s in observed if not net.site(s).discrete]
    assert continuous
    varied = evidence.without(*discrete)  # the discrete outcomes enumerated
    dof = sum(observed_dims(evidence[s]).sum(-1) for s in continuous).to(DTYPE)  # (n,)

    def weights(e: Enumerated, _, rows):
        # Every log-weight below is held relative to the same per-row constant: the
        # offsets of this enumeration's sites other than the observed continuous ones (a
        # continuous initial state's density, say), which the joint shares, so that they
        # cancel exactly instead of swallowing the differences at a large magnitude.
        centred = e.log_weight  # log p(c, y*, E) less every offset, (E..., n)
        own_total = 0.0  # the observed continuous sites' offsets
        d2 = torch.zeros((), dtype=DTYPE)
        log_density = torch.zeros((), dtype=DTYPE)  # theirs less their offsets
        for s in continuous:
            node = e.trace.nodes[s]
            d2 = d2 + mahalanobis(node["fn"], node["value"])
            own = e.offsets.get(s, 0.0)
            log_density = log_density + (node["log_prob"] - own)
            own_total = own_total + own
        log_w = centred + own_total
        log_prior = torch.where(torch.isfinite(centred), centred - log_density, -torch.inf)
        # log p(o*, E) less the same constant: log p(o*, E) / p(varied) by the offsets
        # that cancel, plus the varied evidence's own normaliser
        full = enumerate_model(net, params, evidence.rows(rows))
        joint = log_ratio(full, e) + e.log_norm + own_total
        joint = torch.where(full.log_norm > -torch.inf, joint, -torch.inf)  # nothing possible
        out = tuple(_by_outcome(e, discrete, t.expand(log_w.shape)) for t in (log_w, log_prior, d2))
        return (*out, joint)

    log_w, log_prior, d2, log_joint = over_row_chunks(net, params, varied, discrete, weights)
    log_joint = log_joint[:, None, None]
    prob = (log_prior - log_prior.logsumexp((1, 2), keepdim=True)).exp()  # P(c | E)
    # one component per outcome: the chi-square probability of the ellipsoid
    r2 = (d2 + 2 * (log_w - log_joint)).clamp_min(0).nan_to_num(0.0)
    inside = torch.special.gammainc(dof.clamp_min(1)[:, None, None] / 2, r2 / 2)
    # no continuous dimension observed in a row: only the discrete outcome's probability
    outcome = (log_w.logsumexp(-1, keepdim=True) > log_joint + _TIE).to(DTYPE)
    inside = torch.where(dof[:, None, None] > 0, inside, outcome)
    mixed = ((torch.isfinite(log_prior).sum(-1) > 1).any(-1)) & (dof > 0)
    if bool(mixed.any()):
        rows = mixed.nonzero().squeeze(-1)
        mean, tril = _joint_gaussians(net, params, varied.rows(rows), continuous, discrete)
        seen = torch.cat([observed_dims(evidence[s][rows]) for s in continuous], -1)
        inside = inside.clone()
        # rows by observed dimensions: their marginal is the joint's observed block (an
        # unobserved dimension is independent of the others in the masked layout)
        for pattern in torch.unique(seen, dim=0):
            group = (seen == pattern).all(-1)
            dims = pattern.nonzero().squeeze(-1)
            inside[rows[group]] = _quadrature(
                log_prior[rows[group]],
                mean[group][..., dims],
                tril[group][..., dims, :][..., dims],
                log_joint[rows[group], 0, 0],
                n_points,
                seed,
            )
    share = torch.where(prob > 0, prob * inside, 0.0)
    # an outcome of probability 0 (a density underflowed in float64): every other is likelier
    impossible = log_joint[:, 0, 0] == -torch.inf
    return torch.where(impossible, 1.0, share.sum((1, 2)).clamp(0, 1))


def _by_outcome(e: Enumerated, outcomes: list[str], t: torch.Tensor) -> torch.Tensor:
    """``t`` ``(E..., n, *event)`` laid out ``(n, O, K, *event)``.

    The rows, the discrete outcomes' configurations, the other enumerated sites' configurations.
    """
    depth = e.log_weight.dim()
    event = t.dim() - depth
    rows = depth - 1
    first = [depth + e.dims[s] for s in outcomes]
    rest = [d for d in range(rows) if d not in first]
    n = t.shape[rows]
    o = math.prod(t.shape[d] for d in first)
    order = [rows, *first, *rest, *range(depth, depth + event)]
    return t.permute(order).reshape(n, o, -1, *t.shape[depth:])


def _joint_gaussians(net, params, evidence: Evidence, continuous, discrete):
    """Per row and component the joint Gaussian of the observed continuous end features.

    ``(n, O, K, D)`` mean and ``(n, O, K, D, D)`` Cholesky factor, ``D`` their summed dimensions,
    laid out as :func:`mask_unobserved` writes a partial observation (an unobserved dimension: mean
    0, unit variance, independent of the others).

    The model samples the features in its trace's order, each given those before it
    (a shared unknown parameter conditioned on them); its mean is affine in their
    values, so each slope column is the change of the mean when one observed value moves.
    """

    def steps(e: Enumerated, chunk: Evidence, _):
        order = [s for s in e.trace.nodes if s in continuous]
        shape = e.log_weight.shape
        locs, covs, values, seens = {}, {}, {}, {}
        for s in order:
            fn = e.trace.nodes[s]["fn"]
            d = fn.loc.shape[-1]
            locs[s] = fn.loc.expand(*shape, d)
            covs[s] = fn.covariance_matrix.expand(*shape, d, d)
        slopes = {}  # (s, t) -> (E..., n, d_s, d_t): d mean_s / d y_t
        for t in order[:-1]:
            y = chunk[t]
            step = 1.0 + y.abs().nan_to_num(0.0)
            columns = []
            for i in range(y.shape[-1]):
                moved = y.clone()
                moved[:, i] = y[:, i] + step[:, i]  # NaN stays NaN: no slope
                trace = enumerate_model(net, params, chunk | {t: moved}, keep=discrete).trace
                columns.append(
                    {
                        s: (trace.nodes[s]["fn"].loc.expand_as(locs[s]) - locs[s])
                        / step[:, i, None]
                        for s in order[order.index(t) + 1 :]
                    }
                )
            for s in order[order.index(t) + 1 :]:
                slopes[s, t] = torch.stack([c[s] for c in columns], -1)
        means, trils = [], []
        for s in order:
            y, loc, cov, seen = mask_unobserved(chunk[s], locs[s], covs[s])
            values[s], seens[s] = y, seen
            mean = loc
            lower = []  # the rows of the joint factor to the left of s's own block
            for t, prev_mean in zip(order[: len(means)], means, strict=True):
                slope = torch.where(seen[..., :, None] & seens[t][..., None, :], slopes[s, t], 0)
                mean = mean + (slope @ (prev_mean - values[t])[..., None])[..., 0]
                lower.append(slope)
            left = torch.cat(lower, -1) @ _assemble(trils) if lower else None
            own = torch.linalg.cholesky(cov)
            means.append(mean)
            trils.append((left, own))
        mean = torch.cat(means, -1)
        tril = _assemble(trils)
        return _by_outcome(e, discrete, mean), _by_outcome(e, discrete, tril)

    return over_row_chunks(net, params, evidence, discrete, steps)


def _assemble(blocks) -> torch.Tensor:
    """A block lower-triangular matrix from per-feature ``(left, own)`` blocks.

    ``left`` the rows' part under the earlier features (``None`` for the first).
    """
    sizes = [own.shape[-1] for _, own in blocks]
    total = sum(sizes)
    shape = torch.broadcast_shapes(*(own.shape[:-2] for _, own in blocks))
    out = torch.zeros(*shape, total, total, dtype=DTYPE)
    start = 0
    for (left, own), d in zip(blocks, sizes, strict=True):
        if left is not None:
            out[..., start : start + d, :start] = left
        out[..., start : start + d, start : start + d] = own
        start += d
    return out


def _directions(dim: int, n_points: int, seed: int) -> tuple[torch.Tensor, int]:
    """Fixed unit directions ``(J, dim)`` and the radii per direction for ``n_points``."""
    if dim == 1:
        u = torch.tensor([[1.0], [-1.0]], dtype=DTYPE)
    elif dim == 2:
        j = max(4, 2 * round(math.sqrt(n_points) / 2))
        angle = (torch.arange(j, dtype=DTYPE) + 0.5) * (2 * math.pi / j)
        u = torch.stack([angle.cos(), angle.sin()], -1)
    else:
        half = max(2, round(math.sqrt(n_points) / 2))
        sobol = torch.quasirandom.SobolEngine(dim, scramble=True, seed=seed)
        z = torch.special.ndtri(sobol.draw(half, dtype=DTYPE).clamp(1e-12, 1 - 1e-12))
        u = torch.cat([z, -z], 0)
    u = u / u.norm(dim=-1, keepdim=True)
    return u, max(8, n_points // len(u))


def _neighbours(offset, slope, weight, top):
    """For each component ``c``, the components ``c'`` whose density can matter near ``c``.

    Near ``c`` is on the ball of radius ``top`` around ``c`` (in ``c``'s whitened coordinates):
    ``c'``'s term there is at most ``weight_c' - D^2 / 2``, ``D`` the least distance of the ball
    from ``c'``'s mean in ``c'``'s whitened coordinates (``|b| - top |A|``, ``b`` the offset and
    ``A`` the slope), and ``c``'s own term at least ``weight_c - top^2 / 2``; a term below that by
    more than 60 nats changes no float64 sum. Returns ``offset``, ``slope`` and ``weight``
    (broadcast to ``(m, O, K, K'')``) over the fewest ``K''`` components that hold every one that
    can matter (all of them where the components overlap).
    """
    m, o, k = weight.shape
    reach = offset.norm(dim=-1) - top * slope.square().sum((-2, -1)).sqrt()
    bound = weight[:, :, None, :] - 0.5 * reach.clamp_min(0).square()  # (m, O, K, K')
    own = weight - 0.5 * top**2  # (m, O, K)
    needed = bound > (own - 60.0)[..., None]
    count = int(needed.sum(-1).max())
    weight = weight[:, :, None, :].expand(m, o, k, k)
    if count == k:
        return offset, slope, weight
    index = torch.where(needed, bound, -torch.inf).topk(count, dim=-1).indices  # (m, O, K, K'')
    return (
        offset.gather(3, index[..., None].expand(-1, -1, -1, -1, offset.shape[-1])),
        slope.gather(3, index[..., None, None].expand(-1, -1, -1, -1, *slope.shape[-2:])),
        weight.gather(3, index),
    )


def _quadrature(log_prior, mean, tril, log_joint, n_points, seed) -> torch.Tensor:
    """``(m, O, K)``: per component, the probability of an outcome more likely than the observed.

    The outcome's discrete part is the component's. ``log_prior`` ``(m, O, K)``: ``log p(c, E)``;
    ``mean`` ``(m, O, K, d)``, ``tril``: the components' Gaussians over the ``d`` observed
    dimensions; ``log_joint`` ``(m,)``: ``log p(o*, E)``.
    """
    m, o, k, dim = mean.shape
    u, n_radii = _directions(dim, n_points, seed)  # (J, d)
    # every component c's points in every component c''s whitened coordinates:
    # z = L_c'^-1 (mu_c - mu_c') + r L_c'^-1 L_c u
    eye = torch.eye(dim, dtype=DTYPE)
    inverse = torch.linalg.solve_triangular(tril, eye.expand_as(tril), upper=False)
    inverse = inverse[:, :, None]  # (m, O, 1, K', D, D)
    offset = (inverse @ (mean[:, :, :, None] - mean[:, :, None])[..., None])[..., 0]
    slope = inverse @ tril[:, :, :, None]  # (m, O, K, K', d, d)
    log_det = tril.diagonal(dim1=-2, dim2=-1).log().sum(-1)  # (m, O, K')
    weight = log_prior - log_det  # (m, O, K'): each component's log-density up to |z|^2
    top = math.sqrt(dim) + 8.0  # radii beyond: chi-square tail below 1e-15
    offset, slope, weight = _neighbours(offset, slope, weight, top)  # (m, O, K, K'', ...)
    along = torch.einsum("mokpde,je->mokpjd", slope, u)  # (m, O, K, K'', J, d)
    # |z|^2 = |b|^2 + r (2 b.v + r |v|^2) along each ray, b the offset, v the direction
    # (the terms lose digits only where |b| is so large that c' adds nothing there)
    square = offset.square().sum(-1)[..., None, None]  # (m, O, K, K'', 1, 1)
    linear = (offset[..., None, :] * along).sum(-1)[..., None]  # (m, O, K, K'', J, 1)
    quadratic = 0.5 * along.square().sum(-1)[..., None]
    base = weight[..., None, None] - 0.5 * square  # (m, O, K, K'', 1, 1)
    radius = torch.linspace(0, top, n_radii, dtype=DTYPE).expand(m, -1)  # (m, G)
    level = (log_joint + dim / 2 * LOG_2PI)[:, None, None, None, None]
    cdf_dof = torch.full((m, 1, 1, 1, 1), dim / 2, dtype=DTYPE)
    j = u.shape[0]
    per_row = o * k * offset.shape[3] * j * n_radii
    out = []
    for part in row_chunks(m, per_row, _QUADRATURE_CHUNK):
        r = radius[part][:, None, None, None, None, :]  # (r, 1, 1, 1, 1, G)
        log_density = torch.addcmul(linear[part], r, quadratic[part]).mul_(r)
        log_density = torch.sub(base[part], log_density).logsumexp(3)  # (r, O, K, J, G)
        excess = log_density - level[part]
        # the chi-square mass of the radii where excess > 0: per grid interval the CDF
        # at its ends where they lie above, and at the interpolated crossing where not
        s = radius[part].square()  # (r, G)
        cdf = cdf_dof[part][..., 0]  # (r, 1, 1, 1)
        at_nodes = torch.special.gammainc(cdf[..., None], s[:, None, None, None, :] / 2)
        above = excess > 0
        mass = (above[..., 1:] * at_nodes[..., 1:] - above[..., :-1] * at_nodes[..., :-1]).sum(-1)
        mass = mass + above[..., -1] * torch.special.gammaincc(cdf, s[:, -1, None, None, None] / 2)
        crossing = above[..., 1:] != above[..., :-1]
        if bool(crossing.any()):
            a, b = excess[..., :-1][crossing], excess[..., 1:][crossing]
            s0 = s[:, None, None, None, :-1].expand_as(crossing)[crossing]
            s1 = s[:, None, None, None, 1:].expand_as(crossing)[crossing]
            rows, outcome, comp, ray, _ = crossing.nonzero().unbind(-1)
            at = _crossing(
                base[part][rows, outcome, comp, :, 0, 0],
                linear[part][rows, outcome, comp, :, ray, 0],
                quadratic[part][rows, outcome, comp, :, ray, 0],
                level[part][rows, 0, 0, 0, 0],
                (s0, a),
                (s1, b),
            )
            shape = cdf[..., None].expand_as(crossing)[crossing]
            signed = torch.where(a > 0, 1.0, -1.0) * torch.special.gammainc(shape, at / 2)
            mass = mass + torch.zeros_like(excess[..., 1:]).index_put_(
                tuple(crossing.nonzero().T), signed
            ).sum(-1)
        out.append(mass.mean(-1))  # over the directions
    return torch.cat(out, 0)


#: Illinois steps that refine each crossing of the level along a ray (from the linear
#: interpolation in r^2, exact where one component dominates, to float64 rounding where
#: several overlap).
_CROSSING_STEPS = 12


def _crossing(base, linear, quadratic, level, low, high) -> torch.Tensor:
    """``(N,)`` squared radii where the mixture's log-density along a ray meets ``level``.

    The log-density is ``logsumexp(base - r (linear + r quadratic))`` over the components (``(N,
    K)`` each), ``level`` ``(N,)``: the Illinois variant of regula falsi in ``r^2`` between the
    bracketing nodes ``low`` and ``high`` (``(r^2, excess)`` pairs of opposite signs).
    """
    (s0, f0), (s1, f1) = low, high
    for _ in range(_CROSSING_STEPS):
        step = torch.where(f1 != f0, f1 * (s1 - s0) / (f1 - f0), 0.0)
        s = (s1 - step).clamp(torch.minimum(s0, s1), torch.maximum(s0, s1))
        r = s.sqrt()[:, None]
        f = torch.sub(base, r * torch.addcmul(linear, r, quadratic)).logsumexp(-1) - level
        switch = f * f1 < 0
        s0, f0 = torch.where(switch, s1, s0), torch.where(switch, f1, f0 / 2)
        s1, f1 = s, f
        if not bool((f != 0).any()):
            break
    return s1
