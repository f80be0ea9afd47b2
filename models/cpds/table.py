"""A discrete child of discrete parents: a table of probabilities.

``probs[P..., k]`` is the probability of state ``k`` given the parents' states; the
maximum-likelihood table is the normalised counts. Pseudo-count policy (``alpha``): a
row is ``(counts + alpha) / (n + K alpha)``, so a configuration no row reached is
uniform. Pseudo-counts per cell (a Dirichlet prior per row, ``alpha`` ``(P..., K)``)
give the posterior mean ``(counts + alpha) / (n + sum_k alpha)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import pyro.distributions as dist
import torch
from effect_networks.models.cpds.base import CPD
from effect_networks.models.dtype import DTYPE
from pyro.ops.indexing import Vindex
from torch.utils.weak import WeakIdKeyDictionary

if TYPE_CHECKING:
    from effect_networks.models.evidence import Evidence


@dataclass(frozen=True)
class TableParams:
    """Categorical child of discrete parents: ``probs`` ``(P..., K)``, ``n`` ``(P...)``."""

    probs: torch.Tensor
    n: torch.Tensor


@dataclass(frozen=True)
class Counts:
    """A table's counts, ``(P..., K)`` float64.

    Row counts are whole numbers, exact in any order of addition below 2**53 rows;
    expectation-maximisation stores fractional counts (responsibilities) in the same
    type. Float from the start: converting a large integer table to probabilities costs
    more than counting it.
    """

    counts: torch.Tensor

    def __add__(self, other: Counts) -> Counts:
        return Counts(self.counts + other.counts)

    def add_(self, other: Counts) -> None:
        """Add ``other``'s counts to these, in place."""
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
    params_type = TableParams
    discrete = True
    tabular = True

    @classmethod
    def refuses(cls, discrete: bool, width: int) -> str | None:
        """A table has no continuous parents (:meth:`~models.CPD.refuses`)."""
        if width:
            return "a table has no continuous parents (use 'softmax')"
        return super().refuses(discrete, width)

    def shapes(self) -> dict[str, tuple[int, ...]]:
        """The shape of every tensor of a :class:`TableParams` (:meth:`~models.CPD.shapes`)."""
        return {"probs": (*self.card, self.size), "n": self.card}

    def pin(self, probs: torch.Tensor) -> torch.Tensor:
        """``probs`` with the pinned configurations on state 0."""
        if self.pinned is None:
            return probs
        fixed = torch.zeros(self.size, dtype=probs.dtype)
        fixed[0] = 1.0
        return torch.where(self.pinned[..., None], fixed, probs)

    def pin_logs(self, logs: torch.Tensor) -> torch.Tensor:
        """``logs`` with the pinned configurations exactly on state 0.

        Log-probability 0 there and ``-inf`` elsewhere. (A zero probability's log is otherwise
        clamped to ``log(eps)``, about -36, which would let a pinned configuration's other states
        into every sum over them.)
        """
        if self.pinned is None:
            return logs
        fixed = torch.full((self.size,), -torch.inf, dtype=logs.dtype)
        fixed[0] = 0.0
        return torch.where(self.pinned[..., None], fixed, logs)

    def n_free(self, reachable: torch.Tensor | None = None) -> int:
        """``K - 1`` per parent configuration; a pinned configuration has none."""
        configs = self.configurations(reachable)
        if self.pinned is not None:
            configs = configs & ~self.pinned
        return int(configs.sum()) * (self.size - 1)

    def initialize(
        self, generator: torch.Generator | None = None, unseen: float = 0.0
    ) -> TableParams:
        """Uniform tables, or random ones (:meth:`~models.CPD.initialize`)."""
        shape = self.shapes()["probs"]
        if generator is None:
            probs = torch.full(shape, 1.0 / self.size, dtype=DTYPE)
            return TableParams(self.pin(probs), torch.zeros(self.card, dtype=DTYPE))
        n = self.counts_reached(generator, unseen)
        return TableParams(self.pin((2 * self.noise(generator, shape)).softmax(-1)), n)

    def log_table(self, params: TableParams, cache: dict | None) -> torch.Tensor:
        """Log-probabilities of the table, taken once per model call (``cache``).

        A Categorical built from probabilities takes their log lazily over its whole
        batch: for a table gathered at enumerated parents that is the enumerated
        tensor, far larger than the table. The values are those ``Categorical(probs)``
        computes (normalised, clamped to ``[eps, 1 - eps]``, then log), so a zero
        probability stays finite, except in pinned configurations (:meth:`pin_logs`):
        their other states are impossible, ``-inf``. A table that is not being fitted by gradient keeps its
        logs (until its ``probs`` change in place), so repeated queries take them once.
        """
        if cache is not None and self.site in cache:
            return cache[self.site]
        probs = params.probs
        kept = params.__dict__.get("_logs")  # fitted tables: once per TableParams, not per call
        if kept is not None and kept[0] is probs and kept[1] == probs._version:
            logs = kept[2]
        else:
            logs = self.pin_logs(_logits(probs))
            if not probs.requires_grad:
                object.__setattr__(params, "_logs", (probs, probs._version, logs))
        if cache is not None:
            cache[self.site] = logs
        return logs

    def distribution(self, params: TableParams, index, x, cache) -> dist.TorchDistribution:
        """The site's categorical given its parents (:meth:`~models.CPD.distribution`)."""
        logs = self.log_table(params, cache)
        if not index:
            return dist.Categorical(logits=logs)
        return GatheredCategorical(logs, tuple(index))

    def statistics(self, index: torch.Tensor, x, y: torch.Tensor, weights=None) -> Counts:
        """Counts of the site's states per parent configuration (:meth:`~models.CPD.statistics`)."""
        return counts(index, y, self.card, self.size, weights)

    def m_step(
        self, stats: Counts, alpha: float | torch.Tensor, min_variance: float
    ) -> TableParams:
        """Normalised counts, pinned configurations kept on state 0 (:meth:`~models.CPD.m_step`).

        ``alpha``: one symmetric pseudo-count or Dirichlet pseudo-counts ``(P..., K)``
        (:func:`normalised`); the table is their posterior mean.
        """
        table = normalised(stats.counts, alpha)
        return TableParams(self.pin(table.probs), table.n) if self.pinned is not None else table

    def free(self, params: TableParams) -> dict[str, torch.Tensor]:
        """The tables' log-probabilities (:meth:`~models.CPD.free`)."""
        return {"logits": params.probs.clamp_min(1e-12).log()}

    def bound(self, free: dict[str, torch.Tensor], params: TableParams) -> TableParams:
        """The tables ``free`` stands for, its softmax (:meth:`~models.CPD.bound`)."""
        return TableParams(self.pin(free["logits"].softmax(-1)), params.n)


def _logits(probs: torch.Tensor) -> torch.Tensor:
    """``probs_to_logits`` of the normalised ``probs`` in one new tensor.

    ``probs`` clamped to ``[eps, 1 - eps]``, then log: the same values, without a temporary per step
    (a large table's log is taken once per fit).
    """
    eps = torch.finfo(probs.dtype).eps
    logs = probs / probs.sum(-1, keepdim=True)
    return logs.clamp_(min=eps, max=1 - eps).log_()


class GatheredCategorical(dist.TorchDistribution):
    """``Categorical(logits=logs[index...])``, gathered lazily.

    A table gathered at enumerated parents is the enumerated tensor times the child's
    states (for an observed child with 42 states under 90,090 parent configurations and
    30 rows: 113 million values), of which ``log_prob`` keeps one per configuration.
    This distribution gathers ``logs[(*index, value)]`` in one step instead; only
    ``sample`` (forward draws) gathers the whole rows. ``logs`` ``(P..., K)`` must be
    normalised log-probabilities (:meth:`TableCPD.log_table`); ``index`` one integer
    tensor per parent, broadcasting to the batch shape.
    """

    arg_constraints: dict = {}
    has_enumerate_support = True

    def __init__(self, logs: torch.Tensor, index: tuple, batch_shape=None, validate_args=None):
        self.logs, self.index = logs, index
        if batch_shape is None:
            batch_shape = broadcast_shapes(*(i.shape for i in index))
        super().__init__(torch.Size(batch_shape), torch.Size(), validate_args=False)

    @property
    def support(self):
        """The states ``0`` to ``K - 1``."""
        return dist.constraints.integer_interval(0, self.logs.shape[-1] - 1)

    @property
    def logits(self) -> torch.Tensor:
        """``(..., K)``: each row's log-probabilities, gathered."""
        rows = Vindex(self.logs)[(*self.index, slice(None))]
        return rows.expand(*self.batch_shape, rows.shape[-1])

    @property
    def probs(self) -> torch.Tensor:
        """``(..., K)``: each row's probabilities, gathered."""
        return self.logits.exp()

    def expand(self, batch_shape, _instance=None):
        """The same tables, gathered for ``batch_shape``."""
        return GatheredCategorical(self.logs, self.index, batch_shape)

    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        """Each row's log-probability of its state ``value``, gathered for that state only."""
        value = value.long()
        k = self.logs.shape[-1]
        if value.numel() and (int(value.min()) < 0 or int(value.max()) >= k):
            raise ValueError(f"a state index outside 0..{k - 1}: {value.unique().tolist()}")
        index = (*self.index, value)
        lp = gather(self.logs, index)
        return lp.expand(broadcast_shapes(lp.shape, self.batch_shape))

    def sample(self, sample_shape: tuple[int, ...] = ()) -> torch.Tensor:
        """Forward draws of ``sample_shape`` from the gathered rows."""
        return dist.Categorical(logits=self.logits).sample(torch.Size(sample_shape))

    def enumerate_support(self, expand: bool = True) -> torch.Tensor:
        """Every state, shaped to broadcast over the batch (expanded to it if ``expand``)."""
        k = self.logs.shape[-1]
        values = torch.arange(k).reshape((k,) + (1,) * len(self.batch_shape))
        return values.expand((k, *self.batch_shape)) if expand else values


def broadcast_shapes(*shapes: tuple[int, ...]) -> torch.Size:
    """``torch.broadcast_shapes`` of concrete shapes, in plain Python.

    torch's own checks symbolic sizes too and costs tens of microseconds, paid per site of every
    trace.
    """
    out = [1] * max((len(s) for s in shapes), default=0)
    for shape in shapes:
        for i, k in enumerate(shape, len(out) - len(shape)):
            if k != 1:
                if out[i] not in (1, k):
                    raise RuntimeError(f"shapes {list(shapes)} do not broadcast")
                out[i] = k
    return torch.Size(out)


def gather(table: torch.Tensor, index: tuple[torch.Tensor, ...]) -> torch.Tensor:
    """``Vindex(table)[index]``: one integer index per axis of ``table``, broadcast.

    Under enumeration most indices are either a whole axis (an enumerated site's values
    ``arange(K)`` on its own dim) or one value per row (shape ``(n,)``). Then the
    answer is a strided view of ``table`` with the row-indexed axes selected in one
    ``index_select`` (a copy of the answer's size, no broadcast index arithmetic);
    any other index goes through :class:`pyro.ops.indexing.Vindex`.
    """
    shape = broadcast_shapes(*(i.shape for i in index))
    whole: dict[int, int] = {}  # axis -> its (negative) dim in the answer
    rows: list[int] = []
    for axis, i in enumerate(index):
        size = table.shape[axis]
        big = [d - i.dim() for d, k in enumerate(i.shape) if k != 1]
        if (
            i.dim() == 1
            and len(shape) >= 1
            and i.shape[0] == shape[-1]
            and (i.shape[0] != size or len(big) != 1 or not _is_range(i))
        ):
            rows.append(axis)
        elif len(big) == 1 and i.shape[big[0]] == size and big[0] != -1 and _is_range(i):
            whole[axis] = big[0]
        elif i.numel() == 1 and size == 1:
            continue  # a single state: the axis has size 1
        else:
            return Vindex(table)[index]
    if len(set(whole.values())) != len(whole):
        return Vindex(table)[index]
    # the other axes in the answer's order (outer enumeration dims first), so that the
    # answer is laid out as the enumerated tensors it is added to
    kept = sorted((a for a in range(table.dim()) if a not in rows), key=lambda a: whole.get(a, 0))
    if not rows:
        moved = table.permute(kept)
    else:
        n = shape[-1]
        row = torch.zeros(n, dtype=torch.long)
        for axis in rows:
            row = row * table.shape[axis] + index[axis]
        # rows first: each row's values are one contiguous block, copied whole (the
        # answer's rows are its outermost stride; the enumeration dims keep their order)
        picked = _rows_first(table, tuple(rows), tuple(kept)).index_select(0, row)
        moved = picked.reshape(n, *(table.shape[a] for a in kept))
    offset = 1 if rows else 0
    strides = [0] * len(shape)
    for position, axis in enumerate(kept):
        if axis in whole:
            strides[len(shape) + whole[axis]] = moved.stride(position + offset)
    if rows:
        strides[-1] = moved.stride(0)
    return moved.as_strided(shape, strides, moved.storage_offset())


_ROWS_FIRST: WeakIdKeyDictionary = WeakIdKeyDictionary()


def _rows_first(table: torch.Tensor, rows: tuple[int, ...], kept: tuple[int, ...]) -> torch.Tensor:
    """``table`` as ``(prod(rows), rest)``, contiguous.

    The axes ``rows`` first, merged, and the axes ``kept`` flattened behind them. Kept per table (a
    cached log table is gathered this way on every query of one evidence pattern).
    """
    per_table = _ROWS_FIRST.setdefault(table, {})
    key = (rows, kept)
    if table.requires_grad or key not in per_table:
        size = math.prod(table.shape[a] for a in rows)
        moved = table.permute(*rows, *kept).reshape(size, -1).contiguous()
        if table.requires_grad:
            return moved
        per_table[key] = moved
    return per_table[key]


def _is_range(i: torch.Tensor) -> bool:
    flat = i.reshape(-1)
    if flat.shape[0] <= 64:  # an enumerated site's states: Python's compare is cheaper
        return flat.tolist() == list(range(flat.shape[0]))
    return bool((flat == torch.arange(flat.shape[0])).all())


def flat_index(enc: Evidence, sites: tuple[str, ...], card: tuple[int, ...]) -> torch.Tensor:
    """``(n,)`` row-major index of the rows' configuration of ``sites``."""
    if not sites:
        return torch.zeros(enc.n_rows, dtype=torch.long)
    index = enc[sites[0]]
    for s, k in zip(sites[1:], card[1:], strict=True):
        index = index * k + enc[s]
    return index


def counts(
    index: torch.Tensor,
    child: torch.Tensor,
    card: tuple[int, ...],
    k: int,
    weights: torch.Tensor | None = None,
) -> Counts:
    """Counts of ``child`` states per flattened parent configuration ``index``.

    Each row counts its weight, default 1.
    """
    size = math.prod(card)
    flat = child if not card else torch.add(child, index, alpha=k)  # no parents: index 0
    if weights is None:  # ones: the counts come out as float64
        weights = torch.ones(flat.shape[0], dtype=DTYPE)
    found = torch.bincount(flat, weights=weights.to(DTYPE), minlength=size * k).to(DTYPE)
    return Counts(found.reshape(*card, k))


def normalised(counts: torch.Tensor, alpha: float | torch.Tensor) -> TableParams:
    """The posterior-mean table of ``counts`` under the Dirichlet pseudo-counts ``alpha``.

    ``(counts + alpha) / (n + sum_k alpha)`` per row (a new tensor; ``counts`` is kept).
    ``alpha`` is one symmetric pseudo-count (the pseudo-count policy: a row no sample
    reached is uniform) or a tensor of pseudo-counts broadcasting to ``counts``' shape
    ``(P..., K)`` (a row no sample reached is the prior's mean ``alpha / sum alpha``, or
    uniform where its pseudo-counts are all 0).
    """
    counts = counts.to(DTYPE)  # no copy for float64 counts
    k = counts.shape[-1]
    n = counts.sum(-1)
    if not isinstance(alpha, torch.Tensor):
        probs = (counts + alpha).div_((n + k * alpha).clamp_min(1e-300)[..., None])
        unseen = n == 0
        if bool(unseen.any()):
            probs[unseen] = 1.0 / k
        return TableParams(probs, n)
    shifted = counts + alpha.to(DTYPE)
    total = shifted.sum(-1)
    probs = shifted.div_(total.clamp_min(1e-300)[..., None])
    empty = total == 0
    if bool(empty.any()):
        probs[empty] = 1.0 / k
    return TableParams(probs, n)
