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
from collections.abc import Hashable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import torch

FeatureKind = Literal["object", "meta", "world"]
_KINDS = ("object", "meta", "world")

ACTION = "action"
DTYPE = torch.float64  # every continuous value and every probability is float64


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
        object.__setattr__(self, "states", tuple(self.states))
        if len(self.states) < 2:
            raise ValueError(f"feature {self.name!r} needs at least two states, got {self.states}")
        if len(set(self.states)) != len(self.states):
            raise ValueError(f"feature {self.name!r} has repeated states: {self.states}")
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
        for attr in ("low", "high", "bins", "actions"):
            value = getattr(self, attr)
            object.__setattr__(
                self, attr, (value,) if isinstance(value, int | float | str) else tuple(value)
            )
        d = len(self.low)
        if d == 0 or len(self.high) != d or len(self.bins) != d:
            raise ValueError(
                f"parameter {self.name!r}: low, high and bins must have the same length >= 1, "
                f"got {len(self.low)}, {len(self.high)}, {len(self.bins)}"
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
        """``(n_actions,)`` bool: which actions use ``parameter``."""
        return torch.tensor([a in parameter.actions for a in self.actions])

    def action_index(self, action: str) -> int:
        try:
            return self.actions.index(action)
        except ValueError:
            raise ValueError(
                f"unknown action {action!r}; actions are {list(self.actions)}"
            ) from None

    # ----------------------------------------------------------------- evidence
    def encode(self, evidence: Mapping[str, object]) -> dict[str, torch.Tensor]:
        """Validate evidence and turn it into tensors, one row per query.

        Keys are site names (``initial.f``, ``end.f``, ``action``, ``param.p``,
        ``cluster.p``). Discrete values are state labels (a label or a sequence of labels;
        action names for ``action``), or a ``torch.long`` tensor of state indices.
        Continuous values are floats of shape ``(n, dim)`` (or ``(dim,)`` for one row).
        All values must have the same number of rows ``n``.

        Raises
        ------
        ValueError
            Naming the site and the problem: unknown site, unknown state, wrong
            dimension, NaN or inf, or rows that disagree in number.
        """
        encoded: dict[str, torch.Tensor] = {}
        for name, value in evidence.items():
            if name not in self._sites:
                raise ValueError(
                    f"evidence on site {name!r}, which does not exist; sites are {list(self._sites)}"
                )
            spec = self._sites[name]
            encoded[name] = (
                self._encode_discrete(spec, value)
                if spec.discrete
                else self._encode_continuous(spec, value)
            )
        rows = {name: v.shape[0] for name, v in encoded.items()}
        if len(set(rows.values())) > 1:
            raise ValueError(f"evidence rows disagree in number: {rows}")
        return encoded

    def _labels(self, spec: SiteSpec) -> tuple[Hashable, ...]:
        if spec.role == "action":
            return self.actions
        if spec.role == "cluster":
            return tuple(range(spec.size))
        feature = self.feature(spec.feature)
        assert isinstance(feature, Discrete)
        return feature.states

    def _encode_discrete(self, spec: SiteSpec, value: object) -> torch.Tensor:
        if (
            isinstance(value, torch.Tensor)
            and not value.is_floating_point()
            and value.dtype != torch.bool
        ):
            index = (
                value
                if value.dtype == torch.long and value.dim() == 1
                else value.long().reshape(-1)
            )
            if index.numel():
                low, high = (int(v) for v in torch.aminmax(index))
                if low < 0 or high >= spec.size:
                    bad = index[(index < 0) | (index >= spec.size)][0]
                    raise ValueError(
                        f"site {spec.name!r}: state index {int(bad)} outside 0..{spec.size - 1}"
                    )
            return index
        labels = self._labels(spec)
        lookup = {label: i for i, label in enumerate(labels)}
        values = [value] if _is_scalar_label(value) else list(value)
        out = []
        for v in values:
            v = v.item() if hasattr(v, "item") else v
            if v not in lookup:
                shown = (
                    list(labels)
                    if len(labels) <= 12
                    else f"{list(labels[:12])} ... ({len(labels)} states)"
                )
                raise ValueError(
                    f"site {spec.name!r}: value {v!r} is not one of its states {shown}"
                )
            out.append(lookup[v])
        return torch.tensor(out, dtype=torch.long)

    def _encode_continuous(self, spec: SiteSpec, value: object) -> torch.Tensor:
        x = torch.as_tensor(value, dtype=DTYPE)
        if x.dim() == 1 and spec.size > 1 or x.dim() == 0:
            x = x.reshape(1, -1)
        elif x.dim() == 1:
            x = x.reshape(-1, 1)
        if x.dim() != 2 or x.shape[-1] != spec.size:
            raise ValueError(
                f"site {spec.name!r}: expected shape (n, {spec.size}), got {tuple(torch.as_tensor(value).shape)}"
            )
        bad = ~torch.isfinite(x)
        if spec.role == "param":
            # A parameter is missing (all NaN) in rows whose action does not use it.
            bad = bad & ~torch.isnan(x).all(-1, keepdim=True)
        if bad.any():
            row = int(bad.any(-1).nonzero()[0])
            raise ValueError(f"site {spec.name!r}: NaN or inf in row {row}: {x[row].tolist()}")
        return x

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


def _is_scalar_label(value: object) -> bool:
    if isinstance(value, str | bytes | bool | int | float):
        return True
    if isinstance(value, torch.Tensor):
        return value.dim() == 0
    return not isinstance(value, Sequence) and not hasattr(value, "__len__")
