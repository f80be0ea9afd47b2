"""Exact sums over the discrete sites of an effect network's Pyro model.

The model is traced once under ``poutine.enum`` with the evidence as observations: every
latent discrete site gets an enumeration dim (-2, -3, ... to the left of the rows plate)
and every site's ``log_prob`` broadcasts over the dims of the sites it depends on.
Adding the log-probabilities gives the joint log-weight of all enumerated values per row;
``logsumexp`` over dims gives evidence and marginals. Unobserved end sites that are not
asked for, and that no observed or asked-for end site depends on, are left out: summing
them out contributes exactly 1.
Unobserved parameters never appear as latent sites: the model integrates them out in
closed form. Nothing here samples.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from functools import cached_property

import torch
from pyro import poutine

from models.declaration import EffectNetwork
from models.evidence import Evidence
from models.model import effect_model
from models.params import NetworkParams


@dataclass(frozen=True)
class Enumerated:
    """A traced model with its joint log-weight over the enumerated sites.

    ``log_weight`` has shape ``(E_k, ..., E_1, n)``: one dim per enumerated site (its
    number of states, or 1 where no kept factor depends on it) then the rows.
    ``dims[site]`` is the (negative) dim of an enumerated site.

    The joint is held in log space per row: ``log_weight + log_offset`` is the log-joint,
    where ``offsets`` ``{name: (n,)}`` hold the parts that are the same for every
    configuration of a row (a continuous initial state's density, each unbounded
    factor's largest value, and under ``""`` the sum's), so that ``log_weight`` keeps the
    differences between configurations to float64's precision at any magnitude of the
    evidence, and every distribution normalised from it sums to one. Kept per site, they
    cancel exactly between two evidence sets that share a site (:func:`log_ratio`).
    """

    log_weight: torch.Tensor
    dims: dict[str, int]
    trace: poutine.Trace
    offsets: dict[str, torch.Tensor] = field(default_factory=dict)

    @property
    def log_offset(self) -> torch.Tensor | float:
        """``(n,)`` the offsets' sum (``0.0`` without any)."""
        return sum(self.offsets.values(), 0.0)

    @cached_property  # a sum over the whole joint, which queries ask for more than once
    def log_norm(self) -> torch.Tensor:
        """``(n,)`` ``log sum exp(log_weight)`` over the configurations of each row."""
        w = self.log_weight
        if w.dim() == 1:
            return w
        rows_first = w.movedim(-1, 0)
        if rows_first.is_contiguous():  # the rows outermost in memory: reduce along them
            return rows_first.reshape(w.shape[-1], -1).logsumexp(1)
        return w.reshape(-1, w.shape[-1]).logsumexp(0)

    @cached_property
    def log_evidence(self) -> torch.Tensor:
        """``(n,)`` log-probability of the evidence (kept sites), all latents summed out."""
        return self.log_norm + self.log_offset

    def marginal(self, site: str) -> torch.Tensor:
        """``(n, K)`` exact posterior of an enumerated site given the evidence."""
        dim = self.dims[site]
        w = self.log_weight
        if w.shape[dim] == 1:  # no kept factor depends on the site: its prior alone
            w = w + torch.zeros(_states(self.trace, site), *([1] * (-dim - 1)), dtype=w.dtype)
        others = [d for d in range(w.dim() - 1) if d != w.dim() + dim]
        m = w.logsumexp(others) if others else w
        norm = m.logsumexp(0, keepdim=True)
        self._check_possible(norm[0])
        return (m - norm).exp().T

    def posterior(self, *, strict: bool = True) -> torch.Tensor:
        """Normalised joint weight, same shape as ``log_weight``.

        A row whose evidence has probability 0 has no posterior: ``ValueError``, or with
        ``strict=False`` a weight of 0 everywhere in that row (for sums over the
        posterior that are 0 where nothing is possible).

        With the rows outermost in memory and the sum not yet taken, both come from one
        pass of ``exp``: ``e = exp(w - max)``, ``log_norm = max + log(sum e)`` (as
        ``logsumexp`` computes it) and the posterior ``e / sum e``.
        """
        w = self.log_weight
        rows_first = w.movedim(-1, 0)
        if "log_norm" in self.__dict__ or w.dim() == 1 or not rows_first.is_contiguous():
            if strict:
                self._check_possible(self.log_norm)
            norm = self.log_norm
            return (w - torch.where(norm > -torch.inf, norm, 0.0)).exp()
        flat = rows_first.reshape(w.shape[-1], -1)
        top = flat.amax(1, keepdim=True)
        top = torch.where(torch.isfinite(top), top, 0.0)  # a row of -inf: as logsumexp
        post = (flat - top).exp_()
        total = post.sum(1, keepdim=True)
        self.__dict__["log_norm"] = (total.log() + top).squeeze(1)
        if strict:
            self._check_possible(self.log_norm)
        total = torch.where(total > 0, total, 1.0)  # an impossible row stays 0
        return post.div_(total).reshape(rows_first.shape).movedim(0, -1)

    def _check_possible(self, log_norm: torch.Tensor) -> None:
        """Refuse a row whose evidence has probability 0 under every configuration: no
        posterior exists (in float64, a density also underflows to 0 where the value lies
        beyond about 1e154 of the component's standard deviations)."""
        if bool((log_norm > -torch.inf).all()):
            return
        row = int((log_norm == -torch.inf).nonzero()[0])

        def zero_everywhere(lp: torch.Tensor) -> bool:
            if lp.dim() == 0:
                return bool(lp == -torch.inf)
            at = lp[..., row] if lp.shape[-1] > 1 else lp[..., 0]
            return bool((at == -torch.inf).all())

        zero = [
            name
            for name, site in self.trace.nodes.items()
            if site["type"] == "sample" and "log_prob" in site and zero_everywhere(site["log_prob"])
        ]
        raise ValueError(
            f"evidence row {row} has probability 0 under every configuration of the model"
            + (f" (the factor of {zero} is 0 in float64 everywhere)" if zero else "")
            + ": no posterior exists. A state the model never reaches, or a value too far "
            "from every component for float64 (rescale the feature)"
        )


def _states(trace: poutine.Trace, site: str) -> int:
    # the support, not ``fn.probs``: that would take softmax over the whole batch
    return int(trace.nodes[site]["fn"].enumerate_support(expand=False).shape[0])


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
    n = evidence.n_rows
    missing_initial = [
        s.name
        for s in net.sites
        if s.role == "initial" and not s.discrete and s.name not in evidence
    ]
    if missing_initial:
        raise ValueError(
            f"queries need the initial state of continuous features; missing {missing_initial}"
        )
    trace = poutine.trace(poutine.enum(effect_model, first_available_dim=-2)).get_trace(
        net,
        params,
        evidence,
        end_sites=set(evidence) | keep | trace_only,
        collapse=True,
        masks=masks,
    )
    trace.compute_log_prob()
    bounded: list[torch.Tensor] = []  # tables and factors: 0, -inf or a probability's log
    unbounded: dict[str, torch.Tensor] = {}  # densities and softmaxes, as traced
    dims: dict[str, int] = {}
    for name, site in trace.nodes.items():
        if site["type"] != "sample":
            continue
        if site["infer"].get("_enumerate_dim") is not None:
            dims[name] = site["infer"]["_enumerate_dim"]
        if name in trace_only:
            continue
        if _unbounded(net, name):
            unbounded[name] = site["log_prob"]
        else:
            bounded.append(site["log_prob"])
    assert bounded or unbounded
    # A density (or a softmax of continuous inputs) may sit anywhere in float64: a per-row
    # constant of each goes to the offsets before the factors are summed, so that a large
    # constant does not swallow the differences of the others. First each one's row
    # maximum; where the factors' optima then disagree by far (a density left out for
    # the actions not using a parameter and far in its tail for the others), each one's
    # value at the row's most probable configuration, where the sum is then near 0 and
    # the configurations near it keep their differences to float64's precision.
    # The most probable configuration is known only to the rounding of the sum it is read
    # from: configurations whose large factors are equal and whose small ones differ tie
    # there, and centring on the wrong one of them turns its small factors into large
    # differences that round. So centre again on the argmax of the centred sum, whose
    # rounding is float64's precision of what the last one hid, until it stays.
    offsets: dict[str, torch.Tensor] = {}  # (n,) each: see Enumerated
    for name, lp in unbounded.items():
        offsets[name] = _row_max(lp).reshape(-1).expand(n)
    total = _centred_sum(bounded, unbounded, offsets, dims, n)
    top = _row_max(total)
    best = None
    for _ in range(_RECENTRINGS):
        if not unbounded or not bool((top.abs() > _CENTRED).any()):
            break
        argmax = total.reshape(-1, n).argmax(0)  # (n,) each row's most probable configuration
        if best is not None and bool((argmax == best).all()):
            break
        best = argmax
        for name, lp in unbounded.items():
            at_best = lp.expand(total.shape).reshape(-1, n).gather(0, best[None])[0]
            # a row where nothing is possible keeps its maximum
            offsets[name] = torch.where(torch.isfinite(at_best), at_best, offsets[name])
        total = _centred_sum(bounded, unbounded, offsets, dims, n)
        top = _row_max(total)
    if bool((top.abs() > _CENTRED).any()):  # the factors' optima still disagree by far
        total = total - top
        offsets[""] = top.reshape(-1)
    return Enumerated(total, dims, trace, offsets)


def _centred_sum(
    bounded: list[torch.Tensor],
    unbounded: dict[str, torch.Tensor],
    offsets: dict[str, torch.Tensor],
    dims: dict[str, int],
    n: int,
) -> torch.Tensor:
    """The factors' sum, ``(E_k, ..., E_1, n)``, each unbounded one less its ``(n,)``
    offset."""
    factors = bounded + [lp - offsets[name] for name, lp in unbounded.items()]
    # the largest factors first: their sum is one plain pass in their own memory order
    # (rows outermost for gathered tables), and the small ones broadcast onto it once
    factors = sorted(factors, key=lambda lp: -lp.numel())
    total = factors[0]
    for i, lp in enumerate(factors[1:]):
        fits = (
            torch.broadcast_shapes(total.shape, lp.shape) == total.shape
            and torch.result_type(total, lp) == total.dtype
        )
        # a new tensor once (the trace's own log_prob stays as it is), then in place:
        # every fresh joint-sized tensor costs page faults
        total = total.add_(lp) if i > 0 and fits else total + lp
    depth = max([-d for d in dims.values()], default=1)
    total = total.expand(*total.shape[:-1], n) if total.shape[-1] != n else total
    while total.dim() < depth:
        total = total.unsqueeze(0)
    return total


def log_ratio(a: Enumerated, b: Enumerated) -> torch.Tensor:
    """``(n,)`` ``log p(a's evidence) - log p(b's evidence)`` for the same rows, where the
    factors both share (a continuous initial state's density, say) cancel exactly, at
    any magnitude; the difference of the two ``log_evidence`` loses what such a factor's
    size hides."""
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
    """``(n,)`` ``log p(evidence | given) = log_joint - log_given`` (``given``: some of the
    evidence's sites, ``log_joint`` and ``log_given`` their ``log_evidence``), recomputed
    by :func:`log_ratio` in the rows where either is large enough that the subtraction
    would lose digits (a density far in its tail)."""
    ratio = log_joint - log_given
    far = (log_joint.abs() > _CENTRED) | (log_given.abs() > _CENTRED)
    if not bool(far.any()):
        return ratio
    rows = far.nonzero().squeeze(-1)
    joint, part = evidence.rows(rows), given.rows(rows)
    size = max(enumeration_size(net, joint), enumeration_size(net, part))
    exact = [
        log_ratio(
            enumerate_model(net, params, joint.rows(s)), enumerate_model(net, params, part.rows(s))
        )
        for s in row_chunks(len(rows), size)
    ]
    return ratio.index_put((rows,), torch.cat(exact))


#: Largest row maximum of a joint left uncentred: its rounding, 1e3 * 2^-52, is below 1e-12.
_CENTRED = 1e3

#: Most centrings on a configuration: each tells apart what the last one's rounding, 2^-52
#: of its sum, hid; twenty take float64's largest numbers to below ``_CENTRED``.
_RECENTRINGS = 24


def _unbounded(net: EffectNetwork, name: str) -> bool:
    """Whether a site's log-probability can take any magnitude: a continuous site's
    density, or a discrete site with continuous inputs (a softmax). A table's (and a
    factor's) is ``0``, ``-inf`` or a log-probability above float64's smallest."""
    try:
        spec = net.site(name)
    except KeyError:  # a factor (the cluster's cell, an observed mask): 0 or -inf
        return False
    return not spec.discrete or bool(net.cpd(name).inputs)


def _row_max(lp: torch.Tensor) -> torch.Tensor:
    """Per row (last dim), the largest value over the other dims, kept as dims of size 1;
    a row whose largest value is not finite (all ``-inf``) gets 0."""
    top = lp.amax(tuple(range(lp.dim() - 1)), keepdim=True) if lp.dim() > 1 else lp
    return torch.where(torch.isfinite(top), top, 0.0)


def over_row_chunks(
    net: EffectNetwork,
    params: NetworkParams,
    evidence: Evidence,
    keep: Iterable[str],
    fn,
    trace_only: Iterable[str] = (),
):
    """``fn(enumerated, chunk, rows)`` over row chunks of encoded ``evidence`` (``chunk``
    its rows ``rows``, a slice; ``enumerated`` the model summed on them with ``keep`` and
    ``trace_only`` as :func:`enumerate_model` takes them), the results concatenated along
    the rows (a tuple element by element)."""
    size = enumeration_size(net, evidence, keep)
    outs = []
    for rows in row_chunks(evidence.n_rows, size):
        chunk = evidence.rows(rows)
        enumerated = enumerate_model(net, params, chunk, keep=keep, trace_only=trace_only)
        outs.append(fn(enumerated, chunk, rows))
    if isinstance(outs[0], tuple):
        return tuple(torch.cat(parts, 0) for parts in zip(*outs, strict=True))
    return torch.cat(outs, 0)


# Elements of one chunk's joint tensor (8 MiB of float64). Larger chunks cost more than
# they save: each joint-sized tensor of a chunk is fresh memory, and glibc hands blocks of
# tens of MiB back to the system when they are freed, so every call pays page faults on
# them again (the can network's latent query: 1.9-2.0 ms per row with 2**23, 1.0-1.1
# with 2**20, 1.35-1.4 with 2**19, where the trace's fixed cost per chunk starts to show).
CHUNK_ELEMENTS = 1 << 20


def row_chunks(n: int, enum_size: int, budget: int | None = None) -> list[slice]:
    """Row slices so that one chunk's joint tensor stays below ``budget`` elements
    (default ``CHUNK_ELEMENTS``)."""
    budget = CHUNK_ELEMENTS if budget is None else budget
    step = max(1, budget // max(1, enum_size))
    return [slice(i, min(n, i + step)) for i in range(0, n, step)] or [slice(0, 0)]


def enumeration_size(net: EffectNetwork, evidence: Evidence, keep: Iterable[str] = ()) -> int:
    """Upper bound on the product of enumerated site sizes for this evidence."""
    ends = net.end_sites_needed({*evidence, *keep})
    latent = [
        s.size
        for s in net.sites
        if s.discrete and s.name not in evidence and (s.role != "end" or s.name in ends)
    ]
    return math.prod(latent)
