"""Evidence: values of a network's sites, validated and encoded for the model.

**The one convention.** Everywhere a user gives values (training rows, query evidence,
``effect_model``'s ``data``), a discrete site takes *state labels*: the states a feature
was declared with (``False``/``True``, ``"open"``, ``3``), action names for ``action``,
cluster numbers ``0..C-1`` for ``cluster.<p>``. That holds for every container: a label,
a list, a tuple, a numpy array or a torch tensor. For states ``(1, 2, 3)`` the values
``[1]``, ``np.array([1])`` and ``torch.tensor([1])`` all mean the state ``1``.

State *indices* (positions in the declared states, what the model computes with) enter
only through one named path, :meth:`EffectNetwork.encode_indices`, and come out of
:meth:`EffectNetwork.encode`. Both return :class:`Evidence`, which every query, ``fit``
and ``effect_model`` accept as already encoded, and which Pyro's handlers take as it is
(``pyro.condition(effect_model, data=net.encode({...}))``).

Continuous sites take floats of shape ``(n, dim)`` (``(dim,)`` is one row; for ``dim`` 1
a flat ``(n,)`` is ``n`` rows), any float or int dtype; they are stored as float64.
Complex numbers are refused (their imaginary part has no meaning here). NaN is refused
except in an action parameter ``param.<p>``, where a row of NaN means "unknown": rows
whose action does not use the parameter may leave it NaN, and queries integrate an
unknown value out, row by row.

**One magnitude rule.** A continuous value beyond ``+-MAX_MAGNITUDE`` (1e150) is refused
wherever evidence enters (training rows, queries, the model's ``data``), naming the site:
its square, and a sum of such squares over many rows, must stay finite in float64 for
the fit's statistics and for every Gaussian density a query takes. Within the limit every
query answers with distributions that sum to 1.

**Partial continuous evidence.** ``Partial(value, observed=mask)`` gives some dimensions
of a continuous *end* feature: ``mask`` is bool, ``(dim,)`` shared by every row or
``(n, dim)`` per row. Queries marginalise the unobserved dimensions (for a Gaussian:
drop their rows and columns). Encoded, the unobserved dimensions hold NaN; that is the
only NaN an encoded end feature holds (a NaN given as a plain value is still an error).
"""

from __future__ import annotations

from collections.abc import Hashable, Iterator, Mapping
from typing import Protocol

import numpy as np
import torch
from effect_networks.models.dtype import DTYPE, MAX_MAGNITUDE
from effect_networks.models.features import Feature
from effect_networks.models.sites import SiteSpec

__all__ = [
    "DTYPE",
    "MAX_MAGNITUDE",
    "Evidence",
    "Network",
    "Partial",
    "check_magnitude",
    "decode",
    "encode",
    "is_partial",
    "labels",
    "observed_dims",
]


class Network(Protocol):
    """What evidence reads of a network: :class:`~models.declaration.EffectNetwork` is one.

    (Written out here so that evidence depends on the declarations' leaves only, not on
    the network that encodes with it.)
    """

    @property
    def actions(self) -> tuple[str, ...]:
        """The network's actions, in order."""

    @property
    def sites(self) -> tuple[SiteSpec, ...]:
        """Every site of the network, in site order."""

    def site(self, name: str) -> SiteSpec:
        """The site named ``name``."""

    def feature(self, name: str) -> Feature:
        """The feature named ``name``."""

    def encode(self, evidence: Mapping[str, object]) -> Evidence:
        """``evidence`` encoded for the network's sites."""


class Partial:
    """Some dimensions of a continuous end feature.

    Evidence ``{"end.xy": Partial(value, observed=[True, False])}`` observes ``x`` and leaves ``y``
    unknown.

    ``value``: numbers of shape ``(n, dim)`` (or ``(dim,)`` for one row), as for full
    evidence; entries in unobserved dimensions are ignored (they may be NaN).
    ``observed``: bool, ``(dim,)`` for every row or ``(n, dim)`` per row; a row with no
    dimension observed leaves the feature unobserved in that row.
    """

    __slots__ = ("observed", "value")

    def __init__(self, value: object, observed: object):
        self.value = value
        self.observed = observed

    def __repr__(self) -> str:
        return f"Partial({self.value!r}, observed={self.observed!r})"


def observed_dims(value: torch.Tensor) -> torch.Tensor:
    """``(n, d)`` bool: the observed dimensions of an encoded continuous end feature."""
    return ~torch.isnan(value)


def is_partial(value: torch.Tensor) -> bool:
    """Whether an encoded continuous end feature leaves some dimension unobserved."""
    return bool(torch.isnan(value).any())


class Evidence(Mapping):
    """Encoded values of some sites of one network, ``n_rows`` rows each.

    Discrete sites hold ``(n,)`` long state indices, continuous ones ``(n, d)`` float64.
    Build it with :meth:`EffectNetwork.encode` (labels) or
    :meth:`EffectNetwork.encode_indices` (indices); never from raw tensors, so that a
    tensor of indices can not be mistaken for labels.

    ``evidence | {"end.count": [3]}`` adds label values (encoded with the same network);
    ``evidence | other_evidence`` merges two encoded ones. Row counts must agree.
    """

    __slots__ = ("_values", "n_rows", "net")

    def __init__(self, net: Network, values: dict[str, torch.Tensor], n_rows: int):
        self.net = net
        self._values = values
        self.n_rows = n_rows

    def __getitem__(self, site: str) -> torch.Tensor:
        return self._values[site]

    def __iter__(self) -> Iterator[str]:
        return iter(self._values)

    def __len__(self) -> int:
        return len(self._values)

    def __repr__(self) -> str:
        shapes = {k: tuple(v.shape) for k, v in self._values.items()}
        return f"Evidence(n_rows={self.n_rows}, {shapes})"

    def __or__(self, other: object) -> Evidence:
        if isinstance(other, Evidence):
            if other.net is not self.net and other.net != self.net:
                raise ValueError("cannot merge evidence encoded for two different networks")
        elif isinstance(other, Mapping):
            other = self.net.encode(other)
        else:
            return NotImplemented
        return _merge(self, other)

    def __ror__(self, other: object) -> Evidence:
        if not isinstance(other, Mapping):
            return NotImplemented
        return _merge(self.net.encode(other), self)

    def rows(self, index: slice | torch.Tensor) -> Evidence:
        """The evidence of some rows (a slice, an index or a bool mask)."""
        if (
            isinstance(index, torch.Tensor)
            and index.dtype == torch.bool
            and index.shape == (self.n_rows,)
            and len(self._values) > 1
        ):
            index = index.nonzero().squeeze(-1)  # once, not once per site
        values = {k: v[index] for k, v in self._values.items()}
        if values:
            n = next(iter(values.values())).shape[0]
        else:
            n = len(range(self.n_rows)[index]) if isinstance(index, slice) else 0
        return Evidence(self.net, values, n)

    def repeat(self, times: int) -> Evidence:
        """Every row repeated ``times`` times in place (row i becomes rows i*times...)."""
        values = {k: v.repeat_interleave(times, 0) for k, v in self._values.items()}
        return Evidence(self.net, values, self.n_rows * times)

    def without(self, *sites: str) -> Evidence:
        """The evidence with some sites left out."""
        return Evidence(
            self.net, {k: v for k, v in self._values.items() if k not in sites}, self.n_rows
        )


def _merge(a: Evidence, b: Evidence) -> Evidence:
    if a._values and b._values and a.n_rows != b.n_rows:
        raise ValueError(f"evidence rows disagree in number: {a.n_rows} and {b.n_rows}")
    n = a.n_rows if a._values else b.n_rows
    return Evidence(a.net, a._values | b._values, n)


def encode(net: Network, evidence: Mapping[str, object], *, indices: bool) -> Evidence:
    """Validate ``evidence`` (labels, or indices when ``indices``) into :class:`Evidence`."""
    if isinstance(evidence, Evidence):
        if indices:
            raise ValueError("this evidence is already encoded; pass it on as it is")
        return evidence
    if not isinstance(evidence, Mapping):
        raise ValueError(
            f"evidence must be a mapping from site name to values, got {type(evidence).__name__}"
        )
    values: dict[str, torch.Tensor] = {}
    for name, value in evidence.items():
        spec = _spec(net, name)
        if spec.discrete:
            values[name] = (
                _encode_indices(spec, value) if indices else _encode_labels(net, spec, value)
            )
        else:
            values[name] = _encode_continuous(spec, value)
    rows = {name: v.shape[0] for name, v in values.items()}
    if len(set(rows.values())) > 1:
        raise ValueError(f"evidence rows disagree in number: {rows}")
    return Evidence(net, values, next(iter(rows.values()), 0))


def _spec(net: Network, name: object) -> SiteSpec:
    names = [s.name for s in net.sites]
    if name not in names:
        raise ValueError(f"evidence on site {name!r}, which does not exist; sites are {names}")
    return net.site(name)


def labels(net: Network, spec: SiteSpec) -> tuple[Hashable, ...]:
    """The labels of a discrete site's states, in index order."""
    if spec.role == "action":
        return net.actions
    if spec.role == "cluster":
        return tuple(range(spec.size))
    return net.feature(spec.feature).states


def _as_array(spec: SiteSpec, value: object) -> np.ndarray:
    if isinstance(value, torch.Tensor):
        return value.detach().cpu().numpy()
    if isinstance(value, str | bytes):
        return np.array([value], dtype=object)
    if isinstance(value, list | tuple) and len({_label_kind(v) for v in value}) > 1:
        # labels of several types stay as they are: numpy would spell [0, "many"] as
        # ["0", "many"] and [True, 2] as [1, 2]
        array = np.empty(len(value), dtype=object)
        array[:] = list(value)
        return array
    try:
        array = np.asarray(value)
    except (TypeError, ValueError):  # ragged or odd containers: keep the Python objects
        array = np.empty(len(value), dtype=object)
        array[:] = list(value)
    if array.ndim == 0:
        array = array.reshape(1)
    if array.ndim != 1:
        raise ValueError(
            f"site {spec.name!r}: expected one label per row, shape (n,), got shape {array.shape}"
        )
    return array


def _label_kind(value: object) -> str:
    """A label's kind as numpy would merge them: numbers (bool apart), text, or other."""
    if isinstance(value, bool | np.bool_):
        return "bool"
    if isinstance(value, int | float | np.number):
        return "number"
    if isinstance(value, str | np.str_):
        return "str"
    return type(value).__name__


def _encode_labels(net: Network, spec: SiteSpec, value: object) -> torch.Tensor:
    array = _as_array(spec, value)
    states = labels(net, spec)
    if array.dtype.kind == "c" and not any(isinstance(s, complex) for s in states):
        raise ValueError(  # 1+0j would equal the state 1
            f"site {spec.name!r}: complex numbers are not labels (got {value!r}); "
            f"its states are {list(states)[:12]}"
        )
    lookup = {label: i for i, label in enumerate(states)}
    if array.dtype != object and array.size:
        # One dictionary look-up per distinct value, not per row.
        try:
            unique, inverse = np.unique(array, return_inverse=True)
        except TypeError:
            unique = None
        if unique is not None:
            mapped = np.array([lookup.get(_hashable(u.item()), -1) for u in unique])
            index = mapped[inverse.reshape(-1)]
            bad = np.flatnonzero(index < 0)
            if bad.size:
                _refuse(spec, states, array[bad[0]].item(), int(bad[0]))
            return torch.as_tensor(index, dtype=torch.long)
    index = []
    for row, v in enumerate(array):
        i = lookup.get(_hashable(_python(v)), -1)
        if i < 0:
            _refuse(spec, states, _python(v), row)
        index.append(i)
    return torch.tensor(index, dtype=torch.long)


def _hashable(v: object) -> object:
    """``v``, or a key no state has when it cannot be hashed (a list where a label goes)."""
    try:
        hash(v)
    except TypeError:
        return _UNHASHABLE
    return v


_UNHASHABLE = object()


def _python(v: object) -> object:
    return v.item() if isinstance(v, np.generic | torch.Tensor) else v


def _refuse(spec: SiteSpec, states: tuple, v: object, row: int) -> None:
    """Raise the error for the first row whose value is not a state: the value, its row."""
    shown = list(states) if len(states) <= 12 else f"{list(states[:12])} ... ({len(states)} states)"
    hint = ""
    if isinstance(v, int) and not isinstance(v, bool) and 0 <= v < len(states):
        hint = " (values are state labels; to give state indices use net.encode_indices({...}))"
    elif _marks_missing(v):
        hint = (
            " (a missing value: evidence gives a discrete site in every row or leaves it out; "
            "ask the rows without it apart, leaving the site out. fit reads gaps by EM)"
        )
    raise ValueError(
        f"site {spec.name!r}: value {v!r} is not one of its states {shown} (row {row}){hint}"
    )


def _marks_missing(v: object) -> bool:
    """Whether ``v`` is one of the marks training rows read as missing (None, NaN, ``pd.NA``)."""
    return (
        v is None
        or (isinstance(v, float) and v != v)
        or type(v).__name__ == "NAType"  # pandas' missing value, pandas not imported
    )


def _encode_indices(spec: SiteSpec, value: object) -> torch.Tensor:
    array = _as_array(spec, value)
    if array.dtype.kind not in "iu":
        raise ValueError(
            f"site {spec.name!r}: state indices must be integers, got dtype {array.dtype}"
        )
    index = torch.as_tensor(array.astype(np.int64, copy=False))
    if index.numel():
        low, high = (int(v) for v in torch.aminmax(index))
        if low < 0 or high >= spec.size:
            bad = index[(index < 0) | (index >= spec.size)][0]
            raise ValueError(
                f"site {spec.name!r}: state index {int(bad)} outside 0..{spec.size - 1}"
            )
    return index


def _rows(spec: SiteSpec, value: object) -> torch.Tensor:
    """``value`` as float64 rows ``(n, size)``; a single row or a 1-d feature may drop an axis."""
    try:
        raw = value.detach() if isinstance(value, torch.Tensor) else np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(
            f"site {spec.name!r}: expected numbers of shape (n, {spec.size}), got {value!r}"
        ) from exc
    if (raw.dtype == torch.bool) if isinstance(raw, torch.Tensor) else raw.dtype.kind == "b":
        raise ValueError(
            f"site {spec.name!r}: bool values are not numbers here (got {value!r}); "
            f"expected real numbers of shape (n, {spec.size})"
        )
    if raw.is_complex() if isinstance(raw, torch.Tensor) else raw.dtype.kind == "c":
        raise ValueError(
            f"site {spec.name!r}: complex numbers are not evidence (got {value!r}); "
            f"expected real numbers of shape (n, {spec.size})"
        )
    try:
        x = torch.as_tensor(raw, dtype=DTYPE)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise ValueError(
            f"site {spec.name!r}: expected numbers of shape (n, {spec.size}), got {value!r}"
        ) from exc
    if x.dim() == 1 and spec.size > 1 or x.dim() == 0:
        x = x.reshape(1, -1)
    elif x.dim() == 1:
        x = x.reshape(-1, 1)
    if x.dim() != 2 or x.shape[-1] != spec.size:
        raise ValueError(
            f"site {spec.name!r}: expected shape (n, {spec.size}), got {tuple(np.shape(value))}"
        )
    return x


def _encode_continuous(spec: SiteSpec, value: object) -> torch.Tensor:
    if isinstance(value, Partial):
        return _encode_partial(spec, value)
    x = _rows(spec, value)
    bad = ~torch.isfinite(x)
    if spec.role == "param":
        nan_row = torch.isnan(x).all(-1, keepdim=True)
        bad = bad & ~nan_row  # a whole row of NaN: the parameter's value is unknown
    if bad.any():
        row = int(bad.any(-1).nonzero()[0])
        what = (
            "NaN or inf (a parameter is unknown only when its whole row is NaN)"
            if spec.role == "param"
            else "NaN or inf"
        )
        raise ValueError(f"site {spec.name!r}: {what} in row {row}: {x[row].tolist()}")
    check_magnitude(spec.name, x)
    return x


def check_magnitude(site: str, value: torch.Tensor) -> None:
    """Refuse a continuous value beyond ``+-MAX_MAGNITUDE`` (NaN, an unknown value, passes)."""
    big = value.nan_to_num(nan=0.0).abs().amax(-1) > MAX_MAGNITUDE
    if bool(big.any()):
        row = int(big.nonzero()[0])
        raise ValueError(
            f"site {site!r}: row {row} holds {value[row].tolist()}, beyond +-{MAX_MAGNITUDE:g} "
            "(the largest magnitude whose squares stay finite in training and queries). "
            "Rescale the feature (other units)"
        )


def _encode_partial(spec: SiteSpec, partial: Partial) -> torch.Tensor:
    if spec.role != "end":
        raise ValueError(
            f"site {spec.name!r}: Partial evidence is for continuous end features only "
            f"(an initial state is needed in full; an unknown parameter is a row of NaN)"
        )
    mask = partial.observed
    mask = torch.as_tensor(mask.detach() if isinstance(mask, torch.Tensor) else np.asarray(mask))
    if mask.dtype != torch.bool:
        raise ValueError(
            f"site {spec.name!r}: Partial's observed must be bool (True = observed), got "
            f"dtype {mask.dtype}"
        )
    value = partial.value
    x = _rows(spec, value)
    if mask.shape not in ((spec.size,), (x.shape[0], spec.size)):
        raise ValueError(
            f"site {spec.name!r}: Partial's observed has shape {tuple(mask.shape)}; expected "
            f"({spec.size},) for every row or ({x.shape[0]}, {spec.size}) per row"
        )
    mask = mask.expand(x.shape)
    bad = mask & ~torch.isfinite(x)
    if bad.any():
        row = int(bad.any(-1).nonzero()[0])
        raise ValueError(
            f"site {spec.name!r}: NaN or inf in an observed dimension of row {row}: "
            f"{x[row].tolist()}"
        )
    x = torch.where(mask, x, torch.nan)
    check_magnitude(spec.name, x)
    return x


def decode(net: Network, site: str, index: torch.Tensor) -> list:
    """State labels of ``(n,)`` state indices of a discrete site."""
    states = labels(net, net.site(site))
    return [states[i] for i in index.reshape(-1).tolist()]
