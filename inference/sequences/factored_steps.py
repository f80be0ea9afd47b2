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

import math
from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import torch
from effect_networks.inference.sequences.states import (
    StateLike,
    state_features,
    state_index,
)
from effect_networks.inference.sequences.transition_tables import (
    PARAMETER_VALUES,
    action_position,
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
        return action_position(self.actions, action)

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
        letters = Letters()
        tables, terms = [], []
        for factor in self.factors:
            tables.append(
                factor.log_table[tuple(fixed.get(q, slice(None)) for q in factor.scope)].exp()
            )
            terms.append(letters.term(q for q in factor.scope if q not in fixed))
        return float(chain_product(torch.ones((), dtype=DTYPE), "", tables, terms, ""))

    def dense(self) -> torch.Tensor:
        """``probs[s, a, s']`` over every state (the last feature fastest): the dense tensor.

        ``S x A x S`` numbers: for small spaces and for checks, as
        :func:`~inference.sequences.transition_tables.transitions` is.
        """
        self._check_kept(self.names)
        s = math.prod(f.cardinality for f in self.features)
        a = len(self.actions)
        if s * a * s > 1 << 27:
            raise ValueError(f"{s} x {a} x {s} is more than {1 << 27} numbers")
        return product_form(self, self.names, {}).matrix().reshape(s, a, s)

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


#: The letters of an einsum, one per site of a contraction.
EINSUM_LETTERS = "abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ"


class Letters:
    """One einsum letter per site, handed out as sites are first named."""

    def __init__(self) -> None:
        self.of: dict[str, str] = {}

    def __call__(self, site: str) -> str:
        """``site``'s letter (a new one the first time)."""
        if site not in self.of:
            if len(self.of) == len(EINSUM_LETTERS):
                raise ValueError(
                    f"a contraction over more than {len(EINSUM_LETTERS)} sites: plan on fewer "
                    "features (a smaller budget=, or a goal on fewer features)"
                )
            self.of[site] = EINSUM_LETTERS[len(self.of)]
        return self.of[site]

    def term(self, sites) -> str:
        """The letters of ``sites``, in order."""
        return "".join(self(q) for q in sites)


def chain_product(first, first_term: str, tables, terms, out: str) -> torch.Tensor:
    """``first`` times every table, summed to the axes ``out``, one table at a time.

    Each axis is summed out as soon as no later table and not ``out`` reads it, so the
    running product never holds more than the axes still to be read (the tables come in
    the network's order: each end site's factor after those it reads).
    """
    acc, acc_term = first, first_term
    for i, (table, term) in enumerate(zip(tables, terms, strict=True)):
        later = set(out).union(*terms[i + 1 :])
        union = "".join(dict.fromkeys(acc_term + term))
        kept = "".join(c for c in union if c in later)
        acc = torch.einsum(f"{acc_term},{term}->{kept}", acc, table)
        acc_term = kept
    return torch.einsum(f"{acc_term}->{out}", acc)


@dataclass(frozen=True)
class ProductForm:
    """The step of some features as einsum operands: probability tables and their letters.

    ``tables[i]`` over ``terms[i]``; ``seen[i]`` alike, 1 where the table's parent
    configuration was reached by a training row; ``now``, ``act``, ``then``: the letters of
    the features' initial sites, the offered action and their end sites; ``sizes``: the
    features' numbers of states.
    """

    tables: list[torch.Tensor]
    seen: list[torch.Tensor]
    terms: list[str]
    now: str
    act: str
    then: str
    sizes: tuple[int, ...]

    def matrix(self) -> torch.Tensor:
        """``P(then | now, act)`` with one axis per letter of ``now + act + then``."""
        one = torch.ones((), dtype=DTYPE)
        return chain_product(one, "", self.tables, self.terms, self.now + self.act + self.then)


def product_form(model: StepModel, features: Sequence[str], held: Mapping[str, int]) -> ProductForm:
    """The step of ``features`` (closed under the step) as einsum operands.

    ``held``: features outside ``features`` whose initial values the tables are read at.
    """
    letters = Letters()
    tables, seen, terms = [], [], []
    for f in model.step_factors(features):
        table, scope, reached = _held_factor(f, held)
        tables.append(table.exp())
        seen.append(reached)
        terms.append(letters.term(scope))
    now = letters.term(initial_site(n) for n in features)
    then = letters.term(end_site(n) for n in features)
    act = letters(OFFERED)
    # an axis no table reads (a feature whose next value ignores its own): a vector of ones
    by_name = {f.name: f.cardinality for f in model.features}
    sizes = tuple(by_name[n] for n in features)
    size_of = dict(zip(now, sizes, strict=True)) | {act: len(model.actions)}
    read = set("".join(terms))
    for c in now + act:
        if c not in read:
            tables.append(torch.ones(size_of[c], dtype=DTYPE))
            seen.append(torch.ones(size_of[c], dtype=DTYPE))
            terms.append(c)
    return ProductForm(tables, seen, terms, now, act, then, sizes)


def _held_factor(f: StepFactor, held: Mapping[str, int]):
    """The factor with the held features' initial sites fixed; its seen indicator alike."""
    seen = torch.ones(f.log_table.shape, dtype=DTYPE)
    if f.unseen is not None:
        seen = (~f.unseen).to(DTYPE).unsqueeze(-1).expand(f.log_table.shape)
    fixed = {initial_site(n): i for n, i in held.items()}
    picks = tuple(fixed.get(q, slice(None)) for q in f.scope)
    return f.log_table[picks], tuple(q for q in f.scope if q not in fixed), seen[picks]
