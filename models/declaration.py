"""What an effect network is: its features, actions and action parameters.

The paper's Fig. 1 structure is built from a small, frozen declaration::

    initial.f1   initial.f2   ...        (one root site per feature, state before the action)
        |  \\      /  |
        |   \\    /   |      action       (one discrete root site, enumerated)
        |    \\  /    |     /
        |     \\/     |    /    cluster.p --> param.p     (optional action parameter)
        v     /\\     v   v        |             |
    end.f1   end.f2   ...  <-------+-------------+  (only the feature the parameter affects)

Every initial site is a parent of every end site, the action is a parent of every end
site, and there are no edges among end sites. An action parameter (paper §III, "tap with
force F") adds a continuous site ``param.<name>`` and a discrete site ``cluster.<name>``
that cuts the parameter's range into equidistant cells; per cluster one joint Gaussian of
the parameter and the feature it affects (a mixture of Gaussians).

A declaration holds structure only. Fitted numbers live in :mod:`models.params`.
"""

from __future__ import annotations

import math
from collections.abc import Hashable, Mapping
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch

from models.evidence import DTYPE, Evidence, decode, encode

FeatureKind = Literal["object", "meta", "world"]
_KINDS = ("object", "meta", "world")

ACTION = "action"


def initial_site(feature: str) -> str:
    """Site name of a feature's initial state."""
    return f"initial.{feature}"


def end_site(feature: str) -> str:
    """Site name of a feature's end state."""
    return f"end.{feature}"


def param_site(parameter: str) -> str:
    """Site name of an action parameter's value."""
    return f"param.{parameter}"


def cluster_site(parameter: str) -> str:
    """Site name of an action parameter's equidistant cluster."""
    return f"cluster.{parameter}"


def _check_name(name: str, what: str) -> None:
    if not isinstance(name, str) or not name.isidentifier():
        raise ValueError(f"{what} name {name!r} must be a Python identifier (letters, digits, _)")


@dataclass(frozen=True)
class Discrete:
    """A discrete feature with named states (e.g. ``visible`` in ``(False, True)``)."""

    name: str
    states: tuple[Hashable, ...]
    kind: FeatureKind = "object"
    initial: bool = True

    def __post_init__(self) -> None:
        _check_name(self.name, "feature")
        if isinstance(self.states, str | bytes) or not hasattr(self.states, "__iter__"):
            raise ValueError(
                f"feature {self.name!r}: states must be a sequence of labels, got {self.states!r}"
            )
        object.__setattr__(self, "states", tuple(_state_label(self.name, s) for s in self.states))
        if len(self.states) < 2:
            raise ValueError(f"feature {self.name!r} needs at least two states, got {self.states}")
        if len(set(self.states)) != len(self.states):
            raise ValueError(
                f"feature {self.name!r} has repeated states: {self.states} (Python counts "
                "1, 1.0 and True as one value)"
            )
        if self.kind not in _KINDS:
            raise ValueError(f"feature {self.name!r}: kind {self.kind!r} is not one of {_KINDS}")

    @property
    def cardinality(self) -> int:
        return len(self.states)


@dataclass(frozen=True)
class Continuous:
    """A continuous feature, a vector of dimension ``dim``.

    ``initial=False`` declares an outcome feature that exists only after the action (the
    hit point of a throw): it has an end site and no initial site.
    """

    name: str
    dim: int = 1
    kind: FeatureKind = "object"
    initial: bool = True

    def __post_init__(self) -> None:
        _check_name(self.name, "feature")
        if not isinstance(self.dim, int) or self.dim < 1:
            raise ValueError(f"feature {self.name!r}: dim must be a positive int, got {self.dim!r}")
        if self.kind not in _KINDS:
            raise ValueError(f"feature {self.name!r}: kind {self.kind!r} is not one of {_KINDS}")


Feature = Discrete | Continuous


@dataclass(frozen=True)
class Parameter:
    """A continuous action parameter with an equidistant cluster site.

    Parameters
    ----------
    name : str
        Parameter name; sites ``param.<name>`` and ``cluster.<name>``.
    low, high : sequence of float, length d
        The parameter's range per dimension; clusters cut it into equal cells.
    bins : sequence of int, length d
        Cells per dimension; the cluster site has ``prod(bins)`` states, row-major.
    actions : sequence of str
        The actions that use the parameter. For other actions it is not observed.
    affects : str
        The continuous feature whose end state the parameter acts on.
    """

    name: str
    low: tuple[float, ...]
    high: tuple[float, ...]
    bins: tuple[int, ...]
    actions: tuple[str, ...]
    affects: str

    def __post_init__(self) -> None:
        _check_name(self.name, "parameter")
        object.__setattr__(self, "low", _numbers(self.name, "low", self.low, float))
        object.__setattr__(self, "high", _numbers(self.name, "high", self.high, float))
        object.__setattr__(self, "bins", _numbers(self.name, "bins", self.bins, int))
        actions = (self.actions,) if isinstance(self.actions, str) else tuple(self.actions)
        object.__setattr__(self, "actions", actions)
        d = len(self.low)
        if d == 0 or len(self.high) != d or len(self.bins) != d:
            raise ValueError(
                f"parameter {self.name!r}: low, high and bins must have the same length >= 1, "
                f"got {len(self.low)}, {len(self.high)}, {len(self.bins)}"
            )
        if not all(math.isfinite(v) for v in self.low + self.high):
            raise ValueError(
                f"parameter {self.name!r}: low and high must be finite, got {self.low}, {self.high}"
            )
        if any(not lo < hi for lo, hi in zip(self.low, self.high, strict=True)):
            raise ValueError(
                f"parameter {self.name!r}: need low < high, got {self.low}, {self.high}"
            )
        if any(not isinstance(b, int) or b < 1 for b in self.bins):
            raise ValueError(
                f"parameter {self.name!r}: bins must be positive ints, got {self.bins}"
            )
        if not self.actions:
            raise ValueError(f"parameter {self.name!r}: name the actions that use it")

    @property
    def dim(self) -> int:
        return len(self.low)

    @property
    def n_clusters(self) -> int:
        return math.prod(self.bins)

    def cluster_of(self, values: torch.Tensor) -> torch.Tensor:
        """Equidistant cell of each value: ``(n, d)`` float -> ``(n,)`` long, row-major.

        Values outside the range fall into the nearest edge cell.
        """
        values = torch.as_tensor(values, dtype=DTYPE)
        low = values.new_tensor(self.low)
        high = values.new_tensor(self.high)
        bins = torch.tensor(self.bins)
        cell = ((values - low) / (high - low) * bins).floor().long()
        cell = torch.minimum(cell.clamp(min=0), bins - 1)
        index = torch.zeros(values.shape[:-1], dtype=torch.long)
        for k in range(self.dim):
            index = index * self.bins[k] + cell[..., k]
        return index

    def cluster_centres(self) -> torch.Tensor:
        """Centres of the ``n_clusters`` cells, ``(n_clusters, d)``, row-major."""
        axes = [
            torch.linspace(lo, hi, 2 * b + 1, dtype=DTYPE)[1::2]
            for lo, hi, b in zip(self.low, self.high, self.bins, strict=True)
        ]
        grid = torch.meshgrid(*axes, indexing="ij")
        return torch.stack([g.reshape(-1) for g in grid], dim=-1)


@dataclass(frozen=True)
class SiteSpec:
    """One Pyro sample site of a network: its name, type and size."""

    name: str
    discrete: bool
    size: int  # number of states (discrete) or dimension (continuous)
    role: Literal["initial", "action", "cluster", "param", "end"]
    feature: str | None = None


@dataclass(frozen=True)
class EffectNetwork:
    """The structure of an effect network (paper Fig. 1), built from a declaration.

    Examples
    --------
    >>> net = EffectNetwork(
    ...     features=(Discrete("visible", (False, True)), Continuous("position", 2)),
    ...     actions=("remove", "tap"),
    ... )
    >>> [s.name for s in net.sites]
    ['initial.visible', 'initial.position', 'action', 'end.visible', 'end.position']
    """

    features: tuple[Feature, ...]
    actions: tuple[str, ...]
    parameters: tuple[Parameter, ...] = ()
    _sites: dict[str, SiteSpec] = field(init=False, repr=False, compare=False)
    _uses: dict[str, torch.Tensor] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
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
        affected = [p.affects for p in self.parameters]
        for p in self.parameters:
            target = by_name.get(p.affects)
            if not isinstance(target, Continuous):
                raise ValueError(
                    f"parameter {p.name!r} affects {p.affects!r}, which must be a continuous "
                    f"feature of this network (continuous features: "
                    f"{[f.name for f in self.features if isinstance(f, Continuous)]})"
                )
            unknown = set(p.actions) - set(self.actions)
            if unknown:
                raise ValueError(f"parameter {p.name!r} names unknown actions {sorted(unknown)}")
        if len(set(affected)) != len(affected):
            raise ValueError("at most one parameter may affect each feature")
        sites: dict[str, SiteSpec] = {}
        for f in self.features:
            if f.initial:
                sites[initial_site(f.name)] = _spec(initial_site(f.name), f, "initial")
        sites[ACTION] = SiteSpec(ACTION, True, len(self.actions), "action")
        for p in self.parameters:
            sites[cluster_site(p.name)] = SiteSpec(
                cluster_site(p.name), True, p.n_clusters, "cluster"
            )
            sites[param_site(p.name)] = SiteSpec(param_site(p.name), False, p.dim, "param")
        for f in self.features:
            sites[end_site(f.name)] = _spec(end_site(f.name), f, "end")
        object.__setattr__(self, "_sites", sites)
        uses = {
            p.name: torch.tensor([a in p.actions for a in self.actions]) for p in self.parameters
        }
        object.__setattr__(self, "_uses", uses)

    # ----------------------------------------------------------------- structure
    @property
    def sites(self) -> tuple[SiteSpec, ...]:
        """All sites in the order the model samples them."""
        return tuple(self._sites.values())

    def site(self, name: str) -> SiteSpec:
        try:
            return self._sites[name]
        except KeyError:
            raise KeyError(
                f"site {name!r} does not exist in this network; its sites are {list(self._sites)}"
            ) from None

    def feature(self, name: str) -> Feature:
        for f in self.features:
            if f.name == name:
                return f
        raise KeyError(
            f"feature {name!r} is not declared; features: {[f.name for f in self.features]}"
        )

    def parameter_of(self, feature: str) -> Parameter | None:
        """The action parameter that acts on ``feature``, if any."""
        return next((p for p in self.parameters if p.affects == feature), None)

    def discrete_parents(self, feature: str) -> tuple[str, ...]:
        """Discrete parent sites of ``end.<feature>``, in table-axis order."""
        parents = [
            initial_site(f.name) for f in self.features if f.initial and isinstance(f, Discrete)
        ]
        parents.append(ACTION)
        p = self.parameter_of(feature)
        if p is not None:
            parents.append(cluster_site(p.name))
        return tuple(parents)

    def continuous_parents(self, feature: str) -> tuple[str, ...]:
        """Continuous parent sites of ``end.<feature>``, concatenated in this order."""
        parents = [
            initial_site(f.name) for f in self.features if f.initial and isinstance(f, Continuous)
        ]
        p = self.parameter_of(feature)
        if p is not None:
            parents.append(param_site(p.name))
        return tuple(parents)

    def uses_parameter(self, parameter: Parameter) -> torch.Tensor:
        """``(n_actions,)`` bool: which actions use ``parameter`` (a copy)."""
        return self._uses[parameter.name].clone()

    def action_index(self, action: str) -> int:
        try:
            return self.actions.index(action)
        except ValueError:
            raise ValueError(
                f"unknown action {action!r}; actions are {list(self.actions)}"
            ) from None

    # ----------------------------------------------------------------- evidence
    def encode(self, evidence: Mapping[str, object]) -> Evidence:
        """Validate evidence given as state labels and encode it, one row per query.

        Keys are site names (``initial.f``, ``end.f``, ``action``, ``param.p``,
        ``cluster.p``). Discrete values are state labels in any container (a label, a
        list, a numpy array, a torch tensor); action names for ``action``. Continuous
        values are numbers of shape ``(n, dim)`` (or ``(dim,)`` for one row). All values
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
        return self._uses[parameter.name][action]

    # ----------------------------------------------------------------- serialisation
    def to_dict(self) -> dict:
        """A JSON-able description (states must be JSON scalars to round-trip)."""
        return {
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
                    "affects": p.affects,
                }
                for p in self.parameters
            ],
        }

    @classmethod
    def from_dict(cls, d: Mapping) -> EffectNetwork:
        features: list[Feature] = []
        for f in d["features"]:
            if f["type"] == "discrete":
                features.append(Discrete(f["name"], tuple(f["states"]), f["kind"], f["initial"]))
            else:
                features.append(Continuous(f["name"], f["dim"], f["kind"], f["initial"]))
        params = [Parameter(**p) for p in d["parameters"]]
        return cls(tuple(features), tuple(d["actions"]), tuple(params))


def _spec(name: str, f: Feature, role: Literal["initial", "end"]) -> SiteSpec:
    if isinstance(f, Discrete):
        return SiteSpec(name, True, f.cardinality, role, f.name)
    return SiteSpec(name, False, f.dim, role, f.name)


def _state_label(feature: str, state: object) -> Hashable:
    """A state as a plain JSON scalar (numpy and 0-d torch scalars become Python ones)."""
    if isinstance(state, np.generic) or isinstance(state, torch.Tensor) and state.dim() == 0:
        state = state.item()
    if state is not None and not isinstance(state, str | bool | int | float):
        raise ValueError(
            f"feature {feature!r}: state {state!r} is a {type(state).__name__}; states must be "
            "str, int, float, bool or None (they are saved as JSON). Name a composite state "
            "with a string, e.g. 'a-b' for ('a', 'b')"
        )
    if isinstance(state, float) and not math.isfinite(state):
        raise ValueError(f"feature {feature!r}: state {state!r} is not a finite number")
    return state


def _numbers(parameter: str, attr: str, value: object, kind: type) -> tuple:
    """``low``, ``high`` or ``bins`` as a tuple of Python floats or ints."""
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().numpy()
    array = np.atleast_1d(np.asarray(value))
    ok = array.ndim == 1 and (
        array.dtype.kind in "iu" if kind is int else array.dtype.kind in "iuf"
    )
    if not ok:
        what = "positive ints" if kind is int else "numbers"
        raise ValueError(
            f"parameter {parameter!r}: {attr} must be a number or a sequence of {what}, "
            f"got {value!r}"
        )
    return tuple(kind(v) for v in array.tolist())
