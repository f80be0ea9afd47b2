"""A discrete child of continuous parents: softmax (multinomial logistic) regression.

``logits = weight[P...] @ x + bias[P...]``. There is no closed form: ``m_step`` gives
the gradient route's start (the counts' log-frequencies with zero slopes), and the
slopes carry the gradient route's L2 prior (:func:`inference.fit_gradient`).
"""

from __future__ import annotations

from dataclasses import dataclass

import pyro.distributions as dist
import torch
from pyro.ops.indexing import Vindex

from models.cpds.base import CPD
from models.cpds.table import Counts, counts, normalised
from models.evidence import DTYPE


@dataclass(frozen=True)
class Softmax:
    """Discrete child of continuous parents: ``logits = weight @ x_parents + bias``.

    ``weight`` ``(P..., K, p)``, ``bias`` ``(P..., K)``, ``n`` ``(P...)``.
    """

    weight: torch.Tensor
    bias: torch.Tensor
    n: torch.Tensor


@dataclass(frozen=True)
class SoftmaxCPD(CPD):
    """Per discrete-parent configuration a linear map of the continuous parents to logits."""

    name = "softmax"
    params_type = Softmax
    discrete = True
    closed_form = False

    @classmethod
    def refuses(cls, discrete: bool, width: int) -> str | None:
        if not width:
            return "a softmax needs continuous parents (use 'table')"
        return super().refuses(discrete, width)

    def shapes(self) -> dict[str, tuple[int, ...]]:
        card, k = self.card, self.size
        return {"weight": (*card, k, self.width), "bias": (*card, k), "n": card}

    def initialize(self, generator: torch.Generator | None = None, unseen: float = 0.0) -> Softmax:
        shapes = self.shapes()
        if generator is None:
            return Softmax(*(torch.zeros(shapes[k], dtype=DTYPE) for k in ("weight", "bias", "n")))
        n = self.counts_reached(generator, unseen)
        return Softmax(
            self.noise(generator, shapes["weight"]), self.noise(generator, shapes["bias"]), n
        )

    def distribution(self, params: Softmax, index, x, cache) -> dist.Categorical:
        # The logits in log space per configuration: slopes and offsets taken relative to
        # their mean over the states (the same softmax), so that a slope all states share
        # cancels before it meets a large input, then shifted by their maximum, so that
        # the normalisation works on numbers near zero at any magnitude of the inputs.
        weight = params.weight - params.weight.mean(-2, keepdim=True)
        bias = params.bias - params.bias.mean(-1, keepdim=True)
        weight = Vindex(weight)[(*index, slice(None), slice(None))]
        logits = (weight @ x.unsqueeze(-1)).squeeze(-1) + Vindex(bias)[(*index, slice(None))]
        top = logits.detach().amax(-1, keepdim=True)
        return dist.Categorical(logits=logits - torch.where(torch.isfinite(top), top, 0.0))

    def statistics(self, index: torch.Tensor, x, y: torch.Tensor) -> Counts:
        return counts(index, y, self.card, self.size)

    def m_step(self, stats: Counts, alpha: float, min_variance: float) -> Softmax:
        # the table's log-frequencies with zero slopes
        start = normalised(stats.counts, max(alpha, 1e-3))
        weight = torch.zeros(self.shapes()["weight"], dtype=DTYPE)
        return Softmax(weight, start.probs.log(), start.n)

    def free(self, params: Softmax) -> dict[str, torch.Tensor]:
        return {"weight": params.weight, "bias": params.bias}

    def bound(self, free: dict[str, torch.Tensor], params: Softmax) -> Softmax:
        return Softmax(free["weight"], free["bias"], params.n)

    def penalised(self, free: dict[str, torch.Tensor]) -> list[torch.Tensor]:
        return [free["weight"]]
