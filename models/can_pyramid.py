r"""The can-tossing effect network (paper Fig. 2, §IV-A).

All sites discrete::

    initial.config   initial.count          (which cans stand; how many)
          \    \    /    /
           \    action (field)
            v    v    v
        end.config   end.count

``config`` is an object-level feature whose states are the physically possible
configurations (10-bit masks, bit i = can i stands); ``count`` is a meta-feature (it
depends on several objects) with states 0..10. The action is the field the ball passes
through; the angle is chosen by data selection (one network per angle).

This module declares the network and turns arrays into training rows; it generates no
data (that is sim2d's job) and imports nothing from it.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from effect_networks.models.declaration import Discrete, EffectNetwork
from effect_networks.models.evidence import Evidence

N_FIELDS = 195
N_CANS = 10


def can_network(configurations: Sequence[int], n_fields: int = N_FIELDS) -> EffectNetwork:
    """Fig. 2's network over the given configuration masks and ``n_fields`` actions."""
    configurations = tuple(int(c) for c in configurations)
    if len(set(configurations)) != len(configurations):
        raise ValueError("configurations must be distinct masks")
    bad = [c for c in configurations if not 0 <= c < 1 << N_CANS]
    if bad:
        raise ValueError(f"configuration masks must lie in 0..1023, got {bad[:5]}")
    return EffectNetwork(
        (
            Discrete("config", configurations, kind="object"),
            Discrete("count", tuple(range(N_CANS + 1)), kind="meta"),
        ),
        tuple(f"field{f}" for f in range(n_fields)),
    )


def can_rows(
    net: EffectNetwork, start_config: np.ndarray, field: np.ndarray, end_config: np.ndarray
) -> Evidence:
    """Training rows (encoded) from arrays of equal length ``(n,)`` int: masks and field indices.

    Counts are derived from the masks. Raises ``ValueError`` for a mask that is not a
    state of ``net`` (an end configuration no start configuration lists, say).
    """
    start_config = np.asarray(start_config, dtype=np.int64)
    field = np.asarray(field, dtype=np.int64)
    end_config = np.asarray(end_config, dtype=np.int64)
    if not start_config.shape == field.shape == end_config.shape or start_config.ndim != 1:
        raise ValueError(
            f"start_config, field and end_config must be (n,) arrays of one length, got "
            f"{start_config.shape}, {field.shape}, {end_config.shape}"
        )
    return net.encode_indices(
        {
            "initial.config": config_index(net, start_config),
            "initial.count": torch.as_tensor(n_cans(start_config)),
            "action": torch.as_tensor(field),
            "end.config": config_index(net, end_config),
            "end.count": torch.as_tensor(n_cans(end_config)),
        }
    )


def config_index(net: EffectNetwork, masks: np.ndarray) -> torch.Tensor:
    """State indices of configuration masks, ``(n,)`` long; ``ValueError`` on unknown ones."""
    states = np.asarray(net.feature("config").states, dtype=np.int64)
    lookup = np.full(1 << N_CANS, -1, dtype=np.int64)
    lookup[states] = np.arange(len(states))
    masks = np.asarray(masks, dtype=np.int64)
    index = lookup[masks]
    if (index < 0).any():
        raise ValueError(f"configuration {int(masks[index < 0][0])} is not a state of the network")
    return torch.as_tensor(index)


def n_cans(masks: np.ndarray) -> np.ndarray:
    """Number of standing cans in each mask."""
    masks = np.asarray(masks, dtype=np.int64)
    return np.array([bin(int(m)).count("1") for m in masks.reshape(-1)], dtype=np.int64).reshape(
        masks.shape
    )
