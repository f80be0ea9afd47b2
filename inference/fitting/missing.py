"""Expectation-maximisation over missing values.

Missing values (:func:`fit_missing`, what :func:`inference.fit` runs when some training
row misses a value) are latent variables, as adaptive clusters are
(:mod:`inference.fitting.em`), so EM serves them alike, with exact E-steps:

* **Discrete values** (None or NaN in the rows, or False in ``masks``): the Pyro model,
  traced under enumeration with them latent
  (:func:`inference.exact.enumeration.enumerate_model`), gives each row's joint
  posterior over its missing values and its log-likelihood with them summed out. Each
  row then stands for one completed row per assignment of its missing values, weighted
  by that assignment's posterior. Where every site is a table, the same expected counts
  come by elimination over the families instead
  (:mod:`inference.fitting.family_marginals`), at the cost of the families, not of the
  missing values' joint.
* **Continuous values** (NaN, whole or in some dimensions, at a continuous initial or
  end site): given an assignment of the discrete values, the row's continuous sites are
  jointly Gaussian (:mod:`inference.exact.gaussian_gaps`). The model, traced with
  their factors left out, gives each assignment's discrete factors; the joint Gaussian
  gives the density of the observed dimensions (the missing ones integrated out) and the
  missing ones' conditional mean and covariance. Each completed row holds the
  conditional means, and the conditional covariances join the sums of the linear
  Gaussians: ``E[v v^T] = E[v] E[v]^T + Cov[v]``.

The M-step is the closed form on the weighted statistics of the completed rows
(:func:`inference.fitting.sufficient_statistics.statistics` with ``weights``, plus the covariance
sums) -- exactly the expected sufficient statistics -- and, for a CPD without a closed
form (softmax), its own weighted maximisation (Newton's method from the current
parameters). The log-likelihood never falls from step to step; with a pseudo-count the
pooled pseudo-rows move with the completed rows, so a step that would lower the
likelihood is not taken and the fit ends there.

What has no closed form is refused by name: a discrete site (a softmax) whose
continuous parent misses a value, a continuous site of a kind other than the linear
Gaussian, and a missing value of a parameter that the row's action uses (``param.p``
NaN means that the action does not use ``p``; where the action is given and uses it, the
row is refused; where the action itself is missing, see below).

A missing action in a network with parameters: a training row gives a parameter's value
exactly when its action uses the parameter (:func:`inference.fit` refuses a row that
breaks the rule where the action is given), so where the action is missing, the
presence of each value is evidence of it. The E-step keeps the actions that use exactly
the parameters the row gives (the model's joint weight of the others is set to zero),
and each completed row's clusters are its values' cells under its action. A row that no
action agrees with (a value missing where every action would use it) is refused.

An *unrecorded* parameter value (``unrecorded=``: the data never held it, as a
demonstration does not record the force of a tap) is another matter: its NaN says nothing
of the action, and where the action uses the parameter the value is integrated out
exactly through its clusters (:mod:`inference.fitting.completion`), its cluster Gaussian
and the features it acts on refitted on the expected sums.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from dataclasses import replace

import torch
from effect_networks.inference.exact.gaussian_gaps import continuous_gaps, refuse_open_forms
from effect_networks.inference.fitting.completion import (
    Completed,
    completed_gaussian,
    completed_rows,
    open_parameters,
)
from effect_networks.inference.fitting.family_marginals import covers, family_counts
from effect_networks.inference.fitting.reading import read_rows
from effect_networks.inference.fitting.result import ConvergenceWarning, FitResult
from effect_networks.inference.fitting.rows import check_settings, missing_masks
from effect_networks.inference.fitting.sufficient_statistics import (
    Statistics,
    maximise_site,
    params_from_statistics,
    statistics,
)
from effect_networks.models.cpds import Counts
from effect_networks.models.declaration import ACTION, EffectNetwork
from effect_networks.models.evidence import DTYPE, Evidence
from effect_networks.models.params import NetworkParams, check_params
from tqdm.auto import tqdm

__all__ = [
    "EM_TOL",
    "EM_TOL_COMPLETED",
    "actions_allowed",
    "available_case_start",
    "fit_missing",
    "gaussian_row_log_likelihoods",
    "missing_log_likelihood",
]


#: EM's default tolerance where every site is a table: a step that raises the per-row
#: log-likelihood by less than this times its magnitude ends the fit. EM converges linearly,
#: and slowly along the directions the gaps leave weakly determined: after a step that gains
#: ``g`` it still gains about ``g r / (1 - r)`` at the rate ``r``, and the parameters keep
#: moving along those directions. A tolerance of 1e-6 ends the fit where the held-out
#: log-likelihood still moves by more than the margin ``benchmarks/em_structure.py`` holds it
#: to beside pyAgrum's EM; this one does not, at a few milliseconds a step by the families.
EM_TOL = 1e-9
#: ... and elsewhere (a continuous site, an action parameter), where a step over the completed
#: rows costs the joint of the missing values and a linear Gaussian's variance may approach
#: its floor for hundreds of steps.
EM_TOL_COMPLETED = 1e-6


def fit_missing(
    net: EffectNetwork,
    enc: Evidence,
    masks: Mapping[str, torch.Tensor],
    *,
    init: NetworkParams,
    pseudo_count: float = 0.01,
    prior: Mapping[str, object] | None = None,
    min_variance: float = 1e-6,
    l2: float = 0.01,
    steps: int = 500,
    tol: float | None = None,
    progress: bool = False,
    by_families: bool = True,
    unrecorded: Mapping[str, torch.Tensor] | None = None,
) -> FitResult:
    """Maximum likelihood with missing values, by EM with exact E-steps.

    ``enc``: checked rows (:func:`inference.fitting.rows.rows_with_gaps`), NaN where a
    continuous initial or end value is missing, any state where a discrete one is;
    ``masks``: ``(n,)`` bool per discrete site, False where the row's value is missing; ``init``: the start (``fit`` gives the closed form on the complete
    rows). At most ``steps`` EM steps; the fit has converged when a step lowers the
    per-row loss by less than ``tol`` times its magnitude (absolute below 1 nat), or would
    raise it. ``tol`` defaults to :data:`EM_TOL` where the E-step goes by the families, else
    :data:`EM_TOL_COMPLETED`; ``FitResult.tol`` and ``max_steps`` report the rule. ``l2``: the softmax slopes' prior.
    ``prior``: each site's prior (:func:`inference.fitting.priors.site_priors`; default
    ``pseudo_count`` everywhere), which the M-step's closed forms take as ``fit``'s do.
    ``by_families``: where every site is a table, the E-step by elimination over the families
    (:mod:`inference.fitting.family_marginals`); False: the completed rows everywhere (the
    route the benchmarks and tests compare it with; the same counts).
    ``unrecorded``: per parameter site (``param.p``), ``(n,)`` bool, True where the row does not
    record the value (NaN there, whatever its action): where the action uses the parameter the
    value is integrated out exactly through its clusters
    (:mod:`inference.fitting.completion`), and its absence says nothing of the action.
    The loss is the likelihood's, without the prior: a step that the prior's pull would
    make lower the likelihood ends the fit, as a pseudo-count's does.

    ``FitResult.losses``: the per-row negative log-likelihood, the missing values summed
    out (a missing action over the actions that agree with the row's parameter values,
    see the module) and the softmax prior included, at the start and after each step. EM cannot raise
    it (with ``pseudo_count = 0``; a pseudo-count's prior can ask for a hair more near the
    optimum): a step that would is not taken, and the fit ends there as converged, so the
    curve never rises. ``FitResult.log_likelihoods``: the summed log-likelihood at the
    same points. A :class:`ConvergenceWarning` names the sites with missing values when
    ``steps`` run out first.
    """
    if tol is None:
        tol = EM_TOL if by_families and covers(net) else EM_TOL_COMPLETED
    check_settings(pseudo_count=pseudo_count, min_variance=min_variance, steps=steps, tol=tol)
    masks = missing_masks(net, masks, enc.n_rows)
    gaps = continuous_gaps(net, enc)
    refuse_open_forms(net, enc, gaps)
    unrecorded = _checked_unrecorded(net, unrecorded, enc.n_rows)
    allowed = actions_allowed(net, enc, masks, unrecorded)
    alpha = pseudo_count if prior is None else prior
    n = enc.n_rows
    params = init
    completed = _e_step(net, params, enc, masks, allowed, by_families, unrecorded)
    curve = [(_prior(net, params, l2) - completed.log_lik) / n]
    log_liks = [completed.log_lik]
    converged = False
    bar = tqdm(total=steps, desc="fit (EM, missing values)", disable=not progress)
    for _ in range(steps):
        proposal = _m_step_missing(net, params, completed, alpha, min_variance, l2)
        step = _e_step(net, proposal, enc, masks, allowed, by_families, unrecorded)
        loss = (_prior(net, proposal, l2) - step.log_lik) / n
        bar.update()
        if not loss <= curve[-1]:  # a dip (a pseudo-count's prior), or NaN: stop before it
            converged = True
            break
        params, completed = proposal, step
        curve.append(loss)
        log_liks.append(step.log_lik)
        bar.set_postfix(loss=f"{loss:.6g}")
        if curve[-2] - curve[-1] <= tol * max(1.0, abs(curve[-1])):
            converged = True
            break
    bar.close()
    if not converged:
        warnings.warn(
            f"EM over the missing values of {sorted([*masks, *gaps, *unrecorded])} did not "
            "settle in "
            f"{steps} steps (last relative gain of the log-likelihood above tol={tol:g}); "
            "raise steps",
            ConvergenceWarning,
            stacklevel=3,
        )
    return FitResult(params, tuple(curve), converged, tuple(log_liks), tol, steps)


def available_case_start(
    net: EffectNetwork,
    enc: Evidence,
    masks: Mapping[str, torch.Tensor],
    pseudo_count: float,
    min_variance: float,
    *,
    prior: Mapping[str, object] | None = None,
) -> NetworkParams:
    """EM's start: each CPD's closed form on the rows that give its site and every parent.

    These are the available cases, so that a start exists wherever each CPD has such rows, even when
    no row gives every value.

    Raises
    ------
    ValueError
        Naming a site that no row gives together with all its parents.
    """
    given = {s: m for s, m in masks.items()}
    for site, x in continuous_gaps(net, enc).items():
        given[site] = ~x.any(-1)
    alpha = pseudo_count if prior is None else prior
    everything = torch.ones(enc.n_rows, dtype=torch.bool)
    for m in given.values():
        everything &= m
    if bool(everything.all()):
        return NetworkParams(
            params_from_statistics(net, statistics(net, enc), alpha, min_variance),
            pseudo_count,
            net,
        )
    # another site's missing values stand in as 0 there: only each site's own sums are kept
    enc = enc | {s: x.nan_to_num() for s, x in enc.items() if x.is_floating_point()}
    sites, by_rows = {}, {}
    for spec in net.sites:
        cpd = net.cpd(spec.name)
        rows = torch.ones(enc.n_rows, dtype=torch.bool)
        for q in (spec.name, *cpd.parents, *cpd.inputs, ACTION if spec.role == "param" else ""):
            if q in given:
                rows = rows & given[q]
        if not bool(rows.any()):
            raise ValueError(
                f"site {spec.name!r}: no training row gives it together with its parents "
                f"{[*cpd.parents, *cpd.inputs]}; EM needs at least one such row to start"
            )
        key = bytes(rows.numpy().tobytes())
        if key not in by_rows:  # sites whose rows agree share one pass
            by_rows[key] = statistics(net, enc if bool(rows.all()) else enc.rows(rows))
        sites[spec.name] = by_rows[key].sites[spec.name]
    stats = Statistics(sites, enc.n_rows)
    cpds = params_from_statistics(net, stats, alpha, min_variance)
    return NetworkParams(cpds, pseudo_count, net)


def missing_log_likelihood(
    net: EffectNetwork,
    params: NetworkParams,
    data: Mapping[str, object],
    masks: Mapping[str, torch.Tensor] | None = None,
) -> float:
    """The summed log-likelihood of training rows with missing values.

    Those values summed and integrated out: what :func:`fit_missing` raises.

    Missing values are marked as :func:`inference.fit` reads them: in the rows (None or
    NaN for a discrete label, NaN for a continuous value or some of its dimensions) or
    by ``masks`` (False where a discrete value is missing).
    """
    check_params(net, params)
    rows = read_rows(net, data, masks)
    enc, masks = rows.enc, missing_masks(net, rows.masks, rows.n_rows)
    refuse_open_forms(net, enc, continuous_gaps(net, enc))
    return _e_step(net, params, enc, masks, actions_allowed(net, enc, masks)).log_lik


def gaussian_row_log_likelihoods(
    net: EffectNetwork, params: NetworkParams, enc: Evidence, masks: Mapping[str, torch.Tensor]
) -> torch.Tensor:
    """``(n,)`` each row's log-likelihood, its missing values summed or integrated out.

    Its missing discrete values summed out and its missing continuous ones integrated out: the terms
    of :func:`missing_log_likelihood`, by the closed-form Gaussian path (every continuous initial
    and end site a linear Gaussian, checked by
    :func:`~inference.exact.gaussian_gaps.refuse_open_forms`).

    ``enc``: checked rows (:func:`inference.fitting.rows.rows_with_gaps`), NaN where a
    continuous value is missing, an adaptive parameter's cluster left out where the rows
    do not give it (it is summed out); ``masks``: ``(n,)`` bool per discrete site, False
    where missing. A row of probability 0 scores ``-inf``.
    """
    masks = {s: m for s, m in masks.items() if not bool(m.all())}
    allowed = actions_allowed(net, enc, masks)
    return completed_gaussian(net, params, enc, masks, allowed, posterior=False).per_row


def actions_allowed(
    net: EffectNetwork, enc: Evidence, masks, unrecorded: Mapping[str, torch.Tensor] | None = None
) -> torch.Tensor | None:
    """The actions that agree with each row's parameter values, where the action is missing.

    ``(A, n)`` bool, in a network with parameters. A training row gives a parameter's value exactly
    when its action uses the parameter (:func:`inference.fit` checks it where the action is given),
    so where the action is missing the presence of each value is evidence of it. ``None`` where
    there is nothing to restrict. A value ``unrecorded`` (per parameter site, ``(n,)`` bool) is no
    evidence either way.
    """
    if ACTION not in masks or not net.mixtures:
        return None
    missing = ~masks[ACTION]
    allowed = torch.ones(len(net.actions), enc.n_rows, dtype=torch.bool)
    for m in net.mixtures:
        present = ~torch.isnan(enc[m.value.site]).any(-1)  # (n,)
        agree = m.uses[:, None] == present[None, :]  # (A, n)
        if unrecorded and m.value.site in unrecorded:
            agree = agree | unrecorded[m.value.site][None, :]
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


def _e_step(net, params, enc, masks, allowed=None, by_families=True, unrecorded=None) -> Completed:
    """The E-step: by elimination over the families where the network is all tables.

    (:mod:`inference.fitting.family_marginals`: the expected counts without completing rows),
    else the completed rows (:func:`~inference.fitting.completion.completed_rows`, its twin in
    the tests).
    """
    if not by_families or not masks or not covers(net) or open_parameters(unrecorded):
        return completed_rows(net, params, enc, masks, allowed, unrecorded)
    found = family_counts(net, params, enc, masks)
    stats = Statistics({s: Counts(c) for s, c in found.counts.items()}, enc.n_rows)
    weights = torch.ones(enc.n_rows, dtype=DTYPE)
    return Completed(enc, weights, found.log_lik, per_row=found.per_row, stats=stats)


#: The most Newton iterations of one M-step (from the last step's optimum it takes a
#: few; an M-step that only raises the objective keeps EM's guarantee all the same).
M_STEP_ITERATIONS = 100


def _m_step_missing(net, params, completed: Completed, alpha, min_variance, l2) -> NetworkParams:
    """Every CPD refitted on the weighted completed rows.

    The closed form on their expected sums, and Newton's method from the current parameters where
    there is none.
    """
    rows, weights = completed.rows, completed.weights
    if completed.stats is not None:  # by elimination: every site a table, all in closed form
        return NetworkParams(
            params_from_statistics(net, completed.stats, alpha, min_variance),
            params.pseudo_count,
            net,
        )
    stats = statistics(net, rows, weights)
    for site, extra in completed.moments.items():
        stats.sites[site] = stats.sites[site] + extra
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
    """The negative log of the Gaussian prior on the penalised tensors.

    The softmax slopes; its constant left out, as :func:`inference.fit_gradient` adds it.
    """
    total = 0.0
    for spec in net.sites:
        cpd = net.cpd(spec.name)
        if cpd.closed_form:  # the closed-form kinds carry no such prior
            continue
        for tensor in cpd.penalised(cpd.free(params[spec.name])):
            total += 0.5 * l2 * float(tensor.square().sum())
    return total


def _checked_unrecorded(net, unrecorded, n: int) -> dict[str, torch.Tensor]:
    """``unrecorded`` as ``(n,)`` bool per parameter site that leaves some value open."""
    sites = {m.value.site for m in net.mixtures}
    out = {}
    for site, mask in (unrecorded or {}).items():
        mask = torch.as_tensor(mask, dtype=torch.bool)
        if site not in sites or mask.shape != (n,):
            raise ValueError(
                f"unrecorded[{site!r}] must be ({n},) bool for a parameter site of the network "
                f"(one of {sorted(sites)}); got shape {tuple(mask.shape)}"
            )
        out[site] = mask
    return open_parameters(out)
