"""Variable elimination over log-factors laid out as the enumerated model lays them out.

Every factor is a tensor broadcastable to ``(E_k, ..., E_1, n)``: one dim per enumerated
site (negative, left of the rows), of size 1 where the factor does not depend on the
site. Summing the sites out one at a time, each time adding only the factors that depend
on the site, is exact (the sum distributes over the factors that do not) and costs the
size of the largest such sum instead of the joint's. The order is chosen greedily, the
site whose sum is smallest first (min-size), and cached per structure.
"""

from __future__ import annotations

import math
from functools import lru_cache

import torch

#: Configurations per row up to which a joint is summed as one dense tensor: below it the
#: one vectorised pass costs less than the contraction's steps.
DENSE_CONFIGURATIONS = 1 << 12
#: ... while the dense joint of all the rows stays this small (elements): a batch of many
#: rows pays the joint's size per row in memory traffic, the contraction only its
#: intermediates' (a batch of 1,000 rows of 8 binary features: 3-4x faster contracted).
DENSE_ELEMENTS = 1 << 16
#: ... or up to this many times the contraction's largest intermediate (a structure that
#: elimination cannot split, as the default one where every end site has every parent).
DENSE_RATIO = 4


def scope(factor: torch.Tensor) -> frozenset[tuple[int, int]]:
    """The ``(dim, size)`` of each enumerated dim (left of the rows) the factor spans."""
    shape = factor.shape
    return frozenset((d - len(shape), k) for d, k in enumerate(shape[:-1]) if k > 1)


def dense_enough(factors: list[torch.Tensor]) -> bool:
    """Whether to sum the factors' joint as one dense tensor.

    It is, where the joint is small enough (per row, and over all the rows), or the
    contraction no cheaper.
    """
    scopes = tuple(scope(f) for f in factors)
    sizes = dict(s for sc in scopes for s in sc)
    joint = math.prod(sizes.values())
    rows = max((f.shape[-1] for f in factors if f.dim()), default=1)
    if joint <= DENSE_CONFIGURATIONS and joint * rows <= DENSE_ELEMENTS:
        return True
    return joint <= DENSE_RATIO * plan(scopes, frozenset(sizes))[1]


@lru_cache(maxsize=256)
def plan(
    scopes: tuple[frozenset[tuple[int, int]], ...], eliminate: frozenset[int]
) -> tuple[tuple[int, ...], int]:
    """A greedy elimination order of the dims ``eliminate`` for factors of these scopes.

    And the largest intermediate it builds (configurations per row).
    """
    live = [{d for d, _ in sc} for sc in scopes]
    sizes = {d: k for sc in scopes for d, k in sc}
    todo = set(eliminate) & set(sizes)
    order, largest = [], 1

    def cost(d: int, live: list[set[int]]) -> int:
        union = set().union(*(s for s in live if d in s))
        return math.prod(sizes[e] for e in union)

    while todo:
        d = min(sorted(todo), key=lambda d: cost(d, live))
        largest = max(largest, cost(d, live))
        union = set().union(*(s for s in live if d in s))
        live = [s for s in live if d not in s] + [union - {d}]
        todo.remove(d)
        order.append(d)
    return tuple(order), largest


def contract_size(scopes: tuple[frozenset[tuple[int, int]], ...]) -> int:
    """Configurations per row of the largest tensor that summing every dim builds.

    The joint's where it is summed dense.
    """
    sizes = dict(s for sc in scopes for s in sc)
    joint = math.prod(sizes.values())
    if joint <= DENSE_CONFIGURATIONS:
        return joint
    largest = plan(scopes, frozenset(sizes))[1]
    return joint if joint <= DENSE_RATIO * largest else largest


@lru_cache(maxsize=256)
def schedule(
    scopes: tuple[frozenset[tuple[int, int]], ...], eliminate: frozenset[int]
) -> tuple[tuple[tuple[int, tuple[int, ...]], ...], tuple[int, ...]]:
    """The steps of summing the dims ``eliminate`` out of factors of these scopes.

    In :func:`plan`'s order: per step the dim and the slots of the factors it sums (the factors are
    slots ``0 .. F-1``; each step's answer takes the next slot), and the slots left at the end.
    Cached per structure, so that a query repeats no planning.
    """
    order, _ = plan(scopes, eliminate)
    spans = {i: {d for d, _ in sc} for i, sc in enumerate(scopes)}
    steps = []
    for d in order:
        involved = tuple(i for i in sorted(spans) if d in spans[i])
        union = set().union(*(spans.pop(i) for i in involved))
        spans[len(scopes) + len(steps)] = union - {d}
        steps.append((d, involved))
    return tuple(steps), tuple(sorted(spans))


def _eliminate(factors, eliminate, reduce, scopes=None):
    """Sum (``reduce``) the dims ``eliminate`` out of the factors, one at a time.

    Returns the remaining factors and, per step, the dim and the summed tensor. ``scopes``: the
    factors' (:func:`scope` of each), where the caller knows them.
    """
    slots = list(factors)
    if scopes is None:
        scopes = tuple(scope(f) for f in slots)
    steps, left = schedule(scopes, frozenset(eliminate))
    done = []
    for d, involved in steps:
        out = reduce(_sum([slots[i] for i in involved]), d)
        done.append((d, out))
        slots.append(out[0] if isinstance(out, tuple) else out)
    return [slots[i] for i in left], done


def _logsumexp(t: torch.Tensor, d: int) -> torch.Tensor:
    return t.logsumexp(d, keepdim=True)


def _sum(factors: list[torch.Tensor]) -> torch.Tensor:
    total = factors[0]
    for f in factors[1:]:
        total = total + f
    return total


def contract(
    factors: list[torch.Tensor],
    eliminate: list[int],
    scopes: tuple[frozenset[tuple[int, int]], ...] | None = None,
) -> torch.Tensor:
    """``log sum exp`` over the dims ``eliminate`` of the factors' sum, by elimination.

    A tensor whose other dims keep their size and whose eliminated dims are 1. ``scopes``: each
    factor's :func:`scope`, where the caller has them.
    """
    if scopes is None:
        scopes = tuple(scope(f) for f in factors)
    steps, left = schedule(scopes, frozenset(eliminate))
    slots = dict(enumerate(factors))
    first = len(factors)
    pending: list[tuple[int, int, torch.Tensor]] = []  # (step, dim, summed factors)
    for n, (d, involved) in enumerate(steps):
        if pending and not all(i < first for i in involved):
            _flush(pending, slots, first)
        total = _sum([slots[i] for i in involved])
        if all(i < first for i in involved):  # a leaf: sums of leaves are batched
            if pending and _key(pending[0][2], pending[0][1]) != _key(total, d):
                _flush(pending, slots, first)
            pending.append((n, d, total))
        else:
            slots[first + n] = total.logsumexp(d, keepdim=True)
    _flush(pending, slots, first)
    return _sum([slots[i] for i in left])


def _key(total: torch.Tensor, d: int) -> tuple[tuple[int, ...], int]:
    """A leaf step's answer's shape and the size of the dim it sums."""
    shape = list(total.shape)
    shape[d] = 1
    return tuple(shape), total.shape[d]


def _flush(pending: list, slots: dict, first: int) -> None:
    """The pending leaf steps' sums, as one ``logsumexp`` over their stacked tensors.

    Each step's tensor with its summed dim moved last is laid out as its answer (every
    other dim it spans is kept, in order), so the steps stack; the answers are the same
    numbers a ``logsumexp`` per step gives.
    """
    if len(pending) == 1:
        n, d, total = pending[0]
        slots[first + n] = total.logsumexp(d, keepdim=True)
    elif pending:
        shape, size = _key(pending[0][2], pending[0][1])
        stacked = torch.stack([t.movedim(d, -1).reshape(*shape, size) for _, d, t in pending])
        summed = stacked.logsumexp(-1)
        for j, (n, _, _) in enumerate(pending):
            slots[first + n] = summed[j]
    pending.clear()


def maximum(factors: list[torch.Tensor], eliminate: list[int]) -> torch.Tensor:
    """The largest value over the dims ``eliminate`` of the factors' sum, by elimination.

    Max-product, laid out as :func:`contract`'s answer.
    """
    left, _ = _eliminate(factors, eliminate, lambda t, d: t.amax(d, keepdim=True))
    return _sum(left)


def sample(factors: list[torch.Tensor], eliminate: list[int], n: int) -> dict[int, torch.Tensor]:
    """One joint draw per row of the dims ``eliminate`` from ``exp(sum of the factors)``.

    The distribution is normalised per row: the dims summed out in order, then each drawn, last
    summed first, given those drawn before it (``{dim: (n,) index}``; torch's global generator).
    Every row must have a possible configuration.
    """
    left, steps = _eliminate(factors, eliminate, lambda t, d: (t.logsumexp(d, keepdim=True), t))
    drawn: dict[int, torch.Tensor] = {}
    for d, (_, total) in reversed(steps):
        logits = torch.stack(
            [value_at(total.narrow(d, j, 1), drawn, n) for j in range(total.shape[d])], -1
        )
        probs = (logits - logits.logsumexp(-1, keepdim=True)).exp()
        drawn[d] = torch.multinomial(probs, 1).squeeze(-1)
    return drawn


def max_config(
    factors: list[torch.Tensor], eliminate: list[int], n: int
) -> tuple[torch.Tensor, dict[int, torch.Tensor]]:
    """Per row, the largest value of the factors' sum and a configuration reaching it.

    Over the dims ``eliminate`` (every enumerated dim), by max-product elimination, then the
    argmaxes traced back: ``(top (n,), {dim: (n,) index})``.
    """
    left, steps = _eliminate(factors, eliminate, lambda t, d: t.max(d, keepdim=True))
    top = _sum(left).reshape(-1).expand(n)
    best: dict[int, torch.Tensor] = {}
    for d, (_, arg) in reversed(steps):
        best[d] = value_at(arg, best, n)
    return top, best


def value_at(t: torch.Tensor, best: dict[int, torch.Tensor], n: int) -> torch.Tensor:
    """``(n,)`` per row, ``t`` at the configuration ``best``.

    A dim ``t`` spans with size 1, or one ``best`` lacks, is read at 0.
    """
    zeros = torch.zeros(n, dtype=torch.long)
    index = []
    for i, k in enumerate(t.shape):
        d = i - t.dim()
        if d == -1:
            index.append(torch.arange(n) if k > 1 else zeros)
        else:
            index.append(best[d] if k > 1 else zeros)
    return t[tuple(index)] if index else t.expand(n)
