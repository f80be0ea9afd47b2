"""Networks chained into one planner.

An upper network's continuous output is read as a lower network's action.

An upper network (say, one that throws) predicts a continuous end feature as a Gaussian
mixture (:class:`~inference.queries.results.GaussianMixture`, what
:func:`~inference.queries.forward.predict` returns for it). A *link* reads a value of
that output as one of a lower network's actions (say, the field of a scene that the
throw hits), or as nothing at all (the *none* label: the lower network is not acted on
and the state stays as it is). Two kinds of link:

* :class:`BoxPartition` -- boxes in the output space (per dimension an interval
  ``[low, high)``, either end possibly infinite), each labelled by a lower action; a
  point in no box is *none*. Its probabilities are exact where they can be (see
  :func:`link_probabilities`).
* :class:`FunctionLink` -- any function from output values to lower actions (or
  *none*); its probabilities are a seeded Monte Carlo estimate with a standard error.

:func:`link_probabilities` gives ``P(lower action | upper row)`` for each row of the
upper network's predicted mixture (one row per upper action or parameter value), and
:func:`chain` combines them with the lower network's transitions ``P(s' | s, lower
action)`` into the chained model

    ``T[s, u, s'] = sum_a P(a | u, s) P(s' | s, a) + P(none | u, s) [s' = s]``

over which the planners of :mod:`inference.sequences.dynamic_programming` plan directly. The link may
depend on the state (the same aim meets different things in different scenes): pass one
link's probabilities per state.

Nothing here knows what the outputs, actions or states mean.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from effect_networks.inference.queries.results import GaussianMixture

__all__ = [
    "BoxPartition",
    "FunctionLink",
    "LinkProbabilities",
    "chain",
    "link_probabilities",
]

NONE = "none"
#: Gauss-Legendre nodes per piece of the 2-D rectangle quadrature (up to 34 pieces a box).
QUADRATURE_NODES = 20
#: The fewest nodes accepted: below them the quadrature's error rises above rounding.
MIN_QUADRATURE_NODES = 12
#: The quadrature's range of the standardised first dimension: 2 Phi(-9) < 3e-19 outside.
Z_CUT = 9.0
#: Where the quadrature splits the standardised first dimension for its density's sake.
PHI_CUTS = (-6.0, -4.5, -3.0, -2.0, -1.0, 0.0, 1.0, 2.0, 3.0, 4.5, 6.0)
#: Where it splits either side of a step of the conditional probability, in step widths.
STEP_CUTS = (-16.0, -8.0, -4.0, -2.0, -1.0, 0.0, 1.0, 2.0, 4.0, 8.0, 16.0)
#: The most a component's disjoint boxes may sum to above 1 and be rounding.
ROUNDING = 1e-12
#: Monte Carlo draws per row of the upper mixture.
SAMPLES = 100_000


@dataclass(frozen=True)
class BoxPartition:
    """Boxes in a ``d``-dimensional output space, each labelled by a lower action.

    Attributes
    ----------
    low, high : torch.Tensor
        ``(K, d)`` float64: box ``k`` holds the points ``x`` with ``low[k] <= x <
        high[k]`` in every dimension; ``-inf`` / ``inf`` leave a side open. Boxes must not
        overlap.
    labels : tuple
        ``K`` lower actions, one per box; several boxes may share one.
    actions : tuple
        The lower actions in the order of the lower transitions' action axis; each label
        is one of them.
    none : Hashable
        The name of "outside every box": no lower action, the state stays.
    """

    low: torch.Tensor
    high: torch.Tensor
    labels: tuple
    actions: tuple
    none: Hashable = NONE

    def __post_init__(self) -> None:
        low = torch.as_tensor(self.low, dtype=torch.float64)
        high = torch.as_tensor(self.high, dtype=torch.float64)
        object.__setattr__(self, "low", low)
        object.__setattr__(self, "high", high)
        object.__setattr__(self, "labels", tuple(self.labels))
        object.__setattr__(self, "actions", tuple(self.actions))
        if low.ndim != 2 or low.shape != high.shape:
            raise ValueError(
                f"BoxPartition: low {tuple(low.shape)} and high {tuple(high.shape)}: expected "
                "two (K, d) arrays of the same shape"
            )
        if torch.isnan(low).any() or torch.isnan(high).any() or not (low <= high).all():
            raise ValueError("BoxPartition: expected low <= high in every box (no NaN)")
        if len(self.labels) != low.shape[0]:
            raise ValueError(
                f"BoxPartition: {len(self.labels)} labels for {low.shape[0]} boxes; expected "
                "one label per box"
            )
        unknown = [label for label in self.labels if label not in self.actions]
        if unknown:
            raise ValueError(
                f"BoxPartition: labels {unknown[:5]} are not lower actions; actions are "
                f"{list(self.actions)[:10]}"
            )
        # boxes overlap when their intervals overlap in every dimension
        overlap = (low[:, None] < high[None, :]) & (low[None, :] < high[:, None])
        overlap = overlap.all(-1) & ~torch.eye(len(low), dtype=torch.bool)
        overlap &= ((high - low) > 0).all(-1)[:, None] & ((high - low) > 0).all(-1)[None, :]
        if overlap.any():
            i, j = overlap.nonzero()[0].tolist()
            raise ValueError(f"BoxPartition: boxes {i} and {j} overlap; expected disjoint boxes")

    @classmethod
    def from_boxes(
        cls, boxes: Sequence[tuple[Hashable, Sequence[tuple[float, float]]]], actions, none=NONE
    ) -> BoxPartition:
        """From ``(label, [(low, high) per dimension])`` pairs."""
        low = [[lo for lo, _ in sides] for _, sides in boxes]
        high = [[hi for _, hi in sides] for _, sides in boxes]
        return cls(low, high, tuple(label for label, _ in boxes), tuple(actions), none)

    @property
    def dim(self) -> int:
        """The output space's dimension ``d``."""
        return self.low.shape[1]

    def label_index(self, points: torch.Tensor) -> torch.Tensor:
        """``(N,)`` index into ``actions`` of each point's box, ``len(actions)`` for none."""
        points = torch.as_tensor(points, dtype=torch.float64)
        inside = ((points[:, None] >= self.low) & (points[:, None] < self.high)).all(-1)
        column = torch.tensor([self.actions.index(label) for label in self.labels])
        found = inside.any(-1)
        return torch.where(found, column[inside.byte().argmax(-1)], len(self.actions))

    def __call__(self, points) -> list:
        """Each point's label (a lower action or ``none``); a :class:`FunctionLink` body."""
        labels = (*self.actions, self.none)
        return [labels[i] for i in self.label_index(points).tolist()]


@dataclass(frozen=True)
class FunctionLink:
    """A user function from output values to lower actions.

    Attributes
    ----------
    function : callable
        ``(N, d)`` float64 numpy array of output values -> ``N`` labels, each a lower
        action or ``none``: a sequence, or (read fastest) a 1-D numpy array of str or
        int labels.
    actions : tuple
        The lower actions in the order of the lower transitions' action axis.
    dim : int
        The output space's dimension ``d``.
    none : Hashable
        The label that means no lower action (the state stays).
    """

    function: Callable[[np.ndarray], Sequence[Hashable]]
    actions: tuple
    dim: int
    none: Hashable = NONE

    def label_index(self, points: torch.Tensor) -> torch.Tensor:
        """``(N,)`` index into ``actions`` of each point's label, ``len(actions)`` for none."""
        column = {label: i for i, label in enumerate(self.actions)}
        column[self.none] = len(self.actions)
        labels = self.function(np.asarray(points, dtype=np.float64))
        if len(labels) != len(points):
            raise ValueError(
                f"FunctionLink: the function gave {len(labels)} labels for {len(points)} "
                "points; expected one label per point"
            )
        if isinstance(labels, np.ndarray) and labels.ndim == 1 and labels.dtype.kind in "biuU":
            # a numpy array of labels: one lookup per distinct label
            distinct, inverse = np.unique(labels, return_inverse=True)
        else:
            distinct, inverse = list(dict.fromkeys(labels)), None
        unknown = [label for label in distinct if _item(label) not in column]
        if unknown:
            raise ValueError(
                f"FunctionLink: labels {[_item(u) for u in unknown][:5]} are neither lower "
                f"actions nor none ({self.none!r}); actions are {list(self.actions)[:10]}"
            )
        if inverse is None:
            return torch.tensor([column[label] for label in labels], dtype=torch.long)
        lookup = np.array([column[_item(label)] for label in distinct], dtype=np.int64)
        return torch.as_tensor(lookup[inverse.reshape(-1)])


@dataclass(frozen=True)
class LinkProbabilities:
    """``P(lower action | upper row)`` from :func:`link_probabilities`.

    Attributes
    ----------
    probs : torch.Tensor
        ``(U, A)`` float64 over ``actions``, one row per upper action or parameter value.
    none : torch.Tensor
        ``(U,)`` probability of no lower action (the state stays). A row of ``probs`` and
        its ``none`` sum to 1, except a row of zeros (an upper action not offered).
    actions : tuple
        The lower actions, the columns of ``probs``.
    stderr : torch.Tensor or None
        ``(U, A)`` Monte Carlo standard errors of ``probs``; None where computed exactly.
    method : str
        ``"exact"`` (normal CDFs, every box), ``"quadrature"`` (a 2-D box under a
        correlated component; the other boxes still exact) or ``"monte carlo"``.
    """

    probs: torch.Tensor
    none: torch.Tensor
    actions: tuple
    stderr: torch.Tensor | None = None
    method: str = "exact"

    def prob(self, action: Hashable) -> torch.Tensor:
        """``(U,)`` probability of the lower action ``action``."""
        if action not in self.actions:
            raise ValueError(f"unknown lower action {action!r}; actions are {list(self.actions)}")
        return self.probs[:, self.actions.index(action)]

    def padded(self, rows: Sequence[int], n_upper: int) -> LinkProbabilities:
        """These rows placed at upper actions ``rows`` of ``n_upper``.

        The others are zero rows (upper actions not offered: the chained model gives them no
        transitions).
        """
        rows = torch.as_tensor(rows, dtype=torch.long)
        if rows.shape != (len(self.probs),):
            raise ValueError(
                f"padded: {tuple(rows.shape)} rows for {len(self.probs)} upper rows; "
                "expected one upper action index per row"
            )
        probs = self.probs.new_zeros(n_upper, len(self.actions))
        probs[rows] = self.probs
        none = self.none.new_zeros(n_upper)
        none[rows] = self.none
        stderr = None
        if self.stderr is not None:
            stderr = self.stderr.new_zeros(n_upper, len(self.actions))
            stderr[rows] = self.stderr
        return LinkProbabilities(probs, none, self.actions, stderr, self.method)


def link_probabilities(
    link: BoxPartition | FunctionLink,
    mixture: GaussianMixture,
    *,
    samples: int = SAMPLES,
    seed: int = 0,
    nodes: int = QUADRATURE_NODES,
) -> LinkProbabilities:
    """``P(lower action | upper row)``.

    The upper network's predicted mixture integrated over the link.

    Parameters
    ----------
    link : BoxPartition or FunctionLink
        How an output value reads as a lower action.
    mixture : GaussianMixture
        ``U`` rows of the upper network's predicted output (``weights (U, M)``, ``means
        (U, M, d)``, ``covs (U, M, d, d)``), e.g. ``predict(...).continuous[feature]``
        with one evidence row per upper action or parameter value.
    samples : int
        Monte Carlo draws per row (a :class:`FunctionLink`, or boxes bounded in more
        than two dimensions under correlated components).
    seed : int
        Seeds the Monte Carlo draws.
    nodes : int
        Gauss-Legendre nodes per piece of the 2-D rectangle quadrature, at least 12.

    Returns
    -------
    LinkProbabilities
        ``probs (U, A)`` and ``none (U,)``.

    Notes
    -----
    A box partition is integrated over each Gaussian component box by box, each box in
    the dimensions it bounds (the others integrate to 1), whatever the other boxes bound:

    * exactly, as products of per-dimension normal CDF differences, when the box bounds
      one dimension, or several that the component does not correlate (``method="exact"``
      when every box is);
    * in two correlated dimensions, by conditioning on the first: ``P = integral of
      phi(z) P(a2 <= x2 < b2 | z) dz`` over the box's standardised first side, cut to
      ``|z| <= 9``, split at fixed points for ``phi`` and around where the conditional
      mean of ``x2`` crosses ``a2`` and ``b2``, Gauss-Legendre with ``nodes`` nodes on each
      of up to 34 pieces (``method="quadrature"``): deterministic; absolute error below
      ``1e-10`` per box at the default ``nodes`` for correlations up to 0.99999 (tested
      against the bivariate normal CDF's closed form in Owen's T function and
      ``scipy.integrate.dblquad``);
    * the whole partition by Monte Carlo, as for a :class:`FunctionLink`, when a box bounds
      three or more dimensions that a component correlates.

    The boxes are disjoint, so each component's box probabilities and *none* (the rest)
    sum to 1: a sum of box probabilities above 1 by more than rounding (``1e-12``) is a
    defect and asserted against; rounding is normalised away in log space. Every
    probability lies in [0, 1].

    A :class:`FunctionLink` is estimated from ``samples`` seeded draws per row
    (``method="monte carlo"``): each probability has standard error ``sqrt(p (1 - p) /
    samples)`` (reported as ``stderr``, from the estimate), below ``0.5 /
    sqrt(samples)``, 0.0016 at the default; an estimate lies within 4 standard errors
    of the exact value with probability above 0.9999.
    """
    _check_mixture(mixture, link.dim)
    if isinstance(link, BoxPartition):
        if not isinstance(nodes, int) or nodes < MIN_QUADRATURE_NODES:
            raise ValueError(
                f"nodes: {nodes!r}; expected an integer of at least {MIN_QUADRATURE_NODES} "
                f"(the default {QUADRATURE_NODES} keeps the quadrature at rounding error)"
            )
        if not _needs_monte_carlo(link, mixture):
            return _boxes(link, mixture, nodes)
    elif not isinstance(link, FunctionLink):
        raise TypeError(f"link: {type(link).__name__}; expected a BoxPartition or a FunctionLink")
    return _monte_carlo(link, mixture, samples, seed)


def chain(
    link: LinkProbabilities
    | Sequence[LinkProbabilities | None]
    | Callable[[int], LinkProbabilities | None],
    lower_transitions: torch.Tensor,
) -> torch.Tensor:
    """The chained transitions ``T[s, u, s']``.

    An upper action is read through the link as the lower network's actions.

    ``T[s, u, s'] = sum_a P(a | u, s) P(s' | s, a) + P(none | u, s) [s' = s]``.

    Parameters
    ----------
    link : LinkProbabilities, sequence or callable
        One :class:`LinkProbabilities` for every state, or one per state (a sequence of
        ``S``, or a function of the state's index), where the link depends on the state;
        None for a state gives it no transitions (a zero row: no action offered there).
    lower_transitions : torch.Tensor
        ``(S, A, S)``: ``P(s' | s, a)`` of the lower network, the actions in the order of
        the link's ``actions`` (any source: a network's own tables, an experiment's
        model, simulations).

    Returns
    -------
    torch.Tensor
        ``(S, U, S)`` float64. A row sums to 1 where its link row and the lower rows it
        reaches do.
    """
    lower = torch.as_tensor(lower_transitions, dtype=torch.float64)
    if lower.ndim != 3 or lower.shape[0] != lower.shape[2]:
        raise ValueError(
            f"lower_transitions: shape {tuple(lower.shape)}; expected (S, A, S) = "
            "P(next state | state, lower action)"
        )
    n_states, n_actions = lower.shape[:2]
    if isinstance(link, LinkProbabilities):
        _check_columns(link, n_actions, "link")
        t = torch.einsum("ua,sat->sut", link.probs, lower)
        idx = torch.arange(n_states)
        t[idx, :, idx] += link.none[None, :]
        return t
    per_state = link if callable(link) else _sequence(link, n_states)
    rows = [per_state(s) for s in range(n_states)]
    given = [r for r in rows if r is not None]
    if not given:
        raise ValueError("link: None for every state; expected link probabilities for some")
    n_upper = len(given[0].probs)
    t = torch.zeros(n_states, n_upper, n_states, dtype=torch.float64)
    for s, r in enumerate(rows):
        if r is None:
            continue
        _check_columns(r, n_actions, f"link of state {s}")
        if len(r.probs) != n_upper:
            raise ValueError(
                f"link of state {s}: {len(r.probs)} upper rows; expected {n_upper} as for "
                "the other states (pad with LinkProbabilities.padded)"
            )
        t[s] = r.probs @ lower[s]
        t[s, :, s] += r.none
    return t


# --- box partitions ----------------------------------------------------------------------


def _boxes(link: BoxPartition, mixture: GaussianMixture, nodes: int) -> LinkProbabilities:
    """Each box by its own route: CDF products, or the quadrature for a correlated pair.

    A box's route depends only on the dimensions it bounds and each component's covariance
    there, never on the other boxes.
    """
    per_box = _cdf_products(link, mixture)  # (U, M, K)
    bounded = _bounded(link)
    method = "exact"
    pairs = {tuple(row.nonzero().flatten().tolist()) for row in bounded if row.sum() == 2}
    for i, j in sorted(pairs):
        correlated = mixture.covs[..., i, j] != 0  # (U, M)
        if not correlated.any():
            continue
        boxes = (bounded.sum(-1) == 2) & bounded[:, i] & bounded[:, j]
        sides = [i, j]
        rectangles = _rectangles(
            mixture, link.low[boxes][:, sides], link.high[boxes][:, sides], i, j, nodes
        )
        per_box[..., boxes] = torch.where(correlated[..., None], rectangles, per_box[..., boxes])
        method = "quadrature"
    undefined = per_box.isnan().flatten(1).any(-1)
    if undefined.any():
        raise ValueError(
            f"mixture: rows {undefined.nonzero().flatten().tolist()[:5]} give undefined box "
            "probabilities; expected finite means and covariances with positive variances"
        )
    per_box, none = _normalised(per_box)
    column = torch.tensor([link.actions.index(label) for label in link.labels], dtype=torch.long)
    weighted = mixture.weights[..., None] * per_box
    probs = weighted.new_zeros(len(weighted), len(link.actions))
    probs.index_add_(1, column, weighted.sum(1))
    none = (mixture.weights * none).sum(1)
    # weights that sum to 1 + 2e-16 would carry a certain box past 1 by as much
    return LinkProbabilities(probs.clamp_(0, 1), none.clamp(0, 1), link.actions, None, method)


def _bounded(link: BoxPartition) -> torch.Tensor:
    """``(K, d)``: whether box ``k`` bounds dimension ``i`` (a finite side)."""
    return torch.isfinite(link.low) | torch.isfinite(link.high)


def _needs_monte_carlo(link: BoxPartition, mixture: GaussianMixture) -> bool:
    """Whether a box bounds three or more dimensions that some component correlates."""
    for dims in {tuple(row.nonzero().flatten().tolist()) for row in _bounded(link)}:
        if len(dims) < 3:
            continue
        covs = mixture.covs[..., dims, :][..., :, dims]
        if (covs - torch.diag_embed(torch.diagonal(covs, dim1=-2, dim2=-1))).any():
            return True
    return False


def _cdf_products(link: BoxPartition, mixture: GaussianMixture) -> torch.Tensor:
    """``(U, M, K)`` products of per-dimension normal CDF differences over each box's sides.

    Exact for a box bounding one dimension, or several that the component does not
    correlate; an unbounded side contributes exactly 1. A side above the mean is read in
    the upper tail (``Phi(-a) - Phi(-b)``), so a far box keeps its relative precision.
    """
    mean = mixture.means[:, :, None, :]  # (U, M, 1, d)
    sd = torch.diagonal(mixture.covs, dim1=-2, dim2=-1).sqrt()[:, :, None, :]
    low, high = (link.low - mean) / sd, (link.high - mean) / sd  # (U, M, K, d)
    upper = low > 0
    per_side = torch.where(
        upper,
        torch.special.ndtr(-low) - torch.special.ndtr(-high),
        torch.special.ndtr(high) - torch.special.ndtr(low),
    )
    per_side = torch.where(_bounded(link), per_side, 1.0)
    return per_side.prod(-1)


def _rectangles(
    mixture: GaussianMixture, low: torch.Tensor, high: torch.Tensor, i: int, j: int, nodes: int
) -> torch.Tensor:
    """``(U, M, K)``: boxes ``[low, high)`` ``(K, 2)`` in dimensions ``(i, j)``, correlated.

    With ``z`` and ``v`` the two dimensions standardised and ``rho`` their correlation,
    ``P = integral over z in [a1, b1] of phi(z) g(z) dz``, ``g(z) = P(a2 <= v < b2 | z)``
    with ``v | z ~ N(rho z, 1 - rho^2)``, the range cut to ``|z| <= Z_CUT``. ``phi`` is
    smooth on the scale 1, so the range is split at ``PHI_CUTS``; ``g`` steps (over a
    width ``w = sqrt(1 - rho^2) / |rho|``) where ``rho z`` crosses ``a2`` or ``b2``, so
    it is split there and at ``w``, ``2 w``, ... ``16 w`` either side, beyond which ``g``
    is within ``Phi(-16) < 1e-57`` of constant. Each piece gets ``nodes`` Gauss-Legendre
    nodes. Entries of uncorrelated components are meaningless (the caller discards them).
    """
    mu1, mu2 = mixture.means[..., i, None], mixture.means[..., j, None]  # (U, M, 1)
    s1 = mixture.covs[..., i, i, None].sqrt()
    s2 = mixture.covs[..., j, j, None].sqrt()
    rho = (mixture.covs[..., i, j, None] / (s1 * s2)).clamp(-1.0, 1.0)
    rho = torch.where(rho == 0, 1.0, rho)  # uncorrelated entries: any finite value
    a1 = ((low[:, 0] - mu1) / s1).clamp(-Z_CUT, Z_CUT)  # (U, M, K)
    b1 = ((high[:, 0] - mu1) / s1).clamp(-Z_CUT, Z_CUT)
    a2, b2 = (low[:, 1] - mu2) / s2, (high[:, 1] - mu2) / s2
    spread = ((1 - rho) * (1 + rho)).sqrt().clamp_min(1e-300)  # sd of v given z
    width = (spread / rho.abs())[..., None, None]
    steps = torch.tensor(STEP_CUTS, dtype=torch.float64)
    cross = torch.stack([a2 / rho, b2 / rho], -1)[..., None]  # (U, M, K, 2, 1), maybe inf
    cuts = (cross + width * steps).flatten(-2)
    fixed = torch.tensor(PHI_CUTS, dtype=torch.float64).expand(*a1.shape, -1)
    cuts = torch.cat([cuts.nan_to_num(0.0), fixed], -1)
    cuts = torch.minimum(torch.maximum(cuts, a1[..., None]), b1[..., None])
    edges = torch.cat([a1[..., None], cuts, b1[..., None]], -1).sort(-1).values
    x, w = np.polynomial.legendre.leggauss(nodes)
    x, w = torch.as_tensor(x), torch.as_tensor(w)
    start, length = edges[..., :-1, None], (edges[..., 1:] - edges[..., :-1])[..., None]
    z = start + length * (x + 1) / 2  # (U, M, K, P, nodes)
    mean = rho[..., None, None] * z
    spread = spread[..., None, None]
    lo = (a2[..., None, None] - mean) / spread
    hi = (b2[..., None, None] - mean) / spread
    inner = torch.where(
        lo > 0,
        torch.special.ndtr(-lo) - torch.special.ndtr(-hi),
        torch.special.ndtr(hi) - torch.special.ndtr(lo),
    )
    density = torch.exp(-0.5 * z * z) / math.sqrt(2 * math.pi)
    return (density * inner * w * length / 2).sum((-1, -2))


def _normalised(per_box: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(U, M, K)`` box probabilities and ``(U, M)`` none, each component's summing to 1.

    The boxes are disjoint, so a component's box probabilities sum to at most 1 and
    *none* is the rest; a sum above 1 by more than ``ROUNDING`` is an error in a route
    (asserted), below it rounding, removed by normalising in log space.
    """
    total = per_box.sum(-1)
    excess = (total - 1).max().item() if total.numel() else 0.0
    assert excess <= ROUNDING, f"box probabilities sum to 1 + {excess:.3g} in a component"
    assert (per_box >= 0).all(), "a negative box probability"
    none = (1 - total).clamp_min(0.0)
    log = torch.cat([per_box, none[..., None]], -1).log()
    log = log - log.logsumexp(-1, keepdim=True)
    return log[..., :-1].exp(), log[..., -1].exp()


# --- Monte Carlo -------------------------------------------------------------------------


def _monte_carlo(link, mixture: GaussianMixture, samples: int, seed: int) -> LinkProbabilities:
    """Seeded draws from each row's mixture, read through the link."""
    if not isinstance(samples, int) or samples < 1:
        raise ValueError(f"samples: {samples!r}; expected a positive integer")
    generator = torch.Generator().manual_seed(seed)
    n_rows, _, d = mixture.means.shape
    component = torch.multinomial(mixture.weights, samples, replacement=True, generator=generator)
    rows = torch.arange(n_rows)[:, None]
    scale = torch.linalg.cholesky(mixture.covs)[rows, component]  # (U, N, d, d)
    noise = torch.randn(n_rows, samples, d, 1, generator=generator, dtype=torch.float64)
    points = mixture.means[rows, component] + (scale @ noise)[..., 0]
    index = torch.stack([link.label_index(row) for row in points])  # (U, N), row by row
    counts = torch.nn.functional.one_hot(index, len(link.actions) + 1).sum(1)
    freq = counts.double() / samples
    probs, none = freq[:, :-1], freq[:, -1]
    stderr = (probs * (1 - probs) / samples).sqrt()
    return LinkProbabilities(probs, none, link.actions, stderr, "monte carlo")


# --- checks ------------------------------------------------------------------------------


def _item(label):
    """A numpy scalar label as the Python value the link's actions hold."""
    return label.item() if isinstance(label, np.generic) else label


def _check_mixture(mixture: GaussianMixture, dim: int) -> None:
    means = mixture.means
    if means.ndim != 3 or means.shape[-1] != dim:
        raise ValueError(
            f"mixture: means {tuple(means.shape)}; expected (U, M, {dim}) for a link over "
            f"{dim} dimensions"
        )
    if mixture.covs.shape != (*means.shape, dim) or mixture.weights.shape != means.shape[:2]:
        raise ValueError(
            f"mixture: weights {tuple(mixture.weights.shape)}, covs "
            f"{tuple(mixture.covs.shape)}; expected {tuple(means.shape[:2])} and "
            f"{(*means.shape, dim)}"
        )


def _check_columns(link: LinkProbabilities, n_actions: int, name: str) -> None:
    if link.probs.shape[-1] != n_actions:
        raise ValueError(
            f"{name}: {link.probs.shape[-1]} lower actions; the lower transitions have "
            f"{n_actions} (their axis 1)"
        )


def _sequence(links: Sequence, n_states: int) -> Callable[[int], LinkProbabilities | None]:
    if len(links) != n_states:
        raise ValueError(
            f"link: {len(links)} per-state links for {n_states} states; expected one per "
            "state (None where no action is offered)"
        )
    return links.__getitem__
