r"""What an effect network is: its features, actions and action parameters.

The paper's Fig. 1 structure is built from a small, frozen declaration::

    initial.f1   initial.f2   ...        (one root site per feature, state before the action)
        |  \      /  |
        |   \    /   |      action       (one discrete root site, enumerated)
        |    \  /    |     /
        |     \/     |    /    cluster.p --> param.p     (optional action parameter)
        v     /\     v   v        |             |
    end.f1   end.f2   ...  <-------+-------------+  (only the features the parameter affects)

By default (the paper's Fig. 1) every initial site is a parent of every end site, the
action is a parent of every end site, and there are no edges among end sites;
``EffectNetwork(..., parents=...)`` declares other parent sets (checked: no cycle, no end
site before an initial one), and ``kinds=`` other conditional-distribution kinds. An action parameter (paper §III, "tap with
force F") adds a continuous site ``param.<name>`` and a discrete site ``cluster.<name>``
that cuts the parameter's range into equidistant cells; per cluster one joint Gaussian of
the parameter and the continuous features it affects (a mixture of Gaussians); a
discrete feature it affects depends on the cluster.

A declaration holds structure only. Fitted numbers live in :mod:`models.params`. The
parts it is declared from are in :mod:`models.features` (features, parameters) and
:mod:`models.sites` (the sites' names), the steps from a declaration to its structure
(sites, parents, order, kinds) in :mod:`models.structure`; their names callers use are
importable from here too.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import torch
from effect_networks.models.cpds import CPD, KINDS, ParameterMixture
from effect_networks.models.dtype import DTYPE
from effect_networks.models.evidence import Evidence, decode, encode
from effect_networks.models.features import (
    LAYOUTS,
    Continuous,
    Discrete,
    Feature,
    FeatureKind,
    Parameter,
)
from effect_networks.models.frames import as_data
from effect_networks.models.sites import (
    ACTION,
    SiteSpec,
    cluster_site,
    end_site,
    initial_site,
    param_site,
)
from effect_networks.models.structure import (
    MAX_CPD_ENTRIES,
    build_cpds,
    check_declaration,
    declared_sites,
    differing_from_fig1,
    fig1_parents,
    parents_of,
    resolve_kinds,
    site_identity,
    topological,
)

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
        features, actions, parameters = check_declaration(
            self.features, self.actions, self.parameters
        )
        object.__setattr__(self, "features", features)
        object.__setattr__(self, "actions", actions)
        object.__setattr__(self, "parameters", parameters)
        declared = declared_sites(features, actions, parameters)
        parents = parents_of(self.parents, parameters, declared)
        object.__setattr__(self, "parents", differing_from_fig1(parents, fig1_parents(declared)))
        sites = {name: declared[name] for name in topological(declared, parents)}
        object.__setattr__(self, "_sites", sites)
        object.__setattr__(self, "kinds", resolve_kinds(self.kinds, sites))
        cpds, mixtures = build_cpds(actions, parameters, dict(self.kinds), sites, parents)
        object.__setattr__(self, "_cpds", cpds)
        object.__setattr__(self, "_mixtures", mixtures)
        identity = {
            s: site_identity(spec, cpds[s], actions, parameters, features)
            for s, spec in sites.items()
        }
        object.__setattr__(self, "_identity", identity)

    # ----------------------------------------------------------------- structure
    @property
    def sites(self) -> tuple[SiteSpec, ...]:
        """All sites in the order the model samples them (parents before children)."""
        return tuple(self._sites.values())

    def site(self, name: str) -> SiteSpec:
        """The site named ``name``.

        Parameters
        ----------
        name
            A site's name, such as ``"initial.f"``, ``"action"`` or ``"end.f"``.

        Raises
        ------
        KeyError
            The network has no site of that name (the message names its sites).
        """
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
        """The declared feature named ``name``.

        Parameters
        ----------
        name
            The feature's name, without a role prefix.

        Raises
        ------
        KeyError
            No feature of that name is declared (the message names the features).
        """
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
        """The end sites among ``sites`` and every end site they depend on.

        Their end ancestors: the end sites whose factors a query on ``sites`` must keep.
        """
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
        """The index of ``action`` among the network's actions.

        Parameters
        ----------
        action
            An action's label.

        Raises
        ------
        ValueError
            ``action`` is not one of the network's actions (the message names them).
        """
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
        returned as it is. See :mod:`models.evidence` for the whole convention. A pandas
        ``DataFrame`` is read by the column convention of :mod:`models.frames`.

        Raises
        ------
        ValueError
            Naming the site and the problem: unknown site, unknown state, wrong
            dimension, NaN or inf, or rows that disagree in number.
        """
        return encode(self, as_data(self, evidence), indices=False)

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
        """The network :meth:`to_dict` described.

        ``kinds``: the user-defined kinds it names (the toolkit's own are known).
        """
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
