"""Choosing a parameter's next values by what they teach the clusters' regressions.

For a network with a grid-layout parameter ``p`` acting on one continuous feature ``g``,
each cluster's linear Gaussian ``g = W [x, p, 1] + e`` is a Bayesian linear regression:
with the rows seen so far in its parent configuration, ``A = lambda I + sum z z^T``
(``z = [x, p, 1]``, the sufficient statistic :func:`inference.fit` sums), one more row at
``z`` tells about ``W`` (with its noise known) the expected information gain, in nats,

    EIG(z) = d / 2 * log(1 + z^T A^-1 z)

(the determinant ratio of the posterior precisions; ``d`` the feature's dimension). It is
largest in configurations no row has reached and at the edges of those seen.
:func:`select_by_information` picks a batch greedily: the best candidate, then ``A`` of
its configuration updated in closed form (``A += z z^T``) before the next pick, so a
batch spreads out instead of piling onto one spot.

:func:`select_by_variance` scores the error that is usually measured instead: the
expected reduction of the predictive variance of the feature's mean, summed over
``reference`` rows spread over the area where the network will be asked (Cohn's active
learning criterion, ALC). The predictive variance at ``r`` in the cluster of ``z`` is
``s2 r^T A^-1 r`` (``s2`` the cluster's residual variance); one more row at ``z`` lowers
it by ``s2 (r^T A^-1 z)^2 / (1 + z^T A^-1 z)`` (Sherman-Morrison), and not at all in the
other clusters. It is picked greedily in batches as above, ``A^-1`` of the pick's
cluster updated in closed form. Both criteria score a linear model's variance: where the
regression is only an approximation (a curved response cut into linear cells), rows at
the cells' edges, which both favour, move the least-squares fit away from the rows it
will be asked about. No scene knowledge: the candidates are rows of the network's sites.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
from effect_networks.inference.fitting.rows import training_rows
from effect_networks.inference.fitting.sufficient_statistics import statistics
from effect_networks.models.declaration import ACTION, EffectNetwork
from effect_networks.models.evidence import DTYPE

__all__ = [
    "regression_information",
    "select_by_information",
    "select_by_variance",
    "variance_reduction",
]


def _design(net: EffectNetwork, parameter: str, enc):
    """The affected feature's CPD, and per row its flat parent configuration and ``z``."""
    m = net.mixture(parameter)
    if m.parameter.adaptive:
        raise ValueError(
            f"parameter {parameter!r} has adaptive clusters: a candidate's cluster is then "
            "uncertain; choose by information with the grid layout"
        )
    if m.child is None or m.affected != (m.child,):
        raise ValueError(
            f"parameter {parameter!r} must act on exactly one continuous feature, "
            f"it acts on {list(m.affected)}"
        )
    cpd = net.cpd(m.child)
    values = dict(enc)
    values[m.cluster.site] = m.cells(enc[m.value.site], enc[ACTION])
    missing = [s for s in (*cpd.parents, *cpd.inputs) if s not in values]
    if missing:
        raise ValueError(f"candidates must give {missing}")
    group = torch.zeros(enc.n_rows, dtype=torch.long)
    for s, k in zip(cpd.parents, cpd.card, strict=True):
        group = group * k + values[s]
    inputs = [values[s].nan_to_num() for s in cpd.inputs]
    z = torch.cat([*inputs, torch.ones(enc.n_rows, 1, dtype=DTYPE)], -1)
    return cpd, group, z


def regression_information(
    net: EffectNetwork,
    parameter: str,
    data: Mapping[str, object],
    candidates: Mapping[str, object],
    *,
    prior_precision: float = 1e-3,
) -> torch.Tensor:
    """``(m,)`` expected information gain (nats) of one more row at each candidate.

    About the regression of the feature ``parameter`` acts on, given the training rows ``data``
    (every site, as for :func:`inference.fit`). ``candidates``: rows giving the action, the
    parameter and the feature's other parents (no end values).
    """
    return _information(net, parameter, data, candidates, prior_precision)[0]


def _moments(net, parameter, data, prior_precision):
    """The affected feature's moments from the rows ``data``, and ``A`` with its prior."""
    if not (isinstance(prior_precision, int | float) and prior_precision > 0):
        raise ValueError(f"prior_precision must be a number > 0, got {prior_precision!r}")
    enc = training_rows(net, data)
    cpd = net.cpd(net.mixture(parameter).child)
    moments = statistics(net, enc).sites[cpd.site]
    zz = moments.zz.clone()  # (G, q, q)
    zz += prior_precision * torch.eye(zz.shape[-1], dtype=DTYPE)
    return moments, zz


def _information(net, parameter, data, candidates, prior_precision):
    cpd = net.cpd(net.mixture(parameter).child)
    _, zz = _moments(net, parameter, data, prior_precision)
    cand = net.encode(candidates)
    _, group, z = _design(net, parameter, cand)
    d = net.site(cpd.site).size
    gain = _gain(zz, group, z, d)
    return gain, zz, group, z, d


def _gain(zz, group, z, d) -> torch.Tensor:
    solved = torch.linalg.solve(zz[group], z[..., None])[..., 0]
    return 0.5 * d * torch.log1p((z * solved).sum(-1))


def select_by_information(
    net: EffectNetwork,
    parameter: str,
    data: Mapping[str, object],
    candidates: Mapping[str, object],
    k: int,
    *,
    prior_precision: float = 1e-3,
) -> torch.Tensor:
    """Indices ``(k,)`` of ``k`` distinct candidates, chosen greedily.

    Chosen by :func:`regression_information`; each pick's row is added to its configuration's
    statistics before the next (see the module).
    """
    _check_k(k)
    gain, zz, group, z, d = _information(net, parameter, data, candidates, prior_precision)

    def add(i: int, g: int, same: torch.Tensor) -> torch.Tensor:
        zz[g] += z[i, :, None] * z[i, None, :]
        return _gain(zz, group[same], z[same], d)

    return _greedy(gain.clone(), group, k, add)


def _check_k(k) -> None:
    if isinstance(k, bool) or not isinstance(k, int) or k < 1:
        raise ValueError(f"k must be a positive int, got {k!r}")


def _greedy(score: torch.Tensor, group: torch.Tensor, k: int, add) -> torch.Tensor:
    """``k`` distinct indices, each the best ``score`` left; a pick rescores its own cluster.

    ``add(i, g, same)`` adds candidate ``i``'s row to cluster ``g`` and returns the new scores
    of the candidates ``same`` in that cluster (a bool mask); ``score`` is overwritten.
    """
    if k > len(score):
        raise ValueError(f"k = {k} exceeds the {len(score)} candidates")
    chosen: list[int] = []
    for _ in range(k):
        i = int(score.argmax())
        chosen.append(i)
        g = int(group[i])
        same = group == g
        score[same] = add(i, g, same)
        score[chosen] = -torch.inf
    return torch.tensor(chosen, dtype=torch.long)


def _residual_variances(moments, zz: torch.Tensor) -> torch.Tensor:
    """``(G,)`` each cluster's residual variance (summed over the feature's dimensions).

    Its residual sum of squares under the ridge fit ``A^-1 sum z y^T``, over its rows beyond
    the coefficients; pooled over the clusters where a cluster has no more rows than
    coefficients (1 where no cluster has).
    """
    coef = torch.linalg.solve(zz, moments.zy)  # (G, q, d)
    rss = (
        torch.diagonal(moments.yy, dim1=-2, dim2=-1).sum(-1) - (coef * moments.zy).sum((-2, -1))
    ).clamp_min(0.0)
    free = moments.n - zz.shape[-1]
    own = free > 0
    pooled = float(rss[own].sum() / free[own].sum()) if bool(own.any()) else 1.0
    return torch.where(own, rss / free.clamp_min(1), torch.full_like(rss, pooled))


def _reduction(inverse, variance, group, z, ref_group, ref_z) -> torch.Tensor:
    """``(m,)`` ALC of each candidate ``z`` in ``group``, over the reference rows."""
    out = torch.zeros(len(z), dtype=DTYPE)
    for g in group.unique().tolist():
        mine = group == g
        solved = z[mine] @ inverse[g]  # (m_g, q): A^-1 z (A symmetric)
        leverage = (solved * z[mine]).sum(-1)
        ref = ref_z[ref_group == g]  # (r_g, q)
        out[mine] = variance[g] * ((ref @ solved.T) ** 2).sum(0) / (1 + leverage)
    return out


def _variance_setup(net, parameter, data, candidates, reference, prior_precision):
    moments, zz = _moments(net, parameter, data, prior_precision)
    _, group, z = _design(net, parameter, net.encode(candidates))
    _, ref_group, ref_z = _design(net, parameter, net.encode(reference))
    return torch.linalg.inv(zz), _residual_variances(moments, zz), group, z, ref_group, ref_z


def variance_reduction(
    net: EffectNetwork,
    parameter: str,
    data: Mapping[str, object],
    candidates: Mapping[str, object],
    reference: Mapping[str, object],
    *,
    prior_precision: float = 1e-3,
) -> torch.Tensor:
    """``(m,)`` expected reduction of the predictive variance by one more row at each candidate.

    Of the mean of the feature ``parameter`` acts on, summed over the ``reference`` rows (the
    places the network will be asked about, given as candidates are), given the training rows
    ``data``: ALC (see the module). ``candidates`` and ``reference``: rows giving the action,
    the parameter and the feature's other parents (no end values).
    """
    inverse, variance, group, z, ref_group, ref_z = _variance_setup(
        net, parameter, data, candidates, reference, prior_precision
    )
    return _reduction(inverse, variance, group, z, ref_group, ref_z)


def select_by_variance(
    net: EffectNetwork,
    parameter: str,
    data: Mapping[str, object],
    candidates: Mapping[str, object],
    k: int,
    *,
    reference: Mapping[str, object] | None = None,
    prior_precision: float = 1e-3,
) -> torch.Tensor:
    """Indices ``(k,)`` of ``k`` distinct candidates, chosen greedily by :func:`variance_reduction`.

    ``reference`` defaults to the candidates themselves (a sample of where the network will be
    asked). Each pick's row is added to its cluster's ``A`` before the next; the residual
    variances stay those of ``data`` (a pick's outcome is not known yet).
    """
    _check_k(k)
    inverse, variance, group, z, ref_group, ref_z = _variance_setup(
        net,
        parameter,
        data,
        candidates,
        candidates if reference is None else reference,
        prior_precision,
    )

    def add(i: int, g: int, same: torch.Tensor) -> torch.Tensor:
        u = inverse[g] @ z[i]  # Sherman-Morrison: A^-1 after the row z_i
        inverse[g] -= torch.outer(u, u) / (1 + z[i] @ u)
        return _reduction(inverse, variance, group[same], z[same], ref_group, ref_z)

    score = _reduction(inverse, variance, group, z, ref_group, ref_z)
    return _greedy(score, group, k, add)
