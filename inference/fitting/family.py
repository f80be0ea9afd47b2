"""Decomposable scores of an end site's family: the site given one choice of parents.

A network's log-likelihood on complete rows is a sum of one term per site, and an end
site's term depends only on the site and its parents (its *family*). Each term here is
computed in closed form from the rows for the conditional-distribution kind the
declaration gives that family (:func:`models.cpds.default_kind`), at the parameters
:func:`inference.fit` finds for it with ``pseudo_count=0``:

* ``table`` (a discrete child of discrete parents): the counts ``c[g, k]`` per parent
  configuration ``g``; log-likelihood ``sum c log(c / n_g)``;
* ``softmax`` (a discrete child of continuous parents): Newton's method per
  configuration (:meth:`models.cpds.SoftmaxCPD.maximise`, with the fit's prior ``l2``
  on the slopes), the log-likelihood of the rows at its optimum;
* ``linear_gaussian`` (a continuous child of dimension ``d``): per configuration the
  least squares of the child on its continuous parents and a one, with the full residual
  covariance (:meth:`models.cpds.LinearGaussianCPD.m_step`, its eigenvalues floored at
  ``min_variance``), log-likelihood ``-1/2 sum_g [n_g (d log 2 pi + log|S_g|) + tr(S_g^-1
  R_g)]`` with ``R_g`` the residual sums of squares. A configuration with fewer rows
  than its mean's numbers plus ``d`` fits them exactly and its covariance is the floor;
  structure learning scores those rows under the residual covariance pooled over the
  other configurations instead (``Families(pooled=True)``), a bounded likelihood.

BIC subtracts ``k / 2 * ln n`` and AIC ``k``, with ``k`` the family's free parameters
over the parent configurations the structure can reach (an action that does not use a
parameter puts its cluster on cell 0; the other cells are unreachable for it):
``K - 1`` per configuration for a table, ``(K - 1)(p + 1)`` for a softmax of ``p``
continuous inputs, ``d (p + 1) + d (d + 1) / 2`` for a linear Gaussian, less the weights
the structure fixes at zero (a parameter's weights under an action not using it). This
counts every reachable configuration, seen by a row or not, as pgmpy's ``BIC`` does.
BDeu (discrete children of discrete parents only) is the log marginal likelihood of the
counts under a Dirichlet prior of ``ess / (configurations x states)`` per cell, pgmpy's
``BDeu``.

A parameter's cluster and value join the family of every feature the parameter affects
(:class:`~models.features.Parameter`), whatever else the parents are.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import torch
from effect_networks.inference.fitting.reading import read_rows
from effect_networks.inference.fitting.rows import check_settings, refuse_adaptive
from effect_networks.models.cpds import (
    Counts,
    LinearGaussianCPD,
    LinearGaussianParams,
    SoftmaxCPD,
    SoftmaxParams,
)
from effect_networks.models.cpds.linear_gaussian import floor_variance
from effect_networks.models.declaration import ACTION, DTYPE, MAX_CPD_ENTRIES, EffectNetwork
from effect_networks.models.sites import SiteSpec

__all__ = ["SCORES", "Families", "family_scores"]

#: The decomposable scores a family can be given.
SCORES = ("bic", "aic", "bdeu", "loglik")

#: A softmax family's starting offset for a state no row of its configuration shows:
#: probabilities below 1e-260 (the supremum of the likelihood puts them at 0).
ABSENT = -600.0


@dataclass(frozen=True)
class Family:
    """One end site with one parent set, scored.

    ``parents`` the chosen parents (the parameter sites excluded), ``loglik`` at the
    maximum-likelihood parameters, ``free`` the free parameters, ``score`` the requested score.
    ``degenerate``: a linear Gaussian with a configuration of fewer rows than its mean's numbers
    plus its dimension, which it fits exactly: the fit's covariance there is the floor
    ``min_variance``, and its likelihood grows without bound as the floor falls.
    """

    site: str
    parents: tuple[str, ...]
    kind: str
    loglik: float
    free: int
    score: float
    degenerate: bool = False


class Families:
    """Complete, encoded training rows and the family scores they give.

    Parameters
    ----------
    net
        A declaration of the features, actions and parameters (its parents do not
        matter: any family of its end sites can be scored).
    data
        Training rows by site, as :func:`inference.fit` takes them (every site given;
        ``param.p`` NaN where the action does not use ``p``).
    score
        One of :data:`SCORES`.
    min_variance, l2, steps, ess
        The covariance floor and the softmax prior and Newton steps (as in
        :func:`inference.fit`); BDeu's equivalent sample size.
    pooled
        Whether a linear Gaussian's configuration that fits its few rows exactly
        (``degenerate``) scores them under the residual covariance pooled over its
        other configurations instead of the floor ``min_variance`` (the fit's): a
        bounded likelihood, so that a family's few exact fits do not buy it a score.
    """

    def __init__(
        self,
        net: EffectNetwork,
        data: Mapping[str, object],
        *,
        score: str = "bic",
        min_variance: float = 1e-6,
        l2: float = 0.01,
        steps: int = 500,
        ess: float = 1.0,
        pooled: bool = False,
    ) -> None:
        if score not in SCORES:
            raise ValueError(f"score must be one of {SCORES}, got {score!r}")
        check_settings(min_variance=min_variance, l2=l2, steps=steps, ess=ess)
        if score == "bdeu":
            mixed = [s.name for s in net.sites if not s.discrete and s.role != "param"]
            if mixed or net.parameters:
                raise ValueError(
                    f"score='bdeu' scores tables (discrete children of discrete parents) only; "
                    f"this network has the continuous sites {mixed or []} and the parameters "
                    f"{[p.name for p in net.parameters]}: use score='bic'"
                )
            if ess <= 0:
                raise ValueError(f"ess (BDeu's equivalent sample size) must be > 0, got {ess}")
        refuse_adaptive(net, "learn_structure")
        rows = read_rows(net, data)
        missing = rows.missing()
        if missing:
            raise ValueError(
                "learn_structure and family_scores score complete rows; the rows miss "
                f"values of {rows.missing_text()}. Learn from the complete rows "
                f"({rows.dropna_text()}; a bare dropna() also drops the rows whose action "
                "leaves a parameter NaN) and fit the learned network on all rows, or fit a "
                "declared structure with the gaps: inference.fit runs EM over them"
            )
        enc = rows.enc
        self.net, self.score_name = net, score
        self.min_variance, self.l2, self.steps, self.ess = min_variance, l2, steps, ess
        self.pooled = pooled
        self.n = enc.n_rows
        self.specs: dict[str, SiteSpec] = {s.name: s for s in net.sites}
        # as the fit reads them: a parameter's value NaN (unused) counts as 0
        self.values = {
            name: enc[name] if spec.discrete else enc[name].nan_to_num()
            for name, spec in self.specs.items()
        }
        self._cache: dict[tuple[str, tuple[str, ...]], Family] = {}

    # ------------------------------------------------------------------ the family's shape
    def fixed_parents(self, site: str) -> tuple[tuple[str, ...], tuple[str, ...]]:
        """The discrete and continuous parents every family of ``site`` has.

        The clusters (and, for a continuous site, the values) of the parameters acting on it.
        """
        acting = [m for m in self.net.mixtures if site in m.affected]
        values = () if self.specs[site].discrete else tuple(m.value.site for m in acting)
        return tuple(m.cluster.site for m in acting), values

    def layout(self, site: str, parents: Iterable[str]):
        """``(discrete parents, their cardinalities, continuous inputs, width)`` of the family.

        In the order :func:`models.structure.build_cpds` gives them.
        """
        chosen = set(parents)
        ordered = [q for q in self.specs if q in chosen]
        clusters, values = self.fixed_parents(site)
        discrete = tuple(q for q in ordered if self.specs[q].discrete) + clusters
        inputs = tuple(q for q in ordered if not self.specs[q].discrete) + values
        card = tuple(self.specs[q].size for q in discrete)
        return discrete, card, inputs, sum(self.specs[q].size for q in inputs)

    def entries(self, site: str, parents: Iterable[str]) -> int:
        """How many numbers the family's conditional distribution would hold."""
        _, card, _, width = self.layout(site, parents)
        groups, size = math.prod(card), self.specs[site].size
        if self.specs[site].discrete:
            return groups * size * (width + 1 if width else 1)
        return groups * (size + size * width + size * size + 1)

    def admissible(self, site: str, parents: Iterable[str]) -> bool:
        """Whether the family can be fitted.

        At most as many parent configurations as rows, and at most
        :data:`~models.structure.MAX_CPD_ENTRIES` numbers.
        """
        _, card, _, _ = self.layout(site, parents)
        return math.prod(card) <= self.n and self.entries(site, parents) <= MAX_CPD_ENTRIES

    # ------------------------------------------------------------------ scores
    def family(self, site: str, parents: Iterable[str]) -> Family:
        """The scored family of ``site`` with ``parents`` (cached)."""
        key = (site, tuple(q for q in self.specs if q in set(parents)))
        found = self._cache.get(key)
        if found is None:
            found = self._cache[key] = self._score(site, key[1])
        return found

    def scored(self, site: str) -> list[Family]:
        """The families of ``site`` scored so far, in the order they were."""
        return [f for (s, _), f in self._cache.items() if s == site]

    def _score(self, site: str, parents: tuple[str, ...]) -> Family:
        discrete, card, inputs, width = self.layout(site, parents)
        spec = self.specs[site]
        index = self._flat(discrete, card)
        reachable = self._reachable(site, discrete, card)
        y = self.values[site]
        x = torch.cat([self.values[q] for q in inputs], -1) if inputs else None
        groups = math.prod(card)
        degenerate = False
        if spec.discrete and x is None:
            kind = "table"
            counts = torch.bincount(index * spec.size + y, minlength=groups * spec.size)
            counts = counts.to(DTYPE).reshape(groups, spec.size)
            loglik = _table_loglik(counts)
            free = (spec.size - 1) * int(reachable.sum())
            if self.score_name == "bdeu":
                return Family(site, parents, kind, loglik, free, _bdeu(counts, self.ess))
        elif spec.discrete:
            kind = "softmax"
            cpd = SoftmaxCPD(site, discrete, card, spec.size, inputs, width)
            counts = torch.bincount(index * spec.size + y, minlength=groups * spec.size)
            counts = counts.to(DTYPE).reshape(*card, spec.size)
            start = cpd.m_step(Counts(counts), 0.0, 0.0)
            # a state no row of a configuration shows has its offset's supremum at minus
            # infinity, which Newton's steps approach by about one per step: start there
            absent = (counts == 0) & (counts.sum(-1, keepdim=True) > 0)
            start = SoftmaxParams(start.weight, start.bias.masked_fill(absent, ABSENT), start.n)
            fitted = cpd.maximise(index, x, y, start, l2=self.l2, steps=self.steps).params
            weight = fitted.weight.reshape(groups, spec.size, width)
            bias = fitted.bias.reshape(groups, spec.size)
            logits = (weight[index] @ x[:, :, None])[..., 0] + bias[index]
            loglik = float(logits.log_softmax(-1).gather(-1, y[:, None]).sum())
            free = (spec.size - 1) * (width + 1) * int(reachable.sum())
        else:
            kind = "linear_gaussian"
            zero = self._zero_weights(site, discrete, card, width)
            cpd = LinearGaussianCPD(site, discrete, card, spec.size, inputs, width, zero)
            moments = cpd.statistics(index, x, y)
            fitted = cpd.m_step(moments, 0.0, self.min_variance)
            d = spec.size
            fixed = zero.sum(-1) if zero is not None else torch.zeros(groups, dtype=torch.long)
            # a configuration with fewer rows than its mean's numbers plus the dimension
            # fits them exactly: its covariance is the floor, its likelihood unbounded
            short = (moments.n > 0) & (moments.n < width + 1 - fixed + d)
            degenerate = bool(short.any())
            if degenerate and self.pooled:
                fitted = _pooled_where(fitted, short, index, x, y, self.min_variance)
            loglik = _gaussian_loglik(fitted, index, x, y)
            per = d * (width + 1) + d * (d + 1) // 2 - d * fixed
            free = int(per[reachable.reshape(-1)].sum())
        score = self._penalised(loglik, free)
        return Family(site, parents, kind, loglik, free, score, degenerate)

    def _penalised(self, loglik: float, free: int) -> float:
        if self.score_name == "bic":
            return loglik - 0.5 * math.log(self.n) * free
        if self.score_name == "aic":
            return loglik - free
        return loglik

    def _flat(self, discrete: tuple[str, ...], card: tuple[int, ...]) -> torch.Tensor:
        index = torch.zeros(self.n, dtype=torch.long)
        for q, k in zip(discrete, card, strict=True):
            index = index * k + self.values[q]
        return index

    def _reachable(self, site: str, discrete: tuple[str, ...], card: tuple[int, ...]):
        """``(P...)`` bool: the configurations an action's use of each acting parameter allows.

        An action not using ``p`` puts ``cluster.p`` on cell 0.
        """
        reachable = torch.ones(card, dtype=torch.bool)
        for m in self.net.mixtures:
            if site not in m.affected:
                continue
            a, c = discrete.index(ACTION), discrete.index(m.cluster.site)
            uses = m.uses.reshape([-1 if i == a else 1 for i in range(len(card))])
            cell0 = (torch.arange(card[c]) == 0).reshape(
                [-1 if i == c else 1 for i in range(len(card))]
            )
            reachable = reachable & (uses | cell0)
        return reachable

    def _zero_weights(self, site, discrete, card, width) -> torch.Tensor | None:
        acting = [m for m in self.net.mixtures if site in m.continuous]
        if not acting:
            return None
        zero = torch.zeros(math.prod(card), width, dtype=torch.bool)
        end = width
        for m in reversed(acting):  # the parameters are the last inputs, in this order
            zero |= m.zero_weights(discrete, card, width, end)
            end -= m.parameter.dim
        return zero


def _table_loglik(counts: torch.Tensor) -> float:
    """``sum c log(c / n_g)`` over the cells of ``counts`` ``(G, K)``."""
    xlogy = torch.special.xlogy
    return float(xlogy(counts, counts).sum() - xlogy(counts.sum(-1), counts.sum(-1)).sum())


def _bdeu(counts: torch.Tensor, ess: float) -> float:
    """The BDeu log marginal likelihood of ``counts`` ``(G, K)``."""
    groups, k = counts.shape
    alpha, beta = ess / groups, ess / (groups * k)
    lg = torch.lgamma
    a, b = torch.tensor(alpha, dtype=DTYPE), torch.tensor(beta, dtype=DTYPE)
    cells = (lg(counts + b) - lg(b)).sum()
    rows = (lg(counts.sum(-1) + a) - lg(a)).sum()
    return float(cells - rows)


def _pooled_where(params, short, index, x, y, min_variance: float) -> LinearGaussianParams:
    """``params`` with the covariance of the configurations ``short`` replaced by a pooled one.

    ``short`` is ``(G,)`` bool; the pooled covariance is the residual covariance over the rows of
    the others (of all rows around their mean where every configuration is short), floored at
    ``min_variance``.
    """
    d = y.shape[-1]
    groups = short.shape[0]
    mean = params.bias.reshape(groups, d)[index]
    if x is not None:
        mean = mean + (params.weight.reshape(groups, d, -1)[index] @ x[:, :, None])[..., 0]
    kept = ~short[index]
    resid = (y - mean)[kept] if bool(kept.any()) else y - y.mean(0)
    cov = floor_variance((resid.mT @ resid / resid.shape[0])[None], min_variance)[0]
    tril = params.scale_tril.reshape(groups, d, d).clone()
    tril[short] = torch.linalg.cholesky(cov)
    return LinearGaussianParams(
        params.weight, params.bias, tril.reshape(params.scale_tril.shape), params.n
    )


def _gaussian_loglik(params, index: torch.Tensor, x: torch.Tensor | None, y: torch.Tensor):
    """The rows' log-likelihood under a linear Gaussian, row by row as the model's density reads it.

    ``-1/2 [d log 2 pi + log|S_g| + r^T S_g^-1 r]`` with ``r`` the row's residual in its
    configuration ``g``.
    """
    d = y.shape[-1]
    groups = params.bias.numel() // d
    mean = params.bias.reshape(groups, d)[index]
    if x is not None:
        weight = params.weight.reshape(groups, d, -1)[index]
        mean = mean + (weight @ x[:, :, None])[..., 0]
    tril = params.scale_tril.reshape(groups, d, d)[index]
    white = torch.linalg.solve_triangular(tril, (y - mean)[:, :, None], upper=False)[..., 0]
    logdet = 2 * tril.diagonal(dim1=-2, dim2=-1).log().sum(-1)
    return float(-0.5 * (d * math.log(2 * math.pi) + logdet + white.square().sum(-1)).sum())


def family_scores(
    net: EffectNetwork,
    data: Mapping[str, object],
    *,
    score: str = "bic",
    min_variance: float = 1e-6,
    l2: float = 0.01,
    steps: int = 500,
    ess: float = 1.0,
) -> dict[str, float]:
    """The score of every end site's family in ``net``.

    The site given its declared parents (see the module).

    Parameters
    ----------
    net
        The network.
    data
        Complete training rows by site, as :func:`inference.fit` takes them.
    score
        ``"bic"``, ``"aic"``, ``"bdeu"`` (tables only) or ``"loglik"`` (no penalty).
    min_variance, l2, steps, ess
        The covariance floor, the softmax slopes' prior and the most Newton steps of
        :func:`inference.fit`; BDeu's equivalent sample size.

    Returns
    -------
    dict
        ``{end site: score}`` in site order. For ``"loglik"`` each is the site's term of
        the log-likelihood of ``fit(net, data, pseudo_count=0, min_variance=min_variance,
        l2=l2, steps=steps)`` on ``data``; BIC and AIC subtract their penalties from it.

    Examples
    --------
    >>> from models import Discrete, EffectNetwork
    >>> net = EffectNetwork((Discrete("lit", (False, True)),), ("push",))
    >>> rows = {"initial.lit": [False, True], "action": ["push", "push"],
    ...         "end.lit": [True, True]}
    >>> family_scores(net, rows, score="loglik")
    {'end.lit': 0.0}
    """
    families = Families(
        net, data, score=score, min_variance=min_variance, l2=l2, steps=steps, ess=ess
    )
    out = {}
    for spec in net.sites:
        if spec.role == "end":
            cpd = net.cpd(spec.name)
            clusters, values = families.fixed_parents(spec.name)
            chosen = [q for q in (*cpd.parents, *cpd.inputs) if q not in (*clusters, *values)]
            found = families.family(spec.name, chosen)
            if found.kind != cpd.name:
                raise ValueError(
                    f"site {spec.name!r} is declared of kind {cpd.name!r}; family scores are "
                    f"computed for the default kinds ({found.kind!r} there)"
                )
            out[spec.name] = found.score
    return out
