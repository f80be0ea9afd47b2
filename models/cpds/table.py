"""A discrete child of discrete parents: a table of probabilities.

``probs[P..., k]`` is the probability of state ``k`` given the parents' states; the
maximum-likelihood table is the normalised counts. Pseudo-count policy (``alpha``): a
row is ``(counts + alpha) / (n + K alpha)``, so a configuration no row reached is
uniform.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import pyro.distributions as dist
import torch
from pyro.ops.indexing import Vindex
from torch.distributions.utils import probs_to_logits

from models.cpds.base import CPD
from models.evidence import DTYPE


@dataclass(frozen=True)
class Table:
    """Categorical child of discrete parents: ``probs`` ``(P..., K)``, ``n`` ``(P...)``."""

    probs: torch.Tensor
    n: torch.Tensor


@dataclass(frozen=True)
class Counts:
    """A table's counts, ``(P..., K)`` int64 (exact in any order of addition)."""

    counts: torch.Tensor

    def __add__(self, other: Counts) -> Counts:
        return Counts(self.counts + other.counts)

    def add_(self, other: Counts) -> None:
        self.counts.add_(other.counts)


@dataclass(frozen=True)
class TableCPD(CPD):
    """A table over the discrete parents.

    ``pinned`` ``(P...)`` bool, or ``None``: configurations whose row is fixed on state
    0 by the structure, not fitted (the cluster of an action that does not use its
    parameter).
    """

    pinned: torch.Tensor | None = field(default=None, compare=False, repr=False)

    name = "table"
    params_type = Table
    discrete = True
    tabular = True

    @classmethod
    def refuses(cls, discrete: bool, width: int) -> str | None:
        if width:
            return "a table has no continuous parents (use 'softmax')"
        return super().refuses(discrete, width)

    def shapes(self) -> dict[str, tuple[int, ...]]:
        return {"probs": (*self.card, self.size), "n": self.card}

    def pin(self, probs: torch.Tensor) -> torch.Tensor:
        """``probs`` with the pinned configurations on state 0."""
        if self.pinned is None:
            return probs
        fixed = torch.zeros(self.size, dtype=probs.dtype)
        fixed[0] = 1.0
        return torch.where(self.pinned[..., None], fixed, probs)

    def initialize(self, generator: torch.Generator | None = None, unseen: float = 0.0) -> Table:
        shape = self.shapes()["probs"]
        if generator is None:
            probs = torch.full(shape, 1.0 / self.size, dtype=DTYPE)
            return Table(self.pin(probs), torch.zeros(self.card, dtype=DTYPE))
        n = self.counts_reached(generator, unseen)
        return Table(self.pin((2 * self.noise(generator, shape)).softmax(-1)), n)

    def log_table(self, params: Table, cache: dict | None) -> torch.Tensor:
        """Log-probabilities of the table, taken once per model call (``cache``).

        A Categorical built from probabilities takes their log lazily over its whole
        batch: for a table gathered at enumerated parents that is the enumerated
        tensor, far larger than the table. The values are those ``Categorical(probs)``
        computes (normalised, clamped to ``[eps, 1 - eps]``, then log), so a zero
        probability stays finite.
        """
        if cache is not None and self.site in cache:
            return cache[self.site]
        probs = params.probs
        logs = probs_to_logits(probs / probs.sum(-1, keepdim=True))
        if cache is not None:
            cache[self.site] = logs
        return logs

    def distribution(self, params: Table, index, x, cache) -> dist.Categorical:
        logs = self.log_table(params, cache)
        if not index:
            return dist.Categorical(logits=logs)
        return dist.Categorical(logits=Vindex(logs)[(*index, slice(None))])

    def statistics(self, index: torch.Tensor, x, y: torch.Tensor) -> Counts:
        return counts(index, y, self.card, self.size)

    def m_step(self, stats: Counts, alpha: float, min_variance: float) -> Table:
        table = normalised(stats.counts, alpha)
        return Table(self.pin(table.probs), table.n) if self.pinned is not None else table

    def free(self, params: Table) -> dict[str, torch.Tensor]:
        return {"logits": params.probs.clamp_min(1e-12).log()}

    def bound(self, free: dict[str, torch.Tensor], params: Table) -> Table:
        return Table(self.pin(free["logits"].softmax(-1)), params.n)


def counts(index: torch.Tensor, child: torch.Tensor, card: tuple[int, ...], k: int) -> Counts:
    """Counts of ``child`` states per flattened parent configuration ``index``."""
    size = math.prod(card)
    flat = child if not card else index * k + child  # no parents: the index is all zeros
    return Counts(torch.bincount(flat, minlength=size * k).reshape(*card, k))


def normalised(counts: torch.Tensor, alpha: float) -> Table:
    """The pseudo-count policy's table of ``counts``."""
    probs = counts.to(DTYPE, copy=True)  # a new tensor: the arithmetic below runs in place
    k = probs.shape[-1]
    n = probs.sum(-1)
    probs.add_(alpha).div_((n + k * alpha).clamp_min(1e-300)[..., None])
    unseen = n == 0
    if bool(unseen.any()):
        probs[unseen] = 1.0 / k
    return Table(probs, n)
