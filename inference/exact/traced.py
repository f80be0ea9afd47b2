"""The model traced under enumeration, and its factors summed: :class:`Enumerated`.

The model is traced once under ``poutine.enum`` with the evidence as observations: every
latent discrete site gets an enumeration dim (-2, -3, ... to the left of the rows plate)
and every site's ``log_prob`` broadcasts over the dims of the sites it depends on.
Adding the log-probabilities gives the joint log-weight of all enumerated values per row;
``logsumexp`` over dims gives evidence and marginals. A small joint is summed so, as one
tensor; a larger one whose structure splits (sparse parents) is summed by elimination,
one site at a time (:mod:`inference.exact.elimination`), and never built unless a
query reads it. Unobserved end sites that are not
asked for, and that no observed or asked-for end site depends on, are left out: summing
them out contributes exactly 1.
Unobserved parameters never appear as latent sites: the model integrates them out in
closed form. Nothing here samples.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property

import pyro
import torch
from effect_networks.inference.exact.elimination import (
    contract,
    dense_enough,
    max_config,
    sample,
    value_at,
)
from effect_networks.models.cpds.table import broadcast_shapes
from effect_networks.models.declaration import EffectNetwork
from effect_networks.models.evidence import Evidence
from effect_networks.models.model import effect_model
from effect_networks.models.params import NetworkParams
from pyro import poutine


@dataclass(frozen=True)
class Enumerated:
    """A traced model with its factors over the enumerated sites.

    ``factors`` are log-factors, each broadcastable to ``(E_k, ..., E_1, n)``: one dim per
    enumerated site (its number of states, or 1 where the factor does not depend on it)
    then the rows. ``dims[site]`` is the (negative) dim of an enumerated site. One factor
    is the joint itself (a small joint is summed once, as a dense tensor); several are
    summed by contraction (:mod:`inference.exact.elimination`), one site at a time in
    an order that keeps every intermediate small, so that sums and marginals never build
    the joint where the structure allows less.

    The joint is held in log space per row: ``log_weight + log_offset`` is the log-joint,
    where ``offsets`` ``{name: (n,)}`` hold the parts that are the same for every
    configuration of a row (a continuous initial state's density, each unbounded
    factor's largest value, and under ``""`` the sum's), so that the factors keep the
    differences between configurations to float64's precision at any magnitude of the
    evidence, and every distribution normalised from them sums to one. Kept per site,
    they cancel exactly between two evidence sets that share a site (:func:`log_ratio`).
    """

    factors: tuple[torch.Tensor, ...]
    dims: dict[str, int]
    trace: poutine.Trace
    offsets: dict[str, torch.Tensor] = field(default_factory=dict)
    rows: int | None = None  # the rows, where no factor spans them all

    @property
    def contracted(self) -> bool:
        """Whether sums run by contraction of several factors (else over the one joint)."""
        return len(self.factors) > 1

    @cached_property
    def n_rows(self) -> int:
        """The rows ``n``."""
        if self.rows is not None:
            return self.rows
        return max(f.shape[-1] if f.dim() else 1 for f in self.factors)

    @cached_property
    def log_weight(self) -> torch.Tensor:
        """``(E_k, ..., E_1, n)`` the joint log-weight, the factors summed.

        Built here, once, when several factors are held: as large as the product of the sites'
        sizes; sums and marginals do not need it.
        """
        if not self.contracted:
            return self.factors[0]
        return _full(_dense_sum(list(self.factors)), self.dims, self.n_rows)

    @cached_property
    def _sums(self) -> dict[frozenset[str], torch.Tensor]:
        """The contractions :meth:`log_sum` has taken (without ``extra``), by ``keep``."""
        return {}

    @property
    def log_offset(self) -> torch.Tensor | float:
        """``(n,)`` the offsets' sum (``0.0`` without any)."""
        return sum(self.offsets.values(), 0.0)

    @cached_property  # a sum over the whole joint, which queries ask for more than once
    def log_norm(self) -> torch.Tensor:
        """``(n,)`` ``log sum exp(log_weight)`` over the configurations of each row."""
        if self.contracted:  # from a sum over one site already taken, where there is one
            done = [w for keep, w in self._sums.items() if len(keep) == 1]
            w = done[0] if done else self.log_sum()
            others = [d for d in range(w.dim() - 1) if w.shape[d] > 1]
            w = w.logsumexp(others) if others else w
            return w.reshape(-1).expand(self.n_rows)
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

    def log_sum(self, keep: Iterable[str] = (), extra: Iterable[torch.Tensor] = ()) -> torch.Tensor:
        """``log sum exp`` of the joint over every enumerated site but ``keep``.

        The log-factors ``extra`` are added, each broadcastable to it: a tensor of the joint's rank,
        ``(..., n)``, whose dims of ``keep`` keep their size and the others are 1. By contraction
        where the factors are several.
        """
        keep = frozenset(keep)
        extra = list(extra)
        if not extra and keep in self._sums:
            return self._sums[keep]
        keep_dims = {self.dims[s] for s in keep}
        factors = [*self.factors, *extra]
        depth = max([-d for d in self.dims.values()], default=1)
        if self.contracted:
            eliminate = [d for d in self.dims.values() if d not in keep_dims]
            total = _full(contract(factors, eliminate), {}, 0, depth)
            if not extra:  # asked again by marginals, sums and masses of one query
                self._sums[keep] = total
            return total
        w = _dense_sum(factors) if len(factors) > 1 else factors[0]
        w = _full(w, {}, 0, depth)
        others = [w.dim() + d for d in self.dims.values() if d not in keep_dims]
        others = [d for d in others if d >= 0 and w.shape[d] > 1]
        return w.logsumexp(others, keepdim=True) if others else w

    def marginal(self, site: str) -> torch.Tensor:
        """``(n, K)`` exact posterior of an enumerated site given the evidence."""
        dim = self.dims[site]
        if self.contracted:
            m = self.log_sum({site})
            m = m.reshape(m.shape[dim], -1)
            m = m.expand(m.shape[0], self.n_rows)
        else:
            w = self.log_weight
            others = [d for d in range(w.dim() - 1) if d != w.dim() + dim]
            m = w.logsumexp(others) if others else w
        if m.shape[0] == 1:  # no kept factor depends on the site: its prior alone
            m = m + torch.zeros(_states(self.trace, site), 1, dtype=m.dtype)
        norm = m.logsumexp(0, keepdim=True)
        self.check_possible(norm[0])
        return (m - norm).exp().T

    def joint(self, sites: Sequence[str]) -> torch.Tensor:
        """``(n, K_1 * ... * K_m)`` the posterior over the joint states of ``sites``.

        The first site varies slowest; every other site is summed out.
        """
        w = self.log_sum(sites)
        keep = [w.dim() + self.dims[s] for s in sites]
        shape = list(w.shape)
        for s, d in zip(sites, keep, strict=True):
            shape[d] = _states(self.trace, s)  # a site no factor spans: its states alike
        shape[-1] = self.n_rows
        w = w.expand(shape)
        others = [d for d in range(w.dim() - 1) if d not in keep]
        w = w.permute(w.dim() - 1, *keep, *others).reshape(w.shape[-1], -1)
        return (w - w.logsumexp(-1, keepdim=True)).exp()

    def sample(self) -> dict[str, torch.Tensor]:
        """One joint draw per row of the enumerated sites some factor depends on.

        From their exact posterior, by contraction (torch's global generator).
        """
        self.check_possible(self.log_norm)
        drawn = sample(list(self.factors), list(self.dims.values()), self.n_rows)
        return {site: drawn[d] for site, d in self.dims.items() if d in drawn}

    def posterior(self, *, strict: bool = True) -> torch.Tensor:
        """Normalised joint weight, same shape as ``log_weight``.

        This builds ``log_weight``: as large as the product of the sites' sizes.

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
                self.check_possible(self.log_norm)
            norm = self.log_norm
            return (w - torch.where(norm > -torch.inf, norm, 0.0)).exp()
        flat = rows_first.reshape(w.shape[-1], -1)
        top = flat.amax(1, keepdim=True)
        top = torch.where(torch.isfinite(top), top, 0.0)  # a row of -inf: as logsumexp
        post = (flat - top).exp_()
        total = post.sum(1, keepdim=True)
        self.__dict__["log_norm"] = (total.log() + top).squeeze(1)
        if strict:
            self.check_possible(self.log_norm)
        total = torch.where(total > 0, total, 1.0)  # an impossible row stays 0
        return post.div_(total).reshape(rows_first.shape).movedim(0, -1)

    def check_possible(self, log_norm: torch.Tensor) -> None:
        """Refuse a row whose evidence has probability 0 under every configuration.

        No posterior exists (in float64, a density also underflows to 0 where the value lies beyond
        about 1e154 of the component's standard deviations).
        """
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


def trace_model(
    net: EffectNetwork,
    params: NetworkParams,
    evidence: Evidence,
    end_sites: set,
    masks: Mapping[str, torch.Tensor] | None = None,
) -> poutine.Trace:
    """The collapsed model traced under enumeration with ``evidence``, ``log_prob`` computed."""
    # Pyro's checks of every site's value and log-probability repeat, per call, what the
    # evidence's encoding and the parameters' check have settled once
    with pyro.validation_enabled(False):
        trace = poutine.trace(poutine.enum(effect_model, first_available_dim=-2)).get_trace(
            net, params, evidence, end_sites=end_sites, collapse=True, masks=masks
        )
        trace.compute_log_prob()
    return trace


def enumerate_traced(
    net: EffectNetwork,
    params: NetworkParams,
    evidence: Evidence,
    *,
    keep: Iterable[str] = (),
    trace_only: Iterable[str] = (),
    masks: Mapping[str, torch.Tensor] | None = None,
) -> Enumerated:
    """Trace the model with ``evidence`` and sum every observed or structural factor.

    The evidence gives every continuous initial value (:func:`~inference.exact.enumeration.enumerate_model`
    takes any evidence). The model runs in its collapsed form (unknown parameters
    integrated out), so every latent site is discrete and enumerated.

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
    end_sites = set(evidence) | keep | trace_only
    trace = trace_model(net, params, evidence, end_sites, masks)
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
    if not dense_enough([*bounded, *unbounded.values()]):
        return _contracted(bounded, unbounded, offsets, dims, trace, n)
    total = _centred_sum(bounded, unbounded, offsets, dims, n)
    top = _row_max(total)
    best = None
    for _ in range(_RECENTRINGS):
        if not unbounded or not bool((top.abs() > CENTRED).any()):
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
    if bool((top.abs() > CENTRED).any()):  # the factors' optima still disagree by far
        total = total - top
        offsets[""] = top.reshape(-1)
    return Enumerated((total,), dims, trace, offsets)


def _contracted(bounded, unbounded, offsets, dims, trace, n) -> Enumerated:
    """The factors kept apart, each unbounded one less its offset.

    Where the row's most probable configuration (by max-product contraction) lies far from 0, each
    unbounded factor is centred at its value there instead, as the dense sum is.
    """
    factors = bounded + [lp - offsets[name] for name, lp in unbounded.items()]
    if unbounded:
        top, best = max_config(factors, list(dims.values()), n)
        if bool((top.abs() > CENTRED).any()):
            for name, lp in unbounded.items():
                at_best = value_at(lp, best, n)
                offsets[name] = torch.where(torch.isfinite(at_best), at_best, offsets[name])
            factors = bounded + [lp - offsets[name] for name, lp in unbounded.items()]
    return Enumerated(tuple(factors), dims, trace, offsets, n)


def _centred_sum(
    bounded: list[torch.Tensor],
    unbounded: dict[str, torch.Tensor],
    offsets: dict[str, torch.Tensor],
    dims: dict[str, int],
    n: int,
) -> torch.Tensor:
    """The factors' sum, ``(E_k, ..., E_1, n)``, each unbounded one less its ``(n,)`` offset."""
    factors = bounded + [lp - offsets[name] for name, lp in unbounded.items()]
    return _full(_dense_sum(factors), dims, n)


def _dense_sum(factors: list[torch.Tensor]) -> torch.Tensor:
    """The log-factors' broadcast sum (a fresh tensor: the factors stay as they are)."""
    # the largest factors first: their sum is one plain pass in their own memory order
    # (rows outermost for gathered tables), and the small ones broadcast onto it once
    factors = sorted(factors, key=lambda lp: -lp.numel())
    total = factors[0]
    for i, lp in enumerate(factors[1:]):
        fits = (
            broadcast_shapes(total.shape, lp.shape) == total.shape
            and torch.result_type(total, lp) == total.dtype
        )
        # a new tensor once (the trace's own log_prob stays as it is), then in place:
        # every fresh joint-sized tensor costs page faults
        total = total.add_(lp) if i > 0 and fits else total + lp
    return total


def _full(
    total: torch.Tensor, dims: Mapping[str, int], n: int, depth: int | None = None
) -> torch.Tensor:
    """``total`` with its rows expanded and dims of size 1 in front.

    Rows expanded to ``n`` (where ``n``), dims of size 1 up to the enumeration's depth.
    """
    if depth is None:
        depth = max([-d for d in dims.values()], default=1)
    if n and (total.dim() == 0 or total.shape[-1] != n):
        total = total.expand(*total.shape[:-1], n) if total.dim() else total.expand(n)
    while total.dim() < depth:
        total = total.unsqueeze(0)
    return total


#: Largest row maximum of a joint left uncentred: its rounding, 1e3 * 2^-52, is below 1e-12.
CENTRED = 1e3

#: Most centrings on a configuration: each tells apart what the last one's rounding, 2^-52
#: of its sum, hid; twenty take float64's largest numbers to below ``CENTRED``.
_RECENTRINGS = 24


def _unbounded(net: EffectNetwork, name: str) -> bool:
    """Whether a site's log-probability can take any magnitude.

    A continuous site's density, or a discrete site with continuous inputs (a softmax). A table's
    (and a factor's) is ``0``, ``-inf`` or a log-probability above float64's smallest.
    """
    try:
        spec = net.site(name)
    except KeyError:  # a factor (the cluster's cell, an observed mask): 0 or -inf
        return False
    return not spec.discrete or bool(net.cpd(name).inputs)


def _row_max(lp: torch.Tensor) -> torch.Tensor:
    """Per row (last dim), the largest value over the other dims, kept as dims of size 1.

    A row whose largest value is not finite (all ``-inf``) gets 0.
    """
    top = lp.amax(tuple(range(lp.dim() - 1)), keepdim=True) if lp.dim() > 1 else lp
    return torch.where(torch.isfinite(top), top, 0.0)
