"""Random networks for tests, and a loader for example scripts."""

from __future__ import annotations

import importlib.util
import itertools
from concurrent.futures import Future
from pathlib import Path

from models import Continuous, Discrete, EffectNetwork, random_params

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def load_example(name: str):
    """Import ``examples/<name>.py`` as a module named ``example_<name>`` (no sys.path edit)."""
    spec = importlib.util.spec_from_file_location(f"example_{name}", EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def discrete_network(cards: list[int], n_actions: int) -> EffectNetwork:
    feats = tuple(Discrete(f"f{i}", tuple(range(k))) for i, k in enumerate(cards))
    return EffectNetwork(feats, tuple(f"a{i}" for i in range(n_actions)))


__all__ = [
    "Continuous",
    "InlineExecutor",
    "brute_joint",
    "discrete_network",
    "load_example",
    "random_params",
]


class InlineExecutor:
    """An executor that runs each task at once, in this process, and counts the tasks."""

    def __init__(self):
        self.submitted = 0

    def submit(self, fn, *args, **kwargs) -> Future:
        self.submitted += 1
        future = Future()
        future.set_result(fn(*args, **kwargs))
        return future


def brute_joint(net, params):
    """p(initial..., action, end...) as a dict over full assignments, from the tables."""
    names = [f.name for f in net.features]
    cards = [f.cardinality for f in net.features]
    joint = {}
    for init in itertools.product(*[range(k) for k in cards]):
        for a in range(len(net.actions)):
            for end in itertools.product(*[range(k) for k in cards]):
                p = float(params["action"].probs[a])
                for name, v in zip(names, init, strict=True):
                    p *= float(params[f"initial.{name}"].probs[v])
                for name, v in zip(names, end, strict=True):
                    p *= float(params[f"end.{name}"].probs[(*init, a, v)])
                joint[(init, a, end)] = p
    return joint
