"""What the free query functions derive once per (network, parameters): :func:`tables_for`.

A query of a few rows traces the Pyro model with its evidence and computes every site's
log probability; in a loop of one-row queries that is most of each call, and the sums
themselves are a small part. For an all-discrete network the free
:func:`~inference.queries.action.infer_action` instead keeps the network's factor tables
(:class:`~inference.queries.action_tables.CompiledNetwork`: the model traced once with
every site enumerated, each site's log-probability table kept, and per evidence pattern
the kept factors summed once) and answers a query of at most ``FEW_ROWS`` rows from them.
They are the numbers :func:`inference.compile` answers from, read off the same model: the
answers agree with the traced ones to rounding (about 1e-15), and every field but the
floating-point ones (the best action, its name, the implausible flag) is the same.

The tables are kept per parameters object while it lives (a weak reference), and
rebuilt when any of its tensors is replaced or edited in place (each tensor's identity
and version counter), or when another network is queried with it.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass, fields

import torch
from effect_networks.inference.queries.action_tables import CompiledNetwork, compile_discrete
from effect_networks.models.declaration import EffectNetwork
from effect_networks.models.params import NetworkParams

#: Queries of at most this many rows are answered from the kept tables. Beyond it the traced
#: query's one pass over all rows is cheaper than the tables' per-row sums can be, for a
#: pattern whose tables are summed row by row (sparse parents, many unknown sites).
FEW_ROWS = 8

# id(params) -> (a weak reference to it, its tables)
_KEPT: dict[int, tuple[weakref.ref, Kept]] = {}


@dataclass(frozen=True)
class Kept:
    """The factor tables of one (network, parameters), with what they were read from."""

    net: EffectNetwork
    stamp: tuple
    tables: CompiledNetwork


def tables_for(net: EffectNetwork, params: NetworkParams) -> CompiledNetwork | None:
    """The kept factor tables of ``(net, params)``, built where missing or stale.

    None for a network with a continuous site (its queries are traced every time).
    """
    if any(not s.discrete for s in net.sites):
        return None
    stamp = _stamp(params)
    key = id(params)
    entry = _KEPT.get(key)
    if entry is not None:
        ref, kept = entry
        if ref() is params and kept.net is net and kept.stamp == stamp:
            return kept.tables
    kept = Kept(net, stamp, compile_discrete(net, params))

    def forget(dead: weakref.ref, key: int = key) -> None:
        if key in _KEPT and _KEPT[key][0] is dead:
            del _KEPT[key]

    _KEPT[key] = (weakref.ref(params, forget), kept)
    return kept.tables


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
