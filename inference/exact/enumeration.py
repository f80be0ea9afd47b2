"""Exact sums over the discrete sites of an effect network's Pyro model: the entry point.

:func:`enumerate_model` takes any evidence: where it leaves a continuous initial feature
out, the feature is integrated out in closed form
(:mod:`inference.exact.unknown_initial`); otherwise the model is traced and its factors
summed as they are (:mod:`inference.exact.traced`, which holds the result,
:class:`~inference.exact.traced.Enumerated`). Beside it: the sums over row chunks that
keep one chunk's joint small (:func:`over_row_chunks`, :func:`row_chunks`,
:func:`enumeration_size`), and the log ratio of two evidence sets on the same rows
(:func:`log_ratio`, :func:`conditional_log_evidence`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager

import torch
from effect_networks.inference.exact.elimination import contract_size
from effect_networks.inference.exact.traced import CENTRED, Enumerated, enumerate_traced
from effect_networks.inference.exact.unknown_initial import enumerate_unknown_initial
from effect_networks.models.declaration import EffectNetwork
from effect_networks.models.evidence import Evidence
from effect_networks.models.params import NetworkParams


def enumerate_model(
    net: EffectNetwork,
    params: NetworkParams,
    evidence: Evidence,
    *,
    keep: Iterable[str] = (),
    trace_only: Iterable[str] = (),
    masks: Mapping[str, torch.Tensor] | None = None,
) -> Enumerated:
    """Trace the model with ``evidence`` and sum every observed or structural factor.

    The model runs in its collapsed form (unknown parameters integrated out), so every
    latent site is discrete and enumerated.

    Parameters
    ----------
    evidence
        Encoded evidence (:meth:`EffectNetwork.encode`), at least one row.
    keep
        Unobserved end sites to keep as enumerated targets (their factor is added).
    trace_only
        Unobserved continuous end sites to trace for their distribution (``fn``) without
        adding their factor (the model draws a value for them that nothing uses).
    masks
        ``(n,)`` bool per discrete site of ``evidence``: False where the row's value is
        missing; the site is then enumerated (its posterior is the missing value's).
    """
    keep = set(keep)
    trace_only = set(trace_only)
    missing_initial = [
        s.name
        for s in net.sites
        if s.role == "initial" and not s.discrete and s.name not in evidence
    ]
    if missing_initial:  # integrated out in closed form, or refused naming the site
        return enumerate_unknown_initial(
            net, params, evidence, missing_initial, keep=keep, trace_only=trace_only, masks=masks
        )
    return enumerate_traced(net, params, evidence, keep=keep, trace_only=trace_only, masks=masks)


def log_ratio(a: Enumerated, b: Enumerated) -> torch.Tensor:
    """``(n,)`` ``log p(a's evidence) - log p(b's evidence)`` for the same rows.

    The factors both share (a continuous initial state's density, say) cancel exactly, at any
    magnitude; the difference of the two ``log_evidence`` loses what such a factor's size hides.
    """
    ratio = a.log_norm - b.log_norm
    for name in a.offsets.keys() | b.offsets.keys():
        ratio = ratio + (a.offsets.get(name, 0.0) - b.offsets.get(name, 0.0))
    return ratio


def conditional_log_evidence(
    net: EffectNetwork,
    params: NetworkParams,
    evidence: Evidence,
    given: Evidence,
    log_joint: torch.Tensor,
    log_given: torch.Tensor,
) -> torch.Tensor:
    """``(n,)`` ``log p(evidence | given) = log_joint - log_given``.

    ``given``: some of the evidence's sites, ``log_joint`` and ``log_given`` their ``log_evidence``;
    recomputed by :func:`log_ratio` in the rows where either is large enough that the subtraction
    would lose digits (a density far in its tail).
    """
    ratio = log_joint - log_given
    far = (log_joint.abs() > CENTRED) | (log_given.abs() > CENTRED)
    if not bool(far.any()):
        return ratio
    rows = far.nonzero().squeeze(-1)
    joint, part = evidence.rows(rows), given.rows(rows)
    size = max(
        enumeration_size(net, joint, contracted=True), enumeration_size(net, part, contracted=True)
    )
    exact = [
        log_ratio(
            enumerate_model(net, params, joint.rows(s)), enumerate_model(net, params, part.rows(s))
        )
        for s in row_chunks(len(rows), size)
    ]
    return ratio.index_put((rows,), torch.cat(exact))


def over_row_chunks(
    net: EffectNetwork,
    params: NetworkParams,
    evidence: Evidence,
    keep: Iterable[str],
    fn,
    trace_only: Iterable[str] = (),
    *,
    contracted: bool = False,
):
    """``fn(enumerated, chunk, rows)`` over row chunks of encoded ``evidence``.

    ``chunk`` holds its rows ``rows``, a slice; ``enumerated`` is the model summed on them with
    ``keep`` and ``trace_only`` as :func:`enumerate_model` takes them. The results are concatenated
    along the rows (a tuple element by element). ``contracted``: ``fn`` reads sums and marginals
    only, never the joint (``log_weight``, ``posterior``), so chunks are sized by the contraction's
    largest intermediate (:func:`enumeration_size`).
    """
    size = enumeration_size(net, evidence, keep, contracted=contracted)
    outs = []
    chunks = row_chunks(evidence.n_rows, size)
    widest = max((r.stop - r.start for r in chunks), default=0)
    with one_thread_below(size * widest):
        for rows in chunks:
            chunk = evidence.rows(rows)
            enumerated = enumerate_model(net, params, chunk, keep=keep, trace_only=trace_only)
            outs.append(fn(enumerated, chunk, rows))
    if isinstance(outs[0], tuple):
        return tuple(torch.cat(parts, 0) for parts in zip(*outs, strict=True))
    return torch.cat(outs, 0)


#: Elements of one chunk's sums up to which torch's intra-op threads cost more than they
#: save: an op of at most a million numbers gains little from being split, and where other
#: processes hold some of the cores each split op waits for its slowest thread (a batch of
#: 1,000 rows at 8 features ran 20x slower per row on two shared cores with two threads
#: than with one). Such a query runs on one thread, the caller's setting restored after.
SMALL_WORK = 1 << 20


@contextmanager
def one_thread_below(elements: int) -> Iterator[None]:
    """Run the block on one torch thread where ``elements`` is at most :data:`SMALL_WORK`."""
    threads = torch.get_num_threads()
    if threads == 1 or elements > SMALL_WORK:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


# Elements of one chunk's joint tensor (8 MiB of float64). Larger chunks cost more than
# they save: each joint-sized tensor of a chunk is fresh memory, and glibc hands blocks of
# tens of MiB back to the system when they are freed, so every call pays page faults on
# them again (the can network's latent query: 1.9-2.0 ms per row with 2**23, 1.0-1.1
# with 2**20, 1.35-1.4 with 2**19, where the trace's fixed cost per chunk starts to show).
CHUNK_ELEMENTS = 1 << 20


def row_chunks(n: int, enum_size: int, budget: int | None = None) -> list[slice]:
    """Row slices so that one chunk's joint tensor stays below ``budget`` elements.

    ``budget`` defaults to ``CHUNK_ELEMENTS``.
    """
    budget = CHUNK_ELEMENTS if budget is None else budget
    step = max(1, budget // max(1, enum_size))
    return [slice(i, min(n, i + step)) for i in range(0, n, step)] or [slice(0, 0)]


def enumeration_size(
    net: EffectNetwork, evidence: Evidence, keep: Iterable[str] = (), *, contracted: bool = False
) -> int:
    """Upper bound on the configurations per row that one sum over the enumerated sites builds.

    For this evidence: the product of the sites' sizes (the joint), or with ``contracted`` (the
    query sums by :meth:`Enumerated.log_sum` and marginals, never reading the joint) the largest
    intermediate of the contraction, from the declared parents (the joint's where parameters'
    clusters take part), or the kept sites' joint where larger.
    """
    ends = net.end_sites_needed({*evidence, *keep})
    latent = {
        s.name: s.size
        for s in net.sites
        if s.discrete and s.name not in evidence and (s.role != "end" or s.name in ends)
    }
    if not contracted or net.mixtures:
        return math.prod(latent.values())
    scopes = tuple(
        frozenset((q, latent[q]) for q in (s.name, *net.cpd(s.name).parents) if q in latent)
        for s in net.sites
        if s.role != "end" or s.name in ends
    )
    kept = math.prod(latent[s] for s in keep if s in latent)  # a joint over kept sites
    return max(contract_size(scopes), kept)
