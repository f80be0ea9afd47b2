r"""The throw's parameter network (paper §IV-B, Fig. 4): where to aim to hit a point.

One action, ``throw``, with a 2-D parameter, the aimed-at ``target`` point ``[y, z]`` on
the target plane, acting on one outcome feature, the ``hit`` point ``[y, z]`` where the
ball crosses that plane::

    action = throw   (one state)
         |
         v
    cluster.target  --->  param.target  (target [y, z], m)
         |                     |
         +-------> end.hit <---+        (hit [y, z], m)

The cluster site cuts the target area into an equidistant ``bins[0] x bins[1]`` grid;
per cluster the target is Gaussian and the hit is a linear Gaussian of the target, i.e.
one joint Gaussian of (target, hit) per cluster: a mixture of Gaussians that captures
the non-linear target-to-hit mapping piece by piece. ``bins=(1, 1)`` is the single
Gaussian (the cluster site has one state). Fitting and the queries are the core's
:func:`inference.fit`, :func:`inference.infer_parameter` (hit -> target, the paper's
inverse) and :func:`inference.predict` (target -> hit).

This module knows nothing of the kinematics that produce the data (:mod:`sim2d.analytic_throw`):
it declares the network and turns plain ``(n, 2)`` arrays into validated rows.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from effect_networks.models.declaration import (
    ACTION,
    DTYPE,
    Continuous,
    EffectNetwork,
    Parameter,
    end_site,
    param_site,
)

__all__ = [
    "HIT",
    "PAPER_AREA_HIGH",
    "PAPER_AREA_LOW",
    "TARGET",
    "THROW",
    "hit_evidence",
    "throw_data",
    "throw_network",
]

#: Names of the action, the parameter and the outcome feature.
THROW = "throw"
TARGET = "target"
HIT = "hit"

#: The paper's target area (§IV-B: 2 m x 2 m, centred on the robot), ``[y, z]`` in
#: metres: the same numbers as ``sim2d.analytic_throw.TARGET_AREA`` (a test keeps them equal;
#: models/ does not import the simulator).
PAPER_AREA_LOW = (-1.0, 0.4)
PAPER_AREA_HIGH = (1.0, 2.4)


def throw_network(
    bins: Sequence[int] = (12, 12),
    *,
    low: Sequence[float] = PAPER_AREA_LOW,
    high: Sequence[float] = PAPER_AREA_HIGH,
) -> EffectNetwork:
    """Declare the throw network of paper Fig. 4.

    Parameters
    ----------
    bins : (2,) int
        Clusters per axis ``(y, z)`` of the target area; ``(1, 1)`` is one Gaussian.
    low, high : (2,) float, metres
        Corners ``[y, z]`` of the target area the clusters cut.

    Returns
    -------
    EffectNetwork
        Sites ``action``, ``cluster.target`` (``bins[0] * bins[1]`` states, row-major,
        y major), ``param.target`` (2-D) and ``end.hit`` (2-D); no initial state.
    """
    bins = tuple(bins)
    if len(bins) != 2 or any(isinstance(b, bool) or not isinstance(b, int) for b in bins):
        raise ValueError(f"bins = {bins!r}: expected two positive ints, clusters along (y, z)")
    return EffectNetwork(
        features=(Continuous(HIT, 2, kind="world", initial=False),),
        actions=(THROW,),
        parameters=(
            Parameter(
                TARGET,
                low=tuple(float(v) for v in low),
                high=tuple(float(v) for v in high),
                bins=bins,
                actions=(THROW,),
                affects=HIT,
            ),
        ),
    )


def throw_data(net: EffectNetwork, targets: np.ndarray, hits: np.ndarray) -> dict:
    """Training rows for :func:`inference.fit` from throws.

    Parameters
    ----------
    net : EffectNetwork
        A network from :func:`throw_network`; its target area bounds the targets.
    targets : (n, 2) float, metres
        Aimed-at points ``[y, z]``, inside the network's target area.
    hits : (n, 2) float, metres
        Where each throw crossed the target plane (anywhere on it).

    Returns
    -------
    dict
        Encoded rows (:class:`~models.evidence.Evidence`): ``action`` (the one throw),
        ``param.target`` ``(n, 2)`` and ``end.hit`` ``(n, 2)`` float64.

    Raises
    ------
    ValueError
        If an array is not a finite ``(n, 2)`` array, their rows differ in number, or a
        target lies outside the area (it would be filed under an edge cluster).
    """
    parameter = _target_parameter(net)
    targets = _points(targets, "targets")
    hits = _points(hits, "hits")
    if len(targets) != len(hits):
        raise ValueError(
            f"targets has {len(targets)} rows and hits {len(hits)}: expected one hit per target"
        )
    _check_inside(targets, "targets", parameter.low, parameter.high)
    return net.encode(
        {
            ACTION: [net.actions[0]] * len(targets),
            param_site(TARGET): targets,
            end_site(HIT): hits,
        }
    )


def hit_evidence(
    hits: np.ndarray, *, low: Sequence[float], high: Sequence[float]
) -> dict[str, torch.Tensor]:
    """Evidence for the inverse query ``infer_parameter(net, params, "target", evidence)``.

    Parameters
    ----------
    hits : (n, 2) float, metres
        Desired hit points ``[y, z]`` on the target plane.
    low, high : (2,) float, metres
        Corners of the window of the plane where hits are answered: the region the
        training hits cover (hits from throws can lie below the target area, where
        gravity carries low throws). Outside it the mixture only extrapolates.

    Returns
    -------
    dict
        ``{"end.hit": (n, 2) float64}``.

    Raises
    ------
    ValueError
        If ``hits`` is not a finite ``(n, 2)`` array or a hit lies outside the window.
    """
    hits = _points(hits, "hits")
    _check_inside(hits, "hits", low, high)
    return {end_site(HIT): torch.as_tensor(hits, dtype=DTYPE)}


def _target_parameter(net: EffectNetwork) -> Parameter:
    parameter = next((p for p in net.parameters if p.name == TARGET), None)
    if parameter is None or parameter.affects != HIT or parameter.dim != 2:
        raise ValueError(
            f"net has no 2-D parameter {TARGET!r} acting on {HIT!r}: build it with throw_network()"
        )
    return parameter


def _points(points: np.ndarray, name: str) -> np.ndarray:
    try:
        array = np.array(points, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise ValueError(
            f"{name} = {points!r}: expected an (n, 2) float array of [y, z] in metres"
        ) from error
    if array.ndim != 2 or array.shape[1] != 2:
        raise ValueError(
            f"{name} with shape {array.shape}: expected (n, 2), one [y, z] row per throw; "
            "reshape a single point with np.reshape(point, (1, 2))"
        )
    bad = ~np.all(np.isfinite(array), axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(
            f"{name}[{i}] = {array[i].tolist()}: expected finite numbers "
            f"({int(bad.sum())} row(s) hold NaN or inf)"
        )
    return array


def _check_inside(
    points: np.ndarray, name: str, low: Sequence[float], high: Sequence[float]
) -> None:
    low, high = np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)
    if low.shape != (2,) or high.shape != (2,) or not np.all(low < high):
        raise ValueError(
            f"bounds low = {low.tolist()}, high = {high.tolist()}: expected low < high, (2,) each"
        )
    outside = ~np.all((points >= low) & (points <= high), axis=1)
    if outside.any():
        i = int(np.flatnonzero(outside)[0])
        raise ValueError(
            f"{name}[{i}] = {points[i].tolist()}: expected inside y in [{low[0]:g}, {high[0]:g}] m, "
            f"z in [{low[1]:g}, {high[1]:g}] m ({int(outside.sum())} row(s) outside)"
        )
