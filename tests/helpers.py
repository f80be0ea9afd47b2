"""Random networks and parameters for tests, built without the fitting code."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import torch

from models import (
    Continuous,
    Discrete,
    EffectNetwork,
    LinearGaussian,
    NetworkParams,
    Softmax,
    Table,
)
from models.declaration import DTYPE
from models.params import expected_shapes


def random_params(net: EffectNetwork, seed: int, *, zero_n: float = 0.0) -> NetworkParams:
    """Random CPDs of the right shapes: Dirichlet tables, random linear Gaussians."""
    g = torch.Generator().manual_seed(seed)
    cpds = {}
    for site, (kind, shapes) in expected_shapes(net).items():
        n = (torch.rand(shapes["n"], generator=g, dtype=DTYPE) >= zero_n).to(DTYPE) * 5
        if kind == "Table":
            logits = 2 * torch.randn(shapes["probs"], generator=g, dtype=DTYPE)
            cpds[site] = Table(logits.softmax(-1), n)
        elif kind == "LinearGaussian":
            d = shapes["bias"][-1]
            a = torch.randn(shapes["scale_tril"], generator=g, dtype=DTYPE)
            cov = a @ a.mT / d + 0.3 * torch.eye(d, dtype=DTYPE)
            cpds[site] = LinearGaussian(
                torch.randn(shapes["weight"], generator=g, dtype=DTYPE),
                torch.randn(shapes["bias"], generator=g, dtype=DTYPE),
                torch.linalg.cholesky(cov),
                n,
            )
        else:
            cpds[site] = Softmax(
                torch.randn(shapes["weight"], generator=g, dtype=DTYPE),
                torch.randn(shapes["bias"], generator=g, dtype=DTYPE),
                n,
            )
    for p in net.parameters:  # actions not using a parameter sit on cell 0 (the model's rule)
        t = cpds[f"cluster.{p.name}"]
        fixed = torch.zeros(p.n_clusters, dtype=DTYPE)
        fixed[0] = 1
        cpds[f"cluster.{p.name}"] = Table(
            torch.where(net.uses_parameter(p)[:, None], t.probs, fixed), t.n
        )
    return NetworkParams(cpds, 0.01)


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
