r"""Learn from watching: fit a network on demonstrations whose actions were not labelled.

A demonstration is a sequence of observed scene states; step ``t`` starts in state ``t``
and ends in state ``t + 1``. A robot that watches a person sees the states change, not
the names of the actions; some steps may be labelled (the person said "now I push").
:func:`fit_demonstrations` fits the network by EM over the unknown actions:

* **E-step.** Each unlabelled step's posterior over the actions,
  ``P(a | s_t, s_{t+1}) ∝ P(a | s_t) P(s_{t+1} | s_t, a)``, and over the values the step
  does not show that belong to it alone (an outcome feature, a continuous end value),
  summed out exactly by the network's own sums. Where every state feature is observed at
  every time this *is* the forward-backward of the demonstrations' hidden Markov model:
  the states separate the steps, so the posterior of a step's action given the whole
  sequence is its posterior given its own two states.
* **M-step.** The toolkit's closed forms on the expected counts
  (:func:`~inference.fitting.missing.fit_missing`), the log-likelihood never falling.

Labelled steps and ordinary training rows (``rows=``) join the same fit. EM starts from
the labelled data's closed form, from the *effects' start* (every unlabelled step given
the action of the most common change it is nearest: an action is the change it causes,
so the steps that change the same features are grouped, the ``A`` most common changes
naming the ``A`` actions) and from ``restarts`` random tables, and keeps the start whose
fit has the highest likelihood.

**Identifiability.** Without any labelled step the likelihood does not change when the
actions' names are permuted: the actions are learned up to a relabelling. With labelled
steps the labels anchor the names; the result reports how well the learned network
recognises the labelled steps (``confidence``: the mean posterior of the label with the
label hidden; ``agreement``: the share whose most likely action is the label). Without
any, the actions are named by a reference network's tables where one is given
(``reference=``: the relabelling whose tables are closest to it, by total variation), and
the result says they are not identified (``identifiable=False``) otherwise.

**Hidden state values.** A state feature hidden at some time links the steps on either
side of it (its value at one step's end is its value at the next one's start): a hidden
state carried over time, and the steps are no longer separate rows. Where any
demonstration hides a state value, EM runs by forward-backward over each time's hidden
configurations instead (:mod:`inference.hidden_demonstrations`): exact for the model in
which every step is a row of the network (every step's start drawn from the initial
tables, as the per-step fit counts them), the log-likelihood never falling; with every
state shown it is the per-step fit above. Continuous features join that route where
their values are shown (a continuous outcome may be hidden: its step's table integrates
it), and so do training rows (``rows=``): their expected statistics join the M-step's,
their log-likelihood the objective, and so do action parameters, recorded or not (a
step's value and cluster touch that step alone, so its table sums them). A hidden
*continuous* state value is refused there, naming the demonstration, the time and the
feature: its posterior is a mixture of Gaussians whose components multiply with every
hidden step (a switching linear-Gaussian system), which no finite sum holds exactly; so
is a site without a closed form (a softmax).

**Action parameters.** A step may record its action's parameter (``parameters=``) or not.
A recorded value says the action uses the parameter, as a training row's does; an
unrecorded one is a hidden value of its step: the E-step's posterior is over the action
and the parameter's cluster with the value integrated out exactly, jointly Gaussian with
the continuous features it acts on (:mod:`inference.fitting.completion`), and the M-step
refits the clusters' table and Gaussians from the expected sums, beside hidden state
values as well. EM's starts read an unrecorded value as drawn uniformly over the
parameter's range (:mod:`inference.unrecorded_parameters`).
"""

from __future__ import annotations

import itertools
import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from effect_networks.inference.fitting.maximum_likelihood import fit
from effect_networks.inference.fitting.missing import available_case_start, fit_missing
from effect_networks.inference.fitting.reading import read_rows
from effect_networks.inference.fitting.result import ConvergenceWarning
from effect_networks.inference.hidden_demonstrations import fit_hidden_states
from effect_networks.inference.queries.action import infer_action
from effect_networks.inference.unrecorded_parameters import (
    for_actions,
    parameter_columns,
    placeholders,
    spread_values,
)
from effect_networks.models.cpds.table import TableParams
from effect_networks.models.declaration import ACTION, Continuous, Discrete, EffectNetwork
from effect_networks.models.params import NetworkParams, random_params
from effect_networks.models.sites import end_site, initial_site

#: The most actions whose relabellings are tried one by one (``A!`` of them).
MAX_PERMUTED_ACTIONS = 8


@dataclass(frozen=True)
class WatchedFit:
    """A network fitted on demonstrations (:func:`fit_demonstrations`).

    Attributes
    ----------
    params : NetworkParams
        The fitted tables, their actions named as the network declares them (aligned, see
        ``identifiable``).
    log_likelihoods : tuple of float
        The chosen run's summed log-likelihood at its start and after each EM step
        (never falling).
    converged : bool
        Whether the chosen run settled within ``tol``.
    starts : tuple of float
        The final log-likelihood of every start (``init``; or the labelled data's closed
        form first, where there is labelled data, then the effects' start, then the
        random ones).
    steps, labelled : int
        The demonstrations' steps, and how many of them were labelled.
    identifiable : bool
        Whether the actions' names are fixed by the data: by labelled steps or rows, or
        aligned to ``reference``. False: the actions are learned up to a relabelling.
    confidence, agreement : float
        On the labelled steps, the learned network's mean posterior of the label (the
        label hidden, given the values the step shows at its start and end), and the
        share whose most likely action is the label (NaN without labelled steps).
    """

    params: NetworkParams = field(repr=False)
    log_likelihoods: tuple[float, ...] = field(repr=False)
    converged: bool
    starts: tuple[float, ...]
    steps: int
    labelled: int
    identifiable: bool
    confidence: float
    agreement: float


def fit_demonstrations(
    net: EffectNetwork,
    demonstrations: Sequence[Sequence[Mapping[str, object]]],
    actions: Sequence[Sequence[str | None]] | None = None,
    *,
    rows: Mapping[str, object] | None = None,
    parameters: Sequence[Sequence[Mapping[str, object] | None]] | None = None,
    reference: NetworkParams | None = None,
    init: NetworkParams | None = None,
    restarts: int = 2,
    seed: int = 0,
    pseudo_count: float = 0.01,
    steps: int = 500,
    tol: float = 1e-6,
) -> WatchedFit:
    """Fit ``net`` on demonstrations whose actions may be unlabelled, by EM.

    Parameters
    ----------
    net
        The network (discrete and continuous features, action parameters of the grid
        layout).
    demonstrations
        Demonstrations, each a sequence of ``T + 1 >= 2`` states ``{feature: value}``;
        every continuous feature with an initial node is given at every time; an outcome
        feature (``initial=False``) or a continuous end value may be missing (absent,
        None, NaN). A discrete state feature (one with an initial node) may be hidden
        (absent, None) at some times where every site has a closed form: EM then sums the
        hidden states carried from step to step exactly, beside the continuous values,
        the action parameters and ``rows`` (the module's notes).
    actions
        Per demonstration, ``T`` labels: an action's name where the step was labelled,
        None where not (default: none labelled).
    rows
        Ordinary training rows (by site, as :func:`~inference.fitting.fit` takes them),
        fitted together with the demonstrations.
    parameters
        Per demonstration (None: nothing recorded), ``T`` entries: ``{parameter: value}``
        (``(d,)`` numbers, in the parameter's units) where the step recorded its action's
        parameter, None (or a mapping without it, or NaN) where not (default: none
        recorded). A recorded value
        says the step's action uses the parameter; an unrecorded one says nothing of the
        action, and where the action uses the parameter the value is a hidden value of its
        step, integrated out exactly through its clusters (the module's notes).
    reference
        Parameters whose tables name the actions, for aligning a fit without any label.
    init
        Start EM here alone (parameters fitted before, say), instead of the labelled
        data's closed form and the random starts.
    restarts, seed
        Random starts besides the labelled data's closed form, and their seed.
    pseudo_count, steps, tol
        As :func:`~inference.fitting.fit` takes them (EM's steps and its tolerance).

    Returns
    -------
    WatchedFit
        The fitted parameters, EM's curve, each start's result, and how the actions are
        named (``identifiable``, ``confidence``, ``agreement``).
    """
    adaptive = [p.name for p in net.parameters if p.adaptive]
    if adaptive:
        raise ValueError(
            f"parameters {adaptive} have the adaptive layout: fit_demonstrations integrates a "
            "parameter's value through the cells of the grid layout; declare them with "
            "layout='grid'"
        )
    if not isinstance(restarts, int) or restarts < 0:
        raise ValueError(f"restarts must be an int >= 0, got {restarts!r}")
    if isinstance(demonstrations, Mapping):
        demonstrations = _from_batch(net, demonstrations)
    steps_rows, labels = _step_rows(net, demonstrations, actions)
    unrecorded = parameter_columns(net, demonstrations, steps_rows, parameters)
    hidden = _hidden_state(net, demonstrations)
    if hidden is not None:
        _refuse_beside_hidden_states(net, demonstrations)
    data = _joined(net, steps_rows, rows)
    unrecorded = {s: _padded(u, len(data[ACTION])) for s, u in unrecorded.items()}
    read = read_rows(net, placeholders(net, data, unrecorded))
    enc, gaps = read.enc, read.gaps
    enc = enc | {s: torch.where(u[:, None], torch.nan, enc[s]) for s, u in unrecorded.items()}
    has_labels = labels.any() or (rows is not None and _labelled_rows(rows))
    inits = []
    if init is not None:
        inits.append(init)
    else:
        n_steps = len(steps_rows[ACTION])
        spread = spread_values(net, data, unrecorded, seed)  # the starts' stand-ins
        starts = [lambda: _effect_start(net, spread, n_steps, pseudo_count)]
        if has_labels:
            filled = enc | {s: torch.as_tensor(spread[s]) for s in unrecorded}
            starts.insert(0, lambda: available_case_start(net, filled, gaps, pseudo_count, 1e-6))
        for start in starts:
            try:
                inits.append(start())
            except ValueError:
                # hidden state values may leave a table without a row that gives its
                # family: that start does not exist, the random ones do
                if hidden is None:
                    raise
        inits += [random_params(net, seed + r) for r in range(restarts)]
    if not inits:
        raise ValueError("no labelled step and restarts=0: EM has no start")
    runs = []
    settings = {"pseudo_count": pseudo_count, "steps": steps, "tol": tol}
    if hidden is not None:
        marks = _label_indices(net, steps_rows[ACTION], demonstrations)
        n_steps = len(steps_rows[ACTION])
        training = None if rows is None else enc.rows(slice(n_steps, None))
        masks = {s: m[n_steps:] for s, m in gaps.items()}
        recorded = _by_demonstration(net, steps_rows, demonstrations)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        for init in inits:
            init = NetworkParams(init.cpds, pseudo_count, net)
            if hidden is None:  # a step hides its action and a few outcomes: completing
                # each row over them costs less than the families' contraction
                runs.append(
                    fit_missing(
                        net,
                        enc,
                        gaps,
                        init=init,
                        by_families=False,
                        unrecorded=unrecorded,
                        **settings,
                    )
                )
            else:
                runs.append(
                    fit_hidden_states(
                        net,
                        demonstrations,
                        marks,
                        init=init,
                        rows=training,
                        masks=masks,
                        parameters=recorded,
                        **settings,
                    )
                )
    finals = tuple(r.log_likelihoods[-1] if r.log_likelihoods else -math.inf for r in runs)
    best = runs[int(np.argmax(finals))]
    params = best.params
    identifiable = bool(has_labels)
    if not has_labels and reference is not None:
        params = _aligned(net, params, reference)
        identifiable = True
    elif not has_labels:
        warnings.warn(
            "no labelled step or row: the actions are learned up to a relabelling "
            "(pass reference= to name them, or label a few steps)",
            stacklevel=2,
        )
    confidence, agreement = _recognised(net, params, steps_rows, labels)
    return WatchedFit(
        params,
        best.log_likelihoods,
        best.converged,
        finals,
        int(labels.size),
        int(labels.sum()),
        identifiable,
        confidence,
        agreement,
    )


def _step_rows(net, demonstrations, actions):
    """One row per step (the action None where unlabelled), and which steps are labelled."""
    if isinstance(actions, np.ndarray):
        actions = actions.tolist()
    if not isinstance(demonstrations, Sequence):
        raise ValueError("demonstrations must be a sequence of demonstrations (lists of states)")
    if actions is not None and len(actions) != len(demonstrations):
        raise ValueError(
            f"actions has {len(actions)} demonstrations' labels, demonstrations {len(demonstrations)}"
        )
    out: dict[str, list] = {s.name: [] for s in net.sites if s.role in ("initial", "end")}
    out[ACTION] = []
    labelled = []
    for i, demo in enumerate(demonstrations):
        if isinstance(demo, Mapping) or not isinstance(demo, Sequence) or len(demo) < 2:
            raise ValueError(f"demonstration {i} must be a sequence of at least 2 states")
        marks = [None] * (len(demo) - 1) if actions is None else list(actions[i])
        if len(marks) != len(demo) - 1:
            raise ValueError(f"actions[{i}] has {len(marks)} labels for {len(demo) - 1} steps")
        for t, state in enumerate(demo):
            if not isinstance(state, Mapping):
                raise ValueError(
                    f"demonstration {i}, time {t}: a state is a mapping, got {state!r}"
                )
            unknown = set(state) - {f.name for f in net.features}
            if unknown:
                raise ValueError(f"demonstration {i}, time {t}: {sorted(unknown)} are not features")
        for t in range(len(demo) - 1):
            for f in net.features:
                if f.initial:
                    out[initial_site(f.name)].append(_value(f, demo[t].get(f.name)))
                out[end_site(f.name)].append(_value(f, demo[t + 1].get(f.name)))
            label = marks[t]
            if label is not None and label not in net.actions:
                raise ValueError(f"actions[{i}][{t}] = {label!r} is not one of {net.actions}")
            out[ACTION].append(label)
            labelled.append(label is not None)
    if not labelled:
        raise ValueError("no demonstration has a step")
    rows = {}
    for site, values in out.items():
        spec = net.site(site)
        if spec.discrete:
            column = np.empty(len(values), dtype=object)
            column[:] = values
            rows[site] = column
        else:
            rows[site] = np.asarray(values, dtype=np.float64).reshape(len(values), -1)
    return rows, np.asarray(labelled)


def _hidden_state(net, demonstrations) -> tuple[int, int, str] | None:
    """The first (demonstration, time, feature) that hides a state value, None if none does."""
    for i, demo in enumerate(demonstrations):
        for t, state in enumerate(demo):
            for f in net.features:
                if f.initial and _missing(state.get(f.name)):
                    return i, t, f.name
    return None


def _refuse_beside_hidden_states(net, demonstrations) -> None:
    """What EM over hidden states does not cover: a hidden continuous state value.

    Its posterior given the demonstration so far is a mixture of Gaussians whose number of
    components multiplies with every step that hides an action or a discrete value (a
    switching linear-Gaussian system): no finite exact sum.
    """
    for i, demo in enumerate(demonstrations):
        for t, state in enumerate(demo):
            for f in net.features:
                if isinstance(f, Continuous) and f.initial and _missing(state.get(f.name)):
                    raise ValueError(
                        f"demonstration {i}, time {t} hides continuous {f.name!r}: a hidden "
                        "continuous state value carried over time, whose posterior is a "
                        "Gaussian mixture growing with every hidden step (a switching "
                        "linear-Gaussian system), which fit_demonstrations does not integrate "
                        f"(hidden discrete state values it sums): give {f.name!r} at every "
                        "time (or drop the demonstration's steps around it)"
                    )


def _by_demonstration(net, steps_rows, demonstrations) -> list[dict[str, np.ndarray]]:
    """Per demonstration, each parameter's ``(T, d)`` recorded values (NaN where not)."""
    out, at = [], 0
    for demo in demonstrations:
        steps = len(demo) - 1
        out.append({m.value.site: steps_rows[m.value.site][at : at + steps] for m in net.mixtures})
        at += steps
    return out


def _label_indices(net, labels, demonstrations) -> list[list[int | None]]:
    """Per demonstration, each step's action index (None where not labelled)."""
    flat = [None if x is None else net.action_index(x) for x in labels]
    out, at = [], 0
    for demo in demonstrations:
        out.append(flat[at : at + len(demo) - 1])
        at += len(demo) - 1
    return out


def _effect_start(net, data, n_steps: int, pseudo_count: float) -> NetworkParams:
    """The closed form with each unlabelled step given the action of its nearest common change.

    A step's change: which discrete features' end differs from their start, and each
    outcome feature's value. The ``A`` most common changes among the unlabelled steps
    stand for the actions in order (a labelled step keeps its label); every unlabelled
    step takes the one nearest its own (fewest features differing).
    """
    discrete = [f for f in net.features if isinstance(f, Discrete)]
    columns = []
    for f in discrete:
        end = data[end_site(f.name)][:n_steps]
        if f.initial:
            columns.append(
                np.array(
                    [a != b for a, b in zip(data[initial_site(f.name)][:n_steps], end, strict=True)]
                )
            )
        else:
            states = {v: i for i, v in enumerate(f.states)}
            columns.append(np.array([states.get(v, -1) if v is not None else -1 for v in end]))
    if not columns:
        return random_params(net, 0)
    change = np.stack(columns, 1).astype(np.int64)
    labels = np.array(data[ACTION][:n_steps], dtype=object)  # a copy: the steps keep theirs
    open_steps = np.array([v is None for v in labels])
    kinds, counts = np.unique(change[open_steps], axis=0, return_counts=True)
    common = kinds[np.argsort(-counts, kind="stable")][: len(net.actions)]
    if len(common):
        distance = (change[:, None, :] != common[None, :, :]).sum(-1)
        nearest = distance.argmin(1)
        for i in np.flatnonzero(open_steps):
            labels[i] = net.actions[int(nearest[i])]
    rows = {site: column[:n_steps] for site, column in data.items()}
    rows[ACTION] = labels
    rows |= for_actions(net, rows, labels)
    start = fit(net, rows, pseudo_count=max(pseudo_count, 0.01))
    return start.params


def _from_batch(net, batch: Mapping) -> list[list[dict]]:
    """The batch form (per feature ``(n, T + 1)`` labels or ``(n, T + 1, d)`` numbers)."""
    unknown = set(batch) - {f.name for f in net.features}
    if unknown:
        raise ValueError(f"{sorted(unknown)} are not features of the network")
    arrays = {
        name: np.asarray(v, dtype=object if net.feature(name).__class__ is Discrete else np.float64)
        for name, v in batch.items()
    }
    shapes = {a.shape[:2] for a in arrays.values()}
    if len(shapes) != 1:
        raise ValueError(f"every feature needs the same (n, T + 1) leading shape, got {shapes}")
    n, times = shapes.pop()
    return [[{name: a[i, t] for name, a in arrays.items()} for t in range(times)] for i in range(n)]


def _missing(value) -> bool:
    if value is None:
        return True
    if isinstance(value, float) and math.isnan(value):
        return True
    return (
        isinstance(value, np.ndarray | list | tuple)
        and np.isnan(np.asarray(value, dtype=np.float64)).any()
    )


def _value(f, value):
    if isinstance(f, Continuous):
        if value is None:
            return [math.nan] * f.dim
        return list(np.asarray(value, dtype=np.float64).reshape(f.dim))
    assert isinstance(f, Discrete)
    return None if _missing(value) else value


def _padded(mask: torch.Tensor, n: int) -> torch.Tensor:
    """A steps' mask followed by False for the training rows after them."""
    return torch.cat([mask, torch.zeros(n - len(mask), dtype=torch.bool)])


def _joined(net, steps_rows, rows):
    if rows is None:
        return steps_rows
    if not isinstance(rows, Mapping):
        raise ValueError("rows must be training rows by site (a mapping), as fit takes them")
    out = {}
    for site, column in steps_rows.items():
        if site not in rows:
            raise ValueError(f"rows has no {site!r}: every site of the network is needed")
        theirs = rows[site]
        if net.site(site).discrete:
            other = np.empty(len(theirs), dtype=object)
            other[:] = list(np.asarray(theirs, dtype=object).reshape(-1))
            out[site] = np.concatenate([column, other])
        else:
            other = np.asarray(theirs, dtype=np.float64).reshape(len(theirs), -1)
            out[site] = np.concatenate([column, other])
    return out


def _labelled_rows(rows: Mapping) -> bool:
    return any(not _missing(v) for v in np.asarray(rows[ACTION], dtype=object).reshape(-1))


def _recognised(net, params, steps_rows, labels) -> tuple[float, float]:
    """The mean posterior of the label, and the share recognised, on the labelled steps.

    Each step's posterior given the values it shows (its start and end), the steps that
    show the same sites asked together; a step that shows nothing has the action table.
    """
    if not labels.any():
        return math.nan, math.nan
    sites = [site for site in steps_rows if site != ACTION]
    shown = np.stack(
        [~_value_missing(net, site, steps_rows[site][labels]) for site in sites], 1
    ).reshape(int(labels.sum()), len(sites))
    truth = torch.tensor([net.action_index(a) for a in steps_rows[ACTION][labels]])
    probs = torch.empty(len(truth), len(net.actions), dtype=params[ACTION].probs.dtype)
    patterns, which = np.unique(shown, axis=0, return_inverse=True)
    for k, pattern in enumerate(patterns):
        rows = np.flatnonzero(which.reshape(-1) == k)
        evidence = {
            site: steps_rows[site][labels][rows]
            for site, given in zip(sites, pattern, strict=True)
            if given
        }
        if evidence:
            probs[rows] = infer_action(net, params, evidence).probs
        else:
            probs[rows] = params[ACTION].probs
    mine = probs.gather(1, truth[:, None]).squeeze(1)
    return float(mine.mean()), float((probs.argmax(1) == truth).to(torch.float64).mean())


def _value_missing(net, site, column) -> np.ndarray:
    """``(m,)`` bool: each row of a step column misses its value."""
    if net.site(site).discrete:
        return np.array([v is None for v in column], dtype=bool)
    return np.isnan(np.asarray(column, dtype=np.float64)).any(-1)


def _aligned(net, params, reference) -> NetworkParams:
    """``params`` with its actions renamed by the permutation closest to ``reference``."""
    sites = [s.name for s in net.sites if ACTION in (*net.cpd(s.name).parents, s.name)]
    for site in sites:
        if not isinstance(params[site], TableParams):
            raise ValueError(
                f"aligning to a reference permutes every table read by the action; {site!r} "
                "is not a table"
            )
    a = len(net.actions)
    if a > MAX_PERMUTED_ACTIONS:
        raise ValueError(f"{a} actions: more than {MAX_PERMUTED_ACTIONS} to permute one by one")
    best, best_cost = None, math.inf
    for perm in itertools.permutations(range(a)):
        moved = _permuted(net, params, perm, sites)
        cost = sum(float((moved[s].probs - reference[s].probs).abs().sum()) for s in sites)
        if cost < best_cost:
            best, best_cost = moved, cost
    return best


def _permuted(net, params, perm, sites) -> NetworkParams:
    """The tables with learned action ``perm[j]`` renamed as declared action ``j``."""
    index = torch.tensor(perm)
    cpds = dict(params.cpds)
    for site in sites:
        table = params[site]
        parents = net.cpd(site).parents
        axis = len(parents) if site == ACTION else parents.index(ACTION)
        n_axis = None if site == ACTION else axis
        probs = table.probs.index_select(axis, index)
        n = table.n if n_axis is None else table.n.index_select(n_axis, index)
        cpds[site] = TableParams(probs, n)
    return NetworkParams(cpds, params.pseudo_count, net)
