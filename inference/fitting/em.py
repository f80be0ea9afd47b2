"""Expectation-maximisation for adaptive parameter clusters.

The cluster is a discrete latent variable, so the E-step is an exact posterior and the
M-step the closed form on posterior-weighted statistics. EM over missing discrete values,
the other latent variables it serves, is :mod:`inference.fitting.missing`
(:func:`fit_missing` and :func:`missing_log_likelihood` are re-exported here).

Under the paper's grid layout a parameter's cluster *is* its value's equidistant cell,
so :func:`inference.fit` files every row under one cluster and fits each cell's
Gaussians in closed form. Under the adaptive layout (``Parameter(layout="adaptive")``)
the cluster is a latent mixture component, and :func:`fit_em` places the components
where the data need them: it starts from the grid fit (the cells as hard assignments)
and alternates, for every adaptive parameter ``p`` acting on features ``g``,

* **E-step** -- each row's responsibility of cluster ``c``,
  ``r_c ∝ table[action, c] * N(theta; m_c, S_c) * prod_g p(g | its parents, cluster = c)``:
  the parameter and its effects jointly;
* **M-step** -- every site of the mixture (the cluster table, the cluster Gaussians and
  the affected features' CPDs) refitted in closed form from its sufficient statistics
  weighted by ``r`` (the same statistics and pseudo-count policy as :func:`fit`, with
  fractional row counts).

The E-step is dense, every row against every cluster, and written for that size: each
linear Gaussian's log-density for all clusters is one matrix product of the rows'
quadratic features with per-cluster coefficients (rounding about ``|z|^2 / s^2`` times
float64's epsilon for rows ``z`` about their mean and a cluster's scale ``s``: 1e-8
relative in the parameters after 20 steps on the throw data, against the residual form
it replaced), the ``(C, n)`` responsibilities are computed in the last step's memory,
and log-responsibilities are floored at ``LOG_FLOOR`` before ``exp``. At 256 clusters
and 29,000 rows five steps take about 1.1 s on one thread (3.8 s before).

With ``pseudo_count = 0`` no step can lower the likelihood: the EM guarantee, which the
tests check over random data sets. A pseudo-count makes the M-step a penalised fit whose
pseudo-rows follow the pooled statistics of the current responsibilities, so near
convergence a step may lower the likelihood by a hair (hypothesis found dips of 7.7e-7
and 2.7e-5 nats per row on 300-row data sets with ``pseudo_count = 0.01``, in a curve
that had gained 1.4e-3); the tests bound such dips by ``pseudo_count / 100`` nats per
row and require the curve never to fall below its start, and the stopping rule counts a
dip as converged. The sites no adaptive parameter touches are fitted once in
closed form: their likelihood does not depend on the clusters.

The queries of an EM-fitted network stay exact: the inverse query enumerates the
clusters (their posterior given the effect) and conditions the best cluster's Gaussian,
and the Pyro model is a plain mixture (:mod:`models.model`), so ``Predictive`` and
``TraceEnum_ELBO`` mean what they say.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass

import torch
from effect_networks.inference.fitting.missing import fit_missing, missing_log_likelihood
from effect_networks.inference.fitting.reading import TrainingRows, read_rows
from effect_networks.inference.fitting.rows import check_settings, training_rows
from effect_networks.inference.fitting.sufficient_statistics import (
    params_from_statistics,
    statistics,
)
from effect_networks.models.cpds import (
    Counts,
    LinearGaussianCPD,
    Moments,
    ParameterMixture,
    TableCPD,
)
from effect_networks.models.declaration import ACTION, EffectNetwork
from effect_networks.models.evidence import DTYPE, Evidence
from effect_networks.models.frames import as_data
from effect_networks.models.gaussian import quadratic_features
from effect_networks.models.params import NetworkParams, check_params
from tqdm.auto import tqdm

__all__ = [  # fit_missing and missing_log_likelihood live in inference.fitting.missing
    "EMResult",
    "em_step",
    "fit_em",
    "fit_missing",
    "missing_log_likelihood",
    "mixture_log_likelihood",
    "responsibilities",
]


@dataclass(frozen=True)
class EMResult:
    """What :func:`fit_em` returns.

    ``log_likelihoods``: the mean per-row log-likelihood of the adaptive parameters and
    the features they act on (given their other parents; the rest of the network's
    factors do not change under EM), at the start and after every step: never
    decreasing with ``pseudo_count = 0`` (see the module for a pseudo-count). ``converged``: whether its last gain fell below ``tol``. ``fit_s``: wall
    time in seconds.
    """

    params: NetworkParams
    log_likelihoods: tuple[float, ...]
    converged: bool
    fit_s: float

    @property
    def steps(self) -> int:
        """The number of EM steps taken."""
        return len(self.log_likelihoods) - 1


def fit_em(
    net: EffectNetwork,
    data: Mapping[str, object],
    *,
    init: NetworkParams | None = None,
    steps: int = 50,
    tol: float = 1e-6,
    pseudo_count: float = 0.01,
    min_variance: float = 1e-9,
    progress: bool = False,
) -> EMResult:
    """Fit a network with adaptive parameter clusters by expectation-maximisation.

    Parameters
    ----------
    net
        A network with at least one ``Parameter(layout="adaptive")``; every CPD has a
        closed form (tables and linear Gaussians), and every feature an adaptive
        parameter acts on has that parameter's cluster as its only cluster parent.
    data
        Complete training rows by site name, as for :func:`fit` (``param.p`` NaN where
        the action does not use ``p``; no ``cluster.p``).
    init
        Start; default: the grid fit (each row in its value's equidistant cell).
    steps
        At most this many EM steps (a positive int).
    tol
        Stop when a step raises the mean per-row log-likelihood by less than ``tol``
        (absolute, > 0).
    pseudo_count, min_variance
        The closed form's pseudo-count policy and covariance floor (see :func:`fit`).
        The floor also keeps a component from collapsing onto a single row.
    progress
        A progress bar over the steps, showing the log-likelihood.

    Returns
    -------
    EMResult

    Raises
    ------
    ValueError
        On a bad setting, a network without adaptive parameters or outside the scope
        above, or rows :func:`fit` would refuse.
    """
    check_settings(pseudo_count=pseudo_count, min_variance=min_variance, steps=steps, tol=tol)
    start = time.perf_counter()
    mixtures = _adaptive(net)
    if not isinstance(as_data(net, data), Mapping | TrainingRows):
        raise ValueError(
            f"data must be one mapping or DataFrame of rows (EM revisits them every step), "
            f"got {type(data).__name__}"
        )
    rows = read_rows(net, data)
    missing = rows.missing()
    if missing:
        raise ValueError(
            f"the rows miss values of {rows.missing_text()}: "
            f"fit_em fits adaptive clusters from complete rows; drop the incomplete rows "
            f"({rows.dropna_text()}) or fit the network under the grid layout, where "
            "inference.fit runs EM over the gaps"
        )
    enc = rows.enc
    if init is None:
        init = NetworkParams(
            params_from_statistics(net, statistics(net, enc), pseudo_count, min_variance),
            pseudo_count,
            net,
        )
    else:
        check_params(net, init)
    params = init
    resp, ll = _e_step(net, params, enc, mixtures)
    curve = [ll]
    converged = False
    bar = tqdm(total=steps, desc="fit (EM)", disable=not progress)
    for _ in range(steps):
        params = _m_step(net, params, enc, mixtures, resp, pseudo_count, min_variance)
        resp, ll = _e_step(net, params, enc, mixtures, buffers=resp)
        curve.append(ll)
        bar.update()
        bar.set_postfix(loglik=f"{ll:.6g}")
        if curve[-1] - curve[-2] < tol:
            converged = True
            break
    bar.close()
    return EMResult(params, tuple(curve), converged, time.perf_counter() - start)


def em_step(
    net: EffectNetwork,
    params: NetworkParams,
    data: Mapping[str, object],
    *,
    pseudo_count: float = 0.01,
    min_variance: float = 1e-9,
) -> NetworkParams:
    """One EM step from ``params``.

    Responsibilities under ``params``, then the weighted closed-form refit of every adaptive
    mixture's sites (the others are kept).
    """
    check_settings(pseudo_count=pseudo_count, min_variance=min_variance)
    mixtures = _adaptive(net)
    check_params(net, params)
    enc = training_rows(net, data)
    resp, _ = _e_step(net, params, enc, mixtures)
    return _m_step(net, params, enc, mixtures, resp, pseudo_count, min_variance)


def responsibilities(
    net: EffectNetwork, params: NetworkParams, data: Mapping[str, object]
) -> dict[str, torch.Tensor]:
    """Each adaptive parameter's cluster posterior per row, ``(n, C)``.

    Given the row's value and the features it acts on (keyed by parameter name).
    """
    mixtures = _adaptive(net)
    check_params(net, params)
    resp, _ = _e_step(net, params, training_rows(net, data), mixtures)
    return {m.parameter.name: r.T for m, r in zip(mixtures, resp, strict=True)}


def mixture_log_likelihood(
    net: EffectNetwork, params: NetworkParams, data: Mapping[str, object]
) -> float:
    """The mean per-row log-likelihood :func:`fit_em` reports for ``params``."""
    mixtures = _adaptive(net)
    check_params(net, params)
    return _e_step(net, params, training_rows(net, data), mixtures)[1]


# ---------------------------------------------------------------------------- internals
def _adaptive(net: EffectNetwork) -> tuple[ParameterMixture, ...]:
    """The adaptive mixtures, after checking that EM covers the network."""
    mixtures = tuple(m for m in net.mixtures if m.parameter.adaptive)
    if not mixtures:
        raise ValueError(
            "net has no adaptive parameter (Parameter(layout='adaptive')); fit a grid "
            "layout with inference.fit"
        )
    no_closed_form = [s.name for s in net.sites if not net.cpd(s.name).closed_form]
    if no_closed_form:
        raise ValueError(
            f"fit_em needs closed-form CPDs everywhere; sites {no_closed_form} have none"
        )
    clusters = {m.cluster.site for m in net.mixtures}
    for m in mixtures:
        for site in m.affected:
            cpd = net.cpd(site)
            theirs = [s for s in cpd.parents if s in clusters]
            if theirs != [m.cluster.site] or cpd.parents[-1] != m.cluster.site:
                raise ValueError(
                    f"site {site!r} has the cluster parents {theirs}: fit_em needs "
                    f"{m.cluster.site!r} as its only cluster parent, and last"
                )
            if not isinstance(cpd, LinearGaussianCPD | TableCPD):
                raise ValueError(
                    f"site {site!r} is a {cpd.name} CPD: fit_em refits tables and linear "
                    "Gaussians only"
                )
    return mixtures


def _inputs(enc: Evidence, cpd, m: ParameterMixture) -> torch.Tensor | None:
    """A CPD's continuous inputs, the parameter zero where the action does not use it."""
    uses = m.in_use(enc[ACTION])
    values = []
    for s in cpd.inputs:
        v = enc[s].nan_to_num()
        if s == m.value.site:
            v = torch.where(uses[:, None], v, 0.0)
        values.append(v)
    return torch.cat(values, -1) if values else None


#: Log-responsibilities (relative to the row's best cluster) are raised to this floor
#: before ``exp``: a cluster below it gets 1e-304 of the row instead of less, which no
#: sum in float64 can tell from nothing beside the best cluster's 1, and ``exp`` runs
#: about five times faster on the floored values than on the far tail (denormals).
LOG_FLOOR = -700.0


def _e_step(net, params, enc, mixtures, buffers=None) -> tuple[list[torch.Tensor], float]:
    """Responsibilities ``(C, n)`` per mixture, and the mean per-row log-likelihood.

    ``buffers``: one ``(C, n)`` tensor per mixture to compute the responsibilities in
    (``fit_em`` reuses the last step's: a fresh tensor of that size costs as much as the
    arithmetic, in page faults).
    """
    n = enc.n_rows
    total = torch.zeros(n, dtype=DTYPE)
    resp = []
    for index, m in enumerate(mixtures):
        action = enc[ACTION]
        uses = m.in_use(action)
        # (A, C); an action not using p on cluster 0 only (its other cells impossible)
        log_table = m.cluster.pin_logs(params[m.cluster.site].probs.clamp_min(1e-300).log())
        theta = enc[m.value.site].nan_to_num()
        one = torch.zeros(n, dtype=torch.long)
        log = buffers[index] if buffers is not None else None
        log = _log_density(m.value, params[m.value.site], one, None, theta, out=log)  # (C, n)
        if not bool(uses.all()):
            log.masked_fill_(~uses.expand_as(log), 0.0)
        if bool((action == action[0]).all()):  # one action: a column, broadcast
            log.add_(log_table[action[0]][:, None])
        else:
            log.add_(log_table.T[:, action])
        for site in m.affected:
            cpd = net.cpd(site)
            group = _group(enc, cpd)
            _log_density(
                cpd, params[site], group, _inputs(enc, cpd, m), enc[site], out=log, add=True
            )
        # normalise in place: log-sum-exp over the clusters, then the posterior
        top = log.amax(0)  # the same values as max(0), without the indices
        log.sub_(top).clamp_min_(LOG_FLOOR).exp_()
        mass = log.sum(0)
        log.div_(mass)
        total = total + top + mass.log()
        resp.append(log)  # (C, n)
    return resp, float(total.mean())


def _group(enc: Evidence, cpd) -> torch.Tensor:
    """``(n,)`` row-major index of each row's configuration of the CPD's parents but the last.

    The last parent is the cluster.
    """
    group = torch.zeros(enc.n_rows, dtype=torch.long)
    for s, k in zip(cpd.parents[:-1], cpd.card[:-1], strict=True):
        group = group * k + enc[s]
    return group


def _log_density(cpd, params, group, x, y, out=None, add=False) -> torch.Tensor:
    """``(C, n)``: the CPD's log-density of each row's ``y`` given its parents.

    The last parent (the cluster) is set to each of its ``C`` states in turn.

    A linear Gaussian's log-density is a quadratic form in ``z = [y, x]``: with the
    whitened residual ``L^-1 (y - W x - b) = M z - s``, ``|M z - s|^2 = z^T M^T M z -
    2 s^T M z + |s|^2``. Each configuration of the other parents present takes one matrix
    product of the rows' quadratic features (``z_i z_j``, ``z_i``, 1; ``z`` centred on
    the rows' mean, which keeps the expansion's rounding near that of the residual) with
    every cluster's coefficients.

    ``out``: a ``(C, n)`` tensor to write the result into, or with ``add`` to add it to;
    returned.
    """
    c = cpd.card[-1]
    if out is None:
        out = torch.empty(c, len(group), dtype=DTYPE)

    def put(rows, values):
        if add:
            out[:, rows] += values
        else:
            out[:, rows] = values

    if isinstance(cpd, TableCPD):
        logs = params.probs.reshape(-1, c, cpd.size).clamp_min(1e-300).log()
        for g, mine in _configurations(group):
            put(mine, logs[g][:, y[mine]])
        return out
    d = y.shape[-1]
    bias = params.bias.reshape(-1, c, d)
    weight = params.weight.reshape(bias.shape[0], c, d, -1)
    tril = params.scale_tril.reshape(-1, c, d, d)
    # whitened residual L^-1 (y - W x - b) = [L^-1, -L^-1 W] [y; x] - L^-1 b
    inverse = torch.linalg.solve_triangular(tril, torch.eye(d, dtype=DTYPE), upper=False)
    maps = torch.cat([inverse, -inverse @ weight], -1)  # (G, C, d, d + p)
    shift = (inverse @ bias[..., None])[..., 0]  # (G, C, d)
    constant = tril.diagonal(dim1=-2, dim2=-1).log().sum(-1) + 0.5 * d * math.log(2 * math.pi)
    data = torch.cat([y, x], -1) if x is not None else y
    i, j = torch.triu_indices(data.shape[-1], data.shape[-1])
    for g, mine in _configurations(group):
        rows = data[mine]
        centre = rows.mean(0)
        local = shift[g] - maps[g] @ centre  # the residual's offset for centred rows
        a = maps[g].mT @ maps[g]  # (C, q, q)
        b = (maps[g].mT @ local[..., None])[..., 0]  # (C, q)
        pairs = a[:, i, j] * torch.where(i == j, 1.0, 2.0).to(DTYPE)
        # -1/2 |M z - s|^2 - constant, as coefficients of quadratic_features(z)
        coeffs = torch.cat(
            [-0.5 * pairs, b, (-0.5 * (local * local).sum(-1) - constant[g])[:, None]], -1
        )
        features = quadratic_features(rows - centre)
        if isinstance(mine, slice):  # every row: straight into ``out``, no temporary
            if add:
                return out.addmm_(coeffs, features.T)
            return torch.mm(coeffs, features.T, out=out)
        put(mine, coeffs @ features.T)
    return out


def _configurations(group: torch.Tensor):
    """``(g, rows)`` per parent configuration present.

    A slice of all rows when there is one (no copies), else a mask.
    """
    present = torch.unique(group).tolist()
    if len(present) == 1:
        yield present[0], slice(None)
        return
    for g in present:
        yield g, group == g


def _weighted_sums(group: torch.Tensor, resp: torch.Tensor, rows: torch.Tensor, groups: int):
    """``out[g * C + c] = sum_{i: group_i = g} resp[c, i] * rows[i]`` for rows ``(n, ...)``.

    One matrix product per parent configuration present.
    """
    c = resp.shape[0]
    flat = rows.reshape(rows.shape[0], -1)
    out = torch.zeros(groups, c, flat.shape[1], dtype=DTYPE)
    for g, mine in _configurations(group):
        out[g] = resp[:, mine] @ flat[mine]
    return out.reshape(groups * c, *rows.shape[1:])


def _m_step(net, params, enc, mixtures, resp, alpha, min_variance) -> NetworkParams:
    """Refit every adaptive mixture's sites from the responsibility-weighted statistics."""
    cpds = dict(params.cpds)
    for m, r in zip(mixtures, resp, strict=True):
        action = enc[ACTION]
        uses = m.in_use(action)
        every = bool(uses.all())
        if not every:  # rows not using the parameter: pinned, unfitted
            r = torch.where(uses, r, 0.0)
        n_actions = m.cluster.card[0]
        by_action = torch.nn.functional.one_hot(action, n_actions).to(DTYPE)  # (n, A)
        cluster_counts = (r @ by_action).T  # (A, C): one product, not a scatter of rows
        cpds[m.cluster.site] = m.cluster.m_step(Counts(cluster_counts), alpha, min_variance)
        theta = enc[m.value.site].nan_to_num()
        one = torch.zeros(len(theta), dtype=torch.long)
        cpds[m.value.site] = m.value.m_step(_moments(one, r, None, theta, 1), alpha, min_variance)
        weights = r
        if not every:  # the affected sites' rows not using p: on the pinned cluster 0
            weights = r.clone()
            weights[0, ~uses] = 1.0
        for site in m.affected:
            cpd = net.cpd(site)
            group = _group(enc, cpd)
            groups = math.prod(cpd.card[:-1])
            if isinstance(cpd, TableCPD):
                onehot = torch.nn.functional.one_hot(enc[site], cpd.size).to(DTYPE)
                counts = _weighted_sums(group, weights, onehot, groups)
                stats = Counts(counts.reshape(*cpd.card, cpd.size))
            else:
                stats = _moments(group, weights, _inputs(enc, cpd, m), enc[site], groups)
            cpds[site] = cpd.m_step(stats, alpha, min_variance)
    return NetworkParams(cpds, params.pseudo_count, net)


def _moments(group, r, x, y, groups) -> Moments:
    """A linear Gaussian's statistics with fractional rows.

    ``r`` ``(C, n)`` weights (one weighted sum of every product at once).
    """
    n, d = y.shape
    z = torch.cat([x, torch.ones(n, 1, dtype=DTYPE)], -1) if x is not None else None
    z = z if z is not None else torch.ones(n, 1, dtype=DTYPE)
    q = z.shape[1]
    products = torch.cat(
        [
            (z[:, :, None] * z[:, None, :]).reshape(n, -1),
            (z[:, :, None] * y[:, None, :]).reshape(n, -1),
            (y[:, :, None] * y[:, None, :]).reshape(n, -1),
        ],
        -1,
    )
    sums = _weighted_sums(group, r, products, groups)  # (G C, q q + q d + d d)
    zz, zy, yy = sums.split([q * q, q * d, d * d], -1)
    rows = _weighted_sums(group, r, torch.ones(n, 1, dtype=DTYPE), groups)[:, 0]
    return Moments(zz.reshape(-1, q, q), zy.reshape(-1, q, d), yy.reshape(-1, d, d), rows)
