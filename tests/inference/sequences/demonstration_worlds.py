"""Small networks the demonstration tests read (``explain`` and its dense twin)."""

from __future__ import annotations

from dataclasses import replace

import torch
from effect_networks.models import Discrete, EffectNetwork
from effect_networks.models.cpds import TableParams
from effect_networks.models.declaration import DTYPE

#: a world of two state features and a discrete outcome that depends on the door's end
OUTCOME_NET = EffectNetwork(
    features=(
        Discrete("door", ("shut", "open", "locked")),
        Discrete("light", ("off", "on")),
        Discrete("creak", (False, True), initial=False),
    ),
    actions=("push", "flip", "wait"),
    parents={"end.creak": ("end.door", "action")},
)
PLAIN_NET = EffectNetwork(
    features=(Discrete("a", (0, 1)), Discrete("b", ("x", "y", "z"))),
    actions=("go", "stay"),
)


def uniform_prior(net, params):
    """``params`` with a uniform action table."""
    a = len(net.actions)
    cpds = dict(params.cpds)
    cpds["action"] = TableParams(torch.full((a,), 1 / a, dtype=DTYPE), params["action"].n)
    return replace(params, cpds=cpds)


def flip_world(k: int) -> EffectNetwork:
    """``k`` binary features, ``flip_i`` and ``wait``; parents: own, action, right neighbour."""
    features = tuple(Discrete(f"f{i}", (False, True)) for i in range(k))
    parents = {
        f"end.f{i}": (f"initial.f{i}", "action", *((f"initial.f{i + 1}",) if i + 1 < k else ()))
        for i in range(k)
    }
    actions = (*(f"flip_{i}" for i in range(k)), "wait")
    return EffectNetwork(features=features, actions=actions, parents=parents)
