"""Maximum-likelihood fitting of effect networks.

Two routes to the same optimum, both on the likelihood that :func:`models.effect_model`
defines:

* :func:`fit` -- closed form wherever it exists: tables are normalised counts,
  conditional linear Gaussians are per-configuration least squares with the residual
  covariance, cluster Gaussians are sample means and covariances. Softmax CPDs (a discrete
  child of continuous parents) have no closed form: each parent configuration is a
  multinomial logistic regression, solved by Newton's method
  (:meth:`models.cpds.SoftmaxCPD.maximise`). When some rows miss a value (None or NaN
  for a discrete label, NaN for a continuous value or some of its dimensions, or
  ``masks``), EM with exact E-steps maximises the marginal likelihood, the missing
  values summed and integrated out (:func:`inference.fitting.missing.fit_missing`).
* :func:`fit_gradient` -- ``TraceEnum_ELBO`` with an empty guide, minimised by L-BFGS
  (Adam with gaps) on tensors local to the call (Pyro's global parameter store is left
  alone): with no latent continuous sites, the ELBO *is* the (marginal) log-likelihood.
  It differentiates the model itself, so it serves as the check of the other route and
  fits a kind without a closed form or a ``maximise`` method of its own.

A parameter's cluster is data (:mod:`models.model`): a row that gives ``cluster.p``
is filed under that cluster (rows drawn by :func:`inference.simulate` give the cluster
they were drawn from, so ``fit(simulate(...))`` is the maximum-likelihood fit of the
model that drew them); a row that gives the value alone is filed under the value's
equidistant cell, the paper's clustering (then each cluster's Gaussian is the sample
mean and covariance of the values in its cell).

The rule that an action which does not use a parameter ignores it
(:meth:`EffectNetwork.parameter_in_use`) holds in training too: a row whose action does
not use ``p`` must leave ``param.p`` NaN (a value there is refused, not silently used),
and the affected feature's weights on ``p`` are zero for such actions.

Every loop is bounded and every input checked: a value whose square would overflow
(beyond ``models.evidence.MAX_MAGNITUDE``), a non-finite or negative setting, zero rows, or a covariance
that no jitter makes positive definite raise a ``ValueError`` naming the site.

The closed form runs on sufficient statistics (:mod:`inference.fitting.sufficient_statistics`, where the
pseudo-count policy is written): ``data`` may be an iterable of row chunks whose
statistics are summed, so a data set larger than memory, or partitioned on a cluster,
fits to the same parameters.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable, Mapping

import pyro
import torch
from effect_networks.inference.exact.gaussian_gaps import continuous_gaps
from effect_networks.inference.fitting.missing import available_case_start, fit_missing
from effect_networks.inference.fitting.priors import Prior, site_priors
from effect_networks.inference.fitting.reading import TrainingRows, read_rows
from effect_networks.inference.fitting.result import ConvergenceWarning, FitResult
from effect_networks.inference.fitting.rows import (
    NoRows,
    check_settings,
    refuse_adaptive,
    row_masks,
    training_rows,
)
from effect_networks.inference.fitting.sufficient_statistics import (
    Statistics,
    maximise_site,
    params_from_statistics,
    statistics,
)
from effect_networks.models.declaration import EffectNetwork
from effect_networks.models.evidence import Evidence
from effect_networks.models.frames import as_data, is_frame
from effect_networks.models.model import effect_model
from effect_networks.models.params import NetworkParams, check_params, initial_params
from pyro.infer import TraceEnum_ELBO
from tqdm.auto import tqdm

__all__ = [  # FitResult and ConvergenceWarning live in inference.fitting.result
    "ConvergenceWarning",
    "FitResult",
    "fit",
    "fit_gradient",
    "fit_statistics",
]


def fit(
    net: EffectNetwork,
    data: Mapping[str, object] | Iterable[Mapping[str, object]],
    *,
    pseudo_count: float = 0.01,
    prior: Prior | None = None,
    estimate: str = "mean",
    min_variance: float = 1e-6,
    masks: Mapping[str, torch.Tensor] | None = None,
    steps: int = 500,
    lr: float = 0.05,
    l2: float = 0.01,
    tol: float | None = None,
    progress: bool = False,
) -> FitResult:
    """Fit every CPD of ``net`` by maximum likelihood, or under a prior.

    Parameters
    ----------
    data
        Training rows by site name (see :meth:`EffectNetwork.encode`), or a pandas
        ``DataFrame`` with a column per site (:mod:`models.frames`); every site of the
        network must be present. ``param.p`` holds NaN in rows whose action does not use
        ``p`` (a missing value of a parameter the action uses is refused). A missing
        value is None or NaN for a discrete label (an object or float array), NaN for a
        continuous initial or end value or some of its dimensions (or
        :class:`models.evidence.Partial`); then the fit is EM (see ``masks``). Or an iterable of such row chunks (a generator, say), read once: each
        chunk's sufficient statistics are computed and summed
        (:mod:`inference.fitting.sufficient_statistics`), so the rows never need to be in memory together.
        Chunks serve networks whose CPDs all have a closed form, without ``masks``.
    pseudo_count, min_variance
        The pseudo-count policy (README, "Unseen configurations") and the covariance
        floor. A linear Gaussian's pseudo-rows are its site's pooled statistics, spread
        and all: against a configuration whose inputs span a small part of the pooled
        range they weigh like ``(pooled spread / own spread)**2 * pseudo_count`` rows
        in its slope. Pass 0 when every configuration has rows enough.
    prior, estimate
        Priors per site (:mod:`inference.fitting.priors`): a number (the same as
        ``pseudo_count``), :class:`~inference.fitting.priors.BDeu` ``(ess)``,
        :class:`~inference.fitting.priors.K2` ``()`` or a mapping site -> number, array
        of pseudo-counts ``(P..., K)``, ``BDeu``, ``K2`` or
        :class:`~models.cpds.NormalInverseWishart`; sites it does not name keep
        ``pseudo_count``. A table is the Dirichlet posterior's mean
        (``estimate="mean"``, pgmpy's ``BayesianEstimator``) or mode (``"map"``, every
        pseudo-count >= 1); a linear Gaussian under a normal-inverse-Wishart is the
        posterior's joint mode. EM over gaps uses the same closed forms in its M-step.
    masks
        ``(n,)`` bool per discrete site, False where the row's value is missing (the
        row's value there is ignored), another way to mark missing labels. With gaps
        the fit is EM (see :func:`inference.fitting.missing.fit_missing`), started from
        each CPD's closed form on the rows that give its site and parents; ``FitResult.losses`` is its
        per-row negative log-likelihood (missing values summed out) at the start and
        after each step, never rising, and ``FitResult.log_likelihoods`` the summed
        log-likelihood.
    steps, lr, l2, tol, progress
        ``steps``: the most Newton iterations of a softmax fit, or EM steps with gaps.
        ``l2``: the precision of the softmax slopes' Gaussian prior. ``tol``: EM has
        converged when a step gains less than ``tol`` (relative) per row (default:
        :func:`~inference.fitting.missing.fit_missing`'s, tighter where every site is a
        table); a softmax or gradient fit when its loss changes by less (default 1e-6). ``lr``: the
        gradient route's (:func:`fit_gradient`), for a kind with neither a closed form
        nor a ``maximise`` method. ``progress`` shows bars (over chunks, CPDs, steps).

    Returns
    -------
    FitResult
        The fitted parameters (``params``); for an iterative fit (EM over gaps, a softmax's
        Newton iterations) its loss curve and whether it settled.
    """
    if isinstance(prior, int | float) and not isinstance(prior, bool):
        pseudo_count = prior  # a number is the symmetric pseudo-count itself
    em_tol, tol = tol, 1e-6 if tol is None else tol  # EM's default is fit_missing's
    check_settings(
        pseudo_count=pseudo_count, min_variance=min_variance, steps=steps, lr=lr, l2=l2, tol=tol
    )
    refuse_adaptive(net, "fit")
    alpha = site_priors(net, prior, pseudo_count, estimate)
    data = as_data(net, data)
    if not isinstance(data, Mapping | TrainingRows):
        if isinstance(data, str | bytes) or not isinstance(data, Iterable):
            raise ValueError(
                "data must be a mapping of rows by site or an iterable of such chunks; got "
                f"{type(data).__name__}"
            )
        if masks:
            raise ValueError("masks need the rows in memory: give data as one mapping")
        stats = fit_statistics(net, data, progress=progress)
        if stats.gradient:
            kinds = "/".join(sorted({net.cpd(s).name for s in stats.gradient}))
            raise ValueError(
                f"sites {list(stats.gradient)} are {kinds} CPDs (no closed form): their "
                "gradient fit needs the rows in memory; give data as one mapping"
            )
        cpds = params_from_statistics(net, stats, alpha, min_variance)
        return FitResult(NetworkParams(cpds, pseudo_count, net, stats.sites))
    rows = read_rows(net, data, masks)
    enc, gaps = rows.enc, rows.gaps
    if gaps or continuous_gaps(net, enc):
        return fit_missing(
            net,
            enc,
            gaps,
            init=available_case_start(net, enc, gaps, pseudo_count, min_variance, prior=alpha),
            pseudo_count=pseudo_count,
            prior=alpha,
            min_variance=min_variance,
            l2=l2,
            steps=steps,
            tol=em_tol,
            progress=progress,
        )
    stats = statistics(net, enc)
    cpds = params_from_statistics(net, stats, alpha, min_variance)
    params = NetworkParams(cpds, pseudo_count, net, stats.sites)
    return _fit_open_forms(net, enc, params, steps=steps, lr=lr, l2=l2, tol=tol, progress=progress)


def _fit_open_forms(
    net: EffectNetwork,
    enc: Evidence,
    params: NetworkParams,
    *,
    steps: int,
    lr: float,
    l2: float,
    tol: float,
    progress: bool,
) -> FitResult:
    """Complete rows: the CPDs without a closed form, from the closed form's start.

    A kind with a ``maximise`` method (softmax: Newton's method per parent
    configuration) finds its optimum itself; any other goes to :func:`fit_gradient`.
    ``losses`` are the per-row penalised negative log-likelihood of the maximised CPDs at
    the start and after each Newton iteration.
    """
    open_forms = [s.name for s in net.sites if not net.cpd(s.name).closed_form]
    if not open_forms:
        return FitResult(params)
    maximised = [s for s in open_forms if callable(getattr(net.cpd(s), "maximise", None))]
    cpds = dict(params.cpds)
    curves, unsettled = [], []
    for site in tqdm(maximised, desc="fit (Newton)", disable=not progress):
        result = maximise_site(net, enc, site, params[site], l2=l2, steps=steps)
        cpds[site] = result.params
        curves.append(result.objectives)
        if not result.converged:
            unsettled.append(site)
    longest = max((len(c) for c in curves), default=0)
    losses = tuple(sum(c[min(i, len(c) - 1)] for c in curves) / enc.n_rows for i in range(longest))
    if unsettled:
        warnings.warn(
            f"the Newton fit of {unsettled} did not settle in {steps} steps (its gradient "
            "is above the tolerance; the classes may be separated by the inputs, which "
            "l2 > 0 keeps finite); raise steps",
            ConvergenceWarning,
            stacklevel=3,
        )
    params = NetworkParams(cpds, params.pseudo_count, net, params.statistics)
    rest = [s for s in open_forms if s not in maximised]
    if not rest:
        return FitResult(params, losses, not unsettled)
    result = fit_gradient(
        net, enc, init=params, sites=rest, steps=steps, lr=lr, l2=l2, tol=tol, progress=progress
    )
    return FitResult(result.params, losses + result.losses, result.converged and not unsettled)


def fit_statistics(
    net: EffectNetwork, chunks: Iterable[Mapping[str, object]], *, progress: bool = False
) -> Statistics:
    """The summed sufficient statistics of row chunks (each checked as :func:`fit` does).

    Statistics of partitions computed apart (on a cluster's workers, say) add up with
    ``+``; :func:`inference.fitting.sufficient_statistics.params_from_statistics` turns the sum into
    parameters.

    Parameters
    ----------
    net
        The network whose CPDs the statistics are for.
    chunks
        An iterable of row chunks, each as :func:`fit` reads training rows; read once. One
        mapping of rows or one ``DataFrame`` is one chunk.
    progress
        Show a progress bar over the chunks.

    Returns
    -------
    Statistics
        Every closed-form site's sufficient statistics, summed over the chunks.
    """
    refuse_adaptive(net, "fit_statistics")
    if isinstance(chunks, Mapping | TrainingRows) or is_frame(chunks):
        chunks = [chunks]  # one partition's rows, not an iterable of chunks
    total, empty = None, 0
    for i, chunk in enumerate(
        tqdm(chunks, desc="fit (chunks)", unit="chunk", disable=not progress)
    ):
        chunk = as_data(net, chunk)  # a chunk may be a DataFrame
        if not isinstance(chunk, Mapping | TrainingRows):
            raise ValueError(
                f"data must be a mapping of rows or an iterable of such chunks; got a "
                f"chunk of type {type(chunk).__name__}"
            )
        try:
            rows = read_rows(net, chunk)
        except NoRows:  # a chunk of no rows (a split's last) adds nothing
            empty += 1
            continue
        missing = rows.missing()
        if missing:
            raise ValueError(
                f"chunk {i}: its rows miss values of {rows.missing_text()}; chunks are "
                "summed as sufficient statistics, and EM over missing values revisits every "
                "row each step: give the rows as one mapping or DataFrame"
            )
        total = statistics(net, rows.enc).merged_into(total)
    if total is None:
        why = f"each of the {empty} chunks has 0 rows" if empty else "the iterable was empty"
        raise ValueError(f"no training rows: {why}")
    return total


def fit_gradient(
    net: EffectNetwork,
    data: Mapping[str, object],
    *,
    init: NetworkParams | None = None,
    sites: list[str] | None = None,
    masks: Mapping[str, torch.Tensor] | None = None,
    steps: int = 1000,
    lr: float = 0.05,
    l2: float = 0.01,
    tol: float = 1e-6,
    pseudo_count: float = 0.01,
    progress: bool = False,
) -> FitResult:
    """Maximum likelihood by gradient: ``TraceEnum_ELBO`` with an empty guide.

    With no latent continuous site (unknown parameters are integrated out in closed
    form, missing discrete values are enumerated) the ELBO *is* the marginal
    log-likelihood, so its gradient is the likelihood's. ``sites`` limits the fitted
    CPDs (the others stay at ``init``); ``init`` defaults to uniform tables, standard
    Gaussians and zero softmax weights. The optimiser's tensors are local: Pyro's global
    parameter store is neither read nor changed.

    Softmax weights carry a Gaussian prior of precision ``l2`` (``l2 / 2 * |W|^2`` is
    added to the negative log-likelihood; their offsets are free): it keeps slopes finite
    where the data separate the classes and pulls extrapolation far from the data towards
    the offsets' frequencies. ``l2 = 0`` is plain maximum likelihood.

    With every value given (no gaps in ``masks``) the loss is smooth and, for softmax CPDs,
    convex: L-BFGS with a strong-Wolfe line search minimises it in at most ``steps``
    iterations (``lr`` unused). With gaps, Adam with ``lr`` runs ``steps`` steps. The fit
    has settled when the loss changes by less than ``tol`` (relative) per step; otherwise
    a :class:`ConvergenceWarning` names the CPDs and ``FitResult.converged`` is False.

    Parameters
    ----------
    net
        The network to fit.
    data
        Training rows by site name, as :func:`fit` reads them (no row chunks).
    init
        The parameters to start from (and to keep for the sites not in ``sites``).
    sites
        The sites whose CPDs are fitted (default: every site).
    masks
        ``(n,)`` bool per discrete site, False where a row's value is missing.
    steps, lr, l2, tol
        The most iterations (L-BFGS) or steps (Adam), Adam's learning rate, the softmax
        slopes' prior precision, and the relative change of the loss under which the fit
        has settled.
    pseudo_count
        The pseudo-count policy of the closed-form sites.
    progress
        Show a progress bar over the steps.

    Returns
    -------
    FitResult
        The fitted parameters, the loss curve and whether it settled.
    """
    check_settings(pseudo_count=pseudo_count, steps=steps, lr=lr, l2=l2, tol=tol)
    refuse_adaptive(net, "fit_gradient")
    enc = training_rows(net, data)
    masks = row_masks(net, masks, enc.n_rows)
    if init is not None:
        check_params(net, init)
    init = init or initial_params(net, pseudo_count)
    sites = list(init.cpds) if sites is None else list(sites)
    unknown = [s for s in sites if s not in init.cpds]
    if unknown:
        raise ValueError(f"sites {unknown} are not sites of this network")

    # Unconstrained tensors, one set per fitted CPD, each kind's own parametrisation.
    free = {site: net.cpd(site).free(init.cpds[site]) for site in sites}
    tensors = [t.detach().clone().requires_grad_() for f in free.values() for t in f.values()]
    it = iter(tensors)
    free = {site: {k: next(it) for k in f} for site, f in free.items()}

    def current() -> NetworkParams:
        cpds = dict(init.cpds)
        for site, f in free.items():
            cpds[site] = net.cpd(site).bound(f, init.cpds[site])
        return NetworkParams(cpds, init.pseudo_count, net)

    n = enc.n_rows
    # With every value given, the end sites that are not fitted add a constant to the
    # loss: leave them out (with gaps, their factors join the marginal and stay).
    gaps = any(not bool(m.all()) for m in masks.values())
    end_sites = None if gaps else {s for s in sites if net.site(s).role == "end"}

    def model():
        # Scale to a per-row loss so that one learning rate suits any data size.
        with pyro.poutine.scale(scale=1.0 / n):
            effect_model(net, current(), enc, masks=masks, collapse=True, end_sites=end_sites)

    def guide():
        pass

    elbo = TraceEnum_ELBO(max_plate_nesting=1)
    slopes = [t for site, f in free.items() for t in net.cpd(site).penalised(f)]
    losses: list[float] = []

    def objective() -> torch.Tensor:
        with pyro.validation_enabled(False):  # the rows were validated when encoded
            loss = elbo.differentiable_loss(model, guide)
        if slopes and l2:
            loss = loss + (0.5 * l2 / n) * sum(w.square().sum() for w in slopes)
        return loss

    bar = tqdm(total=steps, desc="fit (gradient)", disable=not progress)
    if gaps:
        optimiser = torch.optim.Adam(tensors, lr=lr)
        for _ in range(steps):
            optimiser.zero_grad()
            loss = objective()
            loss.backward()
            optimiser.step()
            losses.append(loss.item())
            bar.update()
        settled = len(losses) > 1 and _settled(losses[-2], losses[-1], tol)
    else:
        optimiser = torch.optim.LBFGS(
            tensors,
            lr=1.0,
            max_iter=steps,
            tolerance_grad=1e-9,
            tolerance_change=tol * 1e-3,
            history_size=20,
            line_search_fn="strong_wolfe",
        )

        def closure() -> torch.Tensor:
            optimiser.zero_grad()
            loss = objective()
            loss.backward()
            losses.append(loss.item())
            return loss

        optimiser.step(closure)
        state = optimiser.state[optimiser.param_groups[0]["params"][0]]  # LBFGS keeps it there
        iterations = state.get("n_iter", steps)
        exhausted = iterations >= steps or state.get("func_evals", 0) >= steps * 5 // 4
        bar.update(min(iterations, steps))
        with torch.no_grad():
            grad = max(float(t.grad.abs().max()) for t in tensors if t.grad is not None)
        # L-BFGS stops early only on its own tolerances (gradient or change of the loss)
        settled = not exhausted or grad <= 1e-7
    bar.close()
    if not settled:
        warnings.warn(
            f"the gradient fit of {sites} did not settle in {steps} steps (last relative "
            f"change of the loss above tol={tol:g}); raise steps, or lr with masks",
            ConvergenceWarning,
            stacklevel=2,
        )
    with torch.no_grad():
        params = current().map(lambda t: t.detach().clone())
    return FitResult(params, tuple(losses), settled)


def _settled(before: float, after: float, tol: float) -> bool:
    return abs(before - after) <= tol * max(1.0, abs(after))
