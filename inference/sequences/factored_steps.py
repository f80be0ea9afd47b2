r"""A network's step in factored form: one table per site, never the joint.

:func:`~inference.sequences.transition_tables.transitions` writes a step as one tensor
over (state, action, next state): exact and simple, but ``S x A x S`` numbers for ``S``
states, so a world of a dozen binary features is out of its reach. The network itself
is much smaller: each end site's table is over its own parents only. :func:`step_model`
keeps the step that way::

    P(next | state, action) = sum over latent sites of  prod over step factors  phi(scope)

one :class:`StepFactor` per discrete end site that a state feature's end needs (its
parents: initial sites, the action, other end sites, a parameter's cluster; an end-only
feature's end site is latent) and one per parameter cluster those depend on
(``P(cluster | action)``, latent unless ``parameter_values="clusters"`` fixes it per
offered action). Continuous end sites have no discrete child and integrate to one; a
continuous initial feature is the step's context, given as a value (``given=``), and
enters the factors of the sites that read it. Building it reads each site's table once:
time and memory linear in the tables, at any number of features.

A :class:`StepModel` answers one entry exactly (:meth:`StepModel.prob`), writes the dense
tensor for a small space (:meth:`StepModel.dense`, the same numbers
:func:`~inference.sequences.transition_tables.transitions` gives) and says which features
a set of features' next values depend on (:meth:`StepModel.relevant`), which is what the
planner projects onto (:mod:`inference.sequences.factored_planning`).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Collection, Iterable, Mapping
from dataclasses import dataclass, field

import torch
from effect_networks.inference.sequences.states import (
    StateLike,
    StateSpace,
    state_features,
    state_index,
)
from effect_networks.inference.sequences.transition_tables import (
    PARAMETER_VALUES,
    context_evidence,
    offered_actions,
    requested_actions,
)
from effect_networks.models.cpds.base import concat_inputs
from effect_networks.models.cpds.table import TableCPD
from effect_networks.models.declaration import (
    ACTION,
    DTYPE,
    Discrete,
    EffectNetwork,
    end_site,
    initial_site,
)
from effect_networks.models.params import NetworkParams, check_params

#: The scope name of the offered action's axis in every factor that reads the action.
OFFERED = ACTION


@dataclass(frozen=True)
class StepFactor:
    """One site's conditional table in a step.

    Attributes
    ----------
    site : str
        The site whose table this is (``"end.door"``, ``"cluster.force"``, ``"initial.lock"``).
    scope : tuple of str
        The sites of the axes of ``log_table``: the site's discrete parents, then the site
        itself. ``"action"`` is the offered action (``actions``).
    log_table : torch.Tensor
        ``log P(site | parents)`` (float64), one axis per scope site.
    unseen : torch.Tensor or None
        Over the parents' axes (the scope less the site), bool: the parent
        configurations no training row reached (end sites only).
    """

    site: str
    scope: tuple[str, ...]
    log_table: torch.Tensor = field(repr=False)
    unseen: torch.Tensor | None = field(repr=False, default=None)

    @property
    def parents(self) -> tuple[str, ...]:
        """The scope less the site."""
        return self.scope[:-1]


@dataclass(frozen=True)
class StepModel:
    """A network's step, factor by factor (:func:`step_model`).

    Attributes
    ----------
    features : tuple of Discrete
        The state features, in the network's order.
    actions : tuple of str
        The offered actions' labels (as :class:`~inference.sequences.transition_tables.Transitions`
        labels them).
    choices : tuple of dict
        Per offered action the evidence that plays it.
    factors : tuple of StepFactor
        The step's factors: every end site a state feature's end needs, and the clusters
        they read. Their product, summed over ``latent``, is ``P(next | state, action)``.
    latent : tuple of str
        The sites a step sums out: end sites of end-only features, unfixed clusters.
    prior : tuple of StepFactor
        The initial sites' factors (continuous ones at their given values, over their
        discrete parents): ``P(state)`` up to the context's density.
    kept : tuple of str
        The state features whose steps the factors hold (every one, unless
        :func:`step_model` was asked for some with ``features=``).
    """

    features: tuple[Discrete, ...]
    actions: tuple[str, ...]
    choices: tuple[dict[str, object], ...] = field(repr=False)
    factors: tuple[StepFactor, ...] = field(repr=False)
    latent: tuple[str, ...]
    prior: tuple[StepFactor, ...] = field(repr=False)
    kept: tuple[str, ...] = ()

    @property
    def names(self) -> tuple[str, ...]:
        """The state features' names."""
        return tuple(f.name for f in self.features)

    def sizes(self) -> dict[str, int]:
        """The number of values of every site in a scope (the action: offered actions)."""
        out = {}
        for factor in (*self.factors, *self.prior):
            out.update(zip(factor.scope, factor.log_table.shape, strict=True))
        out[OFFERED] = len(self.actions)
        return out

    def action_index(self, action: str | int) -> int:
        """The index of an offered action's label (or a checked index)."""
        if isinstance(action, int) and not isinstance(action, bool):
            if not 0 <= action < len(self.actions):
                raise ValueError(f"action index {action} outside 0..{len(self.actions) - 1}")
            return action
        try:
            return self.actions.index(action)
        except ValueError:
            raise ValueError(f"unknown action {action!r}; actions are {self.actions}") from None

    def relevant(self, features: Iterable[str]) -> tuple[str, ...]:
        """The state features whose values the next values of ``features`` depend on.

        The closure of ``features`` under the step: a feature is added when its initial
        site is in the scope of a factor the step of a relevant feature needs (its end
        site's, the end and latent sites that one reads, transitively). The step
        restricted to the relevant features is exact: their next values depend on
        nothing else. In the network's order.
        """
        by_site = {f.site: f for f in self.factors}
        wanted = set(features)
        unknown = wanted - set(self.names)
        if unknown:
            raise ValueError(f"{sorted(unknown)} are not state features; those are {self.names}")
        self._check_kept(wanted)
        while True:
            todo = [end_site(n) for n in wanted]
            seen: set[str] = set()
            while todo:
                site = todo.pop()
                if site in seen or site not in by_site:
                    continue
                seen.add(site)
                todo.extend(by_site[site].parents)
            found = {q.removeprefix("initial.") for q in seen if q.startswith("initial.")}
            found |= {
                q.removeprefix("initial.")
                for s in seen
                for q in by_site[s].parents
                if q.startswith("initial.")
            }
            grown = wanted | (found & set(self.names))
            if grown == wanted:
                return tuple(n for n in self.names if n in wanted)
            wanted = grown

    def _check_kept(self, features: Collection[str]) -> None:
        missing = [n for n in features if n not in self.kept]
        if missing:
            raise ValueError(
                f"this step model keeps the steps of {self.kept}, not of {missing}: build it "
                "with step_model(..., features=...) naming them"
            )

    def step_factors(self, features: Collection[str]) -> tuple[StepFactor, ...]:
        """The factors the next values of ``features`` need (their ends', and what those read)."""
        self._check_kept(features)
        by_site = {f.site: f for f in self.factors}
        todo = [end_site(n) for n in features]
        out: dict[str, StepFactor] = {}
        while todo:
            site = todo.pop()
            if site in out or site not in by_site:
                continue
            out[site] = by_site[site]
            todo.extend(by_site[site].parents)
        return tuple(f for f in self.factors if f.site in out)

    def prob(self, state: StateLike, action: str | int, next: StateLike) -> float:
        """``P(next | state, action)`` for one entry, the latent sites summed out exactly."""
        self._check_kept(self.names)
        now, then = self._indices(state), self._indices(next)
        fixed = {initial_site(n): i for n, i in zip(self.names, now, strict=True)}
        fixed |= {end_site(n): i for n, i in zip(self.names, then, strict=True)}
        fixed[OFFERED] = self.action_index(action)
        tables = []
        for factor in self.factors:
            picks = tuple(fixed.get(q, slice(None)) for q in factor.scope)
            tables.append((factor.log_table[picks], [q for q in factor.scope if q not in fixed]))
        return float(_contract(tables, [], self.sizes()).exp())

    def dense(self, space: StateSpace | None = None) -> torch.Tensor:
        """``probs[s, a, s']`` over ``space`` (default every state): the dense tensor.

        ``S x A x S`` numbers: for small spaces and for checks, as
        :func:`~inference.sequences.transition_tables.transitions` is.
        """
        self._check_kept(self.names)
        features = self.features
        if space is None:
            sizes = [f.cardinality for f in features]
            index = torch.tensor(
                list(itertools.product(*(range(k) for k in sizes))), dtype=torch.long
            ).reshape(-1, len(features))
        else:
            index = space.index
        s, a = index.shape[0], len(self.actions)
        if s * a * s > 1 << 27:
            raise ValueError(f"{s} x {a} x {s} is more than {1 << 27} numbers")
        position = {}
        for j, f in enumerate(features):
            position[initial_site(f.name)] = index[:, j].reshape(s, 1, 1)
            position[end_site(f.name)] = index[:, j].reshape(1, 1, s)
        position[OFFERED] = torch.arange(a).reshape(1, a, 1)
        tables = []
        for factor in self.factors:
            fixed = [q for q in factor.scope if q in position]
            rest = [q for q in factor.scope if q not in position]
            moved = factor.log_table.permute(
                *[factor.scope.index(q) for q in fixed], *[factor.scope.index(q) for q in rest]
            )
            picked = moved[tuple(position[q] for q in fixed)] if fixed else moved[None, None, None]
            tables.append((picked.reshape(*picked.shape[:3], *moved.shape[len(fixed) :]), rest))
        sizes = self.sizes()
        out = _contract(tables, ["s", "a", "t"], sizes | {"s": s, "a": a, "t": s}, leading=3)
        return out.exp().expand(s, a, s).contiguous()

    def _indices(self, state: StateLike) -> tuple[int, ...]:
        if isinstance(state, Mapping):
            missing = [n for n in self.names if n not in state]
            if missing or len(state) != len(self.names):
                raise ValueError(f"a state names every state feature {self.names}, got {state!r}")
            state = tuple(state[n] for n in self.names)
        state = tuple(state)
        if len(state) != len(self.features):
            raise ValueError(f"a state has {len(self.features)} labels, got {state!r}")
        return tuple(state_index(f, v) for f, v in zip(self.features, state, strict=True))

    def __repr__(self) -> str:
        widest = max((f.log_table.numel() for f in self.factors), default=0)
        return (
            f"StepModel({len(self.features)} state features, {len(self.actions)} actions, "
            f"{len(self.factors)} factors (largest {widest} numbers), latent {self.latent})"
        )


def step_model(
    net: EffectNetwork,
    params: NetworkParams,
    *,
    actions: Iterable[str] | None = None,
    parameter_values: str = "integrate",
    given: Mapping[str, object] | None = None,
    features: Iterable[str] | None = None,
) -> StepModel:
    """The network's step model in factored form: one table per site.

    Parameters
    ----------
    net, params
        The network and its fitted tables.
    actions, parameter_values, given
        As :func:`~inference.sequences.transition_tables.transitions` takes them: the
        actions offered, whether a parameterised action is offered once per cluster, and
        the continuous initial features' values.
    features
        The state features whose steps to keep, with every feature their next values
        read (closed as :meth:`StepModel.relevant` closes them); default all. A planner
        for a goal on a few features of a large world reads only their tables.

    Returns
    -------
    StepModel
        Its factors, latent sites and prior; built in time and memory linear in the
        network's tables.

    Examples
    --------
    >>> from effect_networks.models import Discrete, EffectNetwork
    >>> from effect_networks.inference import fit
    >>> net = EffectNetwork(features=(Discrete("door", ("shut", "open")),), actions=("push", "wait"))
    >>> rows = {"initial.door": ["shut"] * 4, "action": ["push", "push", "wait", "wait"],
    ...         "end.door": ["open", "open", "shut", "shut"]}
    >>> model = step_model(net, fit(net, rows).params)
    >>> [f.scope for f in model.factors]
    [('initial.door', 'action', 'end.door')]
    >>> model.prob(("shut",), "push", ("open",)) > 0.5
    True
    """
    if parameter_values not in PARAMETER_VALUES:
        raise ValueError(
            f"parameter_values must be one of {PARAMETER_VALUES}, got {parameter_values!r}"
        )
    check_params(net, params)
    context = context_evidence(net, given)
    all_features = state_features(net)
    offered = offered_actions(net, params, requested_actions(net, actions), parameter_values)
    kept = _closure(net, all_features, features)
    needed = net.end_sites_needed([end_site(n) for n in kept])
    discrete_ends = [s.name for s in net.sites if s.name in needed and s.discrete]
    clusters = {m.cluster.site: m for m in net.mixtures}
    read = {q for site in discrete_ends for q in net.cpd(site).parents}
    cache: dict = {}
    factors = []
    latent_clusters = [c for c in clusters if c in read and c not in offered.clusters]
    for site in latent_clusters + discrete_ends:
        factors.append(_factor(net, params, site, context, cache, clusters, offered))
    prior = [
        _factor(net, params, site, context, cache, clusters, offered)
        for site in _initial_ancestors(net, kept)
    ]
    state_ends = {end_site(f.name) for f in all_features}
    latent = tuple(f.site for f in factors if f.site not in state_ends)
    return StepModel(
        all_features,
        offered.labels,
        offered.choices,
        tuple(factors),
        latent,
        tuple(prior),
        kept,
    )


def _closure(net: EffectNetwork, features, wanted) -> tuple[str, ...]:
    """The wanted state features and every one their next values read, in order."""
    names = tuple(f.name for f in features)
    if wanted is None:
        return names
    if isinstance(wanted, str):
        raise ValueError(f"features must be a collection of names, got {wanted!r}")
    kept = set(wanted)
    unknown = kept - set(names)
    if unknown:
        raise ValueError(f"{sorted(unknown)} are not state features; those are {names}")
    while True:
        needed = net.end_sites_needed([end_site(n) for n in kept])
        read = {q for site in needed for q in net.cpd(site).parents}
        mixtures = {m.cluster.site: m for m in net.mixtures}
        read |= {mixtures[q].action for q in read if q in mixtures}
        grown = kept | {q.removeprefix("initial.") for q in read if q.startswith("initial.")}
        grown &= set(names)
        if grown == kept:
            return tuple(n for n in names if n in kept)
        kept = grown


def _initial_ancestors(net: EffectNetwork, kept: tuple[str, ...]) -> list[str]:
    """The initial sites of ``kept`` and of what they depend on, in the network's order."""
    todo = [initial_site(n) for n in kept]
    seen: set[str] = set()
    while todo:
        site = todo.pop()
        if site not in seen:
            seen.add(site)
            todo.extend(q for q in net.cpd(site).parents if q.startswith("initial."))
    return [s.name for s in net.sites if s.name in seen]


def _factor(net, params, site, context, cache, clusters, offered) -> StepFactor:
    """``site``'s table over its discrete parents, the action axis the offered actions'."""
    spec = net.site(site)
    if site in clusters:
        m = clusters[site]
        cpd, parents, inputs = m.cluster, (m.action,), ()
    else:
        cpd = net.cpd(site)
        parents, inputs = tuple(cpd.parents), tuple(cpd.inputs)
    not_context = [q for q in inputs if q not in context]
    if not_context or any(not net.site(q).discrete for q in parents):
        raise ValueError(
            f"{site!r} reads {not_context or parents}, which is neither a discrete site nor a "
            "given context: its step is not factored; use transitions() (the dense route)"
        )
    sizes = [net.site(q).size for q in parents]
    rank = len(parents)
    index = [
        torch.arange(k).reshape(*[1] * j, k, *[1] * (rank - j - 1), 1) for j, k in enumerate(sizes)
    ]
    x = concat_inputs([context[q] for q in inputs]) if inputs else None
    if isinstance(cpd, TableCPD):  # the table itself, axes (parents..., site)
        logs, scope = cpd.log_table(params[site], cache).to(DTYPE), (*parents, site)
    elif spec.discrete:
        fn = cpd.distribution(params[site], index, x, cache)
        k = spec.size
        value = torch.arange(k).reshape(k, *[1] * (rank + 1))
        logs = fn.log_prob(value).to(DTYPE)  # (K, P..., 1)
        logs = logs.expand(k, *sizes, 1).reshape(k, *sizes).movedim(0, -1)
        scope = (*parents, site)
    else:  # a continuous initial feature at its given value, over its discrete parents
        fn = cpd.distribution(params[site], index, x, cache)
        logs = fn.log_prob(context[site].reshape(*[1] * rank, 1, -1)).to(DTYPE)
        logs = logs.expand(*sizes, 1).reshape(sizes)
        scope = parents
    unseen = None
    if spec.role == "end":
        seen = cpd.seen(params[site])
        unseen = ~seen.reshape(sizes) if rank else ~seen.reshape(())
    logs, scope, unseen = _on_offered(logs, scope, unseen, offered)
    return StepFactor(site, scope, logs.contiguous(), unseen)


def _on_offered(logs, scope, unseen, offered):
    """Replace the action and fixed cluster axes by one axis over the offered actions.

    ``unseen`` (over the scope less the site) is picked alike; the site stays last.
    """
    picks = {ACTION: offered.action, **offered.clusters}
    fixed = [q for q in scope if q in picks]
    if not fixed:
        return logs, scope, unseen
    rest = [q for q in scope if q not in picks]
    order = [scope.index(q) for q in fixed] + [scope.index(q) for q in rest]
    logs = logs.permute(*order)[tuple(picks[q] for q in fixed)]
    if unseen is not None:  # laid out as the logs, the site's axis of size one
        full = unseen.unsqueeze(-1).permute(*order)[tuple(picks[q] for q in fixed)]
        unseen = full.squeeze(-1)
    return logs, (OFFERED, *rest), unseen


def _contract(tables, out, sizes, leading: int = 0) -> torch.Tensor:
    """``log sum over the non-``out`` axes of exp(sum of tables)``, by torch.einsum.

    ``tables``: ``(log tensor, axis names)`` pairs; with ``leading``, each tensor's first
    ``leading`` axes are named ``out`` (broadcast where 1).
    """
    names: dict[str, str] = {}
    letters = "abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ"

    def letter(q: str) -> str:
        if q not in names:
            if len(names) == len(letters):
                raise ValueError("more than 52 sites in one step: use the factored routes")
            names[q] = letters[len(names)]
        return names[q]

    operands, terms, shifts = [], [], []
    for t, axes in tables:
        axes = [*out[:leading], *axes] if leading else list(axes)
        shift = t.max() if t.numel() and bool(torch.isfinite(t.max())) else torch.tensor(0.0)
        operands.append((t - shift).exp())
        shifts.append(shift)
        terms.append("".join(letter(q) for q in axes))
    if not operands:
        return torch.zeros((), dtype=DTYPE)
    target = "".join(letter(q) for q in out)
    expanded = [
        o.expand(
            [sizes[q] if n == 1 else n for q, n in zip(_names(term, names), o.shape, strict=True)]
        )
        for o, term in zip(operands, terms, strict=True)
    ]
    total = torch.einsum(",".join(terms) + "->" + target, *expanded)
    return total.log() + sum(shifts)


def _names(term: str, names: dict[str, str]) -> list[str]:
    back = {v: k for k, v in names.items()}
    return [back[c] for c in term]


def size_of(model: StepModel, features: Iterable[str]) -> int:
    """The number of joint states of ``features``."""
    by_name = {f.name: f for f in model.features}
    return math.prod(by_name[n].cardinality for n in features)
