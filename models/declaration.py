"""What an effect network is: its features, actions and action parameters.

The paper's Fig. 1 structure is built from a small, frozen declaration::

    initial.f1   initial.f2   ...        (one root site per feature, state before the action)
        |  \\      /  |
        |   \\    /   |      action       (one discrete root site, enumerated)
        |    \\  /    |     /
        |     \\/     |    /    cluster.p --> param.p     (optional action parameter)
        v     /\\     v   v        |             |
    end.f1   end.f2   ...  <-------+-------------+  (only the features the parameter affects)

By default (the paper's Fig. 1) every initial site is a parent of every end site, the
action is a parent of every end site, and there are no edges among end sites;
``EffectNetwork(..., parents=...)`` declares other parent sets (checked: no cycle, no end
site before an initial one), and ``kinds=`` other conditional-distribution kinds. An action parameter (paper §III, "tap with
force F") adds a continuous site ``param.<name>`` and a discrete site ``cluster.<name>``
that cuts the parameter's range into equidistant cells; per cluster one joint Gaussian of
the parameter and the continuous features it affects (a mixture of Gaussians); a
discrete feature it affects depends on the cluster.

A declaration holds structure only. Fitted numbers live in :mod:`models.params`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Literal

import torch

from models.cpds import (
    CPD,
    KINDS,
    LinearGaussianCPD,
    ParameterMixture,
    TableCPD,
    default_kind,
)
from models.dtype import DTYPE
from models.evidence import Evidence, decode, encode
from models.features import LAYOUTS, Continuous, Discrete, Feature, FeatureKind, Parameter
from models.sites import ACTION, SiteSpec, cluster_site, end_site, initial_site, param_site

__all__ = [  # the names callers import from here
    "ACTION",
    "DTYPE",
    "LAYOUTS",
    "MAX_CPD_ENTRIES",
    "Continuous",
    "Discrete",
    "EffectNetwork",
    "Feature",
    "FeatureKind",
    "Parameter",
    "SiteSpec",
    "cluster_site",
    "end_site",
    "initial_site",
    "param_site",
]

#: The most numbers one site's conditional distribution may hold, all its tensors
#: together (a table: parent configurations x states; a linear Gaussian: configurations x
#: (d + d * inputs + d * d + 1)). A declaration beyond it is refused, naming the site,
#: before anything of that size is allocated: 10**8 float64 numbers are 800 MB, and
#: fitting or querying needs several such arrays.
MAX_CPD_ENTRIES = 10**8


@dataclass(frozen=True)
class EffectNetwork:
    """The structure of an effect network, built from a declaration.

    Parameters
    ----------
    features, actions, parameters
        What the network holds (see :class:`Discrete`, :class:`Continuous`,
        :class:`Parameter`).
    parents
        Parent sites per site, ``{"end.f": ("initial.f", "action"), ...}``, for the sites
        whose parents differ from the paper's Fig. 1 (every initial feature and the
        action are parents of every end feature; initial features are roots). An end
        site may have initial sites, the action and *discrete* end sites as parents; an
        initial site only other initial sites. A parameter's cluster and value are
        added to the parents of the feature it affects; they are not named here.
    kinds
        A conditional-distribution kind per site, by name (``"table"``, ``"softmax"``,
        ``"linear_gaussian"``) or as a :class:`~models.cpds.CPD` subclass, for sites
        that should not get their default kind (:func:`models.cpds.default_kind`).

    Raises
    ------
    ValueError
        Naming the offending feature, site or kind: unknown names, a cycle, an end
        site (or the action) as a parent of an initial one, a continuous end site as a
        parent, a kind that cannot model its site, a site whose conditional distribution
        would hold more than :data:`MAX_CPD_ENTRIES` numbers (too many bins, or too many
        discrete parents' configurations).

    Examples
    --------
    >>> net = EffectNetwork(
    ...     features=(Discrete("visible", (False, True)), Continuous("position", 2)),
    ...     actions=("remove", "tap"),
    ... )
    >>> [s.name for s in net.sites]
    ['initial.visible', 'initial.position', 'action', 'end.visible', 'end.position']
    >>> EffectNetwork(
    ...     features=(Discrete("visible", (False, True)), Continuous("position", 2)),
    ...     actions=("remove", "tap"),
    ...     parents={"end.visible": ("initial.visible", "action")},
    ... ).cpd("end.visible").name
    'table'
    """

    features: tuple[Feature, ...]
    actions: tuple[str, ...]
    parameters: tuple[Parameter, ...] = ()
    parents: tuple[tuple[str, tuple[str, ...]], ...] = ()
    kinds: tuple[tuple[str, type[CPD]], ...] = ()
    _sites: dict[str, SiteSpec] = field(init=False, repr=False, compare=False)
    _cpds: dict[str, CPD] = field(init=False, repr=False, compare=False)
    _mixtures: dict[str, ParameterMixture] = field(init=False, repr=False, compare=False)
    _identity: dict[str, tuple] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if isinstance(self.actions, str | bytes) or not hasattr(self.actions, "__iter__"):
            raise ValueError(
                f"actions must be a sequence of action names, got {self.actions!r} (one "
                f"action is written ({self.actions!r},))"
            )
        if isinstance(self.actions, set | frozenset):  # the order gives each action its index
            raise ValueError(
                f"actions must be an ordered sequence (a tuple or a list), got the set "
                f"{self.actions!r}, whose order may change between runs"
            )
        object.__setattr__(self, "features", tuple(self.features))
        object.__setattr__(self, "actions", tuple(self.actions))
        object.__setattr__(self, "parameters", tuple(self.parameters))
        if not self.features:
            raise ValueError("an effect network needs at least one feature")
        if not self.actions or len(set(self.actions)) != len(self.actions):
            raise ValueError(
                f"actions must be a non-empty tuple of distinct names, got {self.actions}"
            )
        names = [f.name for f in self.features] + [p.name for p in self.parameters]
        if len(set(names)) != len(names):
            raise ValueError(f"feature and parameter names must be distinct, got {names}")
        by_name = {f.name: f for f in self.features}
        for p in self.parameters:
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
                if len(continuous) > 1
                and any(f in q.features for q in self.parameters if q is not p)
            ]
            if crowded:
                raise ValueError(
                    f"parameter {p.name!r} acts on several continuous features, so it must "
                    f"be the only parameter acting on each; {crowded} have others (an "
                    "unknown value would couple the parameters). Merge them into one "
                    "parameter of higher dimension"
                )
            shared = [
                f for f in p.features if any(f in q.features for q in self.parameters if q is not p)
            ]
            if p.adaptive and shared:
                raise ValueError(
                    f"parameter {p.name!r} has the adaptive layout, so it must be the only "
                    f"parameter acting on its features; {shared} have others (a given value "
                    "of an adaptive parameter does not fix its cluster)"
                )
            unknown = set(p.actions) - set(self.actions)
            if unknown:
                raise ValueError(f"parameter {p.name!r} names unknown actions {sorted(unknown)}")
        declared: dict[str, SiteSpec] = {}
        for f in self.features:
            if f.initial:
                declared[initial_site(f.name)] = _spec(initial_site(f.name), f, "initial")
        declared[ACTION] = SiteSpec(ACTION, True, len(self.actions), "action")
        for p in self.parameters:
            declared[cluster_site(p.name)] = SiteSpec(
                cluster_site(p.name), True, p.n_clusters, "cluster"
            )
            declared[param_site(p.name)] = SiteSpec(param_site(p.name), False, p.dim, "param")
        for f in self.features:
            declared[end_site(f.name)] = _spec(end_site(f.name), f, "end")
        parents = _parents(self, declared)
        object.__setattr__(self, "parents", _explicit(parents, _fig1_parents(declared)))
        sites = {name: declared[name] for name in _topological(declared, parents)}
        object.__setattr__(self, "_sites", sites)
        object.__setattr__(self, "kinds", _kinds(self.kinds, sites))
        _build_cpds(self, sites, parents)
        object.__setattr__(self, "_identity", {s: _site_identity(self, s) for s in sites})

    # ----------------------------------------------------------------- structure
    @property
    def sites(self) -> tuple[SiteSpec, ...]:
        """All sites in the order the model samples them (parents before children)."""
        return tuple(self._sites.values())

    def site(self, name: str) -> SiteSpec:
        try:
            return self._sites[name]
        except KeyError:
            raise KeyError(
                f"site {name!r} does not exist in this network; its sites are {list(self._sites)}"
            ) from None

    def cpd(self, site: str) -> CPD:
        """The conditional-distribution kind of ``site`` (its parents, sizes and form)."""
        self.site(site)
        return self._cpds[site]

    @property
    def mixtures(self) -> tuple[ParameterMixture, ...]:
        """The cluster/value pair of every action parameter, in declaration order."""
        return tuple(self._mixtures.values())

    def mixture(self, parameter: str) -> ParameterMixture:
        """The :class:`~models.cpds.ParameterMixture` of the parameter named ``parameter``."""
        try:
            return self._mixtures[parameter]
        except KeyError:
            raise ValueError(
                f"unknown parameter {parameter!r}; parameters: {list(self._mixtures)}"
            ) from None

    def acting_on(self, site: str) -> tuple[ParameterMixture, ...]:
        """The parameters whose values are inputs of the continuous ``site``, in input order."""
        return tuple(m for m in self._mixtures.values() if site in m.continuous)

    def feature(self, name: str) -> Feature:
        for f in self.features:
            if f.name == name:
                return f
        raise KeyError(
            f"feature {name!r} is not declared; features: {[f.name for f in self.features]}"
        )

    def parameter_of(self, feature: str) -> Parameter | None:
        """The first action parameter that acts on ``feature``, if any."""
        return next((p for p in self.parameters if feature in p.features), None)

    def discrete_parents(self, feature: str) -> tuple[str, ...]:
        """Discrete parent sites of ``end.<feature>``, in table-axis order."""
        return self.cpd(end_site(feature)).parents

    def continuous_parents(self, feature: str) -> tuple[str, ...]:
        """Continuous parent sites of ``end.<feature>``, concatenated in this order."""
        return self.cpd(end_site(feature)).inputs

    def end_sites_needed(self, sites: Iterable[str]) -> set[str]:
        """The end sites among ``sites`` and every end site they depend on (their end
        ancestors): the end sites whose factors a query on ``sites`` must keep."""
        todo = [s for s in sites if s in self._sites and self._sites[s].role == "end"]
        needed: set[str] = set()
        while todo:
            s = todo.pop()
            if s not in needed:
                needed.add(s)
                todo.extend(q for q in self._cpds[s].parents if self._sites[q].role == "end")
        return needed

    def uses_parameter(self, parameter: Parameter) -> torch.Tensor:
        """``(n_actions,)`` bool: which actions use ``parameter`` (a copy)."""
        return self._mixtures[parameter.name].uses.clone()

    def action_index(self, action: str) -> int:
        try:
            return self.actions.index(action)
        except ValueError:
            raise ValueError(
                f"unknown action {action!r}; actions are {list(self.actions)}"
            ) from None

    def identity(self) -> dict[str, tuple[tuple[str, object], ...]]:
        """What fitted parameters depend on, per site: ``{site: ((what, value), ...)}``.

        A discrete site's states in order (with their types: ``1`` and ``True`` are
        different labels), a continuous site's dimension, the actions in order, a
        parameter's range, bins, layout and the actions using it, and every site's kind
        and parents in table-axis and input order. Two declarations with the same
        identity give their parameters the same meaning; a feature's ``kind`` metadata
        is not part of it. :class:`~models.params.NetworkParams` carry the identity of
        the network they were fitted for (:func:`models.params.check_params`).
        """
        return dict(self._identity)

    # ----------------------------------------------------------------- evidence
    def encode(self, evidence: Mapping[str, object]) -> Evidence:
        """Validate evidence given as state labels and encode it, one row per query.

        Keys are site names (``initial.f``, ``end.f``, ``action``, ``param.p``,
        ``cluster.p``). Discrete values are state labels in any container (a label, a
        list, a numpy array, a torch tensor); action names for ``action``. Continuous
        values are numbers of shape ``(n, dim)`` (or ``(dim,)`` for one row); a
        continuous end feature observed in some dimensions only is
        ``Partial(value, observed=mask)`` (:class:`models.evidence.Partial`). All values
        must have the same number of rows ``n``. Already encoded :class:`Evidence` is
        returned as it is. See :mod:`models.evidence` for the whole convention.

        Raises
        ------
        ValueError
            Naming the site and the problem: unknown site, unknown state, wrong
            dimension, NaN or inf, or rows that disagree in number.
        """
        return encode(self, evidence, indices=False)

    def encode_indices(self, evidence: Mapping[str, object]) -> Evidence:
        """Like :meth:`encode`, but discrete values are state *indices* ``0..K-1``.

        The one explicit path for indices (positions in the declared states, the
        actions or the clusters); everywhere else a discrete value is a label.
        """
        return encode(self, evidence, indices=True)

    def decode(self, site: str, index: torch.Tensor) -> list:
        """The state labels of ``(n,)`` state indices of a discrete site."""
        return decode(self, site, index)

    def parameter_in_use(self, parameter: Parameter, action: torch.Tensor) -> torch.Tensor:
        """Whether ``action`` (state indices, any shape) uses ``parameter``: bool, same shape.

        The rule every part of the toolkit applies: an action that does not use a
        parameter ignores its value. Its effect on the affected feature counts as zero
        (in the model, in fitting and in the closed-form marginal), its own density is
        left out, and its cluster sits on cell 0.
        """
        return self._mixtures[parameter.name].in_use(action)

    # ----------------------------------------------------------------- serialisation
    def to_dict(self) -> dict:
        """A JSON-able description (states must be JSON scalars to round-trip)."""
        d = {
            "features": [
                {
                    "type": "discrete",
                    "name": f.name,
                    "states": list(f.states),
                    "kind": f.kind,
                    "initial": f.initial,
                }
                if isinstance(f, Discrete)
                else {
                    "type": "continuous",
                    "name": f.name,
                    "dim": f.dim,
                    "kind": f.kind,
                    "initial": f.initial,
                }
                for f in self.features
            ],
            "actions": list(self.actions),
            "parameters": [
                {
                    "name": p.name,
                    "low": list(p.low),
                    "high": list(p.high),
                    "bins": list(p.bins),
                    "actions": list(p.actions),
                    "affects": p.affects if isinstance(p.affects, str) else list(p.affects),
                }
                | ({"layout": p.layout} if p.adaptive else {})  # older files read alike
                for p in self.parameters
            ],
        }
        if self.parents:  # only where the structure is not Fig. 1's (older files read alike)
            d["parents"] = {site: list(ps) for site, ps in self.parents}
        if self.kinds:
            d["kinds"] = {site: kind.name for site, kind in self.kinds}
        return d

    @classmethod
    def from_dict(cls, d: Mapping, kinds: Iterable[type[CPD]] = ()) -> EffectNetwork:
        """The network :meth:`to_dict` described; ``kinds``: the user-defined kinds it
        names (the toolkit's own are known)."""
        features: list[Feature] = []
        for f in d["features"]:
            if f["type"] == "discrete":
                features.append(Discrete(f["name"], tuple(f["states"]), f["kind"], f["initial"]))
            else:
                features.append(Continuous(f["name"], f["dim"], f["kind"], f["initial"]))
        params = [Parameter(**p) for p in d["parameters"]]
        known = {k.name: k for k in (*KINDS, *kinds)}
        named = {}
        for site, name in d.get("kinds", {}).items():
            if name not in known:
                raise ValueError(
                    f"site {site!r} has kind {name!r}, which is not one of {sorted(known)}; "
                    "pass the class of a kind you defined (load(path, kinds=(MyKind,)))"
                )
            named[site] = known[name]
        return cls(
            tuple(features),
            tuple(d["actions"]),
            tuple(params),
            parents={site: tuple(ps) for site, ps in d.get("parents", {}).items()},
            kinds=named,
        )


def _site_identity(net: EffectNetwork, site: str) -> tuple[tuple[str, object], ...]:
    """One site's part of :meth:`EffectNetwork.identity`."""
    spec, cpd = net._sites[site], net._cpds[site]
    own: tuple[tuple[str, object], ...]
    if spec.role == "action":
        own = (("actions", net.actions),)
    elif spec.role in ("cluster", "param"):
        p = next(p for p in net.parameters if site in (cluster_site(p.name), param_site(p.name)))
        own = (
            ("range", (p.low, p.high)),
            ("bins", p.bins),
            ("layout", p.layout),
            ("actions using it", tuple(a for a in net.actions if a in p.actions)),
        )
    elif spec.discrete:
        states = net.feature(spec.feature).states
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


def _spec(name: str, f: Feature, role: Literal["initial", "end"]) -> SiteSpec:
    if isinstance(f, Discrete):
        return SiteSpec(name, True, f.cardinality, role, f.name)
    return SiteSpec(name, False, f.dim, role, f.name)


# ---------------------------------------------------------------------------- structure
def _fig1_parents(sites: Mapping[str, SiteSpec]) -> dict[str, tuple[str, ...]]:
    """The paper's Fig. 1: initial sites are roots; every initial site and the action are
    parents of every end site."""
    initial = tuple(s for s, spec in sites.items() if spec.role == "initial")
    return {
        s: (initial + (ACTION,) if spec.role == "end" else ())
        for s, spec in sites.items()
        if spec.role in ("initial", "end")
    }


def _explicit(parents: Mapping, fig1: Mapping) -> tuple[tuple[str, tuple[str, ...]], ...]:
    """The declared parent sets that differ from Fig. 1's (as sets), in site order."""
    return tuple((s, parents[s]) for s in fig1 if set(parents[s]) != set(fig1[s]))


def _parents(net: EffectNetwork, sites: Mapping[str, SiteSpec]) -> dict[str, tuple[str, ...]]:
    """Every initial and end site's declared parents (Fig. 1's where not declared),
    checked: names, roles, duplicates, and the action for a parameter's feature."""
    given = net.parents
    if isinstance(given, Mapping):
        given = tuple(given.items())
    try:
        given = {str(site): ps for site, ps in given}
    except (TypeError, ValueError):
        raise ValueError(
            f"parents must map a site to its parent sites, e.g. "
            f"{{'end.f': ('initial.f', 'action')}}; got {net.parents!r}"
        ) from None
    parents = _fig1_parents(sites)
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
    for p in net.parameters:
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


def _topological(
    sites: Mapping[str, SiteSpec], parents: Mapping[str, tuple[str, ...]]
) -> list[str]:
    """Site names with parents before children, otherwise in declaration order; a cycle
    raises, naming its sites."""
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


def _kinds(given, sites: Mapping[str, SiteSpec]) -> tuple[tuple[str, type[CPD]], ...]:
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
    """Refuse a site whose fitted numbers would exceed :data:`MAX_CPD_ENTRIES`, before
    anything of that size is allocated."""
    entries = sum(math.prod(shape) for shape in cpd.shapes().values())
    if entries > MAX_CPD_ENTRIES:
        raise ValueError(
            f"site {cpd.site!r} would hold {entries:.3g} numbers ({why}); a site holds at "
            f"most MAX_CPD_ENTRIES = {MAX_CPD_ENTRIES:.0e}. Use fewer bins or states, or "
            "declare fewer parents (EffectNetwork(parents=...))"
        )


def _build_cpds(
    net: EffectNetwork, sites: Mapping[str, SiteSpec], parents: Mapping[str, tuple[str, ...]]
) -> None:
    """Every site's kind, the parameters' mixtures first (their sites join the parents of
    the features they affect)."""
    actions = len(net.actions)
    mixtures = {
        p.name: ParameterMixture.of(
            p,
            ACTION,
            torch.tensor([a in p.actions for a in net.actions]),
            cluster_site(p.name),
            param_site(p.name),
            tuple(end_site(f) for f in p.features),
            tuple(end_site(f) for f in p.features if not sites[end_site(f)].discrete),
        )
        for p in net.parameters
    }
    for m in mixtures.values():
        _check_size(m.cluster, f"parameter {m.parameter.name!r} has {m.parameter.n_clusters} cells")
        _check_size(m.value, f"parameter {m.parameter.name!r} has {m.parameter.n_clusters} cells")
    declared = dict(net.kinds)
    cpds: dict[str, CPD] = {}
    for site, spec in sites.items():
        if spec.role == "action":
            cpds[site] = TableCPD(site, (), (), actions)
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
    object.__setattr__(net, "_cpds", {s: cpds[s] for s in sites})
    object.__setattr__(net, "_mixtures", mixtures)
