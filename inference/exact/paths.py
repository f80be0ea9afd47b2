"""Sums and maxima over the steps of a chain whose step tables are shared by many rows.

A batch of ``n`` rows walks a chain whose step ``t`` reads, for row ``i``, one of ``K``
log tables, ``key[i]``: the sums :func:`log_matvec` takes,
``out[i, m] = logsumexp_j(left[i, j] + tables[key[i], j, m])``, are the forward and
backward passes of forward-backward (and, over pairs of states, the posterior of what
links them); :func:`max_matvec` is the same with ``max``, Viterbi's step.

The sums run as matrix products of exponentials, each side scaled by its own largest
value (the row's, the table's): a few small products per distinct table instead of an
``(n, J, M)`` log-sum-exp per step. Where a kept entry of the product comes out below
:data:`TINY` (an underflow the scaling could not prevent: a row whose mass sits where
its table is far below the table's largest entry), that row is summed again exactly, in
log space.
"""

from __future__ import annotations

from functools import cached_property

import torch

#: A product entry below this (after scaling) is summed again in log space.
TINY = 1e-280
#: A row's sum below this (after scaling), where only the sum must keep its precision.
TINY_TOTAL = 1e-200
#: Tables up to this many: products per distinct table; more: one batched product.
GROUPED_KEYS = 64


class LogTables:
    """``K`` log tables ``(K, J, M)``, with their exponentials scaled per table."""

    def __init__(self, log: torch.Tensor):
        self.log = log

    @cached_property
    def scale(self) -> torch.Tensor:
        """``(K,)`` each table's largest finite entry (0 for a table without any)."""
        top = self.log.amax((1, 2))
        return torch.where(torch.isfinite(top), top, 0.0)

    @cached_property
    def exp(self) -> torch.Tensor:
        """``(K, J, M)`` ``exp(log - scale)``."""
        return (self.log - self.scale[:, None, None]).exp()


def log_matvec(
    left: torch.Tensor,
    tables: LogTables,
    key: torch.Tensor,
    where: torch.Tensor | None = None,
    *,
    total: bool = False,
) -> torch.Tensor:
    """``(n, M)`` ``logsumexp_j(left[i, j] + tables.log[key[i], j, m])``.

    ``left`` ``(n, J)`` log values (``-inf`` allowed); ``key`` ``(n,)`` table indices;
    ``where`` ``(n, M)`` bool, the entries that must keep their precision (default all):
    a row where one of them underflows is summed again in log space. ``total``: only
    the row's sum must, above ``TINY_TOTAL`` (a distribution over ``m`` normalised
    afterwards: an entry lost below ``TINY`` is below 1e-80 of it).
    """
    top = left.amax(-1, keepdim=True)
    top = torch.where(torch.isfinite(top), top, 0.0)
    product = _product((left - top).exp(), tables.exp, key)
    out = product.log() + top + tables.scale[key][:, None]
    if total:
        small = product.sum(-1, keepdim=True) < TINY_TOTAL
    else:
        small = product < TINY
        if where is not None:
            small &= where
    redo = small.any(-1).nonzero().squeeze(-1)
    if redo.numel():
        rows = left[redo][:, :, None] + tables.log[key[redo]]
        out[redo] = rows.logsumexp(1)
    return out


def max_matvec(
    left: torch.Tensor, tables: torch.Tensor, key: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(n, M)`` ``max_j(left[i, j] + tables[key[i], j, m])`` and its argmax ``j``."""
    return (left[:, :, None] + tables[key]).max(1)


def _product(left: torch.Tensor, tables: torch.Tensor, key: torch.Tensor) -> torch.Tensor:
    """``(n, M)`` ``left[i] @ tables[key[i]]``.

    One product per distinct table where they are few, one batched product of gathered tables
    otherwise.
    """
    present = key.unique()
    if len(present) == 1:
        return left @ tables[int(present[0])]
    if len(present) <= GROUPED_KEYS:
        out = left.new_empty(left.shape[0], tables.shape[-1])
        for k in present.tolist():
            rows = (key == k).nonzero().squeeze(-1)
            out[rows] = left[rows] @ tables[k]
        return out
    return torch.bmm(left[:, None, :], tables[key]).squeeze(1)
