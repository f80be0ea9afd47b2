"""The checks every fit shares: its settings, its training rows and their masks.

Every fitting route (:func:`inference.fit`, the EM fits, the pooled fit, active
exploration) reads the same training rows and refuses the same mistakes, so the rules
are written once here:

* settings (:func:`check_settings`): finite Python numbers, ``steps`` a positive int;
* rows (:func:`training_rows`): every site given, a parameter's value present exactly
  where the row's action uses it, no partly observed continuous value, nothing whose
  square would overflow; each parameter's cluster added where the rows do not give it
  (its value's equidistant cell);
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

from models.declaration import ACTION, EffectNetwork, cluster_site, param_site
from models.evidence import Evidence, check_magnitude, is_partial

__all__ = [
    "check_settings",
    "ignore_missing",
    "mask_site",
    "mask_values",
    "missing_masks",
    "refuse_adaptive",
    "row_masks",
    "training_rows",
]


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
    """Encode training rows, check them, and add each parameter's cluster where the rows
    do not give it (its value's cell).

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
        raise ValueError("no training rows: fit needs at least one row of every site")
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
