"""How much probability the model gives a row's observed end state: the ``implausible`` flag.

Two numbers per evidence row, each 1 where the row observes no end feature of its kind:

* ``discrete`` -- the probability of the observed *discrete* end features given the rest
  of the evidence (initial state, and the action and parameters where given), every
  latent site summed out under the model: ``p(end_d | initial, ...)``. A locked door
  that ends open, when no action ever opens a locked door, gets only the pseudo-count
  mass (about ``α / n`` per configuration).
* ``tail`` -- for the observed *continuous* end features, the chi-square tail
  probability ``P(χ²_d > D²)`` of their squared Mahalanobis distance ``D²`` to the
  closest Gaussian component the evidence leaves possible (every configuration of the
  latent discrete sites with non-zero weight, the observed discrete ones included), with
  ``d`` the summed dimensions. Under its own component an observation has
  ``D² ~ χ²_d``, so ``tail`` is the probability that a draw from the model's best
  component lies at least this far out.

A row is *implausible* when either number is below a threshold (default
:data:`IMPLAUSIBLE_BELOW`). The flag warns: queries still answer such rows.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from inference.enumeration import enumerate_model, enumeration_size, row_chunks
from models.declaration import DTYPE, EffectNetwork, end_site
from models.evidence import Evidence
from models.params import NetworkParams

IMPLAUSIBLE_BELOW = 1e-4
"""Default threshold: evidence the model gives less than 1 in 10,000 is flagged (a
continuous observation beyond about 3.9 standard deviations in one dimension)."""


@dataclass(frozen=True)
class Plausibility:
    """``discrete`` ``(n,)``: p(observed discrete end state | the rest of the evidence);
    ``tail`` ``(n,)``: chi-square tail probability of the observed continuous end state
    under its closest possible component. Both 1 where nothing of the kind is observed."""

    discrete: torch.Tensor
    tail: torch.Tensor

    def implausible(self, below: float = IMPLAUSIBLE_BELOW) -> torch.Tensor:
        """``(n,)`` bool: either probability below ``below``."""
        return (self.discrete < below) | (self.tail < below)


def check_threshold(below: float) -> float:
    """``below`` validated: a probability strictly between 0 and 1."""
    if not isinstance(below, (int, float)) or not 0 < below < 1:
        raise ValueError(
            f"implausible_below must be a probability in (0, 1), got {below!r} "
            f"(default {IMPLAUSIBLE_BELOW})"
        )
    return float(below)


def plausibility(
    net: EffectNetwork,
    params: NetworkParams,
    evidence: Evidence,
    *,
    log_evidence: torch.Tensor | None = None,
    log_prior: torch.Tensor | None = None,
) -> Plausibility:
    """The two plausibility numbers of every row of encoded ``evidence`` (at least one row).

    A query that has already summed the model may pass ``log_evidence`` ``(n,)``
    (log p(evidence)) and ``log_prior`` (log p(evidence without its end sites)) to save
    the sums; ``log_evidence`` is used only where no continuous end site is observed.
    """
    ends = [end_site(f.name) for f in net.features if end_site(f.name) in evidence]
    discrete = [s for s in ends if net.site(s).discrete]
    continuous = [s for s in ends if not net.site(s).discrete]
    ones = torch.ones(evidence.n_rows, dtype=DTYPE)
    p_discrete = ones
    if discrete:
        if log_evidence is None or continuous:
            given = evidence.without(*continuous)
            log_evidence = _over_rows(net, params, given, lambda e, _: e.log_evidence)
        if log_prior is None:
            prior = evidence.without(*ends)
            log_prior = _over_rows(net, params, prior, lambda e, _: e.log_evidence)
        p_discrete = (log_evidence - log_prior).exp().clamp(0, 1)
    tail = ones
    if continuous:
        d2, dof = _closest_distance(net, params, evidence, continuous)
        tail = torch.special.gammaincc(torch.tensor(dof / 2, dtype=DTYPE), d2 / 2)
    return Plausibility(p_discrete, tail)


def _closest_distance(net, params, evidence, sites) -> tuple[torch.Tensor, int]:
    """``(n,)`` smallest squared Mahalanobis distance over possible configurations, and
    the summed dimension of ``sites``."""
    dof = sum(net.site(s).size for s in sites)

    def fn(e, _):
        d2 = torch.zeros((), dtype=DTYPE)
        for s in sites:
            node = e.trace.nodes[s]
            d2 = d2 + _mahalanobis(node["fn"], node["value"])
        w = e.log_weight
        d2 = torch.where(torch.isfinite(w), d2.expand_as(w), torch.inf)
        return d2.reshape(-1, w.shape[-1]).min(0).values

    return _over_rows(net, params, evidence, fn), dof


def _mahalanobis(fn, value: torch.Tensor) -> torch.Tensor:
    """Squared Mahalanobis distance of ``value`` under the Gaussian ``fn``, batch-shaped."""
    diff = value - fn.loc
    tril = fn.scale_tril
    shape = torch.broadcast_shapes(diff.shape[:-1], tril.shape[:-2])
    z = torch.linalg.solve_triangular(
        tril.expand(*shape, *tril.shape[-2:]),
        diff.expand(*shape, diff.shape[-1])[..., None],
        upper=False,
    )
    return z.squeeze(-1).square().sum(-1)


def _over_rows(net, params, evidence: Evidence, fn) -> torch.Tensor:
    """``fn(enumerated, chunk)`` over row chunks, concatenated."""
    size = enumeration_size(net, evidence)
    return torch.cat(
        [
            fn(enumerate_model(net, params, evidence.rows(s)), evidence.rows(s))
            for s in row_chunks(evidence.n_rows, size)
        ],
        0,
    )
