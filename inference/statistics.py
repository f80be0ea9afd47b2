"""Sufficient statistics of the closed-form fit, and the parameters they give.

Every closed-form CPD is a function of sums over rows: a table of its counts; a
conditional linear Gaussian of ``sum z z^T``, ``sum z y^T``, ``sum y y^T`` and the row
count per parent configuration (``z = [x, 1]``, its continuous parents and a one).
Sums merge by addition, which is associative and commutative, so a data set can be cut
into chunks (or partitions on a cluster), each chunk's :class:`Statistics` computed
apart, and the results added in any grouping: ``statistics(a) + statistics(b)`` is
``statistics(a ∪ b)`` up to the rounding of float additions (counts are exact).
:func:`params_from_statistics` then gives the same parameters as one pass over all rows.

Pseudo-count policy (``pseudo_count``, written alpha): a table row is
``(counts + alpha) / (n + K alpha)``, so a parent configuration no sample reached is
uniform; a Gaussian configuration gets alpha pseudo-rows of the pooled statistics of its
site (all rows together), so an unseen one is the pooled fit and a rarely seen one is
shrunk towards it. Covariances get ``min_variance`` on the diagonal so that a
configuration with fewer rows than dimensions stays positive definite. ``alpha = 0`` and
``min_variance = 0`` give the plain sample statistics where every configuration is seen.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch

from models.declaration import (
    ACTION,
    DTYPE,
    Continuous,
    Discrete,
    EffectNetwork,
    cluster_site,
    end_site,
    initial_site,
    param_site,
)
from models.evidence import Evidence
from models.params import LinearGaussian, Softmax, Table, cell_zero_for_unused, expected_shapes


@dataclass(frozen=True)
class Counts:
    """A table's counts, ``(P..., K)`` int64 (exact in any order of addition)."""

    counts: torch.Tensor

    def __add__(self, other: Counts) -> Counts:
        return Counts(self.counts + other.counts)

    def add_(self, other: Counts) -> None:
        self.counts.add_(other.counts)


@dataclass(frozen=True)
class Moments:
    """A linear Gaussian's sums per parent configuration ``G`` (flattened ``P...``):
    ``zz`` ``(G, q, q)``, ``zy`` ``(G, q, d)``, ``yy`` ``(G, d, d)``, rows ``n`` ``(G,)``."""

    zz: torch.Tensor
    zy: torch.Tensor
    yy: torch.Tensor
    n: torch.Tensor

    def __add__(self, other: Moments) -> Moments:
        return Moments(*(getattr(self, f.name) + getattr(other, f.name) for f in fields(self)))

    def add_(self, other: Moments) -> None:
        for f in fields(self):
            getattr(self, f.name).add_(getattr(other, f.name))


@dataclass(frozen=True)
class Statistics:
    """Sufficient statistics of every closed-form CPD of one network, per site.

    ``softmax`` names the sites whose CPD has no closed form (their counts only seed the
    gradient fit, which needs the rows themselves).
    """

    sites: dict[str, Counts | Moments]
    rows: int
    softmax: tuple[str, ...] = ()

    def __add__(self, other: Statistics) -> Statistics:
        if set(self.sites) != set(other.sites):
            raise ValueError("statistics of two different networks cannot be merged")
        merged = {site: self.sites[site] + other.sites[site] for site in self.sites}
        return Statistics(merged, self.rows + other.rows, self.softmax)

    def merged_into(self, total: Statistics | None) -> Statistics:
        """``total + self``, adding into ``total``'s tensors in place (no copy of a big
        table per chunk); ``self`` when ``total`` is ``None``."""
        if total is None:
            return self
        if set(self.sites) != set(total.sites):
            raise ValueError("statistics of two different networks cannot be merged")
        for site, s in self.sites.items():
            total.sites[site].add_(s)
        return Statistics(total.sites, total.rows + self.rows, total.softmax)


def statistics(net: EffectNetwork, enc: Evidence) -> Statistics:
    """The sums of one chunk of complete, checked rows (see :func:`inference.fit`)."""
    sites: dict[str, Counts | Moments] = {}
    n = enc.n_rows
    no_parent = torch.zeros(n, dtype=torch.long)
    softmax = []
    flat: dict[tuple[str, ...], tuple[torch.Tensor, tuple[int, ...]]] = {}
    for f in net.features:
        if f.initial:
            site = initial_site(f.name)
            if isinstance(f, Discrete):
                sites[site] = _counts(no_parent, enc[site], (), f.cardinality)
            else:
                sites[site] = _moments(no_parent, None, enc[site], (), site)
    sites[ACTION] = _counts(no_parent, enc[ACTION], (), len(net.actions))
    for p in net.parameters:
        c_site, p_site = cluster_site(p.name), param_site(p.name)
        uses = net.parameter_in_use(p, enc[ACTION])
        sites[c_site] = _counts(
            enc[ACTION][uses], enc[c_site][uses], (len(net.actions),), p.n_clusters
        )
        cluster = enc[c_site][uses]
        sites[p_site] = _moments(cluster, None, enc[p_site][uses], (p.n_clusters,), p_site)
    for f in net.features:
        site = end_site(f.name)
        parents = net.discrete_parents(f.name)
        if parents not in flat:  # end sites sharing their parents share the index
            flat[parents] = _flat_index(net, enc, parents)
        index, card = flat[parents]
        cont = [enc[s].nan_to_num() for s in net.continuous_parents(f.name)]
        x = torch.cat(cont, -1) if cont else None
        if isinstance(f, Continuous):
            sites[site] = _moments(index, x, enc[site], card, site)
        else:
            sites[site] = _counts(index, enc[site], card, f.cardinality)
            if x is not None:
                softmax.append(site)
    return Statistics(sites, n, tuple(softmax))


def params_from_statistics(
    net: EffectNetwork, stats: Statistics, alpha: float, min_variance: float
) -> dict:
    """Closed-form maximum-likelihood CPDs (softmax CPDs: a start for the gradient)."""
    shapes = expected_shapes(net)
    cpds: dict = {}
    for site, s in stats.sites.items():
        kind, shape = shapes[site]
        if isinstance(s, Counts):
            table = _table(s.counts, alpha)
            if kind == "Softmax":
                # start from the table's log-frequencies with zero slopes
                start = _table(s.counts, max(alpha, 1e-3))
                cpds[site] = Softmax(
                    torch.zeros(shape["weight"], dtype=DTYPE), start.probs.log(), start.n
                )
            else:
                cpds[site] = table
        else:
            card = shape["n"]
            feature = net.site(site).feature if net.site(site).role == "end" else None
            zero = _unused(net, feature, card) if feature is not None else None
            cpds[site] = _linear_gaussian(s, card, alpha, min_variance, site, zero)
    for p in net.parameters:  # actions not using a parameter sit on cell 0
        t = cpds[cluster_site(p.name)]
        cpds[cluster_site(p.name)] = Table(cell_zero_for_unused(net, p, t.probs), t.n)
    return {name: cpds[name] for name in shapes}


def _flat_index(
    net: EffectNetwork, enc: Evidence, sites: tuple[str, ...]
) -> tuple[torch.Tensor, tuple[int, ...]]:
    card = tuple(net.site(s).size for s in sites)
    index = torch.zeros(enc.n_rows, dtype=torch.long)
    for s, k in zip(sites, card, strict=True):
        index = index * k + enc[s]
    return index, card


def _counts(index: torch.Tensor, child: torch.Tensor, card: tuple[int, ...], k: int) -> Counts:
    size = math.prod(card)
    flat = child if not card else index * k + child  # no parents: the index is all zeros
    return Counts(torch.bincount(flat, minlength=size * k).reshape(*card, k))


def _table(counts: torch.Tensor, alpha: float) -> Table:
    probs = counts.to(DTYPE, copy=True)  # a new tensor: the arithmetic below runs in place
    k = probs.shape[-1]
    n = probs.sum(-1)
    probs.add_(alpha).div_((n + k * alpha).clamp_min(1e-300)[..., None])
    unseen = n == 0
    if bool(unseen.any()):
        probs[unseen] = 1.0 / k
    return Table(probs, n)


def _moments(
    index: torch.Tensor, x: torch.Tensor | None, y: torch.Tensor, card: tuple[int, ...], site: str
) -> Moments:
    groups = math.prod(card)
    n_rows, d = y.shape
    ones = torch.ones(n_rows, 1, dtype=DTYPE)
    z = torch.cat([x, ones], -1) if x is not None else ones
    q = z.shape[-1]
    zz = torch.zeros(groups, q, q, dtype=DTYPE).index_add_(0, index, z[:, :, None] * z[:, None, :])
    zy = torch.zeros(groups, q, d, dtype=DTYPE).index_add_(0, index, z[:, :, None] * y[:, None, :])
    yy = torch.zeros(groups, d, d, dtype=DTYPE).index_add_(0, index, y[:, :, None] * y[:, None, :])
    if not all(bool(t.isfinite().all()) for t in (zz, zy, yy)):
        raise ValueError(
            f"site {site!r}: the fit's second moments overflow float64; rescale the data"
        )
    return Moments(zz, zy, yy, torch.bincount(index, minlength=groups).to(DTYPE))


def _linear_gaussian(
    s: Moments,
    card: tuple[int, ...],
    alpha: float,
    min_variance: float,
    site: str,
    zero_weights: torch.Tensor | None = None,
) -> LinearGaussian:
    """Per-configuration least squares of y on [x, 1] with pooled pseudo-rows.

    ``zero_weights`` ``(G, p)`` bool: weights fixed at zero per configuration (the
    least squares then runs without those columns there).
    """
    szz, szy, syy, n = s.zz, s.zy, s.yy, s.n
    groups, q, d = szy.shape
    n_rows = float(n.sum())
    if n_rows:
        # alpha pseudo-rows of the pooled statistics (an unseen configuration = the pooled fit)
        w = alpha / n_rows
        szz, szy, syy = szz + w * szz.sum(0), szy + w * szy.sum(0), syy + w * syy.sum(0)
    if not all(bool(t.isfinite().all()) for t in (szz, szy, syy)):
        raise ValueError(
            f"site {site!r}: the fit's second moments overflow float64; rescale the data"
        )
    if zero_weights is not None and bool(zero_weights.any()):
        drop = torch.cat([zero_weights, torch.zeros(groups, 1, dtype=torch.bool)], -1)
        keep = (~drop).to(DTYPE)
        szz = szz * keep[:, :, None] * keep[:, None, :] + torch.diag_embed(drop.to(DTYPE))
        szy = szy * keep[:, :, None]
    total = n + (alpha if n_rows else 0.0)
    unseen = total == 0
    if unseen.any():  # alpha == 0: fall back on the pooled fit all the same
        szz, szy, syy, total = szz.clone(), szy.clone(), syy.clone(), total.clone()
        szz[unseen], szy[unseen], syy[unseen], total[unseen] = (
            s.zz.sum(0),
            s.zy.sum(0),
            s.yy.sum(0),
            n_rows,
        )
    ridge = 1e-10 * szz.diagonal(dim1=-2, dim2=-1).mean(-1).clamp_min(1e-12)
    beta = torch.linalg.solve(szz + ridge[:, None, None] * torch.eye(q, dtype=DTYPE), szy)
    resid = syy - szy.mT @ beta - beta.mT @ szy + beta.mT @ szz @ beta
    cov = resid / total.clamp_min(1e-300)[:, None, None]
    cov = 0.5 * (cov + cov.mT) + min_variance * torch.eye(d, dtype=DTYPE)
    tril = _safe_cholesky(cov, site)
    return LinearGaussian(
        beta[:, : q - 1, :].mT.reshape(*card, d, q - 1),
        beta[:, q - 1, :].reshape(*card, d),
        tril.reshape(*card, d, d),
        n.reshape(card),
    )


def _safe_cholesky(cov: torch.Tensor, site: str, tries: int = 24) -> torch.Tensor:
    """Cholesky factors, adding a growing jitter where a covariance is not quite PD."""
    tril, info = torch.linalg.cholesky_ex(cov)
    jitter = 1e-12
    for _ in range(tries):
        bad = info > 0
        if not bad.any():
            return tril
        scale = cov[bad].diagonal(dim1=-2, dim2=-1).abs().mean(-1).clamp_min(1.0)
        cov[bad] = cov[bad] + (jitter * scale)[:, None, None] * torch.eye(
            cov.shape[-1], dtype=cov.dtype
        )
        tril, info = torch.linalg.cholesky_ex(cov)
        jitter *= 10
    if (info > 0).any():
        group = int((info > 0).nonzero()[0])
        raise ValueError(
            f"site {site!r}: configuration {group} has no positive definite covariance "
            f"({cov[group].tolist()}); check its rows for inf, NaN or huge values"
        )
    return tril


def _unused(net: EffectNetwork, feature: str, card: tuple[int, ...]) -> torch.Tensor | None:
    """``(G, p)`` bool: the parameter's weights in configurations of actions not using it.

    The rule of :meth:`EffectNetwork.parameter_in_use`: such an action ignores the
    parameter, so its weights are zero, not fitted (pooled pseudo-rows would otherwise
    lend them the using actions' slope).
    """
    p = net.parameter_of(feature)
    if p is None:
        return None
    width = sum(net.site(s).size for s in net.continuous_parents(feature))
    actions = torch.arange(len(net.actions))
    unused = ~net.parameter_in_use(p, actions)  # the action axis is second to last
    unused = unused[:, None].expand(*card).reshape(-1)
    out = torch.zeros(unused.shape[0], width, dtype=torch.bool)
    out[:, width - p.dim :] = unused[:, None]
    return out
