"""Expectation-maximisation over missing discrete values.

Missing discrete values (:func:`fit_missing`, what :func:`inference.fit` runs when
``masks`` leave gaps) are discrete latent variables, as adaptive clusters are
(:mod:`inference.fitting.em`), so EM serves them alike. The E-step is exact: the
Pyro model, traced under enumeration with the masked values latent
(:func:`inference.queries.enumeration.enumerate_model`), gives each row's joint posterior over its missing
values and its log-likelihood with them summed out. Each row then stands for one
completed row per assignment of its missing values, weighted by that assignment's
posterior, and the M-step is the closed form on the weighted statistics of the completed
rows (:func:`inference.fitting.statistics.statistics` with ``weights``) -- exactly the expected
sufficient statistics -- and, for a CPD without a closed form (softmax), its own
weighted maximisation (Newton's method from the current parameters). Continuous values
are never missing, so the pooled statistics behind the pseudo-count policy do not change
between steps.

A missing action in a network with parameters: a training row gives a parameter's value
exactly when its action uses the parameter (:func:`inference.fit` refuses a row that
breaks the rule where the action is given), so where the action is missing, the
presence of each value is evidence of it. The E-step keeps the actions that use exactly
the parameters the row gives (the model's joint weight of the others is set to zero),
and each completed row's clusters are its values' cells under its action. A row that no
action agrees with (a value missing where every action would use it) is refused.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping
from dataclasses import replace

import torch
from tqdm.auto import tqdm

from inference.fitting.result import ConvergenceWarning, FitResult
from inference.fitting.rows import (
    check_settings,
    ignore_missing,
    mask_values,
    missing_masks,
    training_rows,
)
from inference.fitting.statistics import maximise_site, params_from_statistics, statistics
from inference.queries.enumeration import Enumerated, enumerate_model, row_chunks
from models.declaration import ACTION, EffectNetwork
from models.evidence import DTYPE, Evidence
from models.params import NetworkParams, check_params

__all__ = ["actions_allowed", "fit_missing", "missing_log_likelihood"]


def fit_missing(
    net: EffectNetwork,
    enc: Evidence,
    masks: Mapping[str, torch.Tensor],
    *,
    init: NetworkParams,
    pseudo_count: float = 0.01,
    min_variance: float = 1e-6,
    l2: float = 0.01,
    steps: int = 500,
    tol: float = 1e-6,
    progress: bool = False,
) -> FitResult:
    """Maximum likelihood with missing discrete values, by EM with exact E-steps.

    ``enc``: complete, checked rows (:func:`inference.fit`'s), whatever they hold where a
    value is missing; ``masks``: ``(n,)`` bool per discrete site, False where the row's
    value is missing; ``init``: the start (``fit`` gives the closed form on the complete
    rows). At most ``steps`` EM steps; the fit has converged when a step lowers the
    per-row loss by less than ``tol`` (relative). ``l2``: the softmax slopes' prior.

    ``FitResult.losses``: the per-row negative log-likelihood, the missing values summed
    out (a missing action over the actions that agree with the row's parameter values,
    see the module) and the softmax prior included, at the start and after each step. EM cannot raise
    it (with ``pseudo_count = 0``; a pseudo-count's prior can ask for a hair more near the
    optimum): a step that would is not taken, and the fit ends there as converged, so the
    curve never rises.
    """
    check_settings(pseudo_count=pseudo_count, min_variance=min_variance, steps=steps, tol=tol)
    masks = missing_masks(net, masks, enc.n_rows)
    allowed = actions_allowed(net, enc, masks)
    n = enc.n_rows
    params = init
    expanded, weights, log_lik = _completed_rows(net, params, enc, masks, allowed)
    curve = [(_prior(net, params, l2) - log_lik) / n]
    converged = False
    bar = tqdm(total=steps, desc="fit (EM, missing values)", disable=not progress)
    for _ in range(steps):
        proposal = _m_step_missing(net, params, expanded, weights, pseudo_count, min_variance, l2)
        rows, w, log_lik = _completed_rows(net, proposal, enc, masks, allowed)
        loss = (_prior(net, proposal, l2) - log_lik) / n
        bar.update()
        if not loss <= curve[-1]:  # a dip (a pseudo-count's prior), or NaN: stop before it
            converged = True
            break
        params, expanded, weights = proposal, rows, w
        curve.append(loss)
        bar.set_postfix(loss=f"{loss:.6g}")
        if curve[-2] - curve[-1] <= tol * max(1.0, abs(curve[-1])):
            converged = True
            break
    bar.close()
    if not converged:
        warnings.warn(
            f"EM over the missing values of {sorted(masks)} did not settle in {steps} steps "
            f"(last relative gain of the log-likelihood above tol={tol:g}); raise steps",
            ConvergenceWarning,
            stacklevel=3,
        )
    return FitResult(params, tuple(curve), converged)


def missing_log_likelihood(
    net: EffectNetwork,
    params: NetworkParams,
    data: Mapping[str, object],
    masks: Mapping[str, torch.Tensor],
) -> float:
    """The summed log-likelihood of rows with missing discrete values (False in
    ``masks``), those values summed out: what :func:`fit_missing` raises."""
    check_params(net, params)
    unknown = masks.get(ACTION)
    unknown = None if unknown is None else ~mask_values(ACTION, unknown)
    enc = training_rows(net, ignore_missing(net, data, masks), unknown)
    masks = missing_masks(net, masks, enc.n_rows)
    return _completed_rows(net, params, enc, masks, actions_allowed(net, enc, masks))[2]


def actions_allowed(net: EffectNetwork, enc: Evidence, masks) -> torch.Tensor | None:
    """``(A, n)`` bool, where the action is missing in a network with parameters: the
    actions that agree with the row's parameter values. A training row gives a
    parameter's value exactly when its action uses the parameter (:func:`inference.fit`
    checks it where the action is given), so where the action is missing the presence
    of each value is evidence of it. ``None`` where there is nothing to restrict."""
    if ACTION not in masks or not net.mixtures:
        return None
    missing = ~masks[ACTION]
    allowed = torch.ones(len(net.actions), enc.n_rows, dtype=torch.bool)
    for m in net.mixtures:
        present = ~torch.isnan(enc[m.value.site]).any(-1)  # (n,)
        agree = m.uses[:, None] == present[None, :]  # (A, n)
        allowed &= agree | ~missing[None, :]
        none = ~allowed.any(0)
        if bool(none.any()):
            row = int(none.nonzero()[0])
            what = "gives" if bool(present[row]) else "gives no"
            raise ValueError(
                f"site {ACTION!r}: row {row} is missing and {what} a value of "
                f"{m.value.site!r}, which no action agrees with (a row gives a parameter's "
                "value exactly when its action uses the parameter)"
            )
    return allowed


def _completed_rows(net, params, enc, masks, allowed=None) -> tuple[Evidence, torch.Tensor, float]:
    """The E-step: every row once per assignment of its missing values that has posterior
    weight, with that weight, and the summed log-likelihood (missing values summed out).
    ``allowed`` (:func:`actions_allowed`) restricts a missing action; the parameters'
    clusters then follow each assignment's action (the cell of the value, or cell 0).
    Rows go through the model in chunks whose joint posterior stays below
    :data:`inference.queries.enumeration.CHUNK_ELEMENTS`."""
    if not masks:
        return enc, torch.ones(enc.n_rows, dtype=DTYPE), 0.0
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
            dim = enumerated.dims[ACTION]
            agree = allowed[:, chunk].reshape(len(net.actions), *([1] * (-dim - 2)), -1)
            log_weight = enumerated.log_weight.masked_fill(~agree, -torch.inf)
            enumerated = Enumerated(
                (log_weight,), enumerated.dims, enumerated.trace, enumerated.offsets
            )
        posterior = enumerated.posterior()  # (E_k, ..., E_1, n)
        log_lik += float(enumerated.log_evidence.sum())
        others = [d + posterior.dim() for s, d in enumerated.dims.items() if s not in masks]
        if others:  # the clusters: summed out (each assignment's action fixes them)
            posterior = posterior.sum(others, keepdim=True)
        shape = posterior.shape[:-1]
        flat = posterior.reshape(-1, rows.n_rows)
        assignment, row = flat.nonzero(as_tuple=True)
        values = {}
        for site in masks:
            dim = enumerated.dims[site]
            k = net.site(site).size
            assert posterior.shape[dim] == k, (site, posterior.shape, dim)
            states = torch.arange(k).reshape(k, *([1] * (-dim - 2)))
            values[site] = states.expand(shape).reshape(-1)[assignment]
        completed = enc.rows(chunk).rows(row) | net.encode_indices(values)
        if allowed is not None:
            cells = {
                m.cluster.site: m.cells(completed[m.value.site], completed[ACTION])
                for m in net.mixtures
            }
            completed = completed | net.encode_indices(cells)
        parts.append(completed)
        weights.append(flat[assignment, row])
    if len(parts) == 1:
        return parts[0], weights[0], log_lik
    completed = {site: torch.cat([p[site] for p in parts]) for site in parts[0]}
    return Evidence(net, completed, sum(p.n_rows for p in parts)), torch.cat(weights), log_lik


#: The most Newton iterations of one M-step (from the last step's optimum it takes a
#: few; an M-step that only raises the objective keeps EM's guarantee all the same).
M_STEP_ITERATIONS = 100


def _m_step_missing(net, params, rows, weights, alpha, min_variance, l2) -> NetworkParams:
    """Every CPD refitted on the weighted completed rows: the closed form, and Newton's
    method from the current parameters where there is none."""
    stats = statistics(net, rows, weights)
    cpds = params_from_statistics(net, stats, alpha, min_variance)
    for spec in net.sites:
        if net.cpd(spec.name).closed_form:
            continue
        start = replace(params[spec.name], n=cpds[spec.name].n)  # the new rows' counts
        found = maximise_site(
            net, rows, spec.name, start, weights=weights, l2=l2, steps=M_STEP_ITERATIONS
        )
        cpds[spec.name] = found.params
    return NetworkParams(cpds, params.pseudo_count, net)


def _prior(net: EffectNetwork, params: NetworkParams, l2: float) -> float:
    """The negative log of the Gaussian prior on the penalised tensors (the softmax
    slopes; its constant left out), as :func:`inference.fit_gradient` adds it."""
    total = 0.0
    for spec in net.sites:
        cpd = net.cpd(spec.name)
        if cpd.closed_form:  # the closed-form kinds carry no such prior
            continue
        for tensor in cpd.penalised(cpd.free(params[spec.name])):
            total += 0.5 * l2 * float(tensor.square().sum())
    return total
