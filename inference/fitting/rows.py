"""The checks every fit shares: its settings, its training rows and their masks.

Every fitting route (:func:`inference.fit`, the EM fits, the pooled fit, active
exploration) reads the same training rows and refuses the same mistakes, so the rules
are written once here:

* settings (:func:`check_settings`): finite Python numbers, ``steps`` a positive int;
* rows (:func:`training_rows`): every site given, a parameter's value present exactly
  where the row's action uses it, nothing whose square would overflow; each parameter's
  cluster added where the rows do not give it (its value's equidistant cell);
* missing values (:func:`split_missing`, :func:`rows_with_gaps`): None or NaN for a
  discrete label, NaN for a continuous initial or end value or some of its dimensions;
* masks (:func:`mask_values`, :func:`row_masks`, :func:`missing_masks`): one bool per
  row of a discrete site, False where the value is missing;
* the layout (:func:`refuse_adaptive`): the closed form files each row under its value's
  cell, which adaptive clusters (latent components) forbid.


Each check raises a ``ValueError`` that names the site or setting, the value and what
was expected.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
import torch
from effect_networks.models.declaration import ACTION, EffectNetwork, cluster_site, param_site
from effect_networks.models.evidence import Evidence, Partial, check_magnitude, is_partial

__all__ = [
    "NoRows",
    "check_settings",
    "ignore_missing",
    "mask_site",
    "mask_values",
    "missing_masks",
    "refuse_adaptive",
    "row_masks",
    "split_missing",
    "training_rows",
    "with_gaps",
]


class NoRows(ValueError):
    """Training data of no rows (a chunk of no rows is skipped where chunks are summed)."""


def check_settings(**settings: float) -> None:
    """Refuse settings that would make fitting spin or return NaN.

    Parameters
    ----------
    **settings
        Each setting by name. ``steps`` must be a positive int (a numpy integer counts);
        ``lr`` and ``tol`` a finite number > 0; any other a finite number >= 0. Numbers
        are Python floats or ints (a float32 would turn the float64 arithmetic it
        enters into float32); a bool is refused.

    Raises
    ------
    ValueError
        Naming the first setting that breaks its rule, its value and the rule.
    """
    for name, value in settings.items():
        ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
        if name == "steps":
            ok = isinstance(value, int | np.integer) and not isinstance(value, bool) and value >= 1
        elif name in ("lr", "tol"):
            ok = ok and value > 0
        else:
            ok = ok and value >= 0
        if not ok:
            want = (
                "a positive int"
                if name == "steps"
                else ("a finite number > 0" if name in ("lr", "tol") else "a finite number >= 0")
            )
            if name != "steps":
                want += " (a Python float or int)"
            raise ValueError(f"{name} must be {want}, got {value!r}")


def refuse_adaptive(net: EffectNetwork, name: str) -> None:
    """Refuse a network with adaptive clusters in a fit that files rows by their cells.

    Parameters
    ----------
    net
        The network to fit.
    name
        The refusing function's name, for the message.

    Raises
    ------
    ValueError
        If some parameter of ``net`` has ``layout="adaptive"`` (its clusters are latent
        components: :func:`inference.fit_em` fits them).
    """
    adaptive = [p.name for p in net.parameters if p.adaptive]
    if adaptive:
        raise ValueError(
            f"{name} files each row under its parameter's cell, but the clusters of "
            f"{adaptive} are adaptive (latent components): fit the network with "
            "inference.fit_em"
        )


def training_rows(
    net: EffectNetwork, data: Mapping[str, object], unknown_action: torch.Tensor | None = None
) -> Evidence:
    """Encode training rows, check them, and add each parameter's cluster.

    The cluster is added where the rows do not give it (its value's cell).

    Parameters
    ----------
    net
        The network the rows are for.
    data
        Rows by site name (see :meth:`EffectNetwork.encode`), every site but the
        clusters given; ``param.p`` NaN in rows whose action does not use ``p``.
    unknown_action
        ``(n,)`` bool: rows whose action is missing (``masks``), where a parameter's
        value is not checked against the action and the cluster is a placeholder (EM
        derives it per action).

    Returns
    -------
    Evidence
        The encoded rows, every cluster included.

    Raises
    ------
    ValueError
        On no rows, a site missing, a parameter's value present where the action does
        not use it or absent where it does, a cluster other than 0 for an action that
        does not use the parameter, a partly observed continuous feature, or a value
        whose square would overflow (``models.evidence.MAX_MAGNITUDE``).
    """
    enc = net.encode(data)
    if not len(enc) or enc.n_rows == 0:
        raise NoRows("no training rows: fit needs at least one row of every site")
    missing = [s.name for s in net.sites if s.name not in enc and s.role != "cluster"]
    if missing:
        raise ValueError(
            f"training data must give every site; missing {missing}. (Give parameters as NaN in "
            f"rows whose action does not use them; mark missing discrete values with `masks`.)"
        )
    clusters = {}
    for m in net.mixtures:
        p = m.parameter
        p_site = param_site(p.name)
        uses = m.in_use(enc[ACTION])
        present = ~torch.isnan(enc[p_site]).any(-1)
        known = torch.ones_like(present)
        if unknown_action is not None and unknown_action.shape == known.shape:
            known = ~unknown_action  # (a mask of another shape is refused by row_masks)
        for bad, why in (
            (uses & ~present, "uses the parameter, but the row gives no value"),
            (~uses & present, "does not use the parameter, but the row gives a value (give NaN)"),
        ):
            bad = bad & known
            if bad.any():
                row = int(bad.nonzero()[0])
                raise ValueError(
                    f"site {p_site!r}: row {row} has action "
                    f"{net.actions[int(enc[ACTION][row])]!r}, which {why}"
                )
        given = enc.get(cluster_site(p.name))
        if given is None:  # the rows' clusters are their values' cells
            clusters[cluster_site(p.name)] = m.cells(enc[p_site], enc[ACTION])
            continue
        pinned = ~uses & (given != 0) & known
        if pinned.any():
            row = int(pinned.nonzero()[0])
            raise ValueError(
                f"site {cluster_site(p.name)!r}: row {row} has cluster {int(given[row])} for "
                f"action {net.actions[int(enc[ACTION][row])]!r}, which does not use "
                f"{p.name!r}; such a row's cluster is 0"
            )
    for site, value in enc.items():
        if not net.site(site).discrete:
            if net.site(site).role == "end" and is_partial(value):
                row = int(torch.isnan(value).any(-1).nonzero()[0])
                raise ValueError(
                    f"site {site!r}: row {row} is observed in some dimensions only (Partial); "
                    "fit needs every dimension of every continuous feature"
                )
            check_magnitude(site, value)  # the rule evidence follows (models.evidence)
    return enc | net.encode_indices(clusters) if clusters else enc


# ----------------------------------------------------------------------------------- masks
def mask_site(net: EffectNetwork, site: object):
    """The declared site a mask is given for.

    Parameters
    ----------
    net
        The network.
    site
        The key of the mask in ``masks``.

    Returns
    -------
    Site
        ``net.site(site)``.

    Raises
    ------
    ValueError
        If ``net`` has no such site (the message lists its sites).
    """
    names = [s.name for s in net.sites]
    if site not in names:
        raise ValueError(f"masks[{site!r}]: no such site; the network's sites are {names}")
    return net.site(site)


def mask_values(site: str, mask: object) -> torch.Tensor:
    """A mask as a flat bool tensor.

    Parameters
    ----------
    site
        The site the mask is for, for the message.
    mask
        One entry per row: bools, or the numbers 0 and 1 (a tensor, an array or a
        sequence), False (0) where the row's value is missing.

    Returns
    -------
    torch.Tensor
        ``(n,)`` bool.

    Raises
    ------
    ValueError
        Naming ``site``, for a mask of more than one dimension, of a non-numeric dtype,
        or holding a value other than 0 and 1 (a fraction, NaN).
    """
    if not isinstance(mask, torch.Tensor):
        mask = np.asarray(mask)
        if mask.dtype == object or mask.dtype.kind not in "biuf":
            raise ValueError(
                f"masks[{site!r}] must hold bools (False where missing), got dtype {mask.dtype}"
            )
        mask = torch.tensor(mask)  # a copy: a pandas column's array is read-only
    if mask.dim() > 1:
        raise ValueError(
            f"masks[{site!r}] must be one bool per row, shape (n,), got shape {tuple(mask.shape)}"
        )
    if mask.dtype != torch.bool:
        if mask.is_complex() or not bool(((mask == 0) | (mask == 1)).all()):
            raise ValueError(
                f"masks[{site!r}] must hold bools (False where missing) or 0/1, got values "
                f"other than 0 and 1"
            )
    return mask.to(torch.bool).reshape(-1)


def row_masks(
    net: EffectNetwork, masks: Mapping[str, object] | None, n: int
) -> dict[str, torch.Tensor]:
    """Every mask as ``(n,)`` bool, checked against the network and the rows.

    Parameters
    ----------
    net
        The network.
    masks
        Per discrete site, one bool (or 0/1) per row, False where missing; ``None`` for
        none.
    n
        The number of rows.

    Returns
    -------
    dict of str to torch.Tensor
        Each mask as ``(n,)`` bool, those without gaps included.

    Raises
    ------
    ValueError
        For an unknown or continuous site, or a mask whose length is not ``n``.
    """
    out = {}
    for k, v in (masks or {}).items():
        if not mask_site(net, k).discrete:
            raise ValueError(f"masks are for discrete sites; {k!r} is continuous")
        m = mask_values(k, v)
        if m.shape[0] != n:
            raise ValueError(f"masks[{k!r}] has {m.shape[0]} rows, the data {n}")
        out[k] = m
    return out


def missing_masks(
    net: EffectNetwork, masks: Mapping[str, object], n: int | None
) -> dict[str, torch.Tensor]:
    """The masks with gaps, after checking that EM over them has an M-step.

    Parameters
    ----------
    net
        The network.
    masks
        Per discrete site, one bool (or 0/1) per row, False where missing.
    n
        The number of rows, or ``None`` to check the masks before the rows are read
        (their lengths are then not checked).

    Returns
    -------
    dict of str to torch.Tensor
        The masks that leave some value missing, as ``(n,)`` bool.

    Raises
    ------
    ValueError
        For an unknown or continuous site, a mask of the wrong length, a mask on a
        parameter's cluster (never missing on its own: it is its value's cell), or gaps
        in a network with a CPD that has neither a closed form nor a ``maximise``
        method.
    """
    out = {}
    for site, mask in masks.items():
        spec = mask_site(net, site)
        mask = mask_values(site, mask)
        if not spec.discrete or (n is not None and mask.shape[0] != n):
            kind = "discrete" if spec.discrete else "continuous"
            raise ValueError(
                f"masks[{site!r}] must be {f'({n},) ' if n is not None else ''}bool for a "
                f"discrete site; got shape {tuple(mask.shape)} for a {kind} one"
            )
        if bool(mask.all()):
            continue
        if spec.role == "cluster":
            raise ValueError(
                f"masks[{site!r}]: a parameter's cluster is its value's cell, never missing "
                "on its own; give the parameter's value, or NaN where the action ignores it"
            )
        out[site] = mask
    unfit = [
        s.name
        for s in net.sites
        if not net.cpd(s.name).closed_form
        and not callable(getattr(net.cpd(s.name), "maximise", None))
    ]
    if out and unfit:
        raise ValueError(
            f"sites {unfit} have neither a closed form nor a maximise method: EM over "
            "missing values has no M-step for them"
        )
    return out


def ignore_missing(
    net: EffectNetwork, data: Mapping[str, object], masks: Mapping[str, object]
) -> Mapping[str, object]:
    """The rows with each value that ``masks`` mark missing replaced by a declared state.

    The value there is ignored, so ``None``, NaN, an empty string or any label may stand
    in its place.

    Parameters
    ----------
    net
        The network.
    data
        Rows by site name; encoded rows (:class:`Evidence`) hold valid indices
        throughout and are returned as they are.
    masks
        Per discrete site, one bool (or 0/1) per row, False where missing.

    Returns
    -------
    Mapping
        ``data`` with each masked site's missing values set to its first state (a mask
        of the wrong length is left for :func:`row_masks` to refuse).
    """
    if isinstance(data, Evidence):
        return data
    out = dict(data)
    for site, mask in masks.items():
        if site not in data or not net.site(site).discrete:
            continue
        missing = ~mask_values(site, mask).numpy()
        values = data[site]
        if isinstance(values, torch.Tensor):
            values = values.tolist()
        values = np.asarray(values, dtype=object).reshape(-1)
        if not missing.any() or values.shape != missing.shape:  # a wrong length: refused later
            continue
        spec = net.site(site)
        states = net.actions if site == ACTION else net.feature(spec.feature).states
        values = values.copy()
        values[missing] = states[0]
        out[site] = values
    return out


# ------------------------------------------------------------------- missing values
def split_missing(
    net: EffectNetwork, data: Mapping[str, object]
) -> tuple[Mapping[str, object], dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """The values the rows themselves mark missing, and the rows with placeholders there.

    A discrete value is missing where it is ``None`` (unless ``None`` is one of the
    site's states) or NaN (in a float or object array); a continuous initial or end
    value where it is NaN, whole or in some dimensions. ``param.<p>`` keeps its own
    convention (NaN: the row's action does not use ``p``), and a parameter's cluster is
    never missing on its own; neither is read here.

    Parameters
    ----------
    net
        The network.
    data
        Rows by site name, as :func:`training_rows` reads them (labels; encoded
        :class:`Evidence` may mark a continuous end value missing by NaN).

    Returns
    -------
    data
        ``data`` with each missing discrete value replaced by the site's first state and
        each missing continuous value by 0 (the same object where nothing is missing).
    masks
        ``(n,)`` bool per discrete site that misses a value, False where missing.
    gaps
        The flat bool mask of each continuous site's missing entries, True where
        missing, in the order of the given values' elements (:func:`with_gaps` puts
        NaN back there once the rows are encoded).
    """
    if isinstance(data, Evidence):  # encoded: a continuous initial or end value may be NaN
        partial = {
            s: v
            for s, v in data.items()
            if not net.site(s).discrete and net.site(s).role in ("initial", "end") and is_partial(v)
        }
        gaps = {s: torch.isnan(v).reshape(-1) for s, v in partial.items()}
        filled = {s: v.nan_to_num() for s, v in partial.items()}
        return (data | Evidence(net, filled, data.n_rows) if filled else data), {}, gaps
    masks: dict[str, torch.Tensor] = {}
    gaps = {}
    out = dict(data)
    for site, values in data.items():
        if site not in {s.name for s in net.sites}:
            continue  # refused by the encoding, naming it
        spec = net.site(site)
        if spec.role in ("param", "cluster"):
            continue
        if spec.discrete:
            missing = _missing_labels(values, None in labels_of(net, site))
            if missing is not None and missing.any():
                masks[site] = torch.from_numpy(~missing)
                filled = np.asarray(values, dtype=object).reshape(-1).copy()
                filled[missing] = labels_of(net, site)[0]
                out[site] = filled
            continue
        if isinstance(values, Partial):  # some dimensions observed: the others missing
            values = net.encode({site: values})[site]
        if isinstance(values, str | bytes):
            continue
        raw = values.detach() if isinstance(values, torch.Tensor) else values
        try:
            array = torch.as_tensor(np.asarray(raw, dtype=np.float64))
        except (TypeError, ValueError, RuntimeError):
            continue  # refused by the encoding, naming the site
        nan = torch.isnan(array)
        if bool(nan.any()):
            gaps[site] = nan.reshape(-1)
            out[site] = array.nan_to_num(nan=0.0)
    return (out if masks or gaps else data), masks, gaps


def with_gaps(enc: Evidence, gaps: Mapping[str, torch.Tensor]) -> Evidence:
    """The encoded rows with NaN where :func:`split_missing` found a continuous value missing."""
    if not gaps:
        return enc
    values = dict(enc.items())
    for site, missing in gaps.items():
        values[site] = torch.where(missing.reshape(values[site].shape), torch.nan, values[site])
    return Evidence(enc.net, values, enc.n_rows)


def labels_of(net: EffectNetwork, site: str) -> tuple:
    """A discrete site's states (the actions for ``action``)."""
    spec = net.site(site)
    return net.actions if site == ACTION else net.feature(spec.feature).states


def _missing_labels(values: object, none_is_a_state: bool) -> np.ndarray | None:
    """``(n,)`` bool, True where a discrete value is missing (None or NaN).

    ``None`` where the values cannot hold a missing one (integers, strings, booleans).
    """
    if isinstance(values, str | bytes):
        return None
    if isinstance(values, torch.Tensor):
        if not values.is_floating_point():
            return None
        return torch.isnan(values.detach()).reshape(-1).cpu().numpy()
    try:
        array = np.asarray(values)
    except (TypeError, ValueError):
        return None  # a ragged container: the encoding reads it
    if array.dtype.kind == "f":
        return np.isnan(array).reshape(-1)
    if array.dtype != object:
        return None
    flat = array.reshape(-1)
    return np.fromiter(
        (
            (v is None and not none_is_a_state)
            or (isinstance(v, float | np.floating) and bool(np.isnan(v)))
            or type(v).__name__ == "NAType"  # pandas' missing value, pandas not imported
            for v in flat
        ),
        dtype=bool,
        count=flat.size,
    )


def rows_with_gaps(
    net: EffectNetwork, data: Mapping[str, object], masks: Mapping[str, object] | None
) -> tuple[Evidence, dict[str, torch.Tensor]]:
    """Training rows that may miss values, encoded and checked.

    Parameters
    ----------
    net
        The network.
    data
        Rows by site name; missing values marked in the rows themselves
        (:func:`split_missing`) or by ``masks``.
    masks
        Per discrete site, one bool (or 0/1) per row, False where missing, or ``None``.

    Returns
    -------
    Evidence
        The checked rows (:func:`training_rows`), NaN where a continuous initial or end
        value is missing, a placeholder state where a discrete one is.
    dict of str to torch.Tensor
        ``(n,)`` bool per discrete site (``masks`` and the rows' own marks together),
        False where missing.
    """
    if masks is not None and not isinstance(masks, Mapping):
        raise ValueError(
            f"masks must map discrete site names to (n,) bool masks, got {type(masks).__name__}"
        )
    data, found, gaps = split_missing(net, data)
    masks = dict(masks or {})
    for site, mask in found.items():
        given = None if site not in masks else mask_values(site, masks[site])
        if given is None or given.shape == mask.shape:  # else row_masks refuses the length
            masks[site] = mask if given is None else mask & given
    if masks:
        missing_masks(net, masks, None)  # what EM cannot fill, before the rows' checks
        data = ignore_missing(net, data, masks)
    unknown_action = None
    if ACTION in masks:
        unknown_action = ~mask_values(ACTION, masks[ACTION])
    enc = with_gaps(training_rows(net, data, unknown_action), gaps)
    return enc, row_masks(net, masks, enc.n_rows)
