r"""An action parameter: its cluster, its value, and how they act on the features.

Paper §III: a continuous parameter ``param.p`` (a force, a target) with a discrete
``cluster.p`` over equidistant cells of its range, one Gaussian per cell (a mixture of
Gaussians). A continuous feature it acts on takes the value as its last continuous
input and the cluster as its last discrete parent (a linear Gaussian); a discrete
feature takes the cluster only (its table or softmax has a cell axis)::

    action --> cluster.p --> param.p
       \           \   \         \
        +-----------+---+---------+--> end.g      (continuous: linear Gaussian)
                         \
                          +-----------> end.h      (discrete: depends on the cell)

:class:`ParameterMixture` owns the two sites' kinds (a pinned table and a linear
Gaussian) and every rule that ties them together:

* **An action that does not use the parameter ignores it.** Its cluster is pinned on
  cell 0 (not fitted), its value's density is left out, and the affected features'
  weights on the parameter are zero for it (fixed in the fit, ignored in the model).
* **The cluster is data; under the grid layout a value given alone comes with its
  cell** (:meth:`cells`). The value given its cluster is the cluster's Gaussian,
  untruncated, so the model is a plain mixture; a row giving the value without its
  cluster (training rows, query evidence) is read as observing the value's equidistant
  cell. Under the adaptive layout (``Parameter(layout="adaptive")``) the cluster is a
  latent mixture component instead: a known value leaves its cluster latent (its
  posterior is the mixture's responsibility), and the cells only seed the fit
  (:func:`inference.fit_em`).
* **An unknown value is integrated out in closed form**: for ``theta ~ N(m_c, S_c)`` and
  ``y = W_x x + W_p theta + b + e``, ``y ~ N(W_x x + W_p m_c + b, R + W_p S_c W_p^T)``
  (:meth:`ParameterMixture.marginal`), and ``theta`` given ``y`` is the linear-Gaussian posterior
  (:meth:`condition`); :meth:`query_tables` precomputes both for the compiled query.
  Several parameters on one feature add their terms (:func:`affected_gaussian`); a
  value acting on several continuous features is conditioned on each observed one in
  turn (:meth:`ParameterMixture.update`, :meth:`ParameterMixture.posterior`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import pyro.distributions as dist
import torch
from effect_networks.models.cpds.base import concat_inputs
from effect_networks.models.cpds.linear_gaussian import (
    LinearGaussianCPD,
    LinearGaussianParams,
    gaussian_of,
)
from effect_networks.models.cpds.table import TableCPD
from effect_networks.models.dtype import DTYPE
from effect_networks.models.features import Parameter
from effect_networks.models.gaussian import (
    condition_linear_gaussian,
    lstsq_rows,
    mask_unobserved,
    residual_of,
)
from pyro.ops.indexing import Vindex


@dataclass(frozen=True)
class ParameterMixture:
    """The cluster and value sites of one action parameter (see the module).

    ``uses`` ``(A,)`` bool: which actions use the parameter. ``action`` is the action
    site's name, ``affected`` the end sites the parameter acts on, ``continuous`` those
    among them that take its value as a linear input; the discrete ones have the cluster
    as a parent.
    """

    parameter: Parameter
    action: str
    uses: torch.Tensor = field(compare=False, repr=False)
    cluster: TableCPD
    value: LinearGaussianCPD
    affected: tuple[str, ...]
    continuous: tuple[str, ...]

    name = "parameter_mixture"

    @property
    def child(self) -> str | None:
        """The one continuous site the parameter acts on, if there is exactly one."""
        return self.continuous[0] if len(self.continuous) == 1 else None

    @classmethod
    def of(
        cls,
        parameter: Parameter,
        action: str,
        uses: torch.Tensor,
        cluster: str,
        value: str,
        affected: tuple[str, ...],
        continuous: tuple[str, ...],
    ) -> ParameterMixture:
        """The mixture's kinds: ``cluster`` given the action, ``value`` given the cluster.

        Actions not using the parameter are pinned on cell 0.
        """
        c, k = parameter.n_clusters, parameter.dim
        n_actions = uses.shape[0]
        return cls(
            parameter,
            action,
            uses,
            TableCPD(cluster, (action,), (n_actions,), c, pinned=~uses),
            LinearGaussianCPD(value, (cluster,), (c,), k),
            affected,
            continuous,
        )

    @property
    def sites(self) -> tuple[str, str]:
        """The two sites' names: ``(cluster.p, param.p)``."""
        return self.cluster.site, self.value.site

    def in_use(self, action: torch.Tensor) -> torch.Tensor:
        """Whether ``action`` (state indices, any shape) uses the parameter."""
        return self.uses[action]

    def cells(self, theta: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The cluster a row giving the value alone is read as observing.

        The value's cell, or 0 where the action does not use the parameter (NaN values count as 0
        there).
        """
        return torch.where(self.in_use(action), self.parameter.cluster_of(theta.nan_to_num()), 0)

    # ---------------------------------------------------------------- the affected feature
    def zero_weights(
        self, parents: tuple[str, ...], card: tuple[int, ...], width: int, end: int
    ) -> torch.Tensor:
        """The affected feature's weights on the parameter where the action does not use it.

        ``(G, width)`` bool for the affected feature's linear Gaussian (parents ``parents`` with
        cardinalities ``card``, the parameter its inputs ``end - dim`` to ``end``).
        """
        unused = self._on_action_axis(~self.uses, parents, 0).expand(*card).reshape(-1)
        out = torch.zeros(unused.shape[0], width, dtype=torch.bool)
        out[:, end - self.parameter.dim : end] = unused[:, None]
        return out

    def _on_action_axis(self, per_action: torch.Tensor, parents, trailing: int) -> torch.Tensor:
        """``(A,)`` shaped to broadcast on the action axis of tables.

        The tables are over ``parents`` followed by ``trailing`` more dims.
        """
        after = len(parents) - 1 - parents.index(self.action)
        return per_action.reshape(-1, *([1] * (after + trailing)))

    def marginal(self, params: Mapping, child: LinearGaussianCPD) -> LinearGaussianParams:
        """The affected feature's CPD with the parameter integrated out, per configuration.

        ``weight`` ``W_x`` ``(P..., d, p - k)``, ``bias`` ``b + W_p m_c`` ``(P..., d)``,
        ``scale_tril`` the Cholesky factor of ``R + W_p S_c W_p^T``. For actions not using the
        parameter ``W_p`` counts as zero.
        """
        cpd = params[child.site]
        prior = params[self.value.site]
        k = self.parameter.dim
        q = cpd.weight.shape[-1]
        w_x, w_p = cpd.weight[..., : q - k], cpd.weight[..., q - k :]
        uses = self._on_action_axis(self.uses.to(w_p.dtype), child.parents, 2)
        w_p = w_p * uses
        # prior.bias (C, k) aligns with the cluster axis, the child's last parent
        offset = cpd.bias + (w_p @ prior.bias.unsqueeze(-1)).squeeze(-1)
        cov = cpd.covariance + w_p @ prior.covariance @ w_p.mT
        return LinearGaussianParams(w_x, offset, torch.linalg.cholesky(cov), cpd.n)

    def child_gaussian(
        self,
        params: Mapping,
        child: LinearGaussianCPD,
        index: list[torch.Tensor],
        inputs: list[torch.Tensor],
        action: torch.Tensor,
        known: torch.Tensor,
    ) -> dist.MultivariateNormal:
        """The affected feature's Gaussian.

        Given the parameter where it is ``known`` (bool rows), integrated out where not. ``inputs``:
        the child's continuous parents' values, the parameter last. Its mean is a pair where the
        plain sum may round off (:meth:`LinearGaussianCPD.gaussian`).
        """
        everywhere = bool(known.all())
        nowhere = not bool(known.any())
        inputs = list(inputs)
        if not nowhere:  # the parameter known in some rows: condition on it there
            uses = self.in_use(action)
            inputs[-1] = torch.where(uses[..., None], inputs[-1].nan_to_num(), 0.0)
            fn = child.gaussian(params[child.site], index, concat_inputs(inputs))
        if not everywhere:
            m_fn = child.gaussian(self.marginal(params, child), index, concat_inputs(inputs[:-1]))
            if nowhere:
                return m_fn
            lows = [getattr(f, "loc_low", None) for f in (fn, m_fn)]
            low = None
            if any(x is not None for x in lows):
                low = torch.where(
                    known[..., None],
                    *(torch.zeros((), dtype=DTYPE) if x is None else x for x in lows),
                )
            return gaussian_of(
                torch.where(known[..., None], fn.loc, m_fn.loc),
                torch.where(known[..., None, None], fn.scale_tril, m_fn.scale_tril),
                low,
            )
        return fn

    def condition(
        self,
        params: Mapping,
        child: LinearGaussianCPD,
        values: Mapping[str, torch.Tensor],
        cluster: torch.Tensor,
        prior: tuple[torch.Tensor, torch.Tensor] | None = None,
        acting: tuple[ParameterMixture, ...] = (),
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The parameter's Gaussian given the affected feature's value ``values[child]``.

        Given also its other parents' values and a cluster per row: ``cluster`` ``(n,)``, or ``(n,
        C)`` for several clusters per row (the results then carry the ``C`` dim). ``prior``: the
        cluster's mean and covariance, if already gathered. ``acting``: every parameter acting on
        the child, in input order, when there are several; the others count where ``values`` gives
        them (not NaN) and are integrated out, given their cluster in ``values``, where not.
        """
        w_p, offset, noise, y = self.linear_terms(params, child, values, cluster, acting)
        if prior is None:
            prior = self.belief(params, cluster)
        return _conditioned(prior, w_p, offset, noise, y)

    def linear_terms(
        self,
        params: Mapping,
        child: LinearGaussianCPD,
        values: Mapping[str, torch.Tensor],
        cluster: torch.Tensor,
        acting: tuple[ParameterMixture, ...] = (),
    ) -> tuple[torch.Tensor, dist.MultivariateNormal, torch.Tensor, torch.Tensor]:
        """The child as a linear function of the value, per row and cluster.

        Arguments as for :meth:`condition`: ``y = offset + W_p theta + e``, ``e ~ N(0, noise)``,
        with the other inputs' and the other parameters' terms in ``offset`` and ``noise``. Returns
        ``(W_p, offset, noise, y)``, ``y`` the child's observed value broadcast like the others and
        ``offset`` a Gaussian whose mean is the offset, a pair where the plain sum may round off
        (:meth:`LinearGaussianCPD.gaussian`; its residual :func:`models.gaussian.residual_of`).
        """
        extra = cluster.dim() - 1  # trailing dims the row-wise values must broadcast over

        def rows(t: torch.Tensor) -> torch.Tensor:
            return t.reshape(t.shape[:1] + (1,) * extra + t.shape[1:])

        index = tuple(rows(values[s]) if s != self.cluster.site else cluster for s in child.parents)
        cpd = params[child.site]
        weight = cpd.weight[index]
        others = acting if len(acting) > 1 else (self,)
        q_other = weight.shape[-1] - sum(m.parameter.dim for m in others)
        start = q_other
        noise = cpd.covariance[index]
        inputs = [values[s] for s in child.inputs[: len(child.inputs) - len(others)]]
        # the offset's inputs in the weight's column order, this value's columns 0
        columns = [rows(torch.cat(inputs, -1))] if inputs else []
        for m in others:
            k = m.parameter.dim
            w = weight[..., start : start + k]
            start += k
            if m is self:
                w_p = w
                columns.append(torch.zeros(k, dtype=weight.dtype))
                continue
            theta = values.get(m.value.site)
            c = rows(values[m.cluster.site])
            value, hidden = params[m.value.site].bias[c], None
            if theta is not None:
                given = rows(~torch.isnan(theta).any(-1))
                value = torch.where(given[..., None], rows(theta.nan_to_num()), value)
                hidden = ~given
            uses = rows(m.in_use(values[m.action]))
            columns.append(torch.where(uses[..., None], value, 0.0))
            spread = w @ params[m.value.site].covariance[c] @ w.mT
            hidden = uses if hidden is None else uses & hidden
            noise = noise + hidden[..., None, None] * spread
        offset = child.gaussian(cpd, list(index), concat_inputs(columns))
        return w_p, offset, noise, rows(values[child.site])

    def belief(self, params: Mapping, cluster: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The value's Gaussian given the cluster: mean ``(..., k)`` and covariance."""
        prior = params[self.value.site]
        return Vindex(prior.bias)[cluster, :], Vindex(prior.covariance)[cluster, :, :]

    def _split(self, params, child, index, inputs, action):
        """The child's Gaussian without the value and its weights on the value.

        Its mean is the offset ``b + W_x x``, a pair where it may round off; the weights are zero
        for actions not using the value; both gathered at the parents.
        """
        cpd = params[child.site]
        k = self.parameter.dim
        zero = torch.zeros(k, dtype=cpd.weight.dtype)
        offset = child.gaussian(cpd, index, concat_inputs([*inputs[:-1], zero]))
        weight = Vindex(cpd.weight)[(*index, slice(None), slice(None))]
        uses = self.in_use(action).to(weight.dtype)[..., None, None]
        return offset, weight[..., weight.shape[-1] - k :] * uses

    def shared_gaussian(
        self, params, child, index, inputs, action, known, belief
    ) -> dist.MultivariateNormal:
        """Like :meth:`child_gaussian` for a value acting on several continuous sites.

        Where unknown, the value is integrated out under ``belief`` (the value's Gaussian given the
        cluster and the affected sites observed so far; ``None``: the cluster's own).
        """
        if belief is None:
            return self.child_gaussian(params, child, index, inputs, action, known)
        offset, w_p = self._split(params, child, index, inputs, action)
        tril = offset.scale_tril
        theta = inputs[-1].nan_to_num()
        mean = torch.where(known[..., None], theta, belief[0])
        used = torch.where(self.in_use(action)[..., None], mean, 0.0)
        fn = child.gaussian(params[child.site], index, concat_inputs([*inputs[:-1], used]))
        spread = (~known).to(w_p.dtype)[..., None, None] * (w_p @ belief[1] @ w_p.mT)
        cov = tril @ tril.mT + spread
        return gaussian_of(fn.loc, torch.linalg.cholesky(cov), getattr(fn, "loc_low", None))

    def update(
        self, params, child, index, inputs, action, y, belief
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``belief`` conditioned on the child's observed value ``y``.

        ``None``: the cluster's Gaussian, gathered at the child's last discrete parent.
        """
        if belief is None:
            belief = self.belief(params, index[-1])
        offset, w_p = self._split(params, child, index, inputs, action)
        return _conditioned(belief, w_p, offset, offset.covariance_matrix, y)

    def posterior(
        self,
        params: Mapping,
        children: list[LinearGaussianCPD],
        values: Mapping[str, torch.Tensor],
        cluster: torch.Tensor,
        prior: tuple[torch.Tensor, torch.Tensor] | None = None,
        acting: tuple[ParameterMixture, ...] = (),
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The value's Gaussian given all of ``children``.

        :meth:`condition` on each of ``children`` (observed continuous sites the value acts on) in
        turn.
        """
        for child in children:
            prior = self.condition(params, child, values, cluster, prior, acting)
        return prior

    def whitened(
        self,
        params: Mapping,
        children: list[LinearGaussianCPD],
        values: Mapping[str, torch.Tensor],
        cluster: torch.Tensor,
        acting: tuple[ParameterMixture, ...] = (),
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The observed ``children`` stacked and whitened by their noise, per row and cluster.

        Arguments as for :meth:`posterior`. Returns ``(A, b, log_norm)`` such that ``|b - A
        theta|^2`` is their squared Mahalanobis distance from their prediction at ``theta`` (``A =
        L^-1 W_p`` ``(..., D, k)``, ``b = L^-1 (y - offset)`` ``(..., D)``, ``L`` each child's noise
        Cholesky factor) and ``log_norm`` ``(...)`` their Gaussians' log-normaliser, ``-log det L -
        D/2 log 2 pi``. A child observed in some dimensions only (NaN in the others) counts with its
        observed dimensions' marginal (each unobserved dimension adds the constant ``-1/2 log 2 pi``
        to ``log_norm``).
        """
        slopes, targets, log_norm = [], [], 0.0
        for child in children:
            w_p, offset, noise, y = self.linear_terms(params, child, values, cluster, acting)
            residual = residual_of(offset, y)
            if bool(torch.isnan(residual).any()):  # partial evidence: its observed dims only
                residual, _, noise, seen = mask_unobserved(
                    residual, torch.zeros_like(residual), noise
                )
                w_p = torch.where(seen[..., None], w_p, 0.0)
            tril = torch.linalg.cholesky(noise)
            slopes.append(torch.linalg.solve_triangular(tril, w_p, upper=False))
            r = torch.linalg.solve_triangular(tril, residual[..., None], upper=False)
            targets.append(r[..., 0])
            d = tril.shape[-1]
            log_det = tril.diagonal(dim1=-2, dim2=-1).log().sum(-1)
            log_norm = log_norm - log_det - 0.5 * d * math.log(2 * math.pi)
        lead = torch.broadcast_shapes(
            *(t.shape[:-1] for t in targets), *(a.shape[:-2] for a in slopes)
        )
        slope = torch.cat([a.expand(*lead, -1, -1) for a in slopes], -2)
        target = torch.cat([t.expand(*lead, -1) for t in targets], -1)
        return slope, target, log_norm

    def best_fit(
        self, params: Mapping, whitened: tuple[torch.Tensor, ...], cluster: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The value under which the observed children are most likely given the cluster.

        From their :meth:`whitened` terms ``(A, b, _)``: the least-squares solution of ``A theta =
        b``, i.e. of ``y_j = offset_j + W_j theta`` over the children, each weighted by its inverse
        noise covariance. Where the children leave some directions of ``theta`` free (fewer effect
        dims than parameter dims, or a zero weight), the solution nearest the cluster's mean in the
        cluster's own metric (the minimum-norm least-squares solution in the cluster's whitened
        coordinates). Returns the value ``(..., k)`` and the children's squared Mahalanobis distance
        from their prediction at it, summed ``(...)``: zero when the value produces the observed
        effect exactly.

        The objective is lexicographic: first the children's likelihood, then the cluster's own
        Gaussian among the values reaching it equally well (where the joint density ``p(theta, y |
        cluster)`` is highest among them). It is not the maximiser of the joint density over all
        values: that is the cluster's posterior mode, a generalised least squares of ``[A; L^-1]
        theta = [b; L^-1 mean]``, which gives up part of the effect for prior density (the
        posterior's shrinkage :func:`~inference.parameter_for_effect` is there to avoid).
        On a near-singular regression the value reaching the effect may lie far from the cluster,
        with a low joint density that ranks it behind the other clusters' candidates. The SVD
        solve is backward stable: on a design conditioned ``kappa`` the value is exact for weights
        within a few ``eps`` of the given ones, and its joint density within about ``kappa eps``
        (relative) of the exact optimum's.
        """
        slope, target = whitened[0], whitened[1]
        mean, cov = self.belief(params, cluster)
        # in the cluster's whitened coordinates theta = mean + L z, the solution nearest
        # the mean is the minimum-norm least-squares z (by SVD: exact where directions are
        # free, where a ridge on the normal equations would leave them ill-conditioned)
        tril = torch.linalg.cholesky(cov)
        lead = torch.broadcast_shapes(slope.shape[:-2], tril.shape[:-2], target.shape[:-1])
        design = (slope @ tril).expand(*lead, *slope.shape[-2:])
        rest = (target - (slope @ mean[..., None])[..., 0]).expand(*lead, target.shape[-1])
        if design.dim() > 2:  # per row: rows with one design solved together
            z = lstsq_rows(design, rest)[..., None]
        else:
            z = torch.linalg.lstsq(design, rest[..., None], driver="gelsd").solution
        value = mean[..., None] + tril @ z
        miss = (target - (slope @ value)[..., 0]).square().sum(-1)
        return value[..., 0], miss

    def query_tables(self, params: Mapping, child: LinearGaussianCPD) -> dict[str, torch.Tensor]:
        """Tables of the inverse query, per configuration of the child's parents.

        The marginal's offset, inverse Cholesky factor (``whiten``) and log-normaliser, the other
        inputs' weights, the conditioning gain and posterior covariance, the cluster's log-prior
        given the action, the cluster means and the seen flags.
        """
        marginal = self.marginal(params, child)
        tril = marginal.scale_tril
        cpd = params[child.site]
        prior = params[self.value.site]
        w_p = cpd.weight[..., -self.parameter.dim :]
        # gain = S_c W_p^T (W_p S_c W_p^T + R)^-1, with the marginal's Cholesky factor
        cross = prior.covariance @ w_p.mT  # (P..., k, d)
        gain = torch.cholesky_solve(cross.mT, tril).mT
        post_cov = prior.covariance - gain @ w_p @ prior.covariance
        eye = torch.eye(tril.shape[-1], dtype=tril.dtype)
        return {
            "log_cluster": self.cluster.pin_logs(
                params[self.cluster.site].probs.clamp_min(1e-300).log()
            ),
            "offset": marginal.bias,
            "whiten": torch.linalg.solve_triangular(tril, eye, upper=False),
            "log_norm": -tril.diagonal(dim1=-2, dim2=-1).log().sum(-1)
            - 0.5 * tril.shape[-1] * math.log(2 * math.pi),
            "w_x": marginal.weight,
            "gain": gain,
            "prior_mean": prior.bias,
            "post_cov": 0.5 * (post_cov + post_cov.mT),
            "seen": child.seen(cpd),
        }

    # ---------------------------------------------------------------- fitting
    def statistics(
        self,
        action: torch.Tensor,
        cluster: torch.Tensor,
        theta: torch.Tensor,
        weights: torch.Tensor | None = None,
    ):
        """The two sites' statistics, over the rows whose action uses the parameter.

        Each row counts its weight, default 1.
        """
        uses = self.in_use(action)
        w = None if weights is None else weights[uses]
        return {
            self.cluster.site: self.cluster.statistics(action[uses], None, cluster[uses], w),
            self.value.site: self.value.statistics(cluster[uses], None, theta[uses], w),
        }

    def randomize(
        self, value: LinearGaussianParams, generator: torch.Generator
    ) -> LinearGaussianParams:
        """Random cluster Gaussians, each inside its own cell as a fitted one is.

        Mean in the cell's middle half, standard deviation an eighth of the cell.
        """
        p = self.parameter
        width = (torch.tensor(p.high, dtype=DTYPE) - torch.tensor(p.low, dtype=DTYPE)) / (
            torch.tensor(p.bins, dtype=DTYPE)
        )
        offset = (torch.rand(p.n_clusters, p.dim, generator=generator, dtype=DTYPE) - 0.5) * 0.5
        mean = p.cluster_centres() + offset * width
        tril = torch.diag_embed((width / 8).expand(p.n_clusters, p.dim))
        return LinearGaussianParams(value.weight, mean, tril, value.n)


def _conditioned(belief, w_p, offset: dist.MultivariateNormal, noise, y):
    """Condition ``belief`` on ``y = offset + W_p theta + e`` with the offset ``offset``'s mean.

    :func:`models.gaussian.condition_linear_gaussian`; where the offset is a pair, on the exact
    residual ``y - offset`` (and a zero offset).
    """
    if getattr(offset, "loc_low", None) is None:
        return condition_linear_gaussian(*belief, w_p, offset.loc, noise, y)
    residual = residual_of(offset, y)
    return condition_linear_gaussian(*belief, w_p, torch.zeros_like(residual), noise, residual)


def affected_gaussian(
    acting: tuple[ParameterMixture, ...],
    params: Mapping,
    child: LinearGaussianCPD,
    index: list[torch.Tensor],
    inputs: list[torch.Tensor],
    action: torch.Tensor,
    known: Mapping[str, torch.Tensor],
) -> dist.MultivariateNormal:
    """A continuous feature's Gaussian given the parameters ``acting`` on it.

    Their values are its last inputs, their clusters its last parents, in this order. Each value
    counts where it is ``known`` (rows, by parameter name) and is integrated out where not: ``y ~
    N(b + W_x x + sum_j W_j mu_j, R + sum_j W_j S_j W_j^T)`` over the unknown ``j`` (independent
    given their clusters). Its mean is a pair where the plain sum may round off
    (:meth:`LinearGaussianCPD.gaussian`).
    """
    if len(acting) == 1:
        m = acting[0]
        return m.child_gaussian(params, child, index, inputs, action, known[m.parameter.name])
    cpd = params[child.site]
    weight = Vindex(cpd.weight)[(*index, slice(None), slice(None))]
    _, tril = child.loc_tril(cpd, index, None)
    cov = tril @ tril.mT
    q_other = weight.shape[-1] - sum(m.parameter.dim for m in acting)
    start = q_other
    clusters = index[len(index) - len(acting) :]
    thetas = inputs[len(inputs) - len(acting) :]
    values = []  # each value where known, its cluster's mean where not, 0 where unused
    for m, c, theta in zip(acting, clusters, thetas, strict=True):
        k = m.parameter.dim
        w = weight[..., start : start + k]
        start += k
        given, uses = known[m.parameter.name], m.in_use(action)
        prior = params[m.value.site]
        value = torch.where(given[..., None], theta.nan_to_num(), Vindex(prior.bias)[c, :])
        values.append(torch.where(uses[..., None], value, 0.0))
        hidden = uses & ~given
        if bool(hidden.any()):
            spread = w @ Vindex(prior.covariance)[c, :, :] @ w.mT
            cov = cov + hidden[..., None, None] * spread
    x = concat_inputs(list(inputs[: len(inputs) - len(acting)]) + values)
    fn = child.gaussian(cpd, index, x)
    return gaussian_of(fn.loc, torch.linalg.cholesky(cov), getattr(fn, "loc_low", None))
