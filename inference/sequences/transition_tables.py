r"""Joint transitions of a network: ``P(next state | state, action)``.

For every state and action, exactly, from the network's own tables.

A network's state is its discrete features that have both an initial and an end node
(:mod:`inference.sequences.states`). One step is the network itself: the state's features
are its initial sites, the action its action, the next state's features its end sites::

    initial.f1  initial.f2    action --> cluster.p   (integrated out, or one action per cluster)
         \        |       /      \         |
          v       v      v        v        v
        end.f1 ------> end.f2     end.g (an end-only feature: summed out)

The joint of the end sites is what a step needs, not each one's marginal: end sites that
depend on each other (declared end -> end parents), on an end-only feature or on one
parameter cluster are correlated. The model is traced once with every discrete site
enumerated (:func:`model_tables`); each end site's log table is then read at every
``(state, action, next state)`` and the sites that belong to none of them (clusters,
end-only discrete features an end state feature depends on) are summed out by
elimination (:func:`inference.exact.elimination.contract`). Continuous end features
have no discrete child, so they integrate to one and are left out; a continuous initial
feature is part of the step's context and must be given (``given=``).

:func:`transitions` returns a :class:`Transitions`: the tensor ``probs[s, a, s']``, the
labels of its states and actions, the probability ``unseen[s, a]`` that the step rests on
a configuration no training row reached (answered from the pseudo-count prior alone; the
tables' counts, :meth:`models.cpds.CPD.seen`), and ``outside[s, a]``, the probability of
a next state that the state space leaves out (``states=`` a subset).
"""

from __future__ import annotations

import math
from collections.abc import Collection, Iterable, Mapping
from dataclasses import dataclass, field, replace

import torch
from effect_networks.inference.exact.elimination import contract
from effect_networks.inference.queries.implausibility import (
    IMPLAUSIBLE_BELOW,
    initial_tails,
    outside_training,
)
from effect_networks.inference.sequences.states import StateLike, StateSpace
from effect_networks.models.cpds.table import gather
from effect_networks.models.declaration import (
    ACTION,
    DTYPE,
    Continuous,
    EffectNetwork,
    end_site,
    initial_site,
)
from effect_networks.models.dtype import MAX_MAGNITUDE
from effect_networks.models.model import effect_model
from effect_networks.models.params import NetworkParams, check_params
from pyro import poutine

#: ``parameter_values=`` choices: integrate an unknown parameter out, or offer an
#: action using it once per cluster.
PARAMETER_VALUES = ("integrate", "clusters")
#: The most numbers one table read at every ``(state, action, next state)`` may hold, the
#: latent sites it spans included (float64: 1 GiB).
MAX_ENTRIES = 1 << 27


@dataclass(frozen=True)
class ModelTables:
    """The model's log tables over its enumerated discrete sites, traced once.

    ``order``: the enumerated sites, leftmost axis first; ``factors[site]``: the site's
    log-probability given its parents, one axis per site of ``order`` (size 1 where it
    does not depend on it); ``unseen[site]`` (end sites): bool, laid out alike, true
    where the site's parent configuration no training row reached.
    """

    order: tuple[str, ...]
    factors: dict[str, torch.Tensor] = field(repr=False)
    unseen: dict[str, torch.Tensor] = field(repr=False)


def model_tables(
    net: EffectNetwork,
    params: NetworkParams,
    given: Mapping[str, object] | None = None,
    end_sites: Collection[str] | None = None,
) -> ModelTables:
    """Trace the model once with every discrete site enumerated and keep its tables.

    ``given``: a value for each continuous initial feature (``{feature: (d,) values}``);
    ``end_sites``: the end sites to keep, with those they depend on (default: every
    discrete end site). Unknown parameter values are integrated out in closed form
    (the model's collapsed form), unobserved continuous end sites left out. A value of
    ``given`` far outside the training data warns
    (:class:`~inference.queries.implausibility.OutsideTrainingData`).
    """
    check_params(net, params)
    data = context_evidence(net, given)
    if end_sites is None:
        end_sites = [s.name for s in net.sites if s.role == "end" and s.discrete]
    enc = net.encode(data) if data else None
    if enc is not None:  # a context far from the training data warns, as a query's does
        outside_training(initial_tails(net, params, enc), IMPLAUSIBLE_BELOW)
    model = poutine.enum(effect_model, first_available_dim=-2)
    trace = poutine.trace(model).get_trace(
        net, params, enc, n_rows=None if enc else 1, end_sites=list(end_sites), collapse=True
    )
    trace.compute_log_prob()
    nodes = {n: s for n, s in trace.nodes.items() if s["type"] == "sample"}
    dims = {n: s["infer"].get("_enumerate_dim") for n, s in nodes.items() if not s["is_observed"]}
    dims = {n: d for n, d in dims.items() if d is not None}
    order = tuple(sorted(dims, key=lambda s: dims[s]))
    rank = len(order)

    def laid_out(t: torch.Tensor) -> torch.Tensor:
        t = t.squeeze(-1)  # the rows plate (one row)
        return t.reshape(*[1] * (rank - t.dim()), *t.shape)

    factors = {n: laid_out(nodes[n]["log_prob"]) for n in order}
    values = {n: s["value"] for n, s in nodes.items()}
    unseen = {}
    for n in order:
        if net.site(n).role == "end":
            cpd = net.cpd(n)
            seen = gather(cpd.seen(params[n]), tuple(values[q] for q in cpd.parents))
            unseen[n] = laid_out(~seen.reshape(seen.shape or (1,)))  # (1,): no parents
    return ModelTables(order, factors, unseen)


def context_evidence(
    net: EffectNetwork, given: Mapping[str, object] | None
) -> dict[str, torch.Tensor]:
    """The continuous initial features' values (``given=``, checked) as evidence rows."""
    given = dict(given or {})
    needed = [f for f in net.features if isinstance(f, Continuous) and f.initial]
    names = {f.name for f in needed}
    unknown = [k for k in given if k not in names]
    if unknown:
        raise ValueError(
            f"given names {unknown}, which are not continuous initial features; "
            f"those are {sorted(names)} (the discrete ones make the state)"
        )
    missing = [f.name for f in needed if f.name not in given]
    if missing:
        raise ValueError(
            f"the continuous initial features {missing} are part of every step's context: "
            f"give their values, given={{{missing[0]!r}: [...]}}"
        )
    out = {}
    for f in needed:
        expected = (
            f"given[{f.name!r}] must be {f.dim} finite number(s) of magnitude at most "
            f"{MAX_MAGNITUDE:g} (the feature's value in every step), got {given[f.name]!r}"
        )
        raw = given[f.name]
        if raw is None or isinstance(raw, str | bytes | bool) or _holds_text(raw):
            raise ValueError(expected)
        try:
            value = torch.as_tensor(raw, dtype=DTYPE).reshape(-1)
        except (TypeError, ValueError, RuntimeError) as exc:  # text, None, ragged lists
            raise ValueError(expected) from exc
        if (
            value.shape != (f.dim,)
            or not bool(torch.isfinite(value).all())
            or bool((value.abs() > MAX_MAGNITUDE).any())
        ):
            raise ValueError(expected)
        out[initial_site(f.name)] = value.reshape(1, f.dim)
    return out


def _holds_text(raw: object) -> bool:
    """Whether a list of values holds a label (torch would read ``["1"]`` as 1.0)."""
    return isinstance(raw, list | tuple) and any(
        isinstance(v, str | bytes | bool) or v is None for v in raw
    )


def action_position(labels: tuple[str, ...], action: str | int) -> int:
    """The index of ``action`` among ``labels`` (or ``action``, a checked index)."""
    if isinstance(action, int) and not isinstance(action, bool):
        if not 0 <= action < len(labels):
            raise ValueError(f"action index {action} outside 0..{len(labels) - 1}")
        return action
    try:
        return labels.index(action)
    except ValueError:
        raise ValueError(f"unknown action {action!r}; actions are {labels}") from None


@dataclass(frozen=True)
class Transitions:
    """``probs[s, a, s']``: ``P(next state s' | state s, action a)`` over ``space`` and ``actions``.

    Attributes
    ----------
    space : StateSpace
        The states, both for ``s`` and ``s'``.
    actions : tuple of str
        The action labels: an action's name, or with ``parameter_values="clusters"``
        ``"name[p=c]"`` for the action with its parameter ``p`` in cluster ``c``.
    probs : (S, A, S) float64
        The transition probabilities. A row sums to ``1 - outside[s, a]``.
    unseen : (S, A) float64
        The probability that the step rests on a parent configuration of an end site no
        training row reached (answered by the pseudo-count prior alone).
    outside : (S, A) float64
        The probability of a next state outside ``space`` (0 over the full product).
    prior : (S,) float64
        ``P(state)`` under the network's initial-state tables (not renormalised over a
        subset): the weight a partial start's states get.
    choices : tuple of dict
        Per action the evidence that plays it: ``{"action": name}`` and, per parameter
        fixed to a cluster, ``"cluster.p"`` (the cluster) and ``"param.p"`` (the
        cluster's mean value, ``(d,)``).
    """

    space: StateSpace
    actions: tuple[str, ...]
    probs: torch.Tensor
    unseen: torch.Tensor
    outside: torch.Tensor
    prior: torch.Tensor
    choices: tuple[dict[str, object], ...] = field(repr=False, default=())

    def action_index(self, action: str | int) -> int:
        """The index of an action label (or a checked index)."""
        return action_position(self.actions, action)

    def prob(self, state: StateLike | int, action: str | int, next: StateLike | int) -> float:
        """``P(next | state, action)``; states as label tuples or mappings, the action by label."""
        s, s2 = self.space.index_of(state), self.space.index_of(next)
        return float(self.probs[s, self.action_index(action), s2])

    def next_states(self, state: StateLike | int, action: str | int) -> dict[tuple, float]:
        """The next states of positive probability, by label, most likely first."""
        row = self.probs[self.space.index_of(state), self.action_index(action)]
        order = torch.argsort(row, descending=True, stable=True)
        return {self.space.states[i]: float(row[i]) for i in order.tolist() if row[i] > 0}

    def to_dict(self) -> dict[tuple, dict[str, dict[tuple, float]]]:
        """``{state: {action: {next state: probability}}}`` by labels (positive ones)."""
        return {
            s: {a: self.next_states(i, j) for j, a in enumerate(self.actions)}
            for i, s in enumerate(self.space.states)
        }

    def __repr__(self) -> str:
        s, a = len(self.space), len(self.actions)
        unseen = int((self.unseen > 0.5).sum())
        return (
            f"Transitions({s} states of {self.space.names}, {a} actions, "
            f"{unseen} of {s * a} (state, action) pairs mostly unseen, "
            f"largest outside mass {float(self.outside.max()):.3g})"
        )


def transitions(
    net: EffectNetwork,
    params: NetworkParams,
    *,
    states: Iterable[StateLike] | StateSpace | None = None,
    actions: Iterable[str] | None = None,
    parameter_values: str = "integrate",
    given: Mapping[str, object] | None = None,
    normalise: bool = False,
    tables: ModelTables | None = None,
) -> Transitions:
    """``P(next state | state, action)`` for every state and action, exactly.

    Parameters
    ----------
    net, params
        The network and its fitted tables.
    states
        The states to cover (label tuples in the state features' order, or mappings), or
        a :class:`StateSpace`; default every combination of the state features' states.
        Next states outside them are reported in ``outside``, not renormalised away.
    actions
        The names of the actions to offer (default all), in their order.
    parameter_values
        ``"integrate"`` (default): an action's unknown parameter is integrated out (its
        cluster drawn from the action's cluster table). ``"clusters"``: an action using a
        parameter is offered once per cluster, the cluster fixed (the state features
        depend on a value through its cluster alone; ``choices`` gives the cluster's
        mean value to play it with), labelled ``"name[p=c]"``.
    given
        A value for each continuous initial feature, ``{feature: (d,) values}``: the
        step's context (``ValueError`` naming a feature left out).
    normalise
        Divide each ``(state, action)`` row by its mass inside the state space: the next
        state conditioned on being one of ``states`` (``outside`` still reports the mass
        left out). Useful where ``states`` lists the states that can occur and the model
        gives the others some probability: in the can world, a configuration paired with
        a count that is not its own.
    tables
        :func:`model_tables` already traced for ``given`` (:func:`inference.compile`'s
        ``transitions`` keeps them).

    Returns
    -------
    Transitions
        ``probs`` ``(S, A, S)``, ``unseen`` and ``outside`` ``(S, A)``, labels.

    Examples
    --------
    >>> import numpy as np
    >>> from models import Discrete, EffectNetwork
    >>> from inference import fit
    >>> net = EffectNetwork(features=(Discrete("door", ("shut", "open")),), actions=("push", "wait"))
    >>> rows = {"initial.door": ["shut"] * 4, "action": ["push", "push", "wait", "wait"],
    ...         "end.door": ["open", "open", "shut", "shut"]}
    >>> t = transitions(net, fit(net, rows).params)
    >>> t.prob(("shut",), "push", ("open",)) > 0.5
    True
    >>> bool(t.unseen[t.space.index_of(("open",)), t.action_index("push")] == 1)
    True
    """
    if parameter_values not in PARAMETER_VALUES:
        raise ValueError(
            f"parameter_values must be one of {PARAMETER_VALUES}, got {parameter_values!r}"
        )
    check_params(net, params)
    space = states if isinstance(states, StateSpace) else StateSpace.of(net, states)
    names = requested_actions(net, actions)
    offered = offered_actions(net, params, names, parameter_values)
    _check_size(net, space, offered)
    if tables is None:
        ends = [end_site(f.name) for f in space.features]
        tables = model_tables(net, params, given, ends)
    elif given is not None:
        raise ValueError("give either tables= (traced with their given values) or given=")
    out = _transitions(net, space, offered, tables)
    if not normalise:
        return out
    inside = out.probs.sum(-1, keepdim=True)
    probs = torch.where(inside > 0, out.probs / torch.where(inside > 0, inside, 1.0), 0.0)
    return replace(out, probs=probs)


def _check_size(net: EffectNetwork, space: StateSpace, offered: OfferedActions) -> None:
    """Refuse a question whose tables would hold more than :data:`MAX_ENTRIES` numbers.

    The tables read at every ``(state, action, next state)`` with the latent sites they span.
    """
    s, a = len(space), len(offered.labels)
    fixed = {initial_site(f.name) for f in space.features} | {ACTION, *offered.clusters}
    fixed |= {end_site(f.name) for f in space.features}
    needed = net.end_sites_needed([end_site(f.name) for f in space.features])
    scopes = [(q, *net.cpd(q).parents) for q in needed]
    scopes += [(m.cluster.site,) for m in net.mixtures if m.cluster.site not in fixed]
    widest = max(
        math.prod(net.site(q).size for q in scope if q not in fixed and net.site(q).discrete)
        for scope in scopes
    )
    if s * a * s * widest > MAX_ENTRIES:
        gib = s * a * s * widest * 8 / 2**30
        raise ValueError(
            f"{s} states x {a} actions x {s} next states (x {widest} latent configurations) "
            f"is {s * a * s * widest:.3g} numbers ({gib:.3g} GiB of float64), more than "
            f"{MAX_ENTRIES}: pass states= (the states that occur) or actions=, or keep the "
            "step factored (step_model: one table per site; plan uses it by itself)"
        )


def requested_actions(net: EffectNetwork, actions: Iterable[str] | None) -> list[int]:
    """The network's indices of the actions named (default all), checked."""
    if actions is None:
        return list(range(len(net.actions)))
    if isinstance(actions, str):
        raise ValueError(f"actions must be a collection of action names, got {actions!r}")
    out = [net.action_index(a) for a in actions]
    if not out or len(set(out)) != len(out):
        raise ValueError(f"actions must name distinct actions, at least one; got {actions!r}")
    return out


@dataclass(frozen=True)
class OfferedActions:
    """The offered actions: labels, each one's action index and fixed clusters."""

    labels: tuple[str, ...]
    action: torch.Tensor  # (A,) long
    clusters: dict[str, torch.Tensor]  # cluster site -> (A,) long (clusters mode)
    choices: tuple[dict[str, object], ...]


def offered_actions(net, params, names: list[int], parameter_values: str) -> OfferedActions:
    """The actions offered: each named one, or once per cluster of its parameters."""
    labels, action, choices = [], [], []
    clusters: dict[str, list[int]] = {m.cluster.site: [] for m in net.mixtures}
    for a in names:
        name = net.actions[a]
        used = (
            [m for m in net.mixtures if bool(m.uses[a])] if parameter_values == "clusters" else []
        )
        ranges = [range(m.parameter.n_clusters) for m in used]
        for combo in _product(ranges):
            fixed = dict(zip([m.cluster.site for m in used], combo, strict=True))
            for site in clusters:
                clusters[site].append(fixed.get(site, 0))
            action.append(a)
            choice: dict[str, object] = {ACTION: name}
            parts = []
            for m, c in zip(used, combo, strict=True):
                loc, _ = m.value.loc_tril(params[m.value.site], [torch.tensor([c])], None)
                choice[m.cluster.site] = c
                choice[m.value.site] = tuple(loc.reshape(-1).tolist())
                parts.append(f"{m.parameter.name}={c}")
            labels.append(f"{name}[{','.join(parts)}]" if parts else name)
            choices.append(choice)
    long = lambda v: torch.tensor(v, dtype=torch.long)  # noqa: E731
    fixed_sites = (
        {k: long(v) for k, v in clusters.items()} if parameter_values == "clusters" else {}
    )
    return OfferedActions(tuple(labels), long(action), fixed_sites, tuple(choices))


def _product(ranges: list[range]) -> list[tuple[int, ...]]:
    out: list[tuple[int, ...]] = [()]
    for r in ranges:
        out = [(*o, i) for o in out for i in r]
    return out


def _transitions(
    net, space: StateSpace, offered: OfferedActions, tables: ModelTables
) -> Transitions:
    s, a = len(space), len(offered.labels)
    features = {f.name: j for j, f in enumerate(space.features)}
    index: dict[str, torch.Tensor] = {}  # fixed site -> index broadcastable to (S, A, S')
    for name, j in features.items():
        index[initial_site(name)] = space.index[:, j].reshape(s, 1, 1)
        index[end_site(name)] = space.index[:, j].reshape(1, 1, s)
    index[ACTION] = offered.action.reshape(1, a, 1)
    for site, c in offered.clusters.items():
        index[site] = c.reshape(1, a, 1)
    missing = [q for q in index if q.startswith("end.") and q not in tables.order]
    if missing:
        raise ValueError(f"the tables hold no {missing}: trace them with these end sites")
    latent = [q for q in tables.order if q not in index]
    needed = net.end_sites_needed([end_site(f) for f in features])
    step, prior = [], []
    for site, table in tables.factors.items():
        role = net.site(site).role
        if role == "end" and site not in needed:
            continue  # no end state feature depends on it: it sums to one
        if role == "initial":
            prior.append(_read(table, tables.order, index, latent, (s, 1, 1)))
        elif role == "end" or (role == "cluster" and site not in offered.clusters):
            step.append(_read(table, tables.order, index, latent, (s, a, s)))
    eliminate = [i - len(latent) - 1 for i in range(len(latent))]
    log_t = _sum(step, eliminate, (s, a, s))
    misses = [
        _read(u, tables.order, index, latent, (s, a, s))
        for site, u in tables.unseen.items()
        if site in needed and bool(u.any())
    ]
    probs = log_t.exp()
    total = probs.sum(-1)
    if not misses:
        p_unseen = torch.zeros(s, a, dtype=DTYPE)
    elif not latent:  # every configuration is a next state: weigh the unseen ones
        missed = misses[0]
        for m in misses[1:]:
            missed = missed | m
        p_unseen = (probs * missed.reshape(*missed.shape[:3])).sum(-1)
    else:  # the seen configurations' mass, the latent sites summed out with it
        seen = [torch.where(m, -torch.inf, 0.0).to(DTYPE) for m in misses]
        p_unseen = total - _sum(step + seen, eliminate, (s, a, s)).exp().sum(-1)
    unseen = torch.where(total > 0, p_unseen / torch.where(total > 0, total, 1.0), 0.0)
    log_prior = _sum(prior, [], (s, 1, 1)) if prior else torch.zeros(s, 1, 1, dtype=DTYPE)
    return Transitions(
        space,
        offered.labels,
        probs,
        unseen.clamp(0, 1),
        (1 - total).clamp(0, 1),
        log_prior.reshape(s).exp(),
        offered.choices,
    )


def _read(table, order, index, latent, shape) -> torch.Tensor:
    """``table`` (one axis per site of ``order``) at the fixed sites' indices.

    A tensor ``(S|1, A|1, S'|1, latent sizes..., 1)`` (the trailing 1 is the rows' dim that
    :func:`~inference.exact.elimination.contract` expects).
    """
    fixed = [i for i, q in enumerate(order) if q in index]
    rest = [order.index(q) for q in latent]
    moved = table.permute(*fixed, *rest)
    zero = torch.zeros(1, 1, 1, dtype=torch.long)
    picks = tuple(index[order[i]] if table.shape[i] > 1 else zero for i in fixed)
    out = moved[picks] if picks else moved.reshape(1, 1, 1, *moved.shape)
    if out.dim() == len(rest):  # no fixed axis: the three leading dims are 1
        out = out.reshape(1, 1, 1, *out.shape)
    assert out.dim() == 3 + len(rest) and all(
        k in (1, n) for k, n in zip(out.shape[:3], shape, strict=True)
    )
    return out.unsqueeze(-1)


def _sum(factors: list[torch.Tensor], eliminate: list[int], shape) -> torch.Tensor:
    """The factors' sum with the latent dims summed out (log space), ``shape``."""
    if eliminate:
        total = contract(factors, eliminate)
    else:
        total = factors[0]
        for f in factors[1:]:
            total = total + f
    return total.reshape(*total.shape[:3]).expand(shape).contiguous()
