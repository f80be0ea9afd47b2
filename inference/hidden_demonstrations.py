r"""EM over demonstrations that hide state values: forward-backward over each time's hidden part.

A state feature (discrete, with an initial node) hidden at time ``t`` is step ``t - 1``'s
end and step ``t``'s start at once, so the steps are no longer separate rows: the
demonstration is a hidden Markov model over each time's hidden configurations (the
states that agree with what the time shows, :mod:`inference.sequences.hidden_steps`)::

    H_0 ──a_0──> H_1 ──a_1──> H_2  ...  ──a_{T-1}──> H_T      H_t: the discrete state

**The model fitted.** As :func:`~inference.watching.fit_demonstrations` reads
demonstrations whose states are all shown, every step is a row of the network: its start
drawn from the initial tables, its action from the action table, its end from the end
tables. A demonstration's likelihood is the sum over its hidden configurations of the
product of its steps' rows::

    L = sum over H_0..H_T of  prod_t  p(H_t, x_t) p(a_t) p(H_{t+1}, x_{t+1} | H_t, x_t, a_t)

(``a_t`` summed too where the step is not labelled). Every step's start counts in the
initial tables, not time 0's alone: with every state shown this is the per-step fit
exactly, and the initial tables count the starts of all the steps.
:func:`~inference.sequences.explanation.explain` reads a demonstration with time 0 alone
drawn from them and the actions from a prior it is given; the model here multiplies in
every start's initial probability as well, which weighs a hidden start's configurations
by the initial tables at every time.

**E-step.** Each step's table of ``log p(H_t, x_t) + log p(a) + log p(H_{t+1}, x_{t+1} |
H_t, x_t, a)`` over (start configuration, action, end configuration), read off the
traced model by explain's machinery (:func:`~inference.sequences.hidden_steps.read_step_tables`,
a labelled step's other actions ruled out), and its forward and backward messages
(:func:`~inference.sequences.hidden_paths.forward_backward`) give each step's two-slice
posterior over (configuration at ``t``, action, configuration at ``t + 1``) given the whole
demonstration, exactly.

**Continuous features.** A continuous value shown at both ends of a step is part of the
step's observation: the step table holds its linear Gaussian's density (at the start
under the initial tables, at the end under the end tables), so the messages weigh every
configuration by it. ``x_t`` above holds them.

**M-step.** Each step is completed once per entry of that posterior's support (the
configuration pair read as full states, the action, the continuous values as shown),
weighted by the entry, and the toolkit's closed forms fit the weighted rows
(:func:`~inference.fitting.sufficient_statistics.statistics`,
:func:`~inference.fitting.sufficient_statistics.params_from_statistics`, with the
pseudo-count): the tables on the expected counts, the linear Gaussians on the weighted
moments. Ordinary training rows (``rows``) join it: each completed over what it misses
(:func:`~inference.fitting.completion.completed_rows`), its expected statistics added to
the steps', its log-likelihood to ``L``. EM on ``L`` then never lowers it.

**Action parameters.** A step's parameter value (recorded, or not) and its cluster
belong to that step alone: given the step's two configurations and its action they
depend on no other step. So a network with parameters reads each (pair, action) entry of
a step's table as the step's whole row's likelihood, its cluster summed and an unrecorded
value integrated in closed form through it (the collapsed model, or the joint Gaussian
of :func:`~inference.fitting.completion.completed_gaussian` where a continuous value is
also hidden); a recorded value is read with its cell as cluster (the grid layout's
reading of a row) and rules out the actions that do not use it. The forward-backward is
then exact as above, and the M-step completes each weighted (pair, action) row once more
over its cluster and unrecorded value
(:func:`~inference.fitting.completion.completed_rows`, the weights multiplied): each
cluster's Gaussian refitted on the value's conditional moments. Parameters of the
adaptive layout are refused (no cell reads a recorded value's cluster).

Scope: networks whose sites all have a closed form (tables and linear Gaussians), their
parameters of the grid layout; a continuous feature with an initial node is shown at
every time (hidden, it would be a Gaussian carried from step to step). An outcome feature
(``initial=False``) that a step does not show is summed inside the step's table, and the
M-step completes it too: each completed row once per value of a discrete one, a
continuous one at its conditional mean with its conditional covariance added to the sums,
weighted by its posterior given the row (the step's states and action separate it from
the other steps, so that posterior is exact).

**Cost.** A step's table spans (configurations of its start) x actions x (configurations
of its end): ``A`` entries where both ends show every state feature, ``2^(h + h')`` times
as many where they hide ``h`` and ``h'`` binary ones, read once per distinct
(observation, start, end) per EM step (a step whose continuous values are its own reads
its table alone; with action parameters once per pair and action); the messages and the completed rows are linear in those entries. A step past
:data:`~inference.sequences.hidden_steps.MAX_STEP_TABLE` entries is refused, naming it.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from effect_networks.inference.exact.enumeration import enumerate_model, row_chunks
from effect_networks.inference.exact.gaussian_gaps import continuous_gaps
from effect_networks.inference.fitting.completion import (
    completed_gaussian,
    completed_rows,
    open_parameters,
)
from effect_networks.inference.fitting.missing import actions_allowed
from effect_networks.inference.fitting.result import ConvergenceWarning, FitResult
from effect_networks.inference.fitting.rows import check_settings, missing_masks
from effect_networks.inference.fitting.sufficient_statistics import (
    Statistics,
    params_from_statistics,
    statistics,
)
from effect_networks.inference.sequences.demonstration import Demonstrations
from effect_networks.inference.sequences.hidden_paths import forward_backward
from effect_networks.inference.sequences.hidden_steps import (
    StateCodes,
    hidden_configurations,
    read_step_tables,
    step_pairs,
)
from effect_networks.inference.sequences.states import state_features
from effect_networks.models.declaration import ACTION, DTYPE, Discrete, EffectNetwork
from effect_networks.models.evidence import Evidence
from effect_networks.models.params import NetworkParams
from effect_networks.models.sites import end_site, initial_site

__all__ = ["MIN_VARIANCE", "CompletedSteps", "completed_steps", "fit_hidden_states"]

#: The linear Gaussians' covariance floor (:func:`~inference.fitting.missing.fit_missing`'s).
MIN_VARIANCE = 1e-6


@dataclass(frozen=True)
class CompletedSteps:
    """An E-step's result (:func:`completed_steps`).

    ``rows``: every step completed once per entry of its posterior's support (states,
    action, hidden outcomes; a hidden continuous outcome at its conditional mean);
    ``weights`` ``(m,)`` the entries' posterior probabilities (each step's sum to 1);
    ``log_likelihoods`` ``(n,)`` each demonstration's log-likelihood (the model of the
    module: every step a row, hidden values and unlabelled actions summed out);
    ``moments``: per linear Gaussian, the sums of the hidden continuous outcomes'
    conditional covariances (empty where every continuous value is shown).
    """

    rows: Evidence
    weights: torch.Tensor
    log_likelihoods: torch.Tensor
    moments: dict = field(default_factory=dict)

    @property
    def log_likelihood(self) -> float:
        """The demonstrations' summed log-likelihood."""
        return float(self.log_likelihoods.sum())

    def statistics(self, net: EffectNetwork) -> Statistics:
        """The expected sufficient statistics: the weighted rows' sums and the covariances'."""
        return _with_moments(statistics(net, self.rows, self.weights), self.moments)


def fit_hidden_states(
    net: EffectNetwork,
    demonstrations: Sequence[Sequence[dict]],
    labels: Sequence[Sequence[int | None]],
    *,
    init: NetworkParams,
    rows: Evidence | None = None,
    masks: Mapping[str, torch.Tensor] | None = None,
    parameters: Sequence[Mapping[str, np.ndarray] | None] | None = None,
    pseudo_count: float = 0.01,
    steps: int = 500,
    tol: float = 1e-6,
) -> FitResult:
    """EM on demonstrations whose state values may be hidden, exact for the module's model.

    Parameters
    ----------
    net
        A network whose sites all have a closed form, its action parameters of the grid
        layout.
    demonstrations
        Demonstrations, each ``T + 1 >= 2`` states ``{feature: value}``: a discrete label
        or None (or absent: hidden); a continuous feature's ``(d,)`` numbers, shown at every
        time where it has an initial node (an outcome's may be None or NaN).
    labels
        Per demonstration ``T`` action indices, None where the step is not labelled.
    rows, masks
        Ordinary training rows fitted beside the demonstrations (checked and encoded, as
        :func:`~inference.fitting.reading.read_rows` gives them; NaN where a continuous
        value is missing), and per discrete site ``(m,)`` bool, False where a row misses
        its value. Their expected statistics join the M-step's, their log-likelihood the
        objective.
    parameters
        Per demonstration (None: nothing recorded), ``{parameter site: (T, d) values}``:
        each step's recorded value of the parameter, NaN where not recorded (a hidden value
        of its step where its action uses the parameter, integrated out through the
        parameter's clusters).
    init, pseudo_count, steps, tol
        EM's start, the closed forms' pseudo-count, the most EM steps, and the tolerance:
        the fit has converged when a step raises the per-step log-likelihood by less than
        ``tol`` times its magnitude (absolute below 1 nat), or would lower it (a
        pseudo-count's pull near the optimum); such a step is not taken.

    Returns
    -------
    FitResult
        ``log_likelihoods``: the summed log-likelihood (the demonstrations' and the rows')
        at the start and after each step taken (never falling); ``losses``: minus the same
        per step or row.
    """
    _check_scope(net)
    check_settings(pseudo_count=pseudo_count, steps=steps, tol=tol)
    if rows is not None:
        masks = missing_masks(net, masks or {}, rows.n_rows)
    n_steps = sum(len(d) - 1 for d in demonstrations) + (0 if rows is None else rows.n_rows)
    params = init
    parts = (demonstrations, labels, parameters, rows, masks)
    expected, log_lik = _expected(net, params, *parts)
    log_liks = [log_lik]
    converged = False
    for _ in range(steps):
        cpds = params_from_statistics(net, expected, pseudo_count, MIN_VARIANCE)
        proposal = NetworkParams(cpds, params.pseudo_count, net)
        stats, log_lik = _expected(net, proposal, *parts)
        if not log_lik >= log_liks[-1]:  # a pseudo-count's pull, or NaN
            converged = True
            break
        params, expected = proposal, stats
        log_liks.append(log_lik)
        gain = (log_liks[-1] - log_liks[-2]) / n_steps
        if gain <= tol * max(1.0, abs(log_liks[-1] / n_steps)):
            converged = True
            break
    if not converged:
        warnings.warn(
            f"EM over the demonstrations' hidden states did not settle in {steps} steps; "
            "raise steps",
            ConvergenceWarning,
            stacklevel=2,
        )
    losses = tuple(-x / n_steps for x in log_liks)
    return FitResult(params, losses, converged, tuple(log_liks), tol, steps)


def _expected(
    net, params, demonstrations, labels, parameters, rows, masks
) -> tuple[Statistics, float]:
    """The E-step over the demonstrations and the training rows: statistics, log-likelihood."""
    completed = completed_steps(net, params, demonstrations, labels, parameters)
    stats, log_lik = completed.statistics(net), completed.log_likelihood
    if rows is not None:
        done = completed_rows(net, params, rows, masks, actions_allowed(net, rows, masks))
        stats = stats + _with_moments(statistics(net, done.rows, done.weights), done.moments)
        log_lik += done.log_lik
    return stats, log_lik


def _with_moments(stats: Statistics, moments: dict) -> Statistics:
    """``stats`` with the conditional covariances' sums added to their linear Gaussians."""
    sites = dict(stats.sites)
    for site, extra in moments.items():
        sites[site] = sites[site] + extra
    return Statistics(sites, stats.rows, stats.gradient)


def completed_steps(
    net: EffectNetwork,
    params: NetworkParams,
    demonstrations: Sequence[Sequence[dict]],
    labels: Sequence[Sequence[int | None]],
    parameters: Sequence[Mapping[str, np.ndarray] | None] | None = None,
) -> CompletedSteps:
    """The E-step: every step's two-slice posterior given its whole demonstration, as rows.

    ``parameters`` as :func:`fit_hidden_states` takes them. Demonstrations of the same
    length are read as one batch. ``ValueError`` names a
    demonstration that has probability 0 under ``params``.
    """
    _check_scope(net)
    by_length: dict[int, list[int]] = {}
    for i, demo in enumerate(demonstrations):
        by_length.setdefault(len(demo), []).append(i)
    parts, weights, moments = [], [], {}
    log_liks = torch.empty(len(demonstrations), dtype=DTYPE)
    for which in by_length.values():
        rows, w, extra, lls = _completed_batch(
            net,
            params,
            [demonstrations[i] for i in which],
            [labels[i] for i in which],
            _stacked(net, parameters, which, len(demonstrations[which[0]]) - 1),
        )
        bad = (lls == -torch.inf).nonzero()
        if len(bad):
            raise ValueError(
                f"demonstration {which[int(bad[0])]} has probability 0 under the parameters "
                "(every completion of its hidden values and actions is impossible): no posterior "
                "exists; start from tables with a pseudo-count"
            )
        log_liks[which] = lls
        parts.append(rows)
        weights.append(w)
        for site, value in extra.items():
            moments[site] = moments[site] + value if site in moments else value
    rows = {site: torch.cat([p[site] for p in parts]) for site in parts[0]}
    n = sum(p.n_rows for p in parts)
    return CompletedSteps(Evidence(net, rows, n), torch.cat(weights), log_liks, moments)


def _check_scope(net: EffectNetwork) -> None:
    open_forms = [s.name for s in net.sites if not net.cpd(s.name).closed_form]
    if open_forms:
        raise ValueError(
            "EM over hidden state values covers networks whose sites all have a closed form; "
            f"this one has sites without a closed form {open_forms}: show every state feature "
            "at every time"
        )
    adaptive = [p.name for p in net.parameters if p.adaptive]
    if adaptive:
        raise ValueError(
            f"EM over hidden state values reads a recorded parameter's cluster as its value's "
            f"cell; parameters {adaptive} have the adaptive layout: declare them with "
            "layout='grid'"
        )


def _stacked(net, parameters, which, steps) -> dict[str, np.ndarray]:
    """The recorded values of demonstrations ``which`` (of ``steps`` steps), ``(n * T, d)``."""
    out = {}
    for m in net.mixtures:
        column = np.full((len(which), steps, m.parameter.dim), np.nan)
        for k, i in enumerate(which):
            given = None if parameters is None or parameters[i] is None else parameters[i]
            if given is not None and m.value.site in given:
                column[k] = np.asarray(given[m.value.site], dtype=np.float64).reshape(steps, -1)
        out[m.value.site] = column.reshape(len(which) * steps, -1)
    return out


def _batch(net, demonstrations) -> dict[str, np.ndarray]:
    """The demonstrations of one length in explain's batch form (an outcome hidden at time 0)."""
    n, times = len(demonstrations), len(demonstrations[0])
    batch = {}
    for f in net.features:
        if isinstance(f, Discrete):
            column = np.empty((n, times), dtype=object)
        else:
            column = np.full((n, times, f.dim), np.nan)
        for i, demo in enumerate(demonstrations):
            for t, state in enumerate(demo):
                value = state.get(f.name) if (f.initial or t) else None
                if isinstance(f, Discrete):
                    column[i, t] = value
                elif value is not None:
                    column[i, t] = np.asarray(value, dtype=np.float64).reshape(f.dim)
        batch[f.name] = column
    return batch


def _completed_batch(net, params, demonstrations, labels, parameters=None):
    """:func:`completed_steps` for demonstrations of one length.

    ``parameters``: per parameter site ``(n * T, d)`` the steps' recorded values (NaN where
    not recorded). The completed rows, their weights, the covariances' sums, ``(n,)``
    log-likelihoods.
    """
    n, steps = len(demonstrations), len(demonstrations[0]) - 1
    a = len(net.actions)
    demo = Demonstrations.read(net, None, _batch(net, demonstrations))
    codes = StateCodes.of(state_features(net), None)
    configs = hidden_configurations(demo, codes)
    pairs = step_pairs(configs, (n, steps), a)
    label = torch.tensor(
        [-1 if x is None else int(x) for marks in labels for x in marks], dtype=torch.long
    )[pairs.step]
    other = (label[:, None] >= 0) & (torch.arange(a) != label[:, None])
    if net.mixtures:  # each (pair, action)'s whole row, its cluster and value summed
        parameters = parameters or {}
        every = torch.arange(len(pairs.step))
        pair, action = every.repeat_interleave(a), torch.arange(a).repeat(len(every))
        rows, masks, unrecorded = _step_rows(net, codes, demo, configs, pairs, parameters)(
            pair, action
        )
        factor = _row_log_likelihoods(net, params, rows, masks, unrecorded).reshape(-1, a)
        other = other | _unused_records(net, parameters, pairs.step)
    else:  # every step's start drawn from the initial tables: the pair's whole row
        tables = read_step_tables(net, params, codes, demo, configs, pairs, tails=False)
        factor = tables.log_step + tables.log_start[:, None]  # (P, A)
    factor = factor.masked_fill(other, -torch.inf)
    summed = factor.logsumexp(-1)
    first = torch.zeros(len(configs.state), dtype=DTYPE)
    alpha, beta, log_liks = forward_backward(configs, pairs, summed, first, (n, steps))
    if bool((log_liks == -torch.inf).any()):
        return None, None, {}, log_liks
    z = log_liks[pairs.step // steps]
    joint = alpha[pairs.start, None] + factor + beta[pairs.end, None] - z[:, None]
    weight = joint.exp()
    pair, action = (weight > 0).nonzero(as_tuple=True)
    rows, masks, unrecorded = _step_rows(net, codes, demo, configs, pairs, parameters or {})(
        pair, action
    )
    weights = weight[pair, action]
    if not masks and not continuous_gaps(net, rows) and not open_parameters(unrecorded):
        return rows, weights, {}, log_liks
    # the row's states and action given, its hidden outcomes, cluster and unrecorded value
    # depend on no other step: their posterior given the row alone is exact
    done = completed_rows(net, params, rows, masks, unrecorded=unrecorded, row_weights=weights)
    return done.rows, done.weights, done.moments, log_liks


def _step_rows(net, codes, demo, configs, pairs, parameters):
    """The rows of (pair, action) entries: a function of ``pair`` and ``action`` ``(m,)``.

    Each row: the pair's configurations read as full states, the action, the step's
    continuous values and outcomes as shown, each parameter's recorded value (NaN where
    not recorded or not used by the action) and its cell. Returns the rows, the hidden
    outcomes' masks and the unrecorded values' masks.
    """
    n, steps = demo.shape

    def rows_of(pair, action):
        start = codes.digits(configs.state[pairs.start[pair]])
        end = codes.digits(configs.state[pairs.end[pair]])
        values = {ACTION: action}
        for j, f in enumerate(state_features(net)):
            values[initial_site(f.name)] = start[:, j]
            values[end_site(f.name)] = end[:, j]
        step = pairs.step[pair]
        for name, x in demo.continuous.items():  # shown at both ends, or an outcome's NaN
            if net.feature(name).initial:
                values[initial_site(name)] = torch.from_numpy(x[:, :-1].reshape(n * steps, -1))[
                    step
                ]
            values[end_site(name)] = torch.from_numpy(x[:, 1:].reshape(n * steps, -1))[step]
        masks = {}
        for name, index in demo.outcomes.items():
            outcome = torch.from_numpy(index[:, 1:].reshape(-1))[step]
            values[end_site(name)] = outcome.clamp(min=0)
            if bool((outcome < 0).any()):
                masks[end_site(name)] = outcome >= 0
        unrecorded = {}
        for m in net.mixtures:
            site = m.value.site
            given = parameters.get(site)
            if given is None:
                theta = torch.full((len(step), m.parameter.dim), torch.nan, dtype=DTYPE)
            else:
                theta = torch.as_tensor(given, dtype=DTYPE)[step]
            uses = m.in_use(action)
            theta = torch.where(uses[:, None], theta, torch.nan)
            unrecorded[site] = torch.isnan(theta).any(-1) & uses
            values[site] = theta
            values[m.cluster.site] = m.cells(theta, action)
        # a hidden continuous value stays NaN (what the completion integrates), past the
        # encoding's check for finite values
        shown = {s: v.nan_to_num() if v.is_floating_point() else v for s, v in values.items()}
        numbers = {s: v.to(DTYPE) for s, v in values.items() if v.is_floating_point()}
        rows = Evidence(net, dict(net.encode_indices(shown)) | numbers, len(action))
        return rows, masks, unrecorded

    return rows_of


def _unused_records(net, parameters, step) -> torch.Tensor:
    """``(P, A)`` bool: the actions a pair's step rules out by recording a parameter's value.

    A recorded value says the step's action uses the parameter.
    """
    out = torch.zeros(len(step), len(net.actions), dtype=torch.bool)
    for m in net.mixtures:
        given = parameters.get(m.value.site)
        if given is None:
            continue
        recorded = ~torch.isnan(torch.as_tensor(given, dtype=DTYPE)).any(-1)[step]
        out |= recorded[:, None] & ~m.uses[None, :]
    return out


def _row_log_likelihoods(net, params, rows, masks, unrecorded) -> torch.Tensor:
    """``(m,)`` each row's log-likelihood, its hidden outcomes, cluster and value summed out."""
    if continuous_gaps(net, rows) or open_parameters(unrecorded):
        return completed_gaussian(
            net, params, rows, masks, None, unrecorded, posterior=False
        ).per_row
    size = math.prod(net.site(site).size for site in masks)
    out = []
    for chunk in row_chunks(rows.n_rows, size):
        part = {site: mask[chunk] for site, mask in masks.items()}
        out.append(enumerate_model(net, params, rows.rows(chunk), masks=part).log_evidence)
    return torch.cat(out)
