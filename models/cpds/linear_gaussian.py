"""A continuous child: the conditional linear Gaussian.

Per discrete-parent configuration a linear map of the continuous parents, an offset and
a full covariance: ``y ~ N(weight[P...] @ x + bias[P...], scale_tril scale_tril^T)``.
The maximum-likelihood estimate is per-configuration least squares of ``y`` on
``[x, 1]`` with the residual covariance, computed from sums that merge by addition
(:class:`Moments`). Pseudo-count policy (``alpha``): a configuration gets ``alpha``
pseudo-rows of the pooled statistics of its site, so an unseen one is the pooled fit
and a rarely seen one is shrunk towards it; a covariance's eigenvalues are floored at
``min_variance``, so a configuration with fewer rows than dimensions stays positive
definite and one with more keeps its estimate.

A mean ``W x + b`` whose plain float64 sum may round off against the noise (inputs far
from the origin) is kept as a pair of float64 numbers (:class:`PairMeanNormal`,
:func:`models.gaussian.affine_pair`): a value near it keeps its residual's digits.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from functools import cached_property

import pyro.distributions as dist
import torch
from effect_networks.models.cpds.base import CPD
from effect_networks.models.dtype import DTYPE
from effect_networks.models.gaussian import affine_pair, mahalanobis, sum_rounds_off
from pyro.ops.indexing import Vindex


@dataclass(frozen=True)
class LinearGaussianParams:
    """Conditional linear Gaussian: ``x_child ~ N(weight @ x_parents + bias, scale_tril @ scale_tril.T)``.

    ``weight`` ``(P..., d, p)``, ``bias`` ``(P..., d)``, ``scale_tril`` ``(P..., d, d)``,
    ``n`` ``(P...)``. ``p`` may be 0 (no continuous parents).
    """

    weight: torch.Tensor
    bias: torch.Tensor
    scale_tril: torch.Tensor
    n: torch.Tensor

    @property
    def covariance(self) -> torch.Tensor:
        """``(P..., d, d)``: the noise covariance, ``scale_tril scale_tril^T``."""
        return self.scale_tril @ self.scale_tril.mT

    @cached_property  # read by every traced density of continuous inputs: computed once
    def extremes(self) -> tuple[float, float, float]:
        """The largest ``|weight|`` and ``|bias|``, and the smallest noise scale.

        The noise scale is the square root of the smallest eigenvalue of any configuration's
        covariance.
        """
        if not self.bias.numel():
            return 0.0, 0.0, math.inf
        smallest = torch.linalg.eigvalsh(self.covariance).min().clamp_min(0.0).sqrt()
        weight = self.weight.abs().max() if self.weight.numel() else torch.zeros(())
        return tuple(torch.stack([weight, self.bias.abs().max(), smallest]).tolist())


@dataclass(frozen=True)
class Moments:
    """A linear Gaussian's sums per parent configuration ``G`` (flattened ``P...``).

    ``zz`` ``(G, q, q)``, ``zy`` ``(G, q, d)``, ``yy`` ``(G, d, d)``, rows ``n`` ``(G,)``, with ``z
    = [x, 1]``.
    """

    zz: torch.Tensor
    zy: torch.Tensor
    yy: torch.Tensor
    n: torch.Tensor

    def __add__(self, other: Moments) -> Moments:
        return Moments(*(getattr(self, f.name) + getattr(other, f.name) for f in fields(self)))

    def add_(self, other: Moments) -> None:
        """Add ``other``'s sums to these, in place."""
        for f in fields(self):
            getattr(self, f.name).add_(getattr(other, f.name))


@dataclass(frozen=True)
class NormalInverseWishart:
    """A conjugate prior on a linear Gaussian, the same in every parent configuration.

    With ``B = [W, b]^T`` ``(q, d)`` the coefficients of ``z = [x, 1]``:
    ``Sigma ~ InverseWishart(scale, dof)`` and, given ``Sigma``, ``B`` matrix normal with
    mean 0, row precision ``precision * I_q`` and column covariance ``Sigma`` (each
    coefficient row ``~ N(0, Sigma / precision)``). The fit is the posterior's joint mode
    (MAP), in closed form per configuration from the sums ``S_zz``, ``S_zy``, ``S_yy``
    and ``n`` (:class:`Moments`)::

        B     = (S_zz + precision I)^-1 S_zy
        Sigma = (scale + S_yy - B^T (S_zz + precision I) B) / (n + dof + d + 1 + q)

    ``q`` counts the coefficients the structure leaves free (a weight fixed at zero has
    no prior). A configuration no row reached gets ``B = 0`` and
    ``Sigma = scale / (dof + d + 1 + q)``. ``precision`` and ``dof`` are numbers
    ``>= 0``; ``scale`` a number (times the identity) or a ``(d, d)`` symmetric positive
    semi-definite matrix. The covariance floor ``min_variance`` applies as without a
    prior. ``precision`` pulls the offset towards 0 as well as the weights: centre the
    data, or keep ``precision`` small against ``n``, where the offset is far from 0.
    """

    precision: float = 1.0
    dof: float = 0.0
    scale: object = 0.0

    def scale_matrix(self, site: str, d: int) -> torch.Tensor:
        """``scale`` as a ``(d, d)`` float64 matrix, checked; a ``ValueError`` names ``site``."""
        for name in ("precision", "dof"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(
                    f"site {site!r}: the prior's {name} must be a number, got {value!r}"
                )
            if not math.isfinite(value) or value < 0:
                raise ValueError(
                    f"site {site!r}: the prior's {name} must be finite and >= 0, got {value!r}"
                )
        scale = torch.as_tensor(self.scale, dtype=DTYPE)
        if scale.dim() == 0:
            scale = scale * torch.eye(d, dtype=DTYPE)
        if tuple(scale.shape) != (d, d):
            raise ValueError(
                f"site {site!r}: the prior's scale has shape {tuple(scale.shape)}, expected a "
                f"number or ({d}, {d})"
            )
        if (
            not bool(scale.isfinite().all())
            or not torch.allclose(scale, scale.mT, rtol=1e-12, atol=0)
            or float(torch.linalg.eigvalsh(scale)[0]) < -1e-12 * float(scale.abs().max())
        ):
            raise ValueError(
                f"site {site!r}: the prior's scale must be a finite, symmetric positive "
                f"semi-definite matrix, got {scale.tolist()}"
            )
        return scale


_LOWER_CHOLESKY = dist.transforms.LowerCholeskyTransform()


@dataclass(frozen=True)
class LinearGaussianCPD(CPD):
    """A conditional linear Gaussian.

    ``zero_weights`` ``(G, p)`` bool, or ``None``: weights fixed at zero per flattened
    configuration by the structure (an action that does not use a parameter ignores
    it); the least squares runs without those columns there.
    """

    zero_weights: torch.Tensor | None = field(default=None, compare=False, repr=False)

    name = "linear_gaussian"
    params_type = LinearGaussianParams
    discrete = False

    def shapes(self) -> dict[str, tuple[int, ...]]:
        """The shape of every tensor of the kind's parameters (:meth:`~models.CPD.shapes`)."""
        card, d = self.card, self.size
        return {
            "weight": (*card, d, self.width),
            "bias": (*card, d),
            "scale_tril": (*card, d, d),
            "n": card,
        }

    def n_free(self, reachable: torch.Tensor | None = None) -> int:
        """The number of free parameters per parent configuration.

        ``d p`` weights (less those ``zero_weights`` fixes), ``d`` offsets and ``d (d + 1) / 2`` for
        the full covariance.
        """
        d = self.size
        configs = self.configurations(reachable).reshape(-1)
        per_config = d * self.width + d + d * (d + 1) // 2
        fixed = 0
        if self.zero_weights is not None:
            fixed = d * int(self.zero_weights[configs].sum())
        return int(configs.sum()) * per_config - fixed

    def initialize(
        self, generator: torch.Generator | None = None, unseen: float = 0.0
    ) -> LinearGaussianParams:
        """Zero weights and unit noise, or random parameters (:meth:`~models.CPD.initialize`)."""
        shapes, d = self.shapes(), self.size
        if generator is None:
            eye = torch.eye(d, dtype=DTYPE).expand(shapes["scale_tril"]).clone()
            zeros = (torch.zeros(shapes[k], dtype=DTYPE) for k in ("weight", "bias"))
            return LinearGaussianParams(*zeros, eye, torch.zeros(self.card, dtype=DTYPE))
        n = self.counts_reached(generator, unseen)
        a = self.noise(generator, shapes["scale_tril"])
        cov = a @ a.mT / d + 0.3 * torch.eye(d, dtype=DTYPE)
        weight = self.noise(generator, shapes["weight"])
        bias = self.noise(generator, shapes["bias"])
        return LinearGaussianParams(weight, bias, torch.linalg.cholesky(cov), n)

    def loc_tril(
        self, params: LinearGaussianParams, index, x: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The mean ``(..., d)`` and Cholesky factor ``(..., d, d)`` given the parents."""
        index = _rows_collapsed(index) if index else index
        loc, tril = self._bias_tril(params, index)
        if x is not None:
            loc = loc + (self._weight(params, index) @ x.unsqueeze(-1)).squeeze(-1)
        return loc, tril

    def distribution(
        self, params: LinearGaussianParams, index, x, cache
    ) -> dist.MultivariateNormal:
        """The site's Gaussian given its parents (:meth:`~models.CPD.distribution`)."""
        return self.gaussian(params, index, x)

    def gaussian(
        self, params: LinearGaussianParams, index, x: torch.Tensor | None
    ) -> dist.MultivariateNormal:
        """The site's Gaussian given the parents.

        Its mean is kept as a pair (:class:`PairMeanNormal`) where the plain sum may round off
        against the noise.
        """
        index = _rows_collapsed(index) if index else index
        loc, tril = self._bias_tril(params, index)
        if x is None:
            return dist.MultivariateNormal(loc, scale_tril=tril)
        weight = self._weight(params, index)
        if _mean_rounds_off(params, x):
            # the mean as a pair: a value near a large mean keeps its residual's digits
            loc, low = affine_pair(weight, x, loc)
            return PairMeanNormal(loc, tril, low)
        return dist.MultivariateNormal(
            loc + (weight @ x.unsqueeze(-1)).squeeze(-1), scale_tril=tril
        )

    @staticmethod
    def _bias_tril(params: LinearGaussianParams, index) -> tuple[torch.Tensor, torch.Tensor]:
        if not index:
            return params.bias, params.scale_tril
        loc = Vindex(params.bias)[(*index, slice(None))]
        return loc, Vindex(params.scale_tril)[(*index, slice(None), slice(None))]

    @staticmethod
    def _weight(params: LinearGaussianParams, index) -> torch.Tensor:
        return Vindex(params.weight)[(*index, slice(None), slice(None))]

    def statistics(
        self, index: torch.Tensor, x: torch.Tensor | None, y: torch.Tensor, weights=None
    ) -> Moments:
        """The rows' :class:`Moments` per parent configuration (:meth:`~models.CPD.statistics`)."""
        groups = math.prod(self.card)
        n_rows, d = y.shape
        ones = torch.ones(n_rows, 1, dtype=DTYPE)
        z = torch.cat([x, ones], -1) if x is not None else ones
        q = z.shape[-1]
        weighted = z if weights is None else z * weights.to(DTYPE)[:, None]
        zz = torch.zeros(groups, q, q, dtype=DTYPE).index_add_(
            0, index, weighted[:, :, None] * z[:, None, :]
        )
        zy = torch.zeros(groups, q, d, dtype=DTYPE).index_add_(
            0, index, weighted[:, :, None] * y[:, None, :]
        )
        yw = y if weights is None else y * weights.to(DTYPE)[:, None]
        yy = torch.zeros(groups, d, d, dtype=DTYPE).index_add_(
            0, index, yw[:, :, None] * y[:, None, :]
        )
        if not all(bool(t.isfinite().all()) for t in (zz, zy, yy)):
            raise ValueError(
                f"site {self.site!r}: the fit's second moments overflow float64; rescale the data"
            )
        rows = torch.bincount(index, weights=weighted[:, -1], minlength=groups).to(DTYPE)
        return Moments(zz, zy, yy, rows)

    def m_step(
        self, stats: Moments, alpha: float | NormalInverseWishart, min_variance: float
    ) -> LinearGaussianParams:
        """Per-configuration least squares of y on [x, 1] with pooled pseudo-rows.

        ``alpha`` a :class:`NormalInverseWishart` instead of a pseudo-count: the
        posterior's mode under that prior (:meth:`posterior_mode`).
        """
        if isinstance(alpha, NormalInverseWishart):
            return self.posterior_mode(stats, alpha, min_variance)
        s, card, site = stats, self.card, self.site
        szz, szy, syy, n = s.zz, s.zy, s.yy, s.n
        groups, q, d = szy.shape
        n_rows = float(n.sum())
        if n_rows:
            # alpha pseudo-rows of the pooled statistics (an unseen configuration = the pooled fit)
            w = alpha / n_rows
            szz, szy, syy = szz + w * szz.sum(0), szy + w * szy.sum(0), syy + w * syy.sum(0)
        if not all(bool(t.isfinite().all()) for t in (szz, szy, syy)):
            raise ValueError(
                f"site {site!r}: the fit's second moments overflow float64; rescale the data"
            )
        zero_weights = self.zero_weights
        if zero_weights is not None and bool(zero_weights.any()):
            drop = torch.cat([zero_weights, torch.zeros(groups, 1, dtype=torch.bool)], -1)
            keep = (~drop).to(DTYPE)
            szz = szz * keep[:, :, None] * keep[:, None, :] + torch.diag_embed(drop.to(DTYPE))
            szy = szy * keep[:, :, None]
        total = n + (alpha if n_rows else 0.0)
        unseen = total == 0
        if unseen.any():  # alpha == 0: fall back on the pooled fit all the same
            szz, szy, syy, total = szz.clone(), szy.clone(), syy.clone(), total.clone()
            szz[unseen], szy[unseen], syy[unseen], total[unseen] = (
                s.zz.sum(0),
                s.zy.sum(0),
                s.yy.sum(0),
                n_rows,
            )
        # a ridge only where the inputs are (nearly) collinear: judged on the correlation
        # form, so that a well-posed configuration is plain least squares (a ridge there
        # moves the solution by its share of the smallest eigenvalue: 1e-6 seen)
        diagonal = szz.diagonal(dim1=-2, dim2=-1)
        scale = diagonal.clamp_min(1e-300).rsqrt()
        smallest = torch.linalg.eigvalsh(szz * scale[:, :, None] * scale[:, None, :])[:, 0]
        ridge = 1e-10 * diagonal.mean(-1).clamp_min(1e-12)
        ridge = torch.where(smallest > 1e-8, 0.0, ridge)
        beta = torch.linalg.solve(szz + ridge[:, None, None] * torch.eye(q, dtype=DTYPE), szy)
        resid = syy - szy.mT @ beta - beta.mT @ szy + beta.mT @ szz @ beta
        cov = resid / total.clamp_min(1e-300)[:, None, None]
        cov = floor_variance(0.5 * (cov + cov.mT), min_variance)
        tril = safe_cholesky(cov, site)
        return LinearGaussianParams(
            beta[:, : q - 1, :].mT.reshape(*card, d, q - 1),
            beta[:, q - 1, :].reshape(*card, d),
            tril.reshape(*card, d, d),
            n.reshape(card),
        )

    def posterior_mode(
        self, stats: Moments, prior: NormalInverseWishart, min_variance: float
    ) -> LinearGaussianParams:
        """The joint mode of the coefficients and covariance (:class:`NormalInverseWishart`)."""
        szz, szy, syy, n = stats.zz, stats.zy, stats.yy, stats.n
        groups, q, d = szy.shape
        scale = prior.scale_matrix(self.site, d)
        eye = torch.eye(q, dtype=DTYPE)
        free = torch.full((groups,), float(q), dtype=DTYPE)
        precision = szz + prior.precision * eye
        zero_weights = self.zero_weights
        if zero_weights is not None and bool(zero_weights.any()):
            drop = torch.cat([zero_weights, torch.zeros(groups, 1, dtype=torch.bool)], -1)
            keep = (~drop).to(DTYPE)
            precision = precision * keep[:, :, None] * keep[:, None, :]
            precision = precision + torch.diag_embed(drop.to(DTYPE))
            szy = szy * keep[:, :, None]
            free = free - drop.sum(-1).to(DTYPE)
        if not all(bool(t.isfinite().all()) for t in (precision, szy, syy)):
            raise ValueError(
                f"site {self.site!r}: the fit's second moments overflow float64; rescale the data"
            )
        # a ridge only where the prior leaves the inputs (nearly) collinear: precision 0
        diagonal = precision.diagonal(dim1=-2, dim2=-1)
        unit = diagonal.clamp_min(1e-300).rsqrt()
        smallest = torch.linalg.eigvalsh(precision * unit[:, :, None] * unit[:, None, :])[:, 0]
        ridge = torch.where(smallest > 1e-8, 0.0, 1e-10 * diagonal.mean(-1).clamp_min(1e-12))
        beta = torch.linalg.solve(precision + ridge[:, None, None] * eye, szy)
        resid = syy - szy.mT @ beta - beta.mT @ szy + beta.mT @ precision @ beta
        cov = (scale + resid) / (n + prior.dof + d + 1 + free)[:, None, None]
        cov = floor_variance(0.5 * (cov + cov.mT), min_variance)
        tril = safe_cholesky(cov, self.site)
        card = self.card
        return LinearGaussianParams(
            beta[:, : q - 1, :].mT.reshape(*card, d, q - 1),
            beta[:, q - 1, :].reshape(*card, d),
            tril.reshape(*card, d, d),
            n.reshape(card),
        )

    def free(self, params: LinearGaussianParams) -> dict[str, torch.Tensor]:
        """Weights, offsets and the noise's free Cholesky factor (:meth:`~models.CPD.free`)."""
        return {
            "weight": params.weight,
            "bias": params.bias,
            "tril": _LOWER_CHOLESKY.inv(params.scale_tril),
        }

    def bound(
        self, free: dict[str, torch.Tensor], params: LinearGaussianParams
    ) -> LinearGaussianParams:
        """The parameters ``free`` stands for (:meth:`~models.CPD.bound`)."""
        return LinearGaussianParams(
            free["weight"], free["bias"], _LOWER_CHOLESKY(free["tril"]), params.n
        )


def _mean_rounds_off(params: LinearGaussianParams, x: torch.Tensor) -> bool:
    """Whether ``W x + b`` may round off against the smallest noise scale.

    The smallest noise scale of any configuration (:func:`models.gaussian.sum_rounds_off`).
    """
    weight, bias, smallest = params.extremes
    return sum_rounds_off(weight, bias, x, smallest)


class PairMeanNormal(dist.MultivariateNormal):
    """``N(loc + loc_low, scale_tril scale_tril^T)`` with its mean held as two float64 numbers.

    A Gaussian whose mean is held as two float64 numbers (:func:`models.gaussian.affine_pair`),
    ``loc`` its rounding and ``loc_low`` the rest. Its density reads the residual as ``(value - loc)
    - loc_low``, exact where the value is near the mean at any magnitude of both; everything else
    (sampling, moments, ``loc``) is the plain Gaussian's at ``loc``.
    """

    def __init__(
        self,
        loc: torch.Tensor,
        scale_tril: torch.Tensor,
        loc_low: torch.Tensor,
        validate_args: bool | None = None,
    ):
        super().__init__(loc, scale_tril=scale_tril, validate_args=validate_args)
        self.loc_low = loc_low.expand(self.loc.shape)

    def expand(self, batch_shape, _instance=None) -> PairMeanNormal:
        """The same Gaussian broadcast to ``batch_shape``, its mean's rest with it."""
        new = self._get_checked_instance(PairMeanNormal, _instance)
        new = super().expand(batch_shape, _instance=new)
        new.loc_low = self.loc_low.expand(new.loc.shape)
        return new

    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        """The density at ``value``, its residual read as ``(value - loc) - loc_low``."""
        if self._validate_args:
            self._validate_sample(value)
        half_log_det = self._unbroadcasted_scale_tril.diagonal(dim1=-2, dim2=-1).log().sum(-1)
        k = self._event_shape[0]
        return -0.5 * (k * math.log(2 * math.pi) + mahalanobis(self, value)) - half_log_det


def gaussian_of(
    loc: torch.Tensor, scale_tril: torch.Tensor, loc_low: torch.Tensor | None = None
) -> dist.MultivariateNormal:
    """``N(loc, scale_tril scale_tril^T)``.

    A :class:`PairMeanNormal` where the mean's rest ``loc_low`` is given.
    """
    if loc_low is None:
        return dist.MultivariateNormal(loc, scale_tril=scale_tril)
    return PairMeanNormal(loc, scale_tril, loc_low)


def floor_variance(cov: torch.Tensor, min_variance: float) -> torch.Tensor:
    """``cov`` ``(G, d, d)`` with every eigenvalue below ``min_variance`` raised to it.

    A floor, not an addition: a covariance whose spread is above ``min_variance`` in every
    direction is left as estimated (so refitting rows drawn from fitted parameters gives
    those parameters back, whatever the noise's scale), and one with fewer rows than
    dimensions becomes positive definite.
    """
    if min_variance <= 0 or not cov.numel():
        return cov
    low = torch.linalg.eigvalsh(cov)[..., 0] < min_variance
    if not bool(low.any()):
        return cov
    values, vectors = torch.linalg.eigh(cov[low])
    cov = cov.clone()
    floored = (vectors * values.clamp_min(min_variance)[..., None, :]) @ vectors.mT
    cov[low] = 0.5 * (floored + floored.mT)
    return cov


def safe_cholesky(cov: torch.Tensor, site: str, tries: int = 24) -> torch.Tensor:
    """Cholesky factors, adding a growing jitter where a covariance is not quite PD."""
    tril, info = torch.linalg.cholesky_ex(cov)
    jitter = 1e-12
    for _ in range(tries):
        bad = info > 0
        if not bad.any():
            return tril
        scale = cov[bad].diagonal(dim1=-2, dim2=-1).abs().mean(-1).clamp_min(1.0)
        cov[bad] = cov[bad] + (jitter * scale)[:, None, None] * torch.eye(
            cov.shape[-1], dtype=cov.dtype
        )
        tril, info = torch.linalg.cholesky_ex(cov)
        jitter *= 10
    if (info > 0).any():
        group = int((info > 0).nonzero()[0])
        raise ValueError(
            f"site {site!r}: configuration {group} has no positive definite covariance "
            f"({cov[group].tolist()}); check its rows for inf, NaN or huge values"
        )
    return tril


def _rows_collapsed(index: list) -> list:
    """The parents' indices with the rows dim cut to one where every index is the same along it.

    The rows dim is the last; every index is the same along it for one action for all rows, say. The
    gathered parameters then broadcast over the rows instead of being copied once per row.
    """
    rows = [t for t in index if isinstance(t, torch.Tensor) and t.dim() and t.shape[-1] > 1]
    if not rows or any(bool((t != t[..., :1]).any()) for t in rows):
        return index
    return [
        t[..., :1] if isinstance(t, torch.Tensor) and t.dim() and t.shape[-1] > 1 else t
        for t in index
    ]
