"""The inverse model: the parameter value under which a desired continuous effect is most likely.

:func:`parameter_for_effect`; per cluster by least squares, the clusters' candidates ranked by their
exact joint density with the evidence.

The parameter posterior (:func:`inference.queries.parameter.infer_parameter`) answers
"which value was used, given that this effect was seen"; the inverse model answers "which
value makes this effect most likely". Answered from the traced model, the candidates'
scores in closed form where only the mixture's factors depend on the value
(:func:`inference.compile`'s ``parameter_for_effect`` calls it).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
from effect_networks.inference.exact.enumeration import (
    over_row_chunks,
)
from effect_networks.inference.queries.batching import (
    check_parameter_evidence,
    first_best,
    given_other_parameters,
    no_rows,
    parameter_placeholder,
    prepare,
)
from effect_networks.inference.queries.results import (
    ParameterForEffect,
    outside_range,
)
from effect_networks.models.declaration import (
    ACTION,
    EffectNetwork,
)
from effect_networks.models.evidence import Evidence
from effect_networks.models.params import NetworkParams

LOG_2PI = math.log(2 * math.pi)


def parameter_for_effect(
    net: EffectNetwork,
    params: NetworkParams,
    parameter: str,
    evidence: Mapping[str, object],
) -> ParameterForEffect:
    """The parameter value that produces a desired effect: the inverse model.

    :func:`~inference.queries.parameter.infer_parameter` answers "which value was used, given that this effect was
    seen": the posterior, which weighs the effect against where values usually lie. With
    noisy effects that pulls the answer towards each cluster's mean (by the share of the
    effect's spread that is noise) and a controller that aims with it falls short. This
    query answers "which value makes this effect most likely": for every cluster ``c``
    the value ``theta_c`` that maximises the observed continuous effects' likelihood under
    ``c``'s linear Gaussians (weighted least squares; see
    :meth:`models.cpds.mixture.ParameterMixture.best_fit`), and among these candidates the
    one of highest joint density ``p(theta_c, evidence)``, exact (every cluster summed out;
    under the grid layout a value given without its cluster comes with its cell, so a
    candidate outside its own cell is scored under the cell it falls in). The factors
    that depend on the value (the cluster table, the clusters' Gaussians, the observed
    effects' linear Gaussians, and under the grid layout the value's cell) are summed over the clusters in closed form for every
    candidate; the others are one constant per row, read off a single evaluation of the
    model at the row's best candidate. Where another site depends on the cluster or the
    value (a discrete feature the parameter acts on, an unobserved effect), the model
    scores every candidate instead, ``C`` times the cost (tested equal to the closed
    form where both apply). Ranking by the joint density rather than the effect's
    likelihood alone keeps a cluster whose line, extrapolated far from the values it was
    fitted on, happens to pass through the effect from winning. Partial evidence counts
    its observed dimensions (as in :func:`~inference.queries.parameter.infer_parameter`). Without
    noise and with the effect inside a cluster's reach, the answer reproduces the
    effect exactly under that cluster (``miss`` 0).

    Per cluster the objective is lexicographic, the effects' likelihood first and the
    cluster's Gaussian over the value second (among values reaching the effect equally well
    the candidate has the highest joint density ``p(theta_c, evidence | c)``); it is not the
    joint density's maximiser over all values, which is ``c``'s posterior mode and misses the
    effect by the share that noise explains.

    The evidence is as for :func:`~inference.queries.parameter.infer_parameter` (the parameter and its cluster
    unknown; the action, or the only one using the parameter; the discrete parents of the
    observed effects; any other parameter acting on the same feature given); at least
    one continuous feature the parameter acts on must be observed. Raises ``ValueError``
    otherwise.

    Parameters
    ----------
    net, params
        The network and its fitted parameters.
    evidence
        ``n`` rows of what is known, by site name (labels, numbers, NaN where unknown):
        see :meth:`models.EffectNetwork.encode`.
    parameter
        The action parameter's name; unknown in ``evidence``.

    Returns
    -------
    ParameterForEffect
        Per row, the value to use, the cluster it comes from, its joint density and how
        far its predicted effect misses the desired one.
    """
    m = net.mixture(parameter)
    p = m.parameter
    enc = prepare(net, params, evidence)
    if enc.n_rows == 0:
        return no_rows(parameter_for_effect(net, params, parameter, parameter_placeholder(m, enc)))
    enc, _ = check_parameter_evidence(net, m, enc, "parameter_for_effect")
    children = [net.cpd(s) for s in m.continuous if s in enc]
    if not children:
        raise ValueError(
            f"parameter_for_effect needs an observed continuous feature {p.name!r} acts on "
            f"(one of {list(m.continuous)}): a discrete effect has no value to invert"
        )
    given, acting = given_other_parameters(net, m, enc, children, "parameter_for_effect")
    n, c = enc.n_rows, p.n_clusters
    every = torch.arange(c).expand(n, -1)
    whitened = m.whitened(params, children, given, every, acting=acting)
    candidates, miss = m.best_fit(params, whitened, every)  # (n, C, d), (n, C)
    rows = torch.arange(n)
    fast = _candidate_scores(net, params, m, given, children, acting, candidates, whitened)
    if fast is None:  # a factor beyond the mixture depends on the value: the model scores all
        scored = enc.repeat(c)
        scored = Evidence(net, dict(scored) | {m.value.site: candidates.reshape(n * c, -1)}, n * c)
        log_density = over_row_chunks(net, params, scored, set(), lambda e, *_: e.log_evidence)
        log_density = log_density.reshape(n, c)
    else:  # the model scores each row's best; the rest differ from it by the mixture's terms
        best = first_best(fast)
        scored = Evidence(net, dict(enc) | {m.value.site: candidates[rows, best]}, n)
        exact = over_row_chunks(net, params, scored, set(), lambda e, *_: e.log_evidence)
        top = fast[rows, best]
        shift = torch.where(torch.isfinite(top), exact - top, 0.0)
        log_density = torch.where(torch.isfinite(exact)[:, None], fast + shift[:, None], -torch.inf)
    best = first_best(log_density)
    value = candidates[rows, best]
    return ParameterForEffect(
        value,
        best,
        log_density[rows, best],
        miss[rows, best],
        candidates,
        log_density,
        outside_range(p, value),
    )


#: Elements per row chunk of :func:`_candidate_scores`' ``(rows, C, C)`` tensors.
_SCORE_CHUNK = 1 << 18


def _candidate_scores(net, params, m, given: Evidence, children, acting, candidates, whitened):
    """The factors of ``log p(theta, evidence)`` that depend on the value, in closed form.

    ``log sum_c' p(c' | action) p(theta | c') prod_j p(y_j | ..., c', theta)`` for every row and
    candidate ``theta`` ``(n, C, k)``, from the children's ``whitened`` terms
    (:meth:`models.cpds.mixture.ParameterMixture.whitened`); under the grid layout the value's cell
    is its cluster. The other factors are a constant per row. None where that does not hold: a site
    other than the observed continuous ``children`` depends on the cluster or the value, the cluster
    has parents besides the action, or a child's other continuous inputs are not all given.
    """
    depends = {m.cluster.site, m.value.site}
    mine = {child.site for child in children}
    for spec in net.sites:
        if spec.name in depends or spec.name in mine:
            continue
        if depends & set(net.cpd(spec.name).parents):
            return None
    if tuple(net.cpd(m.cluster.site).parents) != (ACTION,):
        return None
    others = {q.value.site for q in acting}
    for child in children:
        for site in child.inputs:
            if site not in others and (site not in given or bool(torch.isnan(given[site]).any())):
                return None
    n, c, k = candidates.shape
    slope, target, log_norm = whitened  # the children's, per row and cluster c' (n or 1, C')
    mean, cov = m.belief(params, torch.arange(c))  # (C', k), (C', k, k)
    tril = torch.linalg.cholesky(cov)
    eye = torch.eye(k, dtype=cov.dtype).expand_as(cov)
    whiten = torch.linalg.solve_triangular(tril, eye, upper=False)  # (C', k, k)
    log_norm = (
        log_norm
        - tril.diagonal(dim1=-2, dim2=-1).log().sum(-1)
        - k / 2 * LOG_2PI
        + params[m.cluster.site].probs.clamp_min(0.0).log()[given[ACTION]]
    )  # (n, C')
    # The squared distances sum |b - A theta|^2 over the children's whitened rows and the
    # value's, per row and cluster c'. Completed to m0 + |U (theta - theta_hat)|^2 (H =
    # A^T A = U^T U; theta_hat: the value's posterior mean under c'), a sum of squares
    # without cancellation, evaluated one component at a time below.
    lead = target.shape[:-2]  # (n,): the observation is per row
    a = torch.cat([slope.expand(*lead, -1, -1, -1), whiten.expand(*lead, -1, -1, -1)], -2)
    prior = (whiten @ mean[..., None])[..., 0]
    b = torch.cat([target, prior.expand(*lead, -1, -1)], -1)  # (n, C', D + k)
    hessian = a.mT @ a  # (n, C', k, k), positive definite: the value's precision is in it
    upper = torch.linalg.cholesky(hessian).mT
    theta_hat = torch.cholesky_solve(a.mT @ b[..., None], upper.mT)[..., 0]  # (n, C', k)
    m0 = (b - (a @ theta_hat[..., None])[..., 0]).square().sum(-1)  # (n, C')
    base = log_norm - 0.5 * m0  # (n, C')
    shift = (upper @ theta_hat[..., None])[..., 0]  # (n, C', k)
    if not m.parameter.adaptive:  # grid: a value given alone comes with its cell
        cells = m.parameter.cluster_of(candidates)  # (n, C)
        rows = torch.arange(n)[:, None]
        z = (upper[rows, cells] @ candidates[..., None])[..., 0] - shift[rows, cells]
        return base[rows, cells] - 0.5 * z.square().sum(-1)
    out = []
    step = max(1, _SCORE_CHUNK // max(1, c * c))
    for start in range(0, n, step):
        part = slice(start, start + step)
        theta = candidates[part]  # (r, C, k)
        u, sh = upper[part], shift[part]
        total = torch.zeros(len(theta), c, c, dtype=theta.dtype)  # (r, C candidates, C')
        for row in range(k):
            z = torch.addcmul(-sh[:, None, :, row], theta[:, :, None, 0], u[:, None, :, row, 0])
            for col in range(1, k):
                z.addcmul_(theta[:, :, None, col], u[:, None, :, row, col])
            total.addcmul_(z, z)
        log = base[part][:, None, :] - 0.5 * total
        # logsumexp in place; terms below e^-700 of the largest, which change no float64
        # sum, are dropped before exp (its far tail, near the denormals, is slow)
        top = log.amax(-1, keepdim=True)
        top = torch.where(torch.isfinite(top), top, 0.0)
        log = log.sub_(top)
        log = log.masked_fill_(log < -700.0, -torch.inf)
        out.append(log.exp_().sum(-1).log_() + top[..., 0])
    return torch.cat(out, 0)
