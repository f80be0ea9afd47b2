"""Data frames in and out: a pandas ``DataFrame`` as rows by site, and rows as a frame.

**The column convention.** A column per site, named like the site: ``initial.visible``,
``action``, ``param.force``, ``cluster.force``, ``end.position``. A continuous value of
dimension ``d > 1`` takes one column per dimension, ``end.position[0]`` ...
``end.position[d-1]``; a value of dimension 1 takes one column, ``end.x`` (or
``end.x[0]``, read the same). Discrete columns hold state labels (the states a feature
was declared with, action names, cluster numbers) in any dtype, pandas categoricals
included; continuous columns hold numbers.

**Labels read back from text.** A CSV file stores every label as text, and
``pandas.read_csv`` guesses each column's type: ``True``/``False`` come back as bools,
``3`` as an int (or ``3.0`` where the column has a gap), ``"7"`` as the int 7. A value
that is not one of the declared states is matched against them: a string against the
states' text (``"True"`` is the state ``True`` of a feature declared with the states
``(False, True)``), a whole float against the int state it equals, a number against a
string state that spells it. A value that matches no state (or more than one) is kept
as it is, and refused where the rows are encoded, naming the site and its states.

**Missing values** (NaN, ``None``, ``pd.NA``, ``pd.NaT``) stay missing:

* in a discrete column, ``None`` in an object array (the label of no state: ``fit``
  takes such rows with ``masks`` marking them, see :func:`inference.fit`);
* in a continuous column, NaN. A continuous *end* feature with NaN in some rows becomes
  ``Partial(value, observed=~isnan(value))`` (:class:`models.evidence.Partial`), the
  form queries marginalise; a parameter whose whole row is NaN is unknown (the form
  rows of actions that do not use it take); an initial feature keeps its NaN.

Every column must belong to the network (an unknown column is an error unless
``extra="ignore"``), and a vector feature needs every dimension's column.
:func:`to_frame` writes rows back with the same convention (1-d values as one bare
column), so ``from_frame(net, to_frame(net, rows))`` gives the rows again, and so does a
trip through CSV (``frame.to_csv(path, index=False)``, then ``pd.read_csv(path)``; with
pandas before 3.0 pass ``float_precision="round_trip"``, whose default float parser may
change a number's last digit).

pandas is optional (the ``data`` extra): this module imports without it, and only the
functions that build or read a frame need it.
"""

from __future__ import annotations

import re
import sys
from collections import Counter
from collections.abc import Hashable, Mapping
from typing import Any, Literal

import numpy as np
import torch
from effect_networks.models.evidence import Evidence, Network, Partial, labels
from effect_networks.models.sites import SiteSpec

__all__ = ["as_data", "columns", "from_frame", "is_frame", "require_pandas", "to_frame"]

#: A column's name: a site's name, and a dimension for a vector's column.
_COLUMN = re.compile(r"^(?P<site>[^\[\]]+?)(?:\[(?P<dim>\d+)\])?$")


def require_pandas() -> Any:
    """The pandas module, or an ``ImportError`` that names the extra that installs it.

    Returns
    -------
    module
        ``pandas``.

    Raises
    ------
    ImportError
        When pandas is not installed.
    """
    try:
        import pandas
    except ImportError as exc:
        raise ImportError(
            "data frames need pandas, the `data` extra of effect-networks: install it with "
            "`pip install 'effect-networks[data]'` (or `pip install pandas`)"
        ) from exc
    return pandas


def is_frame(data: object) -> bool:
    """Whether ``data`` is a pandas ``DataFrame`` (pandas is not imported to tell).

    Parameters
    ----------
    data
        Anything.

    Returns
    -------
    bool
        True for a ``DataFrame`` (a subclass included).
    """
    pandas = sys.modules.get("pandas")  # a frame exists only once pandas is imported
    return pandas is not None and isinstance(data, pandas.DataFrame)


def as_data(net: Network, data: object) -> object:
    """``data`` in the toolkit's format: a frame converted, anything else as it is.

    The one conversion every function that takes rows or evidence calls at its boundary.

    Parameters
    ----------
    net
        The network the rows are for.
    data
        A ``DataFrame`` (see :func:`from_frame`) or anything else (a mapping, encoded
        :class:`~models.evidence.Evidence`, an iterable of chunks).

    Returns
    -------
    object
        :func:`from_frame` of a frame; ``data`` itself otherwise.
    """
    return from_frame(net, data) if is_frame(data) else data


def columns(net: Network, site: str) -> tuple[str, ...]:
    """The columns :func:`to_frame` writes a site's values to.

    Parameters
    ----------
    net
        The network.
    site
        A site of ``net``.

    Returns
    -------
    tuple of str
        ``(site,)`` for a discrete site or a continuous one of dimension 1;
        ``(f"{site}[0]", ..., f"{site}[{d - 1}]")`` for dimension ``d > 1``.
    """
    spec = net.site(site)
    if spec.discrete or spec.size == 1:
        return (site,)
    return tuple(f"{site}[{i}]" for i in range(spec.size))


def from_frame(
    net: Network, frame: Any, *, extra: Literal["raise", "ignore"] = "raise"
) -> dict[str, object]:
    """Rows by site from a ``DataFrame`` whose columns follow the module's convention.

    Parameters
    ----------
    net
        The network the rows are for.
    frame
        A ``DataFrame``, one row per training row or query; its index is ignored.
    extra
        ``"raise"``: a column that names no site of ``net`` is an error;
        ``"ignore"``: such columns are left out.

    Returns
    -------
    dict
        Per site with columns: discrete sites an ``(n,)`` object array of labels
        (``None`` where missing); continuous sites an ``(n, d)`` float64 array (NaN where
        missing), a continuous end feature with NaN a
        :class:`~models.evidence.Partial`.

    Raises
    ------
    ValueError
        Naming the column: an unknown column (with ``extra="raise"``), a repeated one, a
        dimension the site does not have, a vector feature without every dimension's
        column (or given as one bare column), a discrete site given per dimension, a
        non-numeric or bool column of a continuous site.
    """
    pandas = require_pandas()
    if not isinstance(frame, pandas.DataFrame):
        raise ValueError(f"expected a pandas DataFrame, got {type(frame).__name__}")
    if extra not in ("raise", "ignore"):
        raise ValueError(f"extra must be 'raise' or 'ignore', got {extra!r}")
    repeated = sorted(c for c, k in Counter(map(str, frame.columns)).items() if k > 1)
    if repeated:
        raise ValueError(f"columns {repeated} appear more than once")
    sites = {s.name: s for s in net.sites}
    by_site: dict[str, dict[int | None, Any]] = {}
    unknown = []
    for column in frame.columns:
        match = _COLUMN.match(str(column)) if isinstance(column, str) else None
        if match is None or match["site"] not in sites:
            unknown.append(column)
            continue
        dim = None if match["dim"] is None else int(match["dim"])
        by_site.setdefault(match["site"], {})[dim] = frame[column]
    if unknown and extra == "raise":
        raise ValueError(
            f"columns {unknown} name no site of the network; its sites are {list(sites)} "
            "(a vector's dimensions as site[0], site[1], ...). Leave them out: select the "
            "site columns, or convert with models.from_frame(net, frame, extra='ignore')"
        )
    out: dict[str, object] = {}
    for name, spec in sites.items():  # the network's order
        if name in by_site:
            given = by_site[name]
            if spec.discrete:
                out[name] = _labels(net, spec, _discrete_column(spec, given))
            else:
                out[name] = _numbers(spec, _continuous_columns(spec, given))
    return out


def _discrete_column(spec: SiteSpec, given: dict) -> Any:
    if set(given) != {None}:
        shown = sorted(f"{spec.name}[{d}]" for d in given if d is not None)
        raise ValueError(
            f"columns {shown}: site {spec.name!r} is discrete, one column of labels named "
            f"{spec.name!r}"
        )
    return given[None]


def _continuous_columns(spec: SiteSpec, given: dict) -> list:
    """The site's columns in dimension order, each checked to be the site's."""
    if None in given:
        if spec.size > 1:
            raise ValueError(
                f"column {spec.name!r}: site {spec.name!r} has {spec.size} dimensions, one "
                f"column each: {[f'{spec.name}[{i}]' for i in range(spec.size)]}"
            )
        if 0 in given:
            raise ValueError(
                f"columns {spec.name!r} and {spec.name + '[0]'!r} both give site {spec.name!r}"
            )
        return [given[None]]
    beyond = sorted(d for d in given if d >= spec.size)
    if beyond:
        raise ValueError(
            f"column {f'{spec.name}[{beyond[0]}]'!r}: site {spec.name!r} has {spec.size} "
            f"dimension(s), 0..{spec.size - 1}"
        )
    absent = [f"{spec.name}[{i}]" for i in range(spec.size) if i not in given]
    if absent:
        raise ValueError(
            f"site {spec.name!r} lacks the columns {absent}: a vector feature needs a column "
            f"for every one of its {spec.size} dimensions"
        )
    return [given[i] for i in range(spec.size)]


def _numbers(spec: SiteSpec, series: list) -> object:
    pandas = require_pandas()
    values = []
    for s in series:
        if pandas.api.types.is_bool_dtype(s.dtype):
            raise ValueError(
                f"column {s.name!r}: bools are not numbers here; site {spec.name!r} is continuous"
            )
        try:
            values.append(s.to_numpy(dtype=np.float64, na_value=np.nan))
        except (TypeError, ValueError) as exc:
            raise ValueError(
                f"column {s.name!r}: site {spec.name!r} is continuous, but the column holds "
                f"values that are not numbers ({exc})"
            ) from None
    value = np.stack(values, axis=-1) if values else np.empty((0, spec.size))
    if spec.role == "end" and np.isnan(value).any():
        return Partial(value, observed=~np.isnan(value))
    return value


def _labels(net: Network, spec: SiteSpec, series: Any) -> np.ndarray:
    """The column's values as declared labels, ``None`` where missing.

    One look-up per distinct value.
    """
    pandas = require_pandas()
    codes, uniques = pandas.factorize(series, use_na_sentinel=True)
    states = labels(net, spec)
    matched = np.empty(len(uniques) + 1, dtype=object)  # the last: missing
    for i, value in enumerate(np.asarray(uniques, dtype=object).tolist()):
        matched[i] = _state(states, value)
    matched[-1] = None
    return matched[codes]


def _state(states: tuple[Hashable, ...], value: object) -> object:
    """The declared state ``value`` stands for, or ``value`` itself when none matches."""
    if isinstance(value, np.generic):
        value = value.item()
    for state in states:
        if type(value) is type(state) and value == state:
            return state
    # another type: text read from a file, a whole float for an int state, ...
    spelled = [s for s in states if _spelling(s) == _spelling(value)]
    return spelled[0] if len(spelled) == 1 else value


def _spelling(value: object) -> str:
    """The text a CSV file stores for ``value`` (a whole float as its int)."""
    if isinstance(value, float) and value.is_integer():
        return str(int(value))
    return str(value)


def to_frame(net: Network, data: Mapping[str, object]) -> Any:
    """A ``DataFrame`` of rows by site, with the module's column convention.

    Parameters
    ----------
    net
        The network the rows are for.
    data
        Rows by site (labels, as :meth:`EffectNetwork.encode` takes them, e.g. the rows
        :func:`inference.simulate` draws) or encoded :class:`~models.evidence.Evidence`.

    Returns
    -------
    pandas.DataFrame
        One column per discrete site (its labels) and per dimension of a continuous
        one (float64; NaN where a parameter is unknown or a dimension unobserved), in the
        network's site order.

    Raises
    ------
    ValueError
        For values :meth:`EffectNetwork.encode` refuses (naming the site).
    """
    pandas = require_pandas()
    enc = data if isinstance(data, Evidence) else net.encode(as_data(net, data))
    out: dict[str, object] = {}
    for spec in net.sites:
        if spec.name not in enc:
            continue
        value = enc[spec.name]
        if spec.discrete:
            out[spec.name] = pandas.Series(net.decode(spec.name, value), dtype=_dtype(net, spec))
        else:
            value = value.detach().cpu().numpy() if isinstance(value, torch.Tensor) else value
            for column, v in zip(columns(net, spec.name), value.T, strict=True):
                out[column] = v
    return pandas.DataFrame(out, index=pandas.RangeIndex(enc.n_rows))


def _dtype(net: Network, spec: SiteSpec) -> object:
    """bool, int64 or object: the dtype its declared labels share.

    So a column of bools is a bool column.
    """
    states = labels(net, spec)
    if all(type(s) is bool for s in states):
        return bool
    if all(type(s) is int for s in states):
        return np.int64
    return object
