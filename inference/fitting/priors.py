"""Priors of the closed-form fit: Dirichlet pseudo-counts per table, NIW per Gaussian.

``fit(net, rows, prior=...)`` takes one of

* a number: the symmetric pseudo-count of every table and the pooled pseudo-rows of
  every linear Gaussian (the pseudo-count policy, the same as ``pseudo_count=``);
* :class:`BDeu` ``(ess)``: every table's cells get ``ess / (configurations x states)``
  (pgmpy's ``prior_type="BDeu"``, ``equivalent_sample_size=ess``);
* :class:`K2` ``()``: every table's cells get 1 (pgmpy's ``prior_type="K2"``);
* a mapping site -> prior, for the sites it names (the others keep ``pseudo_count``):
  a table takes a number (a symmetric pseudo-count), an array of pseudo-counts of its
  table's shape ``(P..., K)`` (pgmpy's ``prior_type="dirichlet"`` with
  ``pseudo_counts``, in the toolkit's axis order), :class:`BDeu` or :class:`K2`; a
  linear Gaussian a number (its pooled pseudo-rows) or a
  :class:`~models.cpds.linear_gaussian.NormalInverseWishart`; any other kind a number.

What a fit with a prior is. A table is the Dirichlet posterior's **mean**
``(n + alpha) / (N + sum alpha)`` (pgmpy's ``BayesianEstimator``), or with
``estimate="map"`` its **mode** ``(n + alpha - 1) / (N + sum alpha - K)``, defined where
every pseudo-count is at least 1 (a row whose pseudo-counts are all 1 and that no row
reached is uniform). A linear Gaussian with a normal-inverse-Wishart prior is the
posterior's joint **mode** (MAP) whatever ``estimate`` says; with a number it is the
pseudo-count policy's fit.

:func:`site_priors` turns the argument into each site's ``alpha``, what its kind's
``m_step`` takes: a float, a tensor of pseudo-counts (tables) or a
:class:`~models.cpds.linear_gaussian.NormalInverseWishart`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch
from effect_networks.models.cpds import LinearGaussianCPD, NormalInverseWishart, TableCPD
from effect_networks.models.declaration import EffectNetwork
from effect_networks.models.dtype import DTYPE

__all__ = ["ESTIMATES", "K2", "BDeu", "NormalInverseWishart", "Prior", "site_priors"]

#: A table's point estimate under its Dirichlet prior: the posterior mean or mode.
ESTIMATES = ("mean", "map")


@dataclass(frozen=True)
class BDeu:
    """The BDeu prior: ``equivalent_sample_size`` spread evenly over a table's cells.

    Each cell gets ``equivalent_sample_size / (configurations x states)``.
    """

    equivalent_sample_size: float = 1.0


@dataclass(frozen=True)
class K2:
    """The K2 prior: a pseudo-count of 1 in every cell of a table."""


#: What ``fit(prior=...)`` takes (see the module).
Prior = float | BDeu | K2 | Mapping[str, object]


def site_priors(
    net: EffectNetwork, prior: object, pseudo_count: float, estimate: str = "mean"
) -> dict[str, float | torch.Tensor | NormalInverseWishart]:
    """Each site's ``alpha`` for its kind's ``m_step`` (see the module).

    ``prior`` None means ``pseudo_count`` everywhere. Under ``estimate="map"`` a table's
    pseudo-counts are lowered by 1 (the mode is the mean of ``alpha - 1``).

    Raises
    ------
    ValueError
        Naming the site and what it takes: an unknown site, a prior its kind cannot take,
        pseudo-counts of another shape or negative or non-finite, a map estimate with a
        pseudo-count below 1.
    """
    if estimate not in ESTIMATES:
        raise ValueError(f"estimate must be one of {ESTIMATES}, got {estimate!r}")
    sites = [s.name for s in net.sites]
    if prior is None or isinstance(prior, BDeu | K2) or _is_number(prior):
        named = dict.fromkeys(sites, pseudo_count if prior is None else prior)
        if not _is_number(prior) and prior is not None:  # BDeu/K2: the tables only
            named = {s: prior if isinstance(net.cpd(s), TableCPD) else pseudo_count for s in sites}
    elif isinstance(prior, Mapping):
        unknown = [s for s in prior if s not in sites]
        if unknown:
            raise ValueError(
                f"prior names {unknown}, which are not sites of this network (its sites: {sites})"
            )
        named = {s: prior.get(s, pseudo_count) for s in sites}
    else:
        raise ValueError(
            "prior must be a number, BDeu(ess), K2() or a mapping site -> prior; got "
            f"{type(prior).__name__}"
        )
    return {site: _alpha(net, site, value, estimate) for site, value in named.items()}


def _alpha(net: EffectNetwork, site: str, value: object, estimate: str):
    cpd = net.cpd(site)
    table = isinstance(cpd, TableCPD)
    if isinstance(value, NormalInverseWishart):
        if not isinstance(cpd, LinearGaussianCPD):
            raise ValueError(
                f"site {site!r}: a NormalInverseWishart prior is for a linear Gaussian; this "
                f"site is a {cpd.name!r} CPD"
            )
        value.scale_matrix(site, cpd.size)  # checked here, before any statistics
        return value
    if not table and not _is_number(value):
        what = (
            "a number or a NormalInverseWishart"
            if isinstance(cpd, LinearGaussianCPD)
            else "a number"
        )
        raise ValueError(f"site {site!r} is a {cpd.name!r} CPD: its prior is {what}, got {value!r}")
    if not table:
        return _checked_number(site, value)
    shape = (*cpd.card, cpd.size)
    if isinstance(value, BDeu):
        ess = _checked_number(site, value.equivalent_sample_size, "equivalent_sample_size")
        alpha: float | torch.Tensor = ess / (math.prod(cpd.card) * cpd.size)
    elif isinstance(value, K2):
        alpha = 1.0
    elif _is_number(value):
        alpha = _checked_number(site, value)
    else:
        alpha = torch.as_tensor(np.asarray(value, dtype=np.float64), dtype=DTYPE)
        if tuple(alpha.shape) != shape:
            raise ValueError(
                f"site {site!r}: pseudo-counts of shape {tuple(alpha.shape)}; its table has "
                f"shape {shape} (parents {list(cpd.parents)}, then its states)"
            )
        if not bool(alpha.isfinite().all()) or bool((alpha < 0).any()):
            raise ValueError(f"site {site!r}: pseudo-counts must be finite and >= 0")
    if estimate == "mean":
        return alpha
    smallest = float(alpha.min()) if isinstance(alpha, torch.Tensor) else alpha
    if smallest < 1:
        raise ValueError(
            f"site {site!r}: the MAP table needs every pseudo-count >= 1 (the Dirichlet's mode "
            f"is undefined below), its smallest is {smallest:g}; use estimate='mean' or raise "
            "the pseudo-counts (name the site in a prior mapping)"
        )
    if isinstance(alpha, torch.Tensor):
        return alpha - 1
    return torch.full(shape, alpha - 1, dtype=DTYPE)  # a tensor: an unseen row is the prior's mode


def _is_number(value: object) -> bool:
    return isinstance(value, int | float | np.integer | np.floating) and not isinstance(value, bool)


def _checked_number(site: str, value: object, name: str = "pseudo-count") -> float:
    if not _is_number(value) or not math.isfinite(value) or value < 0:
        raise ValueError(f"site {site!r}: the {name} must be a finite number >= 0, got {value!r}")
    return float(value)
