"""EM's E-step by completion: every row once per assignment of what it misses, weighted.

What :func:`inference.fitting.missing.fit_missing` runs where the expected counts do not
come by elimination over the families. Each row stands for one completed row per
assignment of its missing discrete values (and, where its action is missing, of the
action and the clusters that follow it), weighted by that assignment's exact posterior
given the row (the Pyro model traced under enumeration,
:func:`inference.exact.enumeration.enumerate_model`). Where a continuous value is missing
the row's continuous sites are jointly Gaussian given the assignment
(:mod:`inference.exact.gaussian_gaps`): each completion holds the missing values'
conditional means, and their conditional covariances join the linear Gaussians' sums.

**Unrecorded parameter values.** A row may leave an action parameter's value unrecorded
(``unrecorded``: a demonstration does not record the force of a tap). Where its
(completed) action uses the parameter, the value is one more dimension of the joint
Gaussian, its cluster's Gaussian (:func:`~inference.exact.gaussian_gaps.joint_gaussian`
with ``parameters``), integrated out exactly; its cluster is enumerated with the rest
(the model leaves it latent where the value is unknown), so each completion is an
(action, cluster, missing values) assignment and its weight the posterior given the whole
row. The completed value is its conditional mean, and its conditional covariance joins
the sums of the cluster's Gaussian and of the features it acts on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from effect_networks.inference.exact.enumeration import enumerate_model, row_chunks
from effect_networks.inference.exact.gaussian_gaps import (
    condition,
    continuous_gaps,
    continuous_sites,
    covariance_moments,
    joint_gaussian,
    refuse_open_forms,
)
from effect_networks.inference.exact.traced import Enumerated
from effect_networks.inference.fitting.sufficient_statistics import Statistics
from effect_networks.models.declaration import ACTION
from effect_networks.models.evidence import DTYPE, Evidence

__all__ = ["Completed", "completed_gaussian", "completed_rows", "open_parameters"]


def completed_rows(
    net, params, enc, masks, allowed=None, unrecorded=None, row_weights=None
) -> Completed:
    """The E-step: every row once per assignment of its missing values, with its weight.

    Every assignment that has posterior weight, with that weight, and the summed log-likelihood
    (missing values summed out). ``allowed`` (:func:`actions_allowed`) restricts a missing action;
    the parameters' clusters then follow each assignment's action (the cell of the value, or cell
    0). Rows go through the model in chunks whose joint posterior stays below
    ``inference.exact.enumeration.CHUNK_ELEMENTS``. Where a continuous value is missing (NaN),
    or a parameter's value is ``unrecorded`` (:func:`open_parameters`), :func:`completed_gaussian`
    serves instead. ``row_weights`` ``(n,)`` (default 1): each row's own weight (a row that is
    itself one completion of something larger), multiplying its completions' weights and its
    conditional covariances' share of the sums; the log-likelihood stays unweighted.
    """
    gaps = continuous_gaps(net, enc)
    if gaps or open_parameters(unrecorded):
        return completed_gaussian(net, params, enc, masks, allowed, unrecorded, row_weights)
    outer = torch.ones(enc.n_rows, dtype=DTYPE) if row_weights is None else row_weights
    if not masks:  # nothing missing: the rows' log-likelihood alone
        log_lik = sum(
            float(enumerate_model(net, params, enc.rows(chunk)).log_evidence.sum())
            for chunk in row_chunks(enc.n_rows, 1)
        )
        return Completed(enc, outer.clone(), log_lik)
    size = math.prod(net.site(site).size for site in masks)
    model_rows = enc
    if allowed is not None:  # the clusters follow the action: the model derives them
        model_rows = enc.without(*(m.cluster.site for m in net.mixtures))
        size *= math.prod(m.cluster.size for m in net.mixtures)
    parts, weights, log_lik = [], [], 0.0
    for chunk in row_chunks(enc.n_rows, size):
        rows = model_rows.rows(chunk)
        chunk_masks = {s: m[chunk] for s, m in masks.items()}
        enumerated = enumerate_model(net, params, rows, masks=chunk_masks)
        assert set(masks) <= set(enumerated.dims), (enumerated.dims, list(masks))
        if allowed is not None:
            enumerated = _restrict_actions(net, enumerated, allowed[:, chunk])
        posterior = enumerated.posterior()  # (E_k, ..., E_1, n)
        log_lik += float(enumerated.log_evidence.sum())
        others = [d + posterior.dim() for s, d in enumerated.dims.items() if s not in masks]
        if others:  # the clusters: summed out (each assignment's action fixes them)
            posterior = posterior.sum(others, keepdim=True)
        flat = posterior.reshape(-1, rows.n_rows)
        assignment, row = flat.nonzero(as_tuple=True)
        values = _assigned(net, enumerated.dims, posterior.shape[:-1], masks, assignment)
        completed = enc.rows(chunk).rows(row) | net.encode_indices(values)
        if allowed is not None:
            completed = _with_cells(net, completed)
        parts.append(completed)
        weights.append(flat[assignment, row] * outer[chunk][row])
    return Completed(_joined(net, parts), torch.cat(weights), log_lik)


@dataclass(frozen=True)
class Completed:
    """An E-step's result.

    The completed rows, their weights, the summed log-likelihood (missing values summed out), the
    conditional covariances' sums per linear Gaussian where continuous values are missing
    (:mod:`inference.exact.gaussian_gaps`), and there each row's log-likelihood ``(n,)``. Where
    the E-step ran by elimination, ``stats`` holds the expected statistics themselves (the rows
    are then the rows as given, not completed).
    """

    rows: Evidence
    weights: torch.Tensor
    log_lik: float
    moments: dict = field(default_factory=dict)
    per_row: torch.Tensor | None = None
    stats: Statistics | None = None


def completed_gaussian(
    net, params, enc, masks, allowed, unrecorded=None, row_weights=None, posterior=True
) -> Completed:
    """The E-step where continuous values are missing.

    The model, traced under enumeration with the missing discrete values latent and every continuous
    initial and end site's factor left out (their values filled in, read by no factor kept), gives
    each completion's discrete factors; the continuous sites' joint Gaussian given the completion
    (:func:`inference.exact.gaussian_gaps.joint_gaussian`) gives the density of the observed
    dimensions and the missing ones' conditional moments. Without ``posterior``, only the rows'
    log-likelihoods (``per_row``, ``-inf`` for a row of probability 0) and their sum: the rows are
    not completed.

    ``unrecorded``: per parameter site, ``(n,)`` bool, True where the row does not record the
    value (NaN there); the value is then part of the joint Gaussian and its cluster enumerated
    (the module's notes).
    """
    refuse_open_forms(net, enc, continuous_gaps(net, enc))
    with_parameters = bool(open_parameters(unrecorded))
    layout = continuous_sites(net, with_parameters)
    # the initial and end values filled in (their factors left out); a parameter's value stays
    # NaN where unknown, so that the model leaves its cluster latent there
    filled = enc | {s: enc[s].nan_to_num() for s in continuous_sites(net)}
    size = math.prod(net.site(site).size for site in masks) if masks else 1
    model_rows = filled
    follow = allowed is not None or with_parameters  # the clusters: derived or enumerated
    if follow:
        model_rows = filled.without(*(m.cluster.site for m in net.mixtures))
        size *= math.prod(m.cluster.size for m in net.mixtures)
    outer = torch.ones(enc.n_rows, dtype=DTYPE) if row_weights is None else row_weights
    parts, weights, covs, per_row, log_lik = [], [], [], [], 0.0
    for chunk in row_chunks(enc.n_rows, size):
        rows = model_rows.rows(chunk)
        n = rows.n_rows
        chunk_masks = {s: m[chunk] for s, m in masks.items()}
        enumerated = enumerate_model(net, params, rows, masks=chunk_masks, trace_only=layout)
        if allowed is not None:
            enumerated = _restrict_actions(net, enumerated, allowed[:, chunk])
        dims = enumerated.dims
        shape = [1] * max([-d for d in dims.values()], default=1)
        for site, d in dims.items():
            shape[d] = net.site(site).size
        shape[-1] = n
        flat = enumerated.log_weight.expand(shape).reshape(-1, n)
        assignment, row = (flat > -torch.inf).nonzero(as_tuple=True)
        values = _assigned(net, dims, tuple(shape[:-1]), dims, assignment)
        completed = enc.rows(chunk).rows(row) | net.encode_indices(values)
        if follow:
            completed = _with_cells(net, completed)
        # the Gaussian part once per row and configuration of the continuous sites'
        # discrete parents (the completions of other sites share it)
        key = row.clone()
        for site in dims:
            if any(site in net.cpd(c).parents for c in layout) or (
                site == ACTION and with_parameters  # which values the action uses
            ):
                key = key * net.site(site).size + completed[site]
        key, inverse = torch.unique(key, return_inverse=True)
        first = torch.zeros(len(key), dtype=torch.long).scatter_(
            0, inverse, torch.arange(len(inverse))
        )
        distinct = completed.rows(first)
        mean, cov = joint_gaussian(net, params, distinct, with_parameters)
        value = torch.cat([distinct[s] for s in layout], -1)
        log_density, post_mean, post_cov = condition(mean, cov, value)
        if with_parameters:  # a value the action does not use: no value, no sums
            post_mean, post_cov = _unused_dropped(net, layout, distinct, post_mean, post_cov)
        joint = torch.full_like(flat, -torch.inf)
        joint[assignment, row] = flat[assignment, row] + log_density[inverse]
        log_norm = joint.logsumexp(0)  # (n,)
        per_row.append(log_norm + enumerated.log_offset)
        if not posterior:
            continue
        if not bool((log_norm > -torch.inf).all()):
            bad = int((log_norm == -torch.inf).nonzero()[0])
            raise ValueError(
                f"training row {bad + (chunk.start or 0)} has probability 0 under every "
                "completion of its missing values: no posterior exists"
            )
        log_lik += float(per_row[-1].sum())
        w = (joint[assignment, row] - log_norm[row]).exp() * outer[chunk][row]
        keep = w > 0
        means = post_mean[inverse[keep]]
        parts.append(completed.rows(keep) | {s: means[:, own] for s, own in layout.items()})
        weights.append(w[keep])
        # the conditional covariances' sums: per distinct Gaussian that misses a value,
        # its completions' weights summed
        gapped = torch.isnan(value).any(-1)
        summed = torch.zeros(len(key), dtype=DTYPE).index_add_(0, inverse, w)
        covs.append((distinct.rows(gapped), post_cov[gapped], summed[gapped]))
    if not posterior:
        scored = torch.cat(per_row)
        return Completed(enc, torch.ones(enc.n_rows, dtype=DTYPE), float(scored.sum()), {}, scored)
    moments = covariance_moments(
        net,
        _joined(net, [c[0] for c in covs]),
        torch.cat([c[1] for c in covs]),
        torch.cat([c[2] for c in covs]),
        with_parameters,
    )
    return Completed(_joined(net, parts), torch.cat(weights), log_lik, moments, torch.cat(per_row))


def _restrict_actions(net, enumerated: Enumerated, allowed: torch.Tensor) -> Enumerated:
    """``enumerated`` with the actions that disagree with a row's parameter values impossible.

    ``allowed`` ``(A, n)``.
    """
    dim = enumerated.dims[ACTION]
    agree = allowed.reshape(len(net.actions), *([1] * (-dim - 2)), -1)
    log_weight = enumerated.log_weight.masked_fill(~agree, -torch.inf)
    return Enumerated((log_weight,), enumerated.dims, enumerated.trace, enumerated.offsets)


def _assigned(net, dims, shape, sites, assignment) -> dict[str, torch.Tensor]:
    """The state of each of ``sites`` in each flat ``assignment`` of a joint of ``shape``.

    ``sites`` are enumerated at ``dims``.
    """
    values = {}
    for site in sites:
        dim = dims[site]
        k = net.site(site).size
        assert shape[dim + 1] == k, (site, shape, dim)
        states = torch.arange(k).reshape(k, *([1] * (-dim - 2)))
        values[site] = states.expand(shape).reshape(-1)[assignment]
    return values


def _with_cells(net, completed: Evidence) -> Evidence:
    """The completed rows with each grid parameter's cluster its value's cell.

    Its cell under the row's (completed) action; an adaptive one's is enumerated with the rest,
    and so is the cluster of a value unknown where the action uses it.
    """
    cells = {}
    for m in net.mixtures:
        if m.parameter.adaptive:
            continue
        theta, action = completed[m.value.site], completed[ACTION]
        unknown = torch.isnan(theta).any(-1) & m.in_use(action)
        cell = m.cells(theta, action)
        cells[m.cluster.site] = torch.where(unknown, completed[m.cluster.site], cell)
    return completed | net.encode_indices(cells)


def open_parameters(unrecorded) -> dict[str, torch.Tensor]:
    """The parameter sites of ``unrecorded`` (``(n,)`` bool each) that leave some value open."""
    return {s: u for s, u in (unrecorded or {}).items() if bool(u.any())}


def _unused_dropped(net, layout, rows: Evidence, mean, cov):
    """The conditional moments with each parameter's value removed where the action ignores it.

    Its mean NaN (the statistics read no value there) and its covariance zero.
    """
    mean, cov = mean.clone(), cov.clone()
    for m in net.mixtures:
        own = layout[m.value.site]
        unused = ~m.in_use(rows[ACTION])
        mean[unused, own] = torch.nan
        cov[unused, own, :] = 0.0
        cov[unused, :, own] = 0.0
    return mean, cov


def _joined(net, parts: list[Evidence]) -> Evidence:
    if len(parts) == 1:
        return parts[0]
    completed = {site: torch.cat([p[site] for p in parts]) for site in parts[0]}
    return Evidence(net, completed, sum(p.n_rows for p in parts))
