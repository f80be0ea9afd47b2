"""The parameter posterior of a parameter acting on one continuous feature, from tables.

From Gaussian tables computed once (:class:`CompiledParameterQuery`): per parent configuration the
affected feature's marginal Cholesky factor and the conditioning gain, so that a query is gathers,
one Gaussian log-density per cluster and one matrix-vector product. Built by
:func:`inference.queries.parameter.compile_parameter_query`; the same answers as the traced
:func:`inference.queries.parameter.infer_parameter`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import torch
from effect_networks.inference.queries.implausibility import (
    IMPLAUSIBLE_BELOW,
    check_threshold,
    initial_tails,
    outside_training,
)
from effect_networks.inference.queries.results import (
    GaussianMixture,
    ParameterPosterior,
    outside_range,
)
from effect_networks.models.declaration import (
    ACTION,
    DTYPE,
    EffectNetwork,
    Parameter,
    end_site,
)
from effect_networks.models.evidence import MAX_MAGNITUDE, Evidence, is_partial
from effect_networks.models.gaussian import (
    affine_pair,
    chi_square_tail,
    mask_unobserved,
    sum_rounds_off,
)
from effect_networks.models.params import NetworkParams


@dataclass(frozen=True)
class CompiledParameterQuery:
    """The parameter posterior with its Gaussian tables precomputed.

    Built by :meth:`models.cpds.ParameterMixture.query_tables` from the marginal of the
    affected feature that the model itself samples when the parameter is unobserved and
    the parameter's cluster Gaussians: per parent configuration, the marginal's Cholesky factor and the
    conditioning gain are computed once, so a query is gathers, one Gaussian log-density
    per cluster and one matrix-vector product. Same results as
    :func:`inference.infer_parameter`.
    """

    net: EffectNetwork
    parameter: Parameter
    parents: tuple[str, ...]  # discrete parents of the affected end site, cluster last
    inputs: tuple[str, ...]  # its continuous parents, the parameter last
    log_cluster: torch.Tensor  # (A, C)
    offset: torch.Tensor  # (P..., d)
    whiten: torch.Tensor  # (P..., d, d): inverse of the marginal's Cholesky factor
    log_norm: torch.Tensor  # (P...): -log det L - d/2 log(2 pi)
    w_x: torch.Tensor  # (P..., d, p - k)
    gain: torch.Tensor  # (P..., k, d)
    prior_mean: torch.Tensor  # (C, k)
    post_cov: torch.Tensor  # (P..., k, k)
    seen: torch.Tensor  # (P...) bool
    # for the initial states' plausibility (inference.queries.implausibility.initial_tails)
    params: NetworkParams | None = field(default=None, repr=False, compare=False)
    # Built on first use: the one-row tables (:meth:`_one_row`), the largest entries
    # :meth:`_rounds_off` reads.
    _one: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def serves(self, sites: set[str]) -> bool:
        """Whether evidence on ``sites`` gets the traced query's answer here.

        The affected feature observed, with its discrete parents and its continuous inputs besides
        the parameter (the action may be left out: the query fills it in where one action uses the
        parameter, and refuses as the traced one does otherwise), and every other site an initial
        state (an observed end site, whose own plausibility the traced query would weigh, is left to
        it).
        """
        y_site = end_site(self.parameter.features[0])
        needed = {*self.parents[:-1], *self.inputs[:-1]} - {ACTION}
        return (
            y_site in sites
            and needed <= sites
            and sites - {y_site}
            <= {ACTION} | {s.name for s in self.net.sites if s.role == "initial"}
        )

    def infer_parameter(
        self,
        evidence: Mapping[str, object],
        *,
        mixture: bool = False,
        implausible_below: float = IMPLAUSIBLE_BELOW,
    ) -> ParameterPosterior:
        """Same contract and result as :func:`inference.infer_parameter`."""
        below = check_threshold(implausible_below)
        one = self._one_row(evidence, mixture, below)
        if one is not None:
            return one
        p = self.parameter
        y_site = end_site(p.features[0])
        enc = self.net.encode(evidence)
        if y_site not in enc:
            raise ValueError(f"the query needs the observed end state {y_site!r}")
        y = enc[y_site]
        n = y.shape[0]
        if ACTION not in enc:
            if len(p.actions) != 1:
                raise ValueError(f"give the action (one of {list(p.actions)}) that used {p.name!r}")
            action = torch.full((n,), self.net.action_index(p.actions[0]))
            enc = Evidence(self.net, dict(enc) | {ACTION: action}, n)
        not_using = ~self.net.parameter_in_use(p, enc[ACTION])
        if not_using.any():
            row = int(not_using.nonzero()[0])
            raise ValueError(
                f"row {row}: action {self.net.actions[int(enc[ACTION][row])]!r} does not use {p.name!r}"
            )
        missing = [s for s in self.parents[:-1] if s not in enc]
        if missing:
            raise ValueError(
                f"the query needs the discrete parents {missing} of {y_site!r} as evidence"
            )
        index = tuple(enc[s] for s in self.parents[:-1])  # (n,) each; the cluster axis stays
        # Rows that share one parent configuration (one action, say) use the tables
        # ungathered: the Gaussian then broadcasts one factor per cluster over the rows.
        shared = n > 0 and all(bool((i == i[0]).all()) for i in index)
        gather = tuple(i[:1] for i in index) if shared else index
        loc = self.offset[gather]  # (n or 1, C, d)
        low = None  # the mean's rest, where it is held as a pair
        others = [enc[s] for s in self.inputs[:-1]]
        x = torch.cat(others, -1) if others else None
        if x is not None and self._rounds_off(x):
            # a mean near a large observed value: its residual keeps its digits
            loc, low = affine_pair(self.w_x[gather], x[:, None, :], loc)
        elif x is not None:
            loc = loc + (self.w_x[gather] @ x[:, None, :, None]).squeeze(-1)
        if is_partial(y):
            return self._infer_partial(enc, y, index, loc, low, mixture, below)
        # log N(y; loc, L L^T) = log_norm - |L^-1 (y - loc)|^2 / 2, with L^-1 and log_norm
        # precomputed from the model's own marginal Cholesky factor L. The residual is
        # taken first and then whitened: a sum of squares without cancellation, where an
        # expanded form y'Ay - 2b'y + c with A ~ 1 / noise loses as many digits as A has.
        whiten = self.whiten[gather][0] if shared else self.whiten[index]  # (C or n, C, d, d)
        d2 = _whitened_distance(y, loc, whiten, low)  # (n, C) squared Mahalanobis distances
        log_cluster = self.log_cluster[enc[ACTION][:1] if shared else enc[ACTION]]
        impossible = ~torch.isfinite(log_cluster)  # (1 or n, C)
        if bool(impossible.any()):
            closest = d2.masked_fill(impossible, torch.inf).amin(-1)
        else:
            closest = d2.amin(-1)
        closest = closest.clamp_min(0.0)  # rounding may leave -1e-12
        # log_norm + log_cluster - d2 / 2, in d2's place: one (n, C) tensor fewer to allocate
        log_post = d2.mul_(-0.5).add_(self.log_norm[gather] + log_cluster)
        dof = torch.tensor(y.shape[-1] / 2, dtype=DTYPE)
        implausible = torch.special.gammaincc(dof, closest / 2) < below
        if self.params is not None:
            initial = initial_tails(self.net, self.params, enc)
            implausible = implausible | outside_training(initial, below)
        refuse_impossible(log_post)
        probs = torch.softmax(log_post, -1, out=log_post)  # in place: log_post is ours
        # numpy's argmax (the first maximum, as torch's) is several times faster here
        best = torch.from_numpy(probs.numpy().argmax(-1))
        rows = torch.arange(n)
        full = (*index, best)
        resid = y - loc.expand(n, *loc.shape[1:])[rows, best]
        if low is not None:
            resid = resid - low.expand(n, *low.shape[1:])[rows, best]
        mean = self.prior_mean[best] + (self.gain[full] @ resid[..., None]).squeeze(-1)
        unseen = (~self.seen[full]).to(DTYPE)
        mix = None
        if mixture:  # every cluster's conditional Gaussian, from the same tables
            resid_all = y[:, None, :] - loc  # (n, C, d)
            if low is not None:
                resid_all = resid_all - low
            gain = self.gain[gather] if shared else self.gain[index]  # (n or 1, C, k, d)
            means = self.prior_mean + (gain @ resid_all[..., None]).squeeze(-1)
            covs = (self.post_cov[gather] if shared else self.post_cov[index]).expand(
                n, *self.post_cov.shape[-3:]
            )
            mix = GaussianMixture(probs, means, covs)
        cov = self.post_cov[full]
        return ParameterPosterior(
            probs, best, mean, cov, unseen, outside_range(p, mean), mix, implausible
        )

    def _one_tables(self) -> dict | None:
        """Per action, the numpy views :meth:`_one_row` reads.

        ``None``: no one-row path, the feature has discrete parents besides the action and the
        cluster, or continuous inputs besides the parameter.
        """
        if "tables" in self._one:
            return self._one["tables"]
        tables = None
        if self.w_x.shape[-1] == 0 and self.parents[:-1] in ((), (ACTION,)):
            net, p = self.net, self.parameter
            actions = torch.arange(len(net.actions))
            by_action = self.parents[:-1] == (ACTION,)
            per = []
            for a in range(len(net.actions)):

                def at(table: torch.Tensor, a: int = a) -> np.ndarray:
                    # the action's slice (a table of size 1 on the action axis is shared)
                    return (table[a if table.shape[0] > 1 else 0] if by_action else table).numpy()

                log_cluster = self.log_cluster[a]
                per.append(
                    {
                        "whiten": at(self.whiten),  # (C, d, d)
                        "base": at(self.log_norm) + log_cluster.numpy(),  # (C,)
                        # None: every cluster possible (most actions), no mask to apply
                        "impossible": (~torch.isfinite(log_cluster)).numpy()
                        if not bool(torch.isfinite(log_cluster).all())
                        else None,
                        "offset": at(self.offset),  # (C, d)
                        "gain": at(self.gain),  # (C, k, d)
                        "post_cov": at(self.post_cov),  # (C, k, k)
                        "seen": at(self.seen),  # (C,)
                    }
                )
            d = self.offset.shape[-1]
            tables = {
                "y_site": end_site(p.features[0]),
                "action": {label: i for i, label in enumerate(net.actions)},
                "in_use": net.parameter_in_use(p, actions).tolist(),
                "default": net.action_index(p.actions[0]) if len(p.actions) == 1 else None,
                "per": per,
                "d": d,
                "prior_mean": self.prior_mean.numpy(),
                "low": np.asarray(p.low, dtype=np.float64),
                "high": np.asarray(p.high, dtype=np.float64),
            }
        self._one["tables"] = tables
        return tables

    def _one_row(self, evidence: object, mixture: bool, below: float) -> ParameterPosterior | None:
        """The query of one fully observed hit with numpy on per-action tables.

        One hit, and perhaps the action as a label: a handful of small operations instead of some
        forty tensor ones. The same steps as the batched query on the same tables, so the same
        answers up to rounding. ``None`` where the evidence is anything else (several rows, a
        partial observation, encoded evidence, an error to report): the general path then serves it.
        """
        if isinstance(evidence, Evidence) or not isinstance(evidence, Mapping):
            return None
        t = self._one_tables()
        if t is None or t["y_site"] not in evidence:
            return None
        if len(evidence) == 1:
            a = t["default"]
        elif len(evidence) == 2 and ACTION in evidence:
            label = evidence[ACTION]
            if isinstance(label, list | tuple) and len(label) == 1:
                label = label[0]
            try:
                a = t["action"].get(label)
            except TypeError:  # unhashable: the general path says what is wrong
                return None
        else:
            return None
        if a is None or not t["in_use"][a]:
            return None
        value = evidence[t["y_site"]]
        if isinstance(value, torch.Tensor):
            y = value.detach().cpu().numpy()
        elif isinstance(value, np.ndarray | list | tuple | float | int):
            try:
                y = np.asarray(value)
            except (TypeError, ValueError):
                return None
        else:  # Partial and the rest
            return None
        if y.dtype.kind not in "fiub":  # complex, objects, strings: refused by encode
            return None
        y = y.astype(np.float64, copy=False)
        d = t["d"]
        if not (y.shape == (1, d) or y.shape == (d,) or (y.ndim == 0 and d == 1)):
            return None
        y = y.reshape(d)
        if not (np.abs(y) <= MAX_MAGNITUDE).all():  # NaN, inf, beyond the magnitude rule
            return None
        at = t["per"][a]
        diff = y - at["offset"]  # (C, d): the residuals first, then whitened, as batched
        whiten = at["whiten"]
        d2 = np.zeros(len(diff))
        with np.errstate(over="ignore"):  # a distance beyond float64 is inf, as in torch
            for i in range(d):  # whiten is lower triangular
                z = whiten[:, i, 0] * diff[:, 0]
                for j in range(1, i + 1):
                    z += whiten[:, i, j] * diff[:, j]
                d2 += z * z
        log_post = at["base"] - 0.5 * d2
        if at["impossible"] is not None:
            d2 = np.where(at["impossible"], np.inf, d2)
        tail = chi_square_tail(d, max(float(d2.min()), 0.0))
        if not log_post.max() > -np.inf:
            return None  # no cluster possible: the general path says so
        probs = np.exp(log_post - log_post.max())
        probs /= probs.sum()
        best = int(probs.argmax())
        resid = y - at["offset"][best]
        mean = t["prior_mean"][best] + at["gain"][best] @ resid
        outside = bool(((mean < t["low"]) | (mean > t["high"])).any())
        mix = None
        if mixture:
            resid_all = y - at["offset"]  # (C, d)
            means = t["prior_mean"] + np.einsum("ckd,cd->ck", at["gain"], resid_all)
            mix = GaussianMixture(
                torch.from_numpy(probs[None].copy()),
                torch.from_numpy(means[None]),
                torch.from_numpy(at["post_cov"][None].copy()),
            )
        return ParameterPosterior(
            torch.from_numpy(probs[None]),
            torch.from_numpy(np.array([best], dtype=np.int64)),
            torch.from_numpy(mean[None]),
            torch.from_numpy(at["post_cov"][best][None].copy()),
            torch.from_numpy(np.array([0.0 if at["seen"][best] else 1.0])),
            torch.from_numpy(np.array([outside])),
            mix,
            torch.from_numpy(np.array([tail < below])),
        )

    def _rounds_off(self, x: torch.Tensor) -> bool:
        """Whether the mean ``offset + w_x x`` may round off against the marginal's noise.

        Against its smallest noise scale (:func:`models.gaussian.sum_rounds_off`; that scale is at
        least ``1 / |whiten|``, the largest Frobenius norm of the inverse factors).
        """
        if "extremes" not in self._one:  # the tables' part, once
            largest_inverse = self.whiten.square().sum((-2, -1)).max().sqrt()
            parts = [self.w_x.abs().max(), self.offset.abs().max(), 1 / largest_inverse]
            self._one["extremes"] = torch.stack(parts).tolist()
        return sum_rounds_off(*self._one["extremes"][:2], x, self._one["extremes"][2])

    def _infer_partial(self, enc, y, index, loc, low, mixture, below) -> ParameterPosterior:
        """The query for ``y`` observed in some dimensions (NaN in the others).

        Each cluster's marginal and conditioning restricted to the observed dimensions. The tables
        hold them for all dimensions; the marginal covariance ``L L^T``, the cross-covariance ``gain
        L L^T`` and the cluster covariance ``post_cov + gain L L^T gain^T`` are read back from them,
        then every observed-dimension quantity is taken from those
        (:func:`models.gaussian.mask_unobserved`).
        """
        n = y.shape[0]
        eye = torch.eye(y.shape[-1], dtype=DTYPE)
        tril = torch.linalg.solve_triangular(self.whiten[index], eye, upper=False)
        marginal = tril @ tril.mT  # (n, C, d, d)
        gain = self.gain[index]
        cross = gain @ marginal  # (n, C, k, d)
        prior_cov = self.post_cov[index] + gain @ cross.mT
        y_, loc_, cov_, seen = mask_unobserved(y[:, None, :], loc, marginal)
        chol = torch.linalg.cholesky(cov_)
        resid = y_ - loc_
        if low is not None:
            resid = resid - torch.where(seen, low, 0.0)
        resid = resid[..., None]
        d2 = torch.linalg.solve_triangular(chol, resid, upper=False).square().sum((-2, -1))
        dof = seen[:, 0].sum(-1).to(DTYPE)  # (n,)
        log_det = chol.diagonal(dim1=-2, dim2=-1).log().sum(-1)
        log_lik = -0.5 * d2 - log_det - 0.5 * dof[:, None] * math.log(2 * math.pi)
        cross = torch.where(seen[..., None, :], cross, 0.0)
        gain = torch.cholesky_solve(cross.mT, chol).mT  # (n, C, k, d)
        means = self.prior_mean + (gain @ resid).squeeze(-1)
        covs = prior_cov - gain @ cross.mT
        covs = 0.5 * (covs + covs.mT)
        log_cluster = self.log_cluster[enc[ACTION]]
        refuse_impossible(log_lik + log_cluster)
        probs = (log_lik + log_cluster).softmax(-1)
        closest = d2.masked_fill(~torch.isfinite(log_cluster), torch.inf).min(-1).values
        tail = torch.special.gammaincc(dof.clamp_min(1) / 2, closest / 2)
        implausible = torch.where(dof > 0, tail, 1.0) < below
        if self.params is not None:
            implausible = implausible | outside_training(
                initial_tails(self.net, self.params, enc), below
            )
        best = probs.argmax(-1)
        rows = torch.arange(n)
        mean, cov = means[rows, best], covs[rows, best]
        unseen = (~self.seen[(*index, best)]).to(DTYPE)
        mix = GaussianMixture(probs, means, covs) if mixture else None
        return ParameterPosterior(
            probs, best, mean, cov, unseen, outside_range(self.parameter, mean), mix, implausible
        )


def refuse_impossible(log_post: torch.Tensor) -> None:
    """Refuse rows ``(n, C)`` whose every cluster has probability 0 (in float64).

    No posterior exists (as :class:`inference.exact.traced.Enumerated` refuses them).
    """
    top = log_post.amax(-1)
    if not bool((top > -torch.inf).all()):
        row = int((top == -torch.inf).nonzero()[0])
        raise ValueError(
            f"evidence row {row} has probability 0 under every configuration of the model "
            "(every cluster): no posterior exists. A value too far from every component "
            "for float64 (rescale the feature)"
        )


def _whitened_distance(
    y: torch.Tensor, loc: torch.Tensor, whiten: torch.Tensor, low: torch.Tensor | None = None
) -> torch.Tensor:
    """``(n, C)`` ``|whiten (y - loc - low)|^2``, one dimension at a time.

    For ``y`` ``(n, d)``, ``loc`` (and the mean's rest ``low``, where it is a pair) ``(n or 1, C,
    d)`` and lower triangular ``whiten`` ``(n or C, ..., d, d)``: the residual first, then whitened,
    one dimension at a time on ``(n, C)`` tensors (a sum of squares without cancellation, and no
    ``(n, C, d)`` temporaries).
    """
    d = y.shape[-1]
    diff = [y[:, j, None] - loc[..., j] for j in range(d)]  # (n, C) each
    if low is not None:
        diff = [r - low[..., j] for j, r in enumerate(diff)]
    d2 = None
    for i in range(d):
        z = diff[0] * whiten[..., i, 0]
        for j in range(1, i + 1):
            z.addcmul_(diff[j], whiten[..., i, j])
        d2 = z.square_() if d2 is None else d2.add_(z.square_())
    return d2
