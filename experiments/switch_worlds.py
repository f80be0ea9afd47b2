"""Worlds of many switches: the sequence questions' scaling worlds, with their true tables.

``k`` binary features (``off``/``on``), one action ``flip_i`` per feature and ``wait``.
Each end feature's parents are its own initial value, the action and at most one
neighbour's initial value; its table is set from the world's rules, not fitted, so a
question's answer depends on the algorithm alone:

* ``flip_i`` flips feature ``i`` 9 times in 10;
* a feature whose neighbour is ``on`` flips 1 time in 20 under any other action;
* in the coupled world each action also disturbs 3 features drawn once per world
  (flipped 1 time in 10), and feature ``i``'s neighbour is ``i + 1``, so that a goal's
  relevant features are all those from its own onwards. In the sparse world neighbours
  come in pairs (``2j`` and ``2j + 1``).

:func:`switch_world` returns the network, its tables (every configuration marked as
seen, or the ``unseen`` actions' marked as never reached) and the goal the benchmarks
plan for.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import torch
from effect_networks.models import Discrete, EffectNetwork
from effect_networks.models.cpds.table import TableParams
from effect_networks.models.declaration import DTYPE
from effect_networks.models.params import NetworkParams

#: The worlds: ``"sparse"`` (pairs of neighbours, goal on 3 features) and ``"coupled"``
#: (a chain of neighbours, disturbing actions, goal on 8 features).
KINDS = ("sparse", "coupled")
SWITCH = ("off", "on")


@dataclass(frozen=True)
class SwitchWorld:
    """A switch world: its network, true tables, goal and start."""

    net: EffectNetwork
    params: NetworkParams
    goal: dict[str, str]
    start: tuple[str, ...]
    neighbour: dict[int, int]
    disturbs: dict[int, tuple[int, ...]]


def switch_world(
    k: int,
    kind: str = "sparse",
    *,
    seed: int = 0,
    flip: float = 0.9,
    spill: float = 0.05,
    disturb: float = 0.1,
    unseen: tuple[str, ...] = (),
) -> SwitchWorld:
    """A world of ``k`` switches (see the module's rules); ``unseen`` names actions no row logged."""
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    if not isinstance(k, int) or k < (3 if kind == "sparse" else 8):
        raise ValueError(f"a {kind} world needs k >= {3 if kind == 'sparse' else 8}, got {k!r}")
    actions = (*(f"flip_{i}" for i in range(k)), "wait")
    if kind == "sparse":
        neighbour = {i: i ^ 1 for i in range(k) if i ^ 1 < k}
        disturbs: dict[int, tuple[int, ...]] = {}
        goal = {f"f{i}": "on" for i in range(3)}
    else:
        neighbour = {i: i + 1 for i in range(k - 1)}
        rng = np.random.default_rng(seed)
        disturbs = {
            a: tuple(int(j) for j in rng.choice(k, 3, replace=False)) for a in range(len(actions))
        }
        goal = {f"f{i}": "on" for i in range(8)}
    parents = {
        f"end.f{i}": (
            f"initial.f{i}",
            "action",
            *((f"initial.f{neighbour[i]}",) if i in neighbour else ()),
        )
        for i in range(k)
    }
    net = EffectNetwork(
        tuple(Discrete(f"f{i}", SWITCH) for i in range(k)), actions, parents=parents
    )
    never = [actions.index(a) for a in unseen]
    a_count = len(actions)
    cpds = {
        "action": TableParams(
            torch.full((a_count,), 1 / a_count, dtype=DTYPE), torch.ones((), dtype=DTYPE)
        )
    }
    for i in range(k):
        cpds[f"initial.f{i}"] = TableParams(
            torch.full((2,), 0.5, dtype=DTYPE), torch.ones((), dtype=DTYPE)
        )
        order = net.cpd(f"end.f{i}").parents  # the table's axes, in the network's order
        shape = [net.site(q).size for q in order]
        probs = torch.zeros(*shape, 2, dtype=DTYPE)
        n = torch.ones(shape, dtype=DTYPE)
        for config in itertools.product(*(range(m) for m in shape)):
            value = dict(zip(order, config, strict=True))
            own, a = value[f"initial.f{i}"], value["action"]
            p = 0.0
            if a == i:
                p = flip
            elif value.get(f"initial.f{neighbour.get(i)}") == 1:
                p = spill
            if i in disturbs.get(a, ()) and a != i:
                p = p + (1 - p) * disturb
            probs[(*config, 1 - own)] = p
            probs[(*config, own)] = 1 - p
            if a in never:
                n[config] = 0
        cpds[f"end.f{i}"] = TableParams(probs, n)
    params = NetworkParams(cpds, 0.01, net)
    return SwitchWorld(net, params, goal, ("off",) * k, neighbour, disturbs)
