"""What a network is declared from: its features and its action parameters.

A feature is discrete (named states) or continuous (a vector); an action parameter is a
continuous value some actions take (paper §III, "tap with force F") together with a
cluster that cuts its range into equidistant cells. These declarations are frozen and
checked when made; :class:`~models.declaration.EffectNetwork` puts them together.
"""

from __future__ import annotations

import math
from collections.abc import Hashable
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
from effect_networks.models.dtype import DTYPE

FeatureKind = Literal["object", "meta", "world"]
_KINDS = ("object", "meta", "world")


def check_name(name: str, what: str) -> None:
    """Raise ``ValueError`` unless ``name`` is a Python identifier; ``what`` names its role."""
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
        check_name(self.name, "feature")
        if isinstance(self.states, str | bytes) or not hasattr(self.states, "__iter__"):
            raise ValueError(
                f"feature {self.name!r}: states must be a sequence of labels, got {self.states!r}"
            )
        if isinstance(self.states, set | frozenset):  # the order gives each state its index
            raise ValueError(
                f"feature {self.name!r}: states must be an ordered sequence (a tuple or a "
                f"list), got the set {self.states!r}, whose order may change between runs"
            )
        states = (json_label(s, f"feature {self.name!r}: state") for s in self.states)
        object.__setattr__(self, "states", tuple(states))
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
        """The number of states."""
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
        check_name(self.name, "feature")
        if not isinstance(self.dim, int) or self.dim < 1:
            raise ValueError(f"feature {self.name!r}: dim must be a positive int, got {self.dim!r}")
        if self.kind not in _KINDS:
            raise ValueError(f"feature {self.name!r}: kind {self.kind!r} is not one of {_KINDS}")


Feature = Discrete | Continuous

#: How a parameter's clusters relate to its value (:class:`Parameter`'s ``layout``).
LAYOUTS = ("grid", "adaptive")


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
    affects : str or sequence of str
        The feature(s) whose end state the parameter acts on. A continuous feature takes
        the value as a linear input; a discrete feature depends on the value's cell (the
        cluster joins its parents), which keeps every query exact. A feature may be
        affected by several parameters, and a parameter may act on several continuous
        features if it is the only parameter acting on each (an unknown value couples
        them; queries integrate it out of their joint).
    layout : {"grid", "adaptive"}
        How rows are clustered; the model is the same mixture under both (the cluster
        from the action's table, the value from the cluster's untruncated Gaussian; see
        :mod:`models.model`). ``"grid"`` (the paper's): a row giving the value without
        its cluster is read as observing the value's equidistant cell as its cluster,
        and :func:`inference.fit` fits each cluster's Gaussian in closed form.
        ``"adaptive"``: the ``prod(bins)`` clusters are latent mixture components whose
        Gaussians may lie anywhere; no cell is read, the cluster prior is the mixture's
        weights, and the cells only seed :func:`inference.fit_em`, which fits the layout
        by expectation-maximisation.
    """

    name: str
    low: tuple[float, ...]
    high: tuple[float, ...]
    bins: tuple[int, ...]
    actions: tuple[str, ...]
    affects: str | tuple[str, ...]
    layout: str = "grid"

    def __post_init__(self) -> None:
        check_name(self.name, "parameter")
        if not isinstance(self.affects, str):
            affects = tuple(self.affects) if hasattr(self.affects, "__iter__") else ()
            if not affects or not all(isinstance(f, str) for f in affects):
                raise ValueError(
                    f"parameter {self.name!r}: affects must be a feature name or a non-empty "
                    f"sequence of them, got {self.affects!r}"
                )
            if len(set(affects)) != len(affects):
                raise ValueError(f"parameter {self.name!r} affects a feature twice: {affects}")
            object.__setattr__(self, "affects", affects[0] if len(affects) == 1 else affects)
        object.__setattr__(self, "low", _numbers(self.name, "low", self.low, float))
        object.__setattr__(self, "high", _numbers(self.name, "high", self.high, float))
        object.__setattr__(self, "bins", _numbers(self.name, "bins", self.bins, int))
        actions = (self.actions,) if isinstance(self.actions, str) else tuple(self.actions)
        what = f"parameter {self.name!r}: action"
        actions = tuple(json_label(a, what, "action names") for a in actions)
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
        if self.layout not in LAYOUTS:
            raise ValueError(
                f"parameter {self.name!r}: layout must be one of {LAYOUTS}, got {self.layout!r}"
            )

    @property
    def adaptive(self) -> bool:
        """Whether the clusters are latent components (``layout="adaptive"``), not cells."""
        return self.layout == "adaptive"

    @property
    def dim(self) -> int:
        """The parameter's dimension."""
        return len(self.low)

    @property
    def features(self) -> tuple[str, ...]:
        """The features the parameter affects."""
        return (self.affects,) if isinstance(self.affects, str) else self.affects

    @property
    def n_clusters(self) -> int:
        """The number of clusters: the product of the cells per dimension."""
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


def json_label(label: object, what: str, kinds: str = "states") -> Hashable:
    """A label as a plain JSON scalar (numpy and 0-d torch scalars become Python ones).

    ``what`` names the label in the error (``"feature 'door': state"``, ``"action"``),
    ``kinds`` what such labels are (``"states"``, ``"action names"``).
    """
    if isinstance(label, np.generic) or isinstance(label, torch.Tensor) and label.dim() == 0:
        label = label.item()
    if label is not None and not isinstance(label, str | bool | int | float):
        raise ValueError(
            f"{what} {label!r} is a {type(label).__name__}; {kinds} must be str, int, float, "
            "bool or None (they are saved as JSON). Name a composite one with a string, e.g. "
            "'a-b' for ('a', 'b')"
        )
    if isinstance(label, float) and not math.isfinite(label):
        raise ValueError(f"{what} {label!r} is not a finite number")
    return label


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
