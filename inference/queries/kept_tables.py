"""What the free query functions derive once per (network, parameters): :func:`tracer_for`.

A one-row query traces the Pyro model with its evidence and computes every site's log
probability; in a loop of one-row queries that is most of each call. For an all-discrete
network the model is traced once with every site enumerated (no evidence), and each
site's log-probability table kept: a one-row query's trace is then rebuilt from them,
each observed site's axis indexed at the row's value and the latent axes laid out as
the traced model lays them out (:class:`~inference.exact.traced.Enumerated`).

Per evidence pattern the first query traces the model as before and checks that the
rebuilt factors equal the traced ones bit for bit (values, shapes and strides); a
pattern that fails the check is traced on every query. The answers are the traced
query's.

The tables are kept per parameters object while it lives (a weak reference), and
rebuilt when any of its tensors is replaced or edited in place (each tensor's identity
and version counter), or when another network is queried with it.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass, fields

import pyro
import torch
from effect_networks.inference.exact.traced import trace_model
from effect_networks.models.declaration import EffectNetwork
from effect_networks.models.evidence import Evidence
from effect_networks.models.model import effect_model
from effect_networks.models.params import NetworkParams
from pyro import poutine

# id(params) -> (a weak reference to it, its tables)
_KEPT: dict[int, tuple[weakref.ref, KeptTables]] = {}


def tracer_for(net: EffectNetwork, params: NetworkParams) -> KeptTables | None:
    """The kept tables of ``(net, params)``, built where missing or stale.

    None for a network with a continuous site or a parameter (those are traced per query).
    """
    if net.mixtures or any(not s.discrete for s in net.sites):
        return None
    stamp = _stamp(params)
    key = id(params)
    entry = _KEPT.get(key)
    if entry is not None:
        ref, tables = entry
        if ref() is params and tables.net is net and tables.stamp == stamp:
            return tables
    tables = KeptTables(net, stamp)

    def forget(dead: weakref.ref, key: int = key) -> None:
        if key in _KEPT and _KEPT[key][0] is dead:
            del _KEPT[key]

    _KEPT[key] = (weakref.ref(params, forget), tables)
    return tables


def _stamp(params: NetworkParams) -> tuple:
    """Each tensor of the parameters with its version counter, and the pseudo-count.

    The tensors themselves are held, so that an identity cannot be reused while kept.
    """
    parts: list[object] = [params.pseudo_count]
    for site, cpd in params.cpds.items():
        parts.append(site)
        for f in fields(cpd):
            value = getattr(cpd, f.name)
            if isinstance(value, torch.Tensor):
                parts.append((_Same(value), value._version))
            else:
                parts.append(value)
    return tuple(parts)


class _Same:
    """A tensor compared by identity (``==`` on tensors compares elements)."""

    __slots__ = ("tensor",)

    def __init__(self, tensor: torch.Tensor) -> None:
        self.tensor = tensor

    def __eq__(self, other: object) -> bool:
        return isinstance(other, _Same) and other.tensor is self.tensor

    def __hash__(self) -> int:
        return id(self.tensor)


@dataclass(frozen=True)
class _Factor:
    """How one site's traced factor is read off its full table for one row."""

    table: torch.Tensor  # the full table, permuted: the observed axes it spans, then the latent
    observed: tuple[str, ...]  # per observed axis its site (the sites it does not span dropped)
    shape: torch.Size  # the traced factor's
    order: tuple[int, ...]  # its dims from the outermost in memory (stride 0: broadcast)


class KeptTables:
    """The log-probability tables of one (network, parameters), and per pattern the layout.

    Called as an :data:`~inference.exact.traced.Tracer`: the trace of a one-row query,
    or None where the model is to be traced.
    """

    def __init__(self, net: EffectNetwork, stamp: tuple) -> None:
        self.net, self.stamp = net, stamp
        self.full: poutine.Trace | None = None
        self.layouts: dict[tuple, tuple[poutine.Trace, dict[str, _Factor]] | None] = {}

    def __call__(
        self, net: EffectNetwork, params: NetworkParams, evidence: Evidence, end_sites: set
    ) -> poutine.Trace | None:
        """The trace of a one-row query with ``evidence``; None: trace the model."""
        if evidence.n_rows != 1:
            return None  # a batch traces once for all its rows
        pattern = (frozenset(evidence), frozenset(end_sites))
        if pattern not in self.layouts:
            trace = trace_model(net, params, evidence, end_sites)
            self.layouts[pattern] = self._layout(params, trace, evidence)
            return trace
        layout = self.layouts[pattern]
        if layout is None:
            return None
        return _rebuilt(*layout, evidence)

    def _layout(self, params, trace: poutine.Trace, evidence: Evidence):
        """The recipe per site, checked against ``trace``; None where it differs."""
        if self.full is None:
            with pyro.validation_enabled(False):
                full = poutine.trace(poutine.enum(effect_model, first_available_dim=-2)).get_trace(
                    self.net, params, n_rows=1, collapse=True
                )
                full.compute_log_prob()
            full.remove_node("_INPUT")  # holds the parameters: they would never be freed
            self.full = full
        full = self.full
        names = {s.name for s in self.net.sites}  # the rows plate is recorded as a site too
        sample = [n for n, s in trace.nodes.items() if s["type"] == "sample" and n in names]
        full_dims = {
            n: s["infer"].get("_enumerate_dim") for n, s in full.nodes.items() if n in names
        }
        if any(full_dims.get(n) is None for n in sample):
            return None
        rank = max(-d for d in full_dims.values() if d is not None) + 1
        latent = {
            n: trace.nodes[n]["infer"]["_enumerate_dim"]
            for n in sample
            if trace.nodes[n]["infer"].get("_enumerate_dim") is not None
        }
        observed = [n for n in sample if n in evidence]
        if len(latent) + len(observed) != len(sample):
            return None
        by_dim = sorted(latent, key=lambda n: latent[n])  # most negative dim first
        factors = {}
        for name in sample:
            real = trace.nodes[name]["log_prob"]
            lp = full.nodes[name]["log_prob"]
            lp = lp.reshape(*[1] * (rank - lp.dim()), *lp.shape)
            obs_axes = [rank + full_dims[s] for s in observed]
            lat_axes = [rank + full_dims[s] for s in by_dim]
            rest = [a for a in range(rank) if a not in obs_axes and a not in lat_axes]
            if any(lp.shape[a] != 1 for a in rest):
                return None
            table = lp.permute(*obs_axes, *lat_axes, *rest)
            table = table.reshape(table.shape[: len(obs_axes) + len(lat_axes)])
            spans = [lp.shape[rank + full_dims[s]] > 1 for s in observed]
            sites = tuple(s for s, kept in zip(observed, spans, strict=True) if kept)
            # an observed axis of size one is read at 0 on every row: dropped here once
            dropped = [
                k
                for k, kept in zip(table.shape, [*spans, *[True] * len(lat_axes)], strict=True)
                if kept
            ]
            table = table.reshape(dropped)
            held = [d for d in range(real.dim()) if real.stride(d) > 0]
            order = sorted(held, key=lambda d: -real.stride(d))
            order += [d for d in range(real.dim()) if d not in order]
            factors[name] = _Factor(table, sites, real.shape, tuple(order))
        try:
            rebuilt = _rebuilt(trace, factors, evidence)
        except RuntimeError:  # a leading dim of more than one state where the trace has none
            return None
        for name in sample:
            mine, real = rebuilt.nodes[name]["log_prob"], trace.nodes[name]["log_prob"]
            strides = [s for s, k in zip(real.stride(), real.shape, strict=True) if k > 1]
            ours = [s for s, k in zip(mine.stride(), mine.shape, strict=True) if k > 1]
            if mine.shape != real.shape or ours != strides or not torch.equal(mine, real):
                return None
        model = poutine.Trace()  # without its inputs (the parameters), as above
        for name, node in trace.nodes.items():
            if node["type"] != "args":
                model.add_node(name, **node)
        return model, factors


def _rebuilt(
    model: poutine.Trace, factors: dict[str, _Factor], evidence: Evidence
) -> poutine.Trace:
    """A copy of ``model`` (a trace of the same pattern) with one row's values and factors."""
    trace = poutine.Trace()
    for name, node in model.nodes.items():
        node = dict(node)
        if name in factors:
            f = factors[name]
            at = tuple(evidence[s] for s in f.observed)
            lp = f.table[at] if at else f.table[None]  # (1, latent sizes...)
            lp = lp.movedim(0, -1)
            # laid out in memory as the traced factor is (a sum's order follows the layout)
            lp = _ranked(lp, len(f.shape)).permute(f.order).contiguous()
            lp = lp.permute(_inverse(f.order)).expand(f.shape)
            node["log_prob"] = node["unscaled_log_prob"] = lp
            if name in evidence:
                node["value"] = evidence[name]
        trace.add_node(name, **node)
    return trace


def _inverse(order: tuple[int, ...]) -> list[int]:
    inverse = [0] * len(order)
    for i, d in enumerate(order):
        inverse[d] = i
    return inverse


def _ranked(t: torch.Tensor, rank: int) -> torch.Tensor:
    """``t`` with leading dims of size 1 added or dropped to ``rank`` dims."""
    if t.dim() < rank:
        return t.reshape(*[1] * (rank - t.dim()), *t.shape)
    return t.reshape(t.shape[t.dim() - rank :])
