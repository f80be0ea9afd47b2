"""Random networks for tests, and a loader for example scripts."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

from models import Continuous, Discrete, EffectNetwork, random_params

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def load_example(name: str):
    """Import ``examples/<name>.py`` as a module (its sibling modules importable too)."""
    if str(EXAMPLES) not in sys.path:
        sys.path.insert(0, str(EXAMPLES))
    return importlib.import_module(name)


def discrete_network(cards: list[int], n_actions: int) -> EffectNetwork:
    feats = tuple(Discrete(f"f{i}", tuple(range(k))) for i, k in enumerate(cards))
    return EffectNetwork(feats, tuple(f"a{i}" for i in range(n_actions)))


__all__ = ["Continuous", "discrete_network", "load_example", "random_params"]
