"""Fit tables with a prior shared by similar actions (for networks learned from few plays).

The maximum-likelihood fit (:func:`inference.fit`) learns every row of an end site's
table from the plays of that row alone. When the actions are points of a space in which
nearby actions have similar effects (the cells of a grid a robot aims at, say) and each
(initial state, action) pair has been played only once or never, that wastes what the
neighbouring actions' plays say. :func:`fit_pooled` keeps the row's own counts and gives
it a Dirichlet prior built from its neighbours' plays under the same other parents:

* ``kernel`` ``W`` ``(A, A)``, non-negative: ``W[a, b]`` how much action ``b``'s plays
  say about action ``a`` (:func:`grid_kernel` gives Gaussian weights on a grid). The
  diagonal is ignored: a row's own plays are its data, not its prior.
* For a row with action ``a`` (the other parents fixed), the neighbours' counts
  ``N[a] = sum_b W[a, b] c[b]`` (``c[b]`` the counts of the row with action ``b``), their
  weight ``t[a] = sum_k N[a, k]`` and their distribution ``m[a] = N[a] / t[a]``.
* The prior is ``Dirichlet(alpha + w[a] m[a])`` with ``w[a] = strength * min(1, t[a])``:
  ``strength`` pseudo-plays of the neighbours' distribution, fewer where the neighbours
  hold less than one (weighted) play, so one distant play does not decide an unplayed
  row. The table row is the posterior mean ``(c[a] + alpha + w[a] m[a]) / (n[a] + K alpha
  + w[a])`` and its evidence count ``n[a] + w[a]`` (a row with no own play but played
  neighbours is not *unseen* to the queries).

``strength = 0`` (or a kernel without off-diagonal weight) gives exactly
:func:`inference.fit`'s tables. Only end sites' tables whose parents include the action are
pooled; every other CPD is the plain fit. Queries on the result are as exact as on any
fitted network: the pooling changes the parameters, not the inference.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping

import torch
from effect_networks.inference.fitting.maximum_likelihood import fit_statistics
from effect_networks.inference.fitting.result import FitResult
from effect_networks.inference.fitting.rows import check_settings
from effect_networks.models.cpds.table import TableCPD, TableParams
from effect_networks.models.declaration import ACTION, EffectNetwork
from effect_networks.models.evidence import DTYPE
from effect_networks.models.frames import as_data
from effect_networks.models.params import NetworkParams

__all__ = ["fit_pooled", "grid_kernel"]


def grid_kernel(grid_shape: tuple[int, int], sigma: float) -> torch.Tensor:
    """``(A, A)`` Gaussian weights ``exp(-d^2 / (2 sigma^2))`` between the cells of a grid.

    A ``(rows, columns)`` grid in row-major order (``A = rows * columns``, ``d`` the distance in
    cells); ``sigma = 0`` gives the identity (no pooling).

    Parameters
    ----------
    grid_shape
        ``(rows, columns)`` of the grid.
    sigma
        The kernel's width, in cells (``>= 0``).

    Returns
    -------
    torch.Tensor
        ``(A, A)`` float64 weights, 1 on the diagonal.
    """
    if len(grid_shape) != 2 or not all(
        isinstance(k, int) and not isinstance(k, bool) and k >= 1 for k in grid_shape
    ):
        raise ValueError(f"grid_shape must be two ints >= 1, got {grid_shape!r}")
    if not isinstance(sigma, (int, float)) or not math.isfinite(sigma) or sigma < 0:
        raise ValueError(f"sigma must be a finite number >= 0, got {sigma!r}")
    rows, cols = grid_shape
    if sigma == 0:
        return torch.eye(rows * cols, dtype=DTYPE)
    cell = torch.arange(rows * cols)
    r, c = cell // cols, cell % cols
    d2 = ((r[:, None] - r[None]) ** 2 + (c[:, None] - c[None]) ** 2).to(DTYPE)
    return torch.exp(-d2 / (2 * sigma**2))


def fit_pooled(
    net: EffectNetwork,
    data: Mapping[str, object] | Iterable[Mapping[str, object]],
    kernel: torch.Tensor,
    *,
    strength: float = 0.5,
    pseudo_count: float = 0.01,
    min_variance: float = 1e-6,
    progress: bool = False,
    sites: Iterable[str] | None = None,
) -> FitResult:
    """Fit ``net`` like :func:`inference.fit`, end tables pooled over similar actions.

    The end sites' table rows are given a prior from the plays of similar actions (see the module).

    Parameters
    ----------
    data
        Training rows (or an iterable of row chunks), as :func:`inference.fit` reads them.
        Every CPD needs a closed form (tables, linear Gaussians).
    kernel
        ``(A, A)`` non-negative weights between the network's actions.
    strength
        Pseudo-plays of the neighbours' distribution in a row's prior (>= 0).
    pseudo_count, min_variance, progress
        As in :func:`inference.fit`.
    sites
        The end sites whose tables are pooled (default: every end table with the action
        among its parents); the others get the plain fit's.

    Returns
    -------
    FitResult
        The parameters, the pooled end tables in place of the plain fit's.
    """
    check_settings(pseudo_count=pseudo_count, min_variance=min_variance)
    if (
        not isinstance(strength, (int, float))
        or isinstance(strength, bool)
        or not math.isfinite(strength)
        or strength < 0
    ):
        raise ValueError(f"strength must be a finite number >= 0, got {strength!r}")
    poolable = [
        spec.name
        for spec in net.sites
        if spec.role == "end"
        and isinstance(net.cpd(spec.name), TableCPD)
        and ACTION in net.cpd(spec.name).parents
        and net.cpd(spec.name).pinned is None
    ]
    chosen = set(poolable) if sites is None else {sites} if isinstance(sites, str) else set(sites)
    if not chosen <= set(poolable):
        raise ValueError(
            f"sites {sorted(chosen - set(poolable))} cannot be pooled; the end tables with "
            f"the action among their parents are {poolable}"
        )
    n_actions = len(net.actions)
    kernel = torch.as_tensor(kernel, dtype=DTYPE)
    if kernel.shape != (n_actions, n_actions):
        raise ValueError(
            f"kernel must be ({n_actions}, {n_actions}) for the network's {n_actions} "
            f"actions, got {tuple(kernel.shape)}"
        )
    if not bool(torch.isfinite(kernel).all()) or bool((kernel < 0).any()):
        raise ValueError("kernel must hold finite non-negative weights")
    data = as_data(net, data)
    chunks = [data] if isinstance(data, Mapping) else data
    stats = fit_statistics(net, chunks, progress=progress)
    if stats.gradient:
        raise ValueError(
            f"sites {list(stats.gradient)} have no closed-form fit; fit_pooled needs every "
            "CPD in closed form (tables and linear Gaussians)"
        )
    off = kernel.clone()
    off.fill_diagonal_(0.0)
    cpds = {}
    for spec in net.sites:
        cpd = net.cpd(spec.name)
        if spec.name not in chosen:  # the plain fit's CPD
            cpds[spec.name] = cpd.m_step(stats.sites[spec.name], pseudo_count, min_variance)
            continue
        axis = cpd.parents.index(ACTION)
        counts = stats.sites[spec.name].counts.to(DTYPE).movedim(axis, -2)  # (..., A, K)
        cpds[spec.name] = _pooled(counts, off, strength, pseudo_count, axis)
    return FitResult(NetworkParams(cpds, pseudo_count, net))


def _pooled(counts, off, strength, alpha, axis) -> TableParams:
    """The pooled table of ``counts`` ``(..., A, K)``.

    The action axis is moved next to last, and back at ``axis`` in what is returned.

    A configuration of the other parents that no row reached (most of them, in a large
    table) has no counts and no neighbours' counts: its rows are computed once and
    copied (element by element the same operations, so the same bits).
    """
    k, n_actions = counts.shape[-1], counts.shape[-2]
    neighbours = torch.einsum("ab,...bk->...ak", off, counts)
    groups = counts.reshape(-1, n_actions, k)
    played = groups.sum((1, 2)) > 0
    some = torch.cat([played.nonzero()[:, 0], (~played).nonzero()[:1, 0]])  # + one unplayed
    probs_of, n_of = _pooled_rows(
        groups[some], neighbours.reshape(-1, n_actions, k)[some], strength, alpha
    )
    probs = torch.empty_like(groups)
    n = torch.empty(groups.shape[:2], dtype=groups.dtype)
    if not bool(played.all()):
        probs[~played] = probs_of[-1]
        n[~played] = n_of[-1]
    probs[played] = probs_of[: int(played.sum())]
    n[played] = n_of[: int(played.sum())]
    probs, n = probs.reshape(counts.shape), n.reshape(counts.shape[:-1])
    return TableParams(probs.movedim(-2, axis), n.movedim(-1, axis))


def _pooled_rows(counts, neighbours, strength, alpha) -> tuple[torch.Tensor, torch.Tensor]:
    """The pooled rows ``(g, A, K)`` and their evidence counts ``(g, A)`` of ``counts``.

    Given the neighbours' weighted counts.
    """
    k = counts.shape[-1]
    weight = neighbours.sum(-1, keepdim=True)
    m = torch.where(weight > 0, neighbours / weight.clamp_min(1e-300), 0.0)
    w = strength * weight.clamp(max=1.0)
    n = counts.sum(-1, keepdim=True)
    total = n + k * alpha + w
    probs = torch.where(total > 0, (counts + alpha + w * m) / total.clamp_min(1e-300), 1.0 / k)
    return probs, (n + w)[..., 0]
