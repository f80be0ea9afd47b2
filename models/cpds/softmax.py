"""A discrete child of continuous parents: softmax (multinomial logistic) regression.

``logits = weight[P...] @ x + bias[P...]``. There is no closed form: ``m_step`` gives
a start (the counts' log-frequencies with zero slopes), and :meth:`SoftmaxCPD.maximise`
finds the optimum of the penalised log-likelihood::

    sum_i w_i log softmax(W[g_i] x_i + b[g_i])[y_i]  -  l2 / 2 |W|^2

(weights ``w_i``, 1 for plain rows, a responsibility in an EM step) by Newton's method:
each parent configuration ``g`` is its own multinomial logistic regression, all of them
solved at once, with the exact gradient and Hessian and a backtracking line search on the
objective, so the iteration converges from any start and quadratically near the
optimum. The slopes carry the L2 prior (precision ``l2``); the offsets are free, and the
likelihood does not change when one number is added to every class's offset: Newton
steps leave that sum as the start has it (so does any gradient method), which fixes the
offsets that the likelihood leaves free.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import pyro.distributions as dist
import torch
from effect_networks.models.cpds.base import CPD
from effect_networks.models.cpds.table import Counts, counts, normalised
from effect_networks.models.dtype import DTYPE
from pyro.ops.indexing import Vindex


@dataclass(frozen=True)
class SoftmaxParams:
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
    params_type = SoftmaxParams
    discrete = True
    closed_form = False

    @classmethod
    def refuses(cls, discrete: bool, width: int) -> str | None:
        """A softmax needs continuous parents (:meth:`~models.CPD.refuses`)."""
        if not width:
            return "a softmax needs continuous parents (use 'table')"
        return super().refuses(discrete, width)

    def shapes(self) -> dict[str, tuple[int, ...]]:
        """The shape of every tensor of a :class:`SoftmaxParams` (:meth:`~models.CPD.shapes`)."""
        card, k = self.card, self.size
        return {"weight": (*card, k, self.width), "bias": (*card, k), "n": card}

    def n_free(self, reachable: torch.Tensor | None = None) -> int:
        """``(K - 1) (p + 1)`` per parent configuration.

        ``K`` slopes of ``p`` inputs and ``K`` offsets, less one class's (adding one vector to every
        class's logits leaves the softmax as it is).
        """
        return int(self.configurations(reachable).sum()) * (self.size - 1) * (self.width + 1)

    def initialize(
        self, generator: torch.Generator | None = None, unseen: float = 0.0
    ) -> SoftmaxParams:
        """Zero slopes and offsets, or random parameters (:meth:`~models.CPD.initialize`)."""
        shapes = self.shapes()
        if generator is None:
            return SoftmaxParams(
                *(torch.zeros(shapes[k], dtype=DTYPE) for k in ("weight", "bias", "n"))
            )
        n = self.counts_reached(generator, unseen)
        return SoftmaxParams(
            self.noise(generator, shapes["weight"]), self.noise(generator, shapes["bias"]), n
        )

    def distribution(self, params: SoftmaxParams, index, x, cache) -> dist.Categorical:
        """The site's categorical given its parents (:meth:`~models.CPD.distribution`)."""
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

    def statistics(self, index: torch.Tensor, x, y: torch.Tensor, weights=None) -> Counts:
        """Counts of the site's states per parent configuration (:meth:`~models.CPD.statistics`)."""
        return counts(index, y, self.card, self.size, weights)

    def m_step(self, stats: Counts, alpha: float, min_variance: float) -> SoftmaxParams:
        """Newton's method on the penalised likelihood (:meth:`~models.CPD.m_step`)."""
        # the table's log-frequencies with zero slopes
        start = normalised(stats.counts, max(alpha, 1e-3))
        weight = torch.zeros(self.shapes()["weight"], dtype=DTYPE)
        return SoftmaxParams(weight, start.probs.log(), start.n)

    def maximise(
        self,
        index: torch.Tensor,
        x: torch.Tensor,
        y: torch.Tensor,
        start: SoftmaxParams,
        *,
        weights: torch.Tensor | None = None,
        l2: float = 0.01,
        steps: int = 100,
    ) -> SoftmaxFit:
        """The penalised maximum-likelihood weights and offsets (see the module).

        ``index`` ``(n,)`` each row's flattened parent configuration, ``x`` ``(n, p)`` the
        continuous parents, ``y`` ``(n,)`` the states, ``weights`` ``(n,)`` (default 1),
        ``start`` the first iterate (its counts ``n`` are kept), ``steps`` the most Newton
        iterations. A configuration has converged when every component of its gradient
        is below ``GRADIENT_TOLERANCE`` times its summed row scale ``sum_i w_i
        max(1, |x_i|_inf)`` (rounding of the sums themselves is about 1e-16 of it).
        """
        k, p = self.size, self.width
        groups = math.prod(self.card)
        n = y.shape[0]
        z = torch.cat([x.to(DTYPE), torch.ones(n, 1, dtype=DTYPE)], -1)  # (n, q)
        q = p + 1
        w = torch.ones(n, dtype=DTYPE) if weights is None else weights.to(DTYPE)
        target = torch.nn.functional.one_hot(y, k).to(DTYPE) * w[:, None]  # (n, K)
        theta = torch.cat([start.weight, start.bias[..., None]], -1).reshape(groups, k, q)
        theta = theta.to(DTYPE).clone()
        penalty = torch.full((q,), float(l2), dtype=DTYPE)
        penalty[-1] = 0.0  # the offsets are free
        # Directions the objective is flat along: every class's offset raised by one
        # number, and without a prior every class's slope on one input. A unit curvature
        # there (the gradient has no component along them) leaves their step at zero.
        flat = torch.ones(q, dtype=DTYPE) if l2 == 0 else torch.zeros(q, dtype=DTYPE)
        flat[-1] = 1.0
        gauge = torch.kron(torch.full((k, k), 1.0 / k, dtype=DTYPE), torch.diag(flat))
        ridge = torch.kron(torch.eye(k, dtype=DTYPE), torch.diag(penalty))
        scale = torch.zeros(groups, dtype=DTYPE).index_add_(
            0, index, w * z.abs().amax(-1).clamp_min(1.0)
        )
        tolerance = GRADIENT_TOLERANCE * scale.clamp_min(1.0)
        chunk = max(1, CHUNK_ELEMENTS // (k * k * q * q))

        def objective(theta, rows):
            """The objective and the rows' log-probabilities, per configuration.

            Over ``rows`` (index, z, target).
            """
            i, zs, t = rows
            logp = torch.einsum("nkq,nq->nk", theta[i], zs).log_softmax(-1)  # (m, K)
            f = torch.zeros(groups, dtype=DTYPE).index_add_(0, i, -(t * logp).sum(-1))
            return f + 0.5 * (penalty * theta.square()).sum((1, 2)), logp

        every = (index, z, target, w)
        f = objective(theta, every[:3])[0]
        curve = [float(f.sum())]
        active = torch.ones(groups, dtype=torch.bool)
        stalled = torch.zeros(groups, dtype=torch.bool)
        unchecked = torch.zeros(groups, dtype=torch.bool)  # took a full step unchecked
        relative = torch.zeros(groups, dtype=DTYPE)
        rows = every
        iterations = 0
        logp = None  # the rows' log-probabilities, when the line search left them current
        while True:
            # only the rows of configurations still moving
            keep = active[rows[0]]
            if not bool(keep.all()):
                rows = tuple(r[keep] for r in rows)
                logp = logp[keep] if logp is not None else None
            i, zs, t, ws = rows
            if logp is None:
                logp = objective(theta, rows[:3])[1]
            prob = logp.exp()
            residual = ws[:, None] * prob - t  # (m, K)
            grad = torch.zeros(groups, k, q, dtype=DTYPE).index_add_(
                0, i, residual[:, :, None] * zs[:, None, :]
            )
            grad += penalty * theta
            now = grad.abs().amax((1, 2)) / tolerance * GRADIENT_TOLERANCE
            # a full step taken without the line search that did not halve the gradient:
            # the rounding floor
            stuck = unchecked & (now > 0.5 * relative)
            stalled |= stuck
            relative = torch.where(active, now, relative)
            active &= (now > GRADIENT_TOLERANCE) & ~stuck
            if not bool(active.any()) or iterations == steps:
                break
            iterations += 1
            keep = active[i]
            if not bool(keep.all()):
                rows = tuple(r[keep] for r in rows)
                i, zs, t, ws = rows
                prob = prob[keep]
            # per row (diag(p) - p p^T) (x) z z^T, summed per configuration: the rows'
            # class part and input part side by side, flat (one contiguous sum)
            curvature = ws[:, None, None] * (
                torch.diag_embed(prob) - prob[:, :, None] * prob[:, None, :]
            )
            curvature = curvature.reshape(-1, k * k)
            inputs = (zs[:, :, None] * zs[:, None, :]).reshape(-1, q * q)
            hessian = torch.zeros(groups, k * k * q * q, dtype=DTYPE)
            for c in range(0, i.shape[0], chunk):
                terms = curvature[c : c + chunk, :, None] * inputs[c : c + chunk, None, :]
                hessian.index_add_(0, i[c : c + chunk], terms.reshape(terms.shape[0], -1))
            hessian = hessian[active].reshape(-1, k, k, q, q).transpose(2, 3)
            hessian = hessian.reshape(-1, k * q, k * q) + ridge + gauge
            g = grad[active].reshape(-1, k * q)
            step = -_solve(hessian, g)  # (A, K q)
            slope = (step * g).sum(-1)  # < 0: a descent direction
            # half the Newton decrement -slope predicts the gain left: below the
            # objective's rounding no line search can see it, and Newton's full step is
            # safe there (the quadratic region): taken unchecked
            near = -slope <= 1e-15 * f[active].abs().clamp_min(1.0)
            pending = ~near
            length = torch.ones_like(slope)
            trial = theta.clone()
            for _ in range(60):  # halvings: 60 reach 1e-18 of a step
                trial[active] = theta[active] + (length[:, None] * step).reshape(-1, k, q)
                f_new, logp = objective(trial, rows[:3])
                ok = f_new[active] <= f[active] + 1e-4 * length * slope
                pending &= ~ok
                if not bool(pending.any()):
                    break
                length = torch.where(pending, 0.5 * length, length)
            moved = active.clone()
            moved[active] = ~pending  # no decrease at any step length: rounding level
            if bool(pending.any()):
                logp = None  # some configurations keep their iterate: not the trial's
            theta[moved] = trial[moved]
            f[moved] = f_new[moved]
            unchecked = active.clone()
            unchecked[active] = near
            stalled |= active & ~moved
            active &= moved
            curve.append(float(f.sum()))
        # a configuration whose line search found no decrease is at the rounding floor
        # of its objective: converged if its gradient is near the tolerance
        floor = torch.where(stalled, STALLED_TOLERANCE, GRADIENT_TOLERANCE)
        converged = bool((relative <= floor).all())
        weight, bias = theta.reshape(*self.card, k, q).split([p, 1], -1)
        params = SoftmaxParams(weight.contiguous(), bias[..., 0].contiguous(), start.n)
        return SoftmaxFit(params, tuple(curve), converged, float(relative.max()))

    def free(self, params: SoftmaxParams) -> dict[str, torch.Tensor]:
        """Slopes and offsets, unconstrained as they are (:meth:`~models.CPD.free`)."""
        return {"weight": params.weight, "bias": params.bias}

    def bound(self, free: dict[str, torch.Tensor], params: SoftmaxParams) -> SoftmaxParams:
        """The parameters ``free`` stands for (:meth:`~models.CPD.bound`)."""
        return SoftmaxParams(free["weight"], free["bias"], params.n)

    def penalised(self, free: dict[str, torch.Tensor]) -> list[torch.Tensor]:
        """The slopes carry the L2 prior (:meth:`~models.CPD.penalised`)."""
        return [free["weight"]]


#: A configuration's Newton iteration stops when its gradient is below this fraction of
#: its summed row scale (see :meth:`SoftmaxCPD.maximise`).
GRADIENT_TOLERANCE = 1e-12
#: ... and is taken as converged below this one when no step length decreases its
#: objective (the objective's own rounding)
STALLED_TOLERANCE = 1e-8

#: Elements of one chunk of per-row Hessian terms (16 MiB of float64).
CHUNK_ELEMENTS = 1 << 21


@dataclass(frozen=True)
class SoftmaxFit:
    """What :meth:`SoftmaxCPD.maximise` returns.

    The parameters; the objective (the penalised negative log-likelihood, summed over rows) at the
    start and after each Newton iteration; whether every configuration converged; and the largest
    gradient component relative to its configuration's row scale at the end.
    """

    params: SoftmaxParams
    objectives: tuple[float, ...]
    converged: bool
    relative_gradient: float


def _solve(matrix: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
    """``matrix^-1 rhs`` for a batch of symmetric positive (semi)definite matrices.

    A Cholesky factor, with a jitter on the diagonal where the curvature vanishes (classes the data
    separate, inputs that do not vary).
    """
    jitter = 0.0
    size = matrix.diagonal(dim1=-2, dim2=-1).abs().mean(-1, keepdim=True).clamp_min(1e-300)
    eye = torch.eye(matrix.shape[-1], dtype=matrix.dtype)
    for _ in range(12):
        factor, info = torch.linalg.cholesky_ex(matrix + (jitter * size)[..., None] * eye)
        if not bool(info.any()):
            return torch.cholesky_solve(rhs[..., None], factor)[..., 0]
        jitter = 1e-12 if jitter == 0.0 else jitter * 100
    return torch.linalg.lstsq(matrix, rhs[..., None]).solution[..., 0]
