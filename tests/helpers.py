"""Random networks, executors and shared settings for tests."""

from __future__ import annotations

import errno
import itertools
import os
from concurrent.futures import Future

import torch
from effect_networks.models import Continuous, Discrete, EffectNetwork, Parameter, random_params
from effect_networks.models.cpds import LinearGaussianParams, TableParams
from effect_networks.models.declaration import DTYPE
from effect_networks.models.params import NetworkParams

#: The adaptive-throw experiment's settings of a run in seconds (its tests, test_parallel).
ADAPTIVE_THROW_TINY = {
    "n_train": 400,
    "n_test": 40,
    "bins": (2, 3),
    "noisy_bins": 2,
    "em_steps": (1, 3),
    "budgets": (40, 80),
    "batch": 20,
    "pool": 60,
    "active_seeds": 2,
    "noise_repeats": 2,
    "workers": 1,  # in this process, so that a test can count calls (its test_parallel: 2)
    "progress": False,
}


def discrete_network(cards: list[int], n_actions: int) -> EffectNetwork:
    feats = tuple(Discrete(f"f{i}", tuple(range(k))) for i, k in enumerate(cards))
    return EffectNetwork(feats, tuple(f"a{i}" for i in range(n_actions)))


__all__ = [
    "ADAPTIVE_THROW_TINY",
    "Continuous",
    "InlineExecutor",
    "brute_joint",
    "discrete_network",
    "random_params",
    "spilling_network",
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


def spilling_network() -> tuple[EffectNetwork, NetworkParams]:
    """A push/wait network whose force clusters spill far out of their cells.

    The force (0-10 N, four cells 2.5 N wide) acts on "push" only; its clusters'
    Gaussians have standard deviations of 0.8-1.5 N, so a drawn force often lies in
    another cluster's cell. The pushed position moves by a slope per cluster times the
    force (noise 5 cm); "wait" keeps it (noise 1 cm).
    """
    net = EffectNetwork(
        (Continuous("pos", 1),),
        ("push", "wait"),
        (Parameter("force", 0.0, 10.0, 4, ("push",), "pos"),),
    )

    def t(values):
        return torch.tensor(values, dtype=DTYPE)

    ones = torch.ones
    sd = t([1.0, 1.5, 0.8, 1.2])
    slope = t([0.05, 0.08, 0.1, 0.12])
    weight = torch.zeros(2, 4, 1, 2, dtype=DTYPE)
    weight[:, :, 0, 0] = t([[1.0] * 4, [0.9, 1.0, 1.0, 1.0]])
    weight[0, :, 0, 1] = slope
    bias = t([[[0.02], [-0.1], [0.05], [0.0]], [[0.01], [0.0], [0.0], [0.0]]])
    noise = t([[0.05] * 4, [0.01, 1.0, 1.0, 1.0]])
    cpds = {
        "initial.pos": LinearGaussianParams(
            torch.zeros(1, 0, dtype=DTYPE), t([0.1]), t([[0.5]]), t(1.0)
        ),
        "action": TableParams(t([0.6, 0.4]), t(1.0)),
        "cluster.force": TableParams(
            t([[0.2, 0.3, 0.4, 0.1], [1.0, 0.0, 0.0, 0.0]]), ones(2, dtype=DTYPE)
        ),
        "param.force": LinearGaussianParams(
            torch.zeros(4, 1, 0, dtype=DTYPE),
            t([[1.5], [3.5], [6.5], [8.0]]),
            sd[:, None, None],
            ones(4, dtype=DTYPE),
        ),
        "end.pos": LinearGaussianParams(
            weight, bias, noise[..., None, None], ones(2, 4, dtype=DTYPE)
        ),
    }
    return net, NetworkParams(cpds, 0.01)


class FillingFile:
    """A file whose disk fills on the first write: 100 bytes land, then ``ENOSPC``."""

    def __init__(self, f):
        self.f = f

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.f.close()

    def write(self, data):
        self.f.write(bytes(data)[:100])
        raise OSError(errno.ENOSPC, "No space left on device")

    def __getattr__(self, name):
        return getattr(self.f, name)


def fill_the_disk(monkeypatch) -> None:
    """Every file the code under test opens with ``os.fdopen`` fills its disk."""
    real_fdopen = os.fdopen
    monkeypatch.setattr(os, "fdopen", lambda fd, mode: FillingFile(real_fdopen(fd, mode)))
