"""How a declaration becomes a network's structure.

Its sites, their parents and order, and each site's conditional-distribution kind.

The steps :class:`~models.declaration.EffectNetwork` takes when it is made, each a
function of the declaration's parts: :func:`check_declaration` (features, actions,
parameters), :func:`declared_sites`, :func:`parents_of` (the paper's Fig. 1 unless
declared otherwise), :func:`topological` (parents before children), :func:`resolve_kinds`
and :func:`build_cpds` (each site's kind, each parameter's
:class:`~models.cpds.ParameterMixture`), and :func:`site_identity` (what fitted numbers
depend on).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Literal

import torch
from effect_networks.models.cpds import (
    CPD,
    KINDS,
    LinearGaussianCPD,
    ParameterMixture,
    TableCPD,
    default_kind,
)
from effect_networks.models.features import Continuous, Discrete, Feature, Parameter, json_label
from effect_networks.models.sites import (
    ACTION,
    SiteSpec,
    cluster_site,
    end_site,
    initial_site,
    param_site,
)

#: The most numbers one site's conditional distribution may hold, all its tensors
#: together (a table: parent configurations x states; a linear Gaussian: configurations x
#: (d + d * inputs + d * d + 1)). A declaration beyond it is refused, naming the site,
#: before anything of that size is allocated: 10**8 float64 numbers are 800 MB, and
#: fitting or querying needs several such arrays.
MAX_CPD_ENTRIES = 10**8


def check_declaration(
    features: Iterable[Feature], actions: Iterable[str], parameters: Iterable[Parameter]
) -> tuple[tuple[Feature, ...], tuple[str, ...], tuple[Parameter, ...]]:
    """A declaration's features, actions and parameters as tuples, checked.

    Actions ordered and distinct, names distinct, every parameter's features and actions known,
    parameters sharing a feature only where an unknown value does not couple them.
    """
    if isinstance(actions, str | bytes) or not hasattr(actions, "__iter__"):
        raise ValueError(
            f"actions must be a sequence of action names, got {actions!r} (one "
            f"action is written ({actions!r},))"
        )
    if isinstance(actions, set | frozenset):  # the order gives each action its index
        raise ValueError(
            f"actions must be an ordered sequence (a tuple or a list), got the set "
            f"{actions!r}, whose order may change between runs"
        )
    features, parameters = tuple(features), tuple(parameters)
    actions = tuple(json_label(a, "action", "action names") for a in actions)
    if not features:
        raise ValueError("an effect network needs at least one feature")
    if not actions or len(set(actions)) != len(actions):
        raise ValueError(f"actions must be a non-empty tuple of distinct names, got {actions}")
    names = [f.name for f in features] + [p.name for p in parameters]
    if len(set(names)) != len(names):
        raise ValueError(f"feature and parameter names must be distinct, got {names}")
    by_name = {f.name: f for f in features}
    for p in parameters:
        unknown = [f for f in p.features if f not in by_name]
        if unknown:
            raise ValueError(
                f"parameter {p.name!r} affects {unknown}, which are not features of this "
                f"network (features: {list(by_name)})"
            )
        continuous = [f for f in p.features if isinstance(by_name[f], Continuous)]
        crowded = [
            f
            for f in continuous
            if len(continuous) > 1 and any(f in q.features for q in parameters if q is not p)
        ]
        if crowded:
            raise ValueError(
                f"parameter {p.name!r} acts on several continuous features, so it must "
                f"be the only parameter acting on each; {crowded} have others (an "
                "unknown value would couple the parameters). Merge them into one "
                "parameter of higher dimension"
            )
        shared = [f for f in p.features if any(f in q.features for q in parameters if q is not p)]
        if p.adaptive and shared:
            raise ValueError(
                f"parameter {p.name!r} has the adaptive layout, so it must be the only "
                f"parameter acting on its features; {shared} have others (a given value "
                "of an adaptive parameter does not fix its cluster)"
            )
        unknown = set(p.actions) - set(actions)
        if unknown:
            raise ValueError(f"parameter {p.name!r} names unknown actions {sorted(unknown)}")
    return features, actions, parameters


def declared_sites(
    features: tuple[Feature, ...], actions: tuple[str, ...], parameters: tuple[Parameter, ...]
) -> dict[str, SiteSpec]:
    """Every site of a declaration, in declaration order.

    Initial sites, the action, each parameter's cluster and value, end sites.
    """
    declared: dict[str, SiteSpec] = {}
    for f in features:
        if f.initial:
            declared[initial_site(f.name)] = _spec(initial_site(f.name), f, "initial")
    declared[ACTION] = SiteSpec(ACTION, True, len(actions), "action")
    for p in parameters:
        declared[cluster_site(p.name)] = SiteSpec(
            cluster_site(p.name), True, p.n_clusters, "cluster"
        )
        declared[param_site(p.name)] = SiteSpec(param_site(p.name), False, p.dim, "param")
    for f in features:
        declared[end_site(f.name)] = _spec(end_site(f.name), f, "end")
    return declared


def _spec(name: str, f: Feature, role: Literal["initial", "end"]) -> SiteSpec:
    if isinstance(f, Discrete):
        return SiteSpec(name, True, f.cardinality, role, f.name)
    return SiteSpec(name, False, f.dim, role, f.name)


def fig1_parents(sites: Mapping[str, SiteSpec]) -> dict[str, tuple[str, ...]]:
    """The paper's Fig. 1.

    Initial sites are roots; every initial site and the action are parents of every end site.
    """
    initial = tuple(s for s, spec in sites.items() if spec.role == "initial")
    return {
        s: (initial + (ACTION,) if spec.role == "end" else ())
        for s, spec in sites.items()
        if spec.role in ("initial", "end")
    }


def differing_from_fig1(parents: Mapping, fig1: Mapping) -> tuple[tuple[str, tuple[str, ...]], ...]:
    """The declared parent sets that differ from Fig. 1's (as sets), in site order."""
    return tuple((s, parents[s]) for s in fig1 if set(parents[s]) != set(fig1[s]))


def parents_of(
    declared: object, parameters: tuple[Parameter, ...], sites: Mapping[str, SiteSpec]
) -> dict[str, tuple[str, ...]]:
    """Every initial and end site's parents, checked.

    ``declared`` (a mapping or pairs) where given and Fig. 1's elsewhere, checked: names, roles,
    duplicates, and the action for a parameter's feature.
    """
    given = declared
    if isinstance(given, Mapping):
        given = tuple(given.items())
    try:
        given = {str(site): ps for site, ps in given}
    except (TypeError, ValueError):
        raise ValueError(
            f"parents must map a site to its parent sites, e.g. "
            f"{{'end.f': ('initial.f', 'action')}}; got {declared!r}"
        ) from None
    parents = fig1_parents(sites)
    for site, ps in given.items():
        spec = sites.get(site)
        if spec is None or spec.role not in ("initial", "end"):
            why = (
                "is not a site of this network"
                if spec is None
                else "has fixed parents (the action is a root; a parameter's cluster and "
                "value hang off the action)"
            )
            raise ValueError(
                f"parents names {site!r}, which {why}; declare the parents of initial or end "
                f"sites: {[s for s in parents]}"
            )
        if isinstance(ps, str) or not hasattr(ps, "__iter__"):
            raise ValueError(f"parents of {site!r} must be a sequence of site names, got {ps!r}")
        ps = tuple(ps)
        if len(set(ps)) != len(ps):
            raise ValueError(f"parents of {site!r} repeat a site: {ps}")
        for q in ps:
            _check_parent(site, spec, q, sites)
        parents[site] = ps
    for p in parameters:
        for f in p.features:
            if ACTION not in parents[end_site(f)]:
                raise ValueError(
                    f"parameter {p.name!r} affects {f!r}, so the action must be a parent of "
                    f"{end_site(f)!r} (it decides whether the parameter is used)"
                )
    return parents


def _check_parent(site: str, spec: SiteSpec, parent: str, sites: Mapping[str, SiteSpec]) -> None:
    q = sites.get(parent)
    if q is None:
        hint = ""
        if isinstance(parent, str) and parent in {s.feature for s in sites.values()}:
            hint = f" (a feature's sites are 'initial.{parent}' and 'end.{parent}')"
        raise ValueError(
            f"parent {parent!r} of {site!r} is not a site of this network{hint}; sites: "
            f"{[s for s, x in sites.items() if x.role in ('initial', 'action', 'end')]}"
        )
    if q.role in ("cluster", "param"):
        raise ValueError(
            f"parent {parent!r} of {site!r}: a parameter's sites join the parents of the "
            "feature it affects by themselves (Parameter(affects=...)); do not name them"
        )
    if spec.role == "initial" and q.role != "initial":
        raise ValueError(
            f"{parent!r} cannot be a parent of the initial site {site!r}: the initial state "
            "is before the action, so its parents can only be other initial sites"
        )
    if spec.role == "end" and q.role == "end" and not q.discrete:
        raise ValueError(
            f"the continuous end site {parent!r} cannot be a parent of {site!r}: queries sum "
            "unobserved parents out exactly, which a continuous end state does not allow; "
            "use its initial site or a discrete end feature"
        )


def topological(sites: Mapping[str, SiteSpec], parents: Mapping[str, tuple[str, ...]]) -> list[str]:
    """Site names with parents before children, otherwise in declaration order.

    A cycle raises, naming its sites.
    """
    order: list[str] = []
    state: dict[str, str] = {}

    def visit(s: str, path: list[str]) -> None:
        if state.get(s) == "done":
            return
        if state.get(s) == "open":
            cycle = path[path.index(s) :] + [s]
            raise ValueError(
                f"the declared parents form a cycle: {' -> '.join(reversed(cycle))}; a site "
                "cannot depend on itself, even through others"
            )
        state[s] = "open"
        for q in parents.get(s, ()):
            visit(q, [*path, s])
        state[s] = "done"
        order.append(s)

    for role in ("initial", "action", "cluster", "end"):
        for s, spec in sites.items():
            if spec.role == role or (role == "cluster" and spec.role == "param"):
                visit(s, [])
    return order


def resolve_kinds(given, sites: Mapping[str, SiteSpec]) -> tuple[tuple[str, type[CPD]], ...]:
    """Declared kinds as ``(site, class)`` pairs in site order, names resolved."""
    if isinstance(given, Mapping):
        given = tuple(given.items())
    known = {k.name: k for k in KINDS}
    out = {}
    for site, kind in given:
        spec = sites.get(site)
        if spec is None or spec.role not in ("initial", "end"):
            raise ValueError(
                f"kinds names {site!r}, which is not an initial or end site of this network; "
                f"sites: {[s for s, x in sites.items() if x.role in ('initial', 'end')]}"
            )
        if isinstance(kind, str):
            if kind not in known:
                raise ValueError(
                    f"site {site!r}: unknown kind {kind!r}; the toolkit's kinds are "
                    f"{sorted(known)} (pass the class of a kind of your own)"
                )
            kind = known[kind]
        if not (isinstance(kind, type) and issubclass(kind, CPD)) or not kind.name:
            raise ValueError(
                f"site {site!r}: kind {kind!r} must be a name or a subclass of models.cpds.CPD "
                "with a name"
            )
        out[site] = kind
    return tuple((s, out[s]) for s in sites if s in out)


def _check_size(cpd: CPD, why: str) -> None:
    """Refuse a site whose fitted numbers would exceed :data:`MAX_CPD_ENTRIES`.

    Before anything of that size is allocated.
    """
    entries = sum(math.prod(shape) for shape in cpd.shapes().values())
    if entries > MAX_CPD_ENTRIES:
        raise ValueError(
            f"site {cpd.site!r} would hold {entries:.3g} numbers ({why}); a site holds at "
            f"most MAX_CPD_ENTRIES = {MAX_CPD_ENTRIES:.0e}. Use fewer bins or states, or "
            "declare fewer parents (EffectNetwork(parents=...))"
        )


def build_cpds(
    actions: tuple[str, ...],
    parameters: tuple[Parameter, ...],
    kinds: Mapping[str, type[CPD]],
    sites: Mapping[str, SiteSpec],
    parents: Mapping[str, tuple[str, ...]],
) -> tuple[dict[str, CPD], dict[str, ParameterMixture]]:
    """Every site's kind in site order, and each parameter's mixture, by parameter name.

    ``kinds`` where declared, the default elsewhere. The mixtures come first: their sites join the
    parents of the features they affect.
    """
    mixtures = {
        p.name: ParameterMixture.of(
            p,
            ACTION,
            torch.tensor([a in p.actions for a in actions]),
            cluster_site(p.name),
            param_site(p.name),
            tuple(end_site(f) for f in p.features),
            tuple(end_site(f) for f in p.features if not sites[end_site(f)].discrete),
        )
        for p in parameters
    }
    for m in mixtures.values():
        _check_size(m.cluster, f"parameter {m.parameter.name!r} has {m.parameter.n_clusters} cells")
        _check_size(m.value, f"parameter {m.parameter.name!r} has {m.parameter.n_clusters} cells")
    declared = dict(kinds)
    cpds: dict[str, CPD] = {}
    for site, spec in sites.items():
        if spec.role == "action":
            cpds[site] = TableCPD(site, (), (), len(actions))
            continue
        if spec.role in ("cluster", "param"):
            continue
        ps = [q for q in sites if q in parents[site]]  # site (topological) order
        discrete = [q for q in ps if sites[q].discrete]
        inputs = [q for q in ps if not sites[q].discrete]
        acting = [m for m in mixtures.values() if site in m.affected]
        discrete += [m.cluster.site for m in acting]
        if not spec.discrete:
            inputs += [m.value.site for m in acting]
        card = tuple(sites[q].size for q in discrete)
        width = sum(sites[q].size for q in inputs)
        kind = declared.get(site) or default_kind(spec.discrete, width)
        refused = kind.refuses(spec.discrete, width)
        if refused is not None:
            what = "discrete" if spec.discrete else "continuous"
            raise ValueError(
                f"site {site!r} ({what}, {width} continuous input dims) cannot have kind "
                f"{kind.name!r}: {refused}"
            )
        _check_size(
            kind(site, tuple(discrete), card, spec.size, tuple(inputs), width),
            f"its discrete parents {discrete} have {math.prod(card)} configurations",
        )
        extra = {}
        if acting and not spec.discrete:
            if not issubclass(kind, LinearGaussianCPD):
                raise ValueError(
                    f"site {site!r} is affected by parameter {acting[0].parameter.name!r}, so "
                    f"its kind must be a linear Gaussian, not {kind.name!r}"
                )
            zero = torch.zeros(math.prod(card), width, dtype=torch.bool)
            end = width
            for m in reversed(acting):  # the parameters are the last inputs, in this order
                zero |= m.zero_weights(tuple(discrete), card, width, end)
                end -= m.parameter.dim
            extra["zero_weights"] = zero
        cpds[site] = kind(site, tuple(discrete), card, spec.size, tuple(inputs), width, **extra)
    for m in mixtures.values():
        cpds[m.cluster.site] = m.cluster
        cpds[m.value.site] = m.value
    return {s: cpds[s] for s in sites}, mixtures


def site_identity(
    spec: SiteSpec,
    cpd: CPD,
    actions: tuple[str, ...],
    parameters: tuple[Parameter, ...],
    features: tuple[Feature, ...],
) -> tuple[tuple[str, object], ...]:
    """One site's part of :meth:`~models.declaration.EffectNetwork.identity`."""
    site = spec.name
    own: tuple[tuple[str, object], ...]
    if spec.role == "action":
        own = (("actions", actions),)
    elif spec.role in ("cluster", "param"):
        p = next(p for p in parameters if site in (cluster_site(p.name), param_site(p.name)))
        own = (
            ("range", (p.low, p.high)),
            ("bins", p.bins),
            ("layout", p.layout),
            ("actions using it", tuple(a for a in actions if a in p.actions)),
        )
    elif spec.discrete:
        states = next(f for f in features if f.name == spec.feature).states
        own = (("states", states), ("state types", tuple(type(x).__name__ for x in states)))
    else:
        own = (("dim", spec.size),)
    return (
        ("role", spec.role),
        *own,
        ("size", spec.size),
        ("kind", cpd.name),
        ("discrete parents", cpd.parents),
        ("continuous parents", cpd.inputs),
    )
