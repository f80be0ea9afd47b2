"""Exact queries on a fitted effect network, batched over evidence rows.

* :func:`predict` -- forward: the end-state distribution given the initial state and an
  action (and its parameter). Discrete end features: probabilities. Continuous ones: a
  Gaussian mixture over whatever discrete sites stay unknown (one component when the
  action and the parameter are given).
* :func:`infer_action` -- emulate: the exact posterior over actions given the initial
  state and a full or partial end state, and the best action: the argmax of the action's
  marginal posterior with every other unobserved discrete site summed out (a marginal
  MAP, as pgmpy's ``map_query``; not the joint MAP ``infer_discrete`` returns).
* :func:`imitation_check` -- imitate: the log-likelihood of an observed end state under
  the executed action, and a surprise score: the predictive probability of an outcome
  strictly more likely than the one observed, over the joint of all observed end
  features (exact for discrete end states and where one Gaussian predicts the continuous
  ones; a deterministic quadrature where a mixture does: :mod:`inference.queries.surprise`).
  Near 1: the action did not do what it usually does.
* :func:`infer_parameter` -- the paper's inverse parameter query: the cluster posterior by
  enumeration, the most probable cluster added to the evidence, then the parameter by
  closed-form Gaussian conditioning.
* :func:`parameter_for_effect` -- the inverse model: the parameter value under which a
  desired continuous effect is most likely (per cluster by least squares, the clusters'
  candidates ranked by their exact joint density with the evidence).

Every query reports ``unseen``: the posterior probability that its answer rests on a
parent configuration no training row reached (answered from the pseudo-count prior alone),
and ``implausible``: a row whose observed end state the model gives almost no probability
(:mod:`inference.queries.plausibility`; threshold ``implausible_below``). Both warn; the answer
is still given.

Evidence follows one convention (:mod:`models.evidence`): state labels for discrete
sites, numbers for continuous ones; a parameter row of NaN is unknown and integrated out
for that row. Empty evidence rows (``n = 0``) give empty results of the right shapes.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Hashable, Mapping
from dataclasses import dataclass, field, fields, is_dataclass, replace

import numpy as np
import torch
from pyro.ops.indexing import Vindex

from inference.queries.enumeration import (
    Enumerated,
    conditional_log_evidence,
    over_row_chunks,
)
from inference.queries.plausibility import IMPLAUSIBLE_BELOW, check_threshold, plausibility
from inference.queries.surprise import QUADRATURE_POINTS, continuous_surprise
from models.declaration import (
    ACTION,
    DTYPE,
    EffectNetwork,
    Parameter,
    cluster_site,
    end_site,
    param_site,
)
from models.evidence import Evidence, is_partial
from models.gaussian import condition_on_observed
from models.params import NetworkParams, check_params

LOG_2PI = math.log(2 * math.pi)


@dataclass(frozen=True)
class GaussianMixture:
    """Per row a mixture: ``weights`` ``(n, M)``, ``means`` ``(n, M, d)``, ``covs`` ``(n, M, d, d)``."""

    weights: torch.Tensor
    means: torch.Tensor
    covs: torch.Tensor

    @property
    def mean(self) -> torch.Tensor:
        """``(n, d)`` mixture mean."""
        return (self.weights[..., None] * self.means).sum(1)

    @property
    def cov(self) -> torch.Tensor:
        """``(n, d, d)`` mixture covariance (law of total covariance)."""
        diff = self.means - self.mean[:, None, :]
        spread = diff[..., :, None] * diff[..., None, :]
        return (self.weights[..., None, None] * (self.covs + spread)).sum(1)


@dataclass(frozen=True)
class Prediction:
    """``discrete[feature]``: ``(n, K)`` probabilities over the feature's states in
    declaration order (``states[feature]``); ``continuous[feature]``: a mixture."""

    discrete: dict[str, torch.Tensor]
    continuous: dict[str, GaussianMixture]
    unseen: torch.Tensor  # (n,) probability of resting on an unseen configuration
    states: dict[str, tuple] = field(default_factory=dict)
    implausible: torch.Tensor | None = None  # (n,) bool; see inference.queries.plausibility

    def prob(self, feature: str, state: Hashable) -> torch.Tensor:
        """``(n,)`` probability that ``feature`` ends in ``state`` (a label)."""
        states = self._states(feature)
        if state not in states:
            raise ValueError(f"feature {feature!r} has no state {state!r}; states: {states}")
        return self.discrete[feature][:, states.index(state)]

    def most_likely(self, feature: str) -> tuple:
        """The most probable end state of ``feature`` per row, as labels."""
        states = self._states(feature)
        return tuple(states[i] for i in self.discrete[feature].argmax(-1).tolist())

    def _states(self, feature: str) -> tuple:
        if feature not in self.discrete:
            raise ValueError(
                f"no discrete prediction for {feature!r}; predicted: {sorted(self.discrete)}"
            )
        return self.states[feature]


@dataclass(frozen=True)
class ActionPosterior:
    """``probs`` ``(n, A)`` over ``actions``; ``best`` ``(n,)`` index; ``unseen`` ``(n, A)``;
    ``implausible`` ``(n,)`` bool: the observed end state has (almost) no probability
    under the model (see :mod:`inference.queries.plausibility`; ``None`` from the compiled
    queries), so ``best`` answers a question the model cannot explain."""

    probs: torch.Tensor
    best: torch.Tensor
    best_names: tuple[str, ...]
    log_evidence: torch.Tensor
    unseen: torch.Tensor
    actions: tuple[str, ...] = ()
    implausible: torch.Tensor | None = None

    def prob(self, action: str) -> torch.Tensor:
        """``(n,)`` posterior probability of the action named ``action``."""
        if action not in self.actions:
            raise ValueError(f"unknown action {action!r}; actions are {list(self.actions)}")
        return self.probs[:, self.actions.index(action)]


@dataclass(frozen=True)
class ImitationCheck:
    """What :func:`imitation_check` answers, per evidence row, ``(n,)`` each.

    With ``E`` the row's evidence other than its observed end sites (the initial state,
    the executed action, a parameter if given) and ``o*`` the observed end state (the
    observed discrete end features' states, the continuous ones' values in their
    observed dimensions):

    * ``log_likelihood``: ``log p(o* | E)``, every latent site summed or integrated out
      (a log-probability for discrete end features, a log-density for continuous ones).
    * ``surprise`` in [0, 1]: ``P_{O ~ p(. | E)}(p(O | E) > p(o* | E))``, the predictive
      probability of the outcomes strictly more likely than the observed one. 0: the
      most likely outcome; near 1: the action did not do what it usually does. For one
      Gaussian component it is the chi-square CDF of the squared Mahalanobis distance,
      ``P(chi2_d < D^2)``.
    * ``unseen``: the posterior probability that the observed end sites' configuration
      was never reached in training.
    * ``implausible`` bool (see :mod:`inference.queries.plausibility`).
    """

    log_likelihood: torch.Tensor
    surprise: torch.Tensor
    unseen: torch.Tensor
    implausible: torch.Tensor | None = None


@dataclass(frozen=True)
class ParameterPosterior:
    """``cluster_probs`` ``(n, C)``, ``best_cluster`` ``(n,)``; the parameter given the best
    cluster (the paper's answer): ``mean`` ``(n, d)``, ``cov`` ``(n, d, d)``.

    ``outside`` ``(n,)`` bool: that mean lies outside the parameter's ``[low, high]`` (an
    action the declaration does not cover). ``mixture``: with ``mixture=True``, the full
    posterior of the parameter, one Gaussian per cluster weighted by ``cluster_probs``.
    ``implausible`` ``(n,)`` bool: the observed end state has (almost) no probability
    under the model (see :mod:`inference.queries.plausibility`; ``None`` from the compiled query).
    """

    cluster_probs: torch.Tensor
    best_cluster: torch.Tensor
    mean: torch.Tensor
    cov: torch.Tensor
    unseen: torch.Tensor
    outside: torch.Tensor | None = None
    mixture: GaussianMixture | None = None
    implausible: torch.Tensor | None = None


@dataclass(frozen=True)
class ParameterForEffect:
    """What :func:`parameter_for_effect` answers, per evidence row.

    ``value`` ``(n, d)``: the parameter value to use; ``cluster`` ``(n,)``: the cluster
    whose linear Gaussian it inverts; ``log_density`` ``(n,)``: ``log p(value, evidence)``,
    the posterior density of ``value`` up to the evidence's own probability; ``miss``
    ``(n,)``: the observed effect's squared Mahalanobis distance from that cluster's
    prediction at ``value`` (zero: the value produces the effect exactly; large: the
    effect lies outside what the cluster reaches). ``candidates`` ``(n, C, d)`` and
    ``candidate_log_density`` ``(n, C)``: every cluster's value and its score.
    ``outside`` ``(n,)`` bool: ``value`` lies outside the parameter's ``[low, high]``.
    """

    value: torch.Tensor
    cluster: torch.Tensor
    log_density: torch.Tensor
    miss: torch.Tensor
    candidates: torch.Tensor
    candidate_log_density: torch.Tensor
    outside: torch.Tensor


TIE_TOLERANCE = 1e-9  # relative: scores this close to the maximum count as tied


def first_best(score: torch.Tensor, top: torch.Tensor | None = None) -> torch.Tensor:
    """``(n,)`` index of the best score per row; among ties (within a relative
    ``TIE_TOLERANCE`` of the maximum, so that rounding does not decide) the lowest index.
    ``top``: the rows' maxima ``(n,)``, if already known."""
    top = score.max(-1).values if top is None else top
    return (score >= (top - TIE_TOLERANCE * top.abs())[:, None]).int().argmax(-1)


def _prepare(net: EffectNetwork, params: NetworkParams, evidence: Mapping[str, object]) -> Evidence:
    check_params(net, params)
    enc = net.encode(evidence)
    if not len(enc):
        raise ValueError("evidence is empty: give at least the initial state")
    return enc


def allowed_actions(net: EffectNetwork, allowed: object, n: int) -> torch.Tensor | None:
    """``allowed`` as an ``(A,)`` or ``(n, A)`` bool mask with at least one action per row.

    Accepts ``None``, a bool mask ``(A,)`` or ``(n, A)``, or a collection of action names.
    """
    if allowed is None:
        return None
    a = len(net.actions)
    if isinstance(allowed, str):
        allowed = [allowed]
    if not isinstance(allowed, torch.Tensor) and all(isinstance(x, str) for x in allowed):
        mask = torch.zeros(a, dtype=torch.bool)
        for name in allowed:
            mask[net.action_index(name)] = True
    else:
        mask = torch.as_tensor(
            np.asarray(allowed) if not isinstance(allowed, torch.Tensor) else allowed
        )
        if mask.dtype != torch.bool:
            raise ValueError(f"allowed must be action names or a bool mask, got dtype {mask.dtype}")
        if mask.shape not in ((a,), (n, a)):
            raise ValueError(
                f"allowed has shape {tuple(mask.shape)}; expected ({a},) or ({n}, {a}) "
                f"(one flag per action), or a list of action names"
            )
    none = ~mask.reshape(-1, a).any(-1)
    if none.any():
        row = int(none.nonzero()[0])
        where = "" if mask.dim() == 1 else f" in row {row}"
        raise ValueError(f"allowed permits no action{where}: allow at least one")
    return mask


def placeholder_row(enc: Evidence) -> Evidence:
    """A placeholder row (state 0, zeros) that stands in for empty evidence: a query runs
    on it and cuts its answer to zero rows (:func:`no_rows`)."""
    values = {k: torch.zeros(1, *v.shape[1:], dtype=v.dtype) for k, v in enc.items()}
    return Evidence(enc.net, values, 1)


def no_rows(result):
    """``result`` (a query's answer for one placeholder row) cut to zero rows."""
    if isinstance(result, torch.Tensor):
        return result[:0]
    if isinstance(result, tuple):
        return ()
    if isinstance(result, dict):
        return {k: no_rows(v) for k, v in result.items()}
    if is_dataclass(result):
        return replace(
            result,
            **{
                f.name: no_rows(getattr(result, f.name))
                for f in fields(result)
                if f.name not in ("states", "actions")
            },
        )
    return result


def _unseen_mass(
    net: EffectNetwork, params: NetworkParams, e: Enumerated, sites: list[str]
) -> torch.Tensor:
    """Joint-posterior-weighted indicator that any of ``sites`` sits on an unseen configuration."""
    values = {name: s["value"] for name, s in e.trace.nodes.items() if s["type"] == "sample"}
    flag = torch.zeros((), dtype=torch.bool)
    for site in sites:
        cpd = net.cpd(site)
        index = [values[s] for s in cpd.parents]
        flag = flag | ~Vindex(cpd.seen(params[site]))[tuple(index)]
    return flag.to(DTYPE)


def predict(
    net: EffectNetwork,
    params: NetworkParams,
    evidence: Mapping[str, object],
    *,
    implausible_below: float = IMPLAUSIBLE_BELOW,
) -> Prediction:
    """End-state distribution of every end feature not in ``evidence``.

    ``implausible`` flags rows whose observed end features (if any are given) have a
    probability below ``implausible_below`` (:mod:`inference.queries.plausibility`).
    """
    below = check_threshold(implausible_below)
    enc = _prepare(net, params, evidence)
    if enc.n_rows == 0:
        return no_rows(predict(net, params, placeholder_row(enc), implausible_below=below))
    targets = [
        f.name
        for f in net.features
        if end_site(f.name) not in enc or is_partial(enc[end_site(f.name)])
    ]
    for m in net.mixtures:  # see effect_model: each is given those sampled before it
        partly = [s for s in m.continuous if s in enc and is_partial(enc[s])]
        theta = enc.get(m.value.site)
        if len(partly) > 1 and (theta is None or bool(torch.isnan(theta).any())):
            raise ValueError(
                f"predict: {partly} are observed in part and share the parameter "
                f"{m.parameter.name!r}, whose value is not given; predict one at a time "
                "(the other observed in full or left out), or give the parameter"
            )
    discrete, continuous = {}, {}
    unseen_sites = [end_site(f) for f in targets]
    for f in targets:
        site = end_site(f)
        if net.site(site).discrete:
            discrete[f] = over_row_chunks(
                net, params, enc, {site}, lambda e, *_, s=site: e.marginal(s)
            )
        else:
            continuous[f] = _mixture(net, params, enc, site)

    def unseen(e, *_):
        post = e.posterior()
        return (
            (post * _unseen_mass(net, params, e, unseen_sites)).reshape(-1, post.shape[-1]).sum(0)
        )

    states = {f: net.feature(f).states for f in discrete}
    # the unseen flag reads the targets' parents: latent end parents must be traced
    end_parents = {q for s in unseen_sites for q in net.cpd(s).parents if net.site(q).role == "end"}
    unseen_mass = over_row_chunks(net, params, enc, end_parents, unseen).clamp(0, 1)
    flag = plausibility(net, params, enc).implausible(below)
    return Prediction(discrete, continuous, unseen_mass, states, flag)


def _mixture(net, params, enc, site) -> GaussianMixture:
    """The site's mixture over the enumerated sites; a partly observed site's components
    are conditioned on its observed dimensions (which hold their value, variance 0)."""
    partial = site in enc

    def fn(e: Enumerated, chunk: Evidence, _):
        post = e.posterior()  # (E..., n)
        d_fn = e.trace.nodes[site]["fn"]
        n = post.shape[-1]
        shape = post.shape
        loc = d_fn.loc.expand(*shape, d_fn.loc.shape[-1])
        cov = d_fn.covariance_matrix.expand(*shape, *d_fn.covariance_matrix.shape[-2:])
        if partial:
            loc, cov = condition_on_observed(chunk[site], loc, cov)
        w = post.reshape(-1, n).T
        return (
            w,
            loc.reshape(-1, n, loc.shape[-1]).transpose(0, 1),
            cov.reshape(-1, n, *cov.shape[-2:]).transpose(0, 1),
        )

    w, m, c = over_row_chunks(net, params, enc, set(), fn, trace_only=set() if partial else {site})
    keep = w.sum(0) > 0  # drop components no row can reach
    return GaussianMixture(w[:, keep], m[:, keep], c[:, keep])


def infer_action(
    net: EffectNetwork,
    params: NetworkParams,
    evidence: Mapping[str, object],
    *,
    allowed: torch.Tensor | None = None,
    avoid_unseen: bool = True,
    implausible_below: float = IMPLAUSIBLE_BELOW,
) -> ActionPosterior:
    """Exact posterior over actions given the initial state and a (partial) end state.

    Parameters
    ----------
    allowed
        Actions that may be chosen as ``best``: a list of action names, or an ``(A,)`` or
        ``(n, A)`` bool mask. ``ValueError`` if a row permits none.
    avoid_unseen
        Never choose as ``best`` an action whose configuration no training row reached
        (its likelihood is the uniform prior's), unless every allowed action is unseen.
    implausible_below
        ``implausible`` flags rows whose observed end state has a probability below this
        under the model, every action summed out (:mod:`inference.queries.plausibility`); such a
        row still gets its posterior and ``best``.
    """
    below = check_threshold(implausible_below)
    enc = _prepare(net, params, evidence)
    if ACTION in enc:
        raise ValueError(
            "evidence names the action; infer_action infers it (use predict or imitation_check)"
        )
    allowed = allowed_actions(net, allowed, enc.n_rows)
    if enc.n_rows == 0:
        return no_rows(
            infer_action(
                net,
                params,
                placeholder_row(enc),
                allowed=allowed,
                avoid_unseen=avoid_unseen,
                implausible_below=below,
            )
        )
    observed_end = [end_site(f.name) for f in net.features if end_site(f.name) in enc]

    def fn(e: Enumerated, *_):
        post = e.posterior()
        dim = e.dims[ACTION]
        others = [d for d in range(post.dim() - 1) if d != post.dim() + dim]
        if post.shape[dim] == 1:  # no kept factor depends on the action (see marginal)
            probs = e.marginal(ACTION)
        else:  # the joint posterior summed over the other sites: one pass, not three
            probs = (post.sum(others) if others else post).T
        flag = _unseen_mass(net, params, e, observed_end) if observed_end else torch.zeros(())
        if not bool(flag.any()):
            return probs, torch.zeros_like(probs), e.log_evidence
        if others and torch.broadcast_shapes(post.shape, flag.shape) == post.shape:
            joint = post.mul_(flag)  # post is this call's own and probs a sum of it
        else:
            joint = (post * flag).expand_as(post)
        per_action = joint.sum(others).T if others else joint.T
        return probs, per_action / probs.clamp_min(1e-300), e.log_evidence

    probs, unseen, log_evidence = over_row_chunks(net, params, enc, set(), fn)
    unseen = unseen.clamp(0, 1)
    score = probs.clone()
    if allowed is not None:
        score = torch.where(allowed.expand_as(score), score, -1.0)
    if avoid_unseen:
        seen_score = torch.where(unseen < 0.5, score, -1.0)
        score = torch.where((seen_score.max(-1, keepdim=True).values >= 0), seen_score, score)
    best = first_best(score)
    names = tuple(net.actions[i] for i in best.tolist())
    flag = plausibility(net, params, enc, log_evidence=log_evidence).implausible(below)
    return ActionPosterior(probs, best, names, log_evidence, unseen, net.actions, flag)


def imitation_check(
    net: EffectNetwork,
    params: NetworkParams,
    evidence: Mapping[str, object],
    *,
    n_samples: int = QUADRATURE_POINTS,
    seed: int = 0,
    implausible_below: float = IMPLAUSIBLE_BELOW,
) -> ImitationCheck:
    """How surprising is each observed end state under the executed action?

    The fields are defined in :class:`ImitationCheck`. Discrete end states are summed
    exactly; with a continuous end feature observed, the surprise is exact where each
    discrete outcome has one Gaussian component (the action and the parameter given, say)
    and a deterministic quadrature where it has several (an unknown parameter's clusters):
    ``n_samples`` points per component (directions times radii), ``seed`` fixing the
    quasi-random directions beyond two continuous dimensions (:mod:`inference.queries.surprise`).
    The same row gets the same answer in any batch. ``implausible`` flags rows whose
    observed end state has a probability below ``implausible_below`` given the executed
    action (:mod:`inference.queries.plausibility`).
    """
    below = check_threshold(implausible_below)
    enc = _prepare(net, params, evidence)
    if ACTION not in enc:
        raise ValueError(
            "imitation_check needs the executed action in the evidence (site 'action')"
        )
    observed = [end_site(f.name) for f in net.features if end_site(f.name) in enc]
    if not observed:
        raise ValueError(
            "imitation_check needs at least one observed end state (sites 'end.<feature>')"
        )
    if not isinstance(n_samples, int) or n_samples < 1:
        raise ValueError(f"n_samples must be a positive int, got {n_samples!r}")
    if enc.n_rows == 0:
        return no_rows(
            imitation_check(
                net, params, placeholder_row(enc), n_samples=1, seed=seed, implausible_below=below
            )
        )
    prior = enc.without(*observed)
    log_joint = over_row_chunks(net, params, enc, set(), lambda e, *_: e.log_evidence)
    log_prior = over_row_chunks(net, params, prior, set(), lambda e, *_: e.log_evidence)
    log_lik = conditional_log_evidence(net, params, enc, prior, log_joint, log_prior)
    if all(net.site(s).discrete for s in observed):
        surprise = _discrete_surprise(net, params, prior, observed, log_lik)
    else:
        surprise = continuous_surprise(net, params, enc, observed, n_points=n_samples, seed=seed)

    def unseen(e, *_):
        post = e.posterior(strict=False)  # an impossible outcome rests on no configuration
        return (post * _unseen_mass(net, params, e, observed)).reshape(-1, post.shape[-1]).sum(0)

    flag = plausibility(net, params, enc, log_evidence=log_joint, log_prior=log_prior)
    flag = flag.implausible(below)
    unseen_mass = over_row_chunks(net, params, enc, set(), unseen).clamp(0, 1)
    return ImitationCheck(log_lik, surprise, unseen_mass, flag)


def _discrete_surprise(net, params, prior, observed, log_lik) -> torch.Tensor:
    """P(outcome strictly more likely than the observed one), by enumerating outcomes."""

    def fn(e: Enumerated, *_):
        w = e.log_weight - e.log_norm  # joint over outcomes and latents, (E..., n)
        outcome_dims = [w.dim() + e.dims[s] for s in observed]
        latent_dims = [d for d in range(w.dim() - 1) if d not in outcome_dims]
        joint = w.logsumexp(latent_dims, keepdim=True) if latent_dims else w
        return joint.reshape(-1, w.shape[-1]).T  # (n, outcomes)

    joint = over_row_chunks(net, params, prior, set(observed), fn)
    more_likely = joint > log_lik[:, None] + 1e-9
    return (joint.exp() * more_likely).sum(-1).clamp(0, 1)


def infer_parameter(
    net: EffectNetwork,
    params: NetworkParams,
    parameter: str,
    evidence: Mapping[str, object],
    *,
    mixture: bool = False,
    implausible_below: float = IMPLAUSIBLE_BELOW,
) -> ParameterPosterior:
    """The paper's inverse parameter query: best cluster by enumeration, then the parameter.

    With ``mixture=True`` the result also holds the parameter's full posterior (every
    cluster's conditional Gaussian, weighted by the cluster posterior), whose mean is the
    posterior mean of the parameter; the paper's best-cluster answer stays in ``mean``.
    ``implausible`` flags rows whose observed end state has a probability below
    ``implausible_below`` given the action, the parameter integrated out
    (:mod:`inference.queries.plausibility`).
    """
    below = check_threshold(implausible_below)
    m = net.mixture(parameter)
    p = m.parameter
    enc = _prepare(net, params, evidence)
    if enc.n_rows == 0:
        return no_rows(
            infer_parameter(
                net,
                params,
                parameter,
                _inverse_placeholder(m, enc),
                mixture=mixture,
                implausible_below=below,
            )
        )
    enc, observed = _inverse_evidence(net, m, enc, "infer_parameter")
    flag = plausibility(net, params, enc).implausible(below)
    children = [net.cpd(s) for s in m.continuous if s in enc]
    if not children:  # only discrete effects observed
        answer = _parameter_from_cluster(net, params, m, enc, observed, mixture)
        return replace(answer, implausible=flag)
    latent = sorted(
        {s for child in children for s in child.parents if s not in enc and s != m.cluster.site}
        - {
            q.cluster.site
            for q in (net.acting_on(m.child) if m.child is not None else ())
            if q is not m
        }
    )
    if latent and all(net.site(s).role == "initial" for s in latent):
        return replace(
            _over_latent_parents(net, params, m, enc, children, latent, mixture), implausible=flag
        )
    enc, acting = _given_others(net, m, enc, children, "infer_parameter")
    probs = over_row_chunks(net, params, enc, set(), lambda e, *_: e.marginal(cluster_site(p.name)))
    best = probs.argmax(-1)
    mean, cov = m.posterior(params, children, enc, best, acting=acting)
    unseen = torch.zeros(enc.n_rows, dtype=torch.bool)
    for child in children:
        index = tuple(enc[s] if s != m.cluster.site else best for s in child.parents)
        unseen = unseen | ~child.seen(params[child.site])[index]
    unseen = unseen.to(DTYPE)
    full = None
    if mixture:
        every = torch.arange(p.n_clusters).expand(enc.n_rows, -1)  # (n, C)
        means, covs = m.posterior(params, children, enc, every, acting=acting)
        full = GaussianMixture(probs, means, covs)
    return ParameterPosterior(
        probs, best, mean, cov, unseen, outside_range(p, mean), full, implausible=flag
    )


def parameter_for_effect(
    net: EffectNetwork,
    params: NetworkParams,
    parameter: str,
    evidence: Mapping[str, object],
) -> ParameterForEffect:
    """The parameter value that produces a desired effect: the inverse model.

    :func:`infer_parameter` answers "which value was used, given that this effect was
    seen": the posterior, which weighs the effect against where values usually lie. With
    noisy effects that pulls the answer towards each cluster's mean (by the share of the
    effect's spread that is noise) and a controller that aims with it falls short. This
    query answers "which value makes this effect most likely": for every cluster ``c``
    the value ``theta_c`` that maximises the observed continuous effects' likelihood under
    ``c``'s linear Gaussians (weighted least squares; see
    :meth:`models.cpds.mixture.ParameterMixture.best_fit`), and among these candidates the
    one of highest joint density ``p(theta_c, evidence)``, exact (every cluster summed out;
    under the grid layout a value given without its cluster comes with its cell, so a
    candidate outside its own cell is scored under the cell it falls in). The factors
    that depend on the value (the cluster table, the clusters' Gaussians, the observed
    effects' linear Gaussians, and under the grid layout the value's cell) are summed over the clusters in closed form for every
    candidate; the others are one constant per row, read off a single evaluation of the
    model at the row's best candidate. Where another site depends on the cluster or the
    value (a discrete feature the parameter acts on, an unobserved effect), the model
    scores every candidate instead, ``C`` times the cost (tested equal to the closed
    form where both apply). Ranking by the joint density rather than the effect's
    likelihood alone keeps a cluster whose line, extrapolated far from the values it was
    fitted on, happens to pass through the effect from winning. Partial evidence counts
    its observed dimensions (as in :func:`infer_parameter`). Without
    noise and with the effect inside a cluster's reach, the answer reproduces the
    effect exactly under that cluster (``miss`` 0).

    The evidence is as for :func:`infer_parameter` (the parameter and its cluster
    unknown; the action, or the only one using the parameter; the discrete parents of the
    observed effects; any other parameter acting on the same feature given); at least
    one continuous feature the parameter acts on must be observed. Raises ``ValueError``
    otherwise.
    """
    m = net.mixture(parameter)
    p = m.parameter
    enc = _prepare(net, params, evidence)
    if enc.n_rows == 0:
        return no_rows(parameter_for_effect(net, params, parameter, _inverse_placeholder(m, enc)))
    enc, _ = _inverse_evidence(net, m, enc, "parameter_for_effect")
    children = [net.cpd(s) for s in m.continuous if s in enc]
    if not children:
        raise ValueError(
            f"parameter_for_effect needs an observed continuous feature {p.name!r} acts on "
            f"(one of {list(m.continuous)}): a discrete effect has no value to invert"
        )
    given, acting = _given_others(net, m, enc, children, "parameter_for_effect")
    n, c = enc.n_rows, p.n_clusters
    every = torch.arange(c).expand(n, -1)
    whitened = m.whitened(params, children, given, every, acting=acting)
    candidates, miss = m.best_fit(params, whitened, every)  # (n, C, d), (n, C)
    rows = torch.arange(n)
    fast = _candidate_scores(net, params, m, given, children, acting, candidates, whitened)
    if fast is None:  # a factor beyond the mixture depends on the value: the model scores all
        scored = enc.repeat(c)
        scored = Evidence(net, dict(scored) | {m.value.site: candidates.reshape(n * c, -1)}, n * c)
        log_density = over_row_chunks(net, params, scored, set(), lambda e, *_: e.log_evidence)
        log_density = log_density.reshape(n, c)
    else:  # the model scores each row's best; the rest differ from it by the mixture's terms
        best = first_best(fast)
        scored = Evidence(net, dict(enc) | {m.value.site: candidates[rows, best]}, n)
        exact = over_row_chunks(net, params, scored, set(), lambda e, *_: e.log_evidence)
        top = fast[rows, best]
        shift = torch.where(torch.isfinite(top), exact - top, 0.0)
        log_density = torch.where(torch.isfinite(exact)[:, None], fast + shift[:, None], -torch.inf)
    best = first_best(log_density)
    value = candidates[rows, best]
    return ParameterForEffect(
        value,
        best,
        log_density[rows, best],
        miss[rows, best],
        candidates,
        log_density,
        outside_range(p, value),
    )


#: Elements per row chunk of :func:`_candidate_scores`' ``(rows, C, C)`` tensors.
_SCORE_CHUNK = 1 << 18


def _candidate_scores(net, params, m, given: Evidence, children, acting, candidates, whitened):
    """``log sum_c' p(c' | action) p(theta | c') prod_j p(y_j | ..., c', theta)`` for every
    row and candidate ``theta`` ``(n, C, k)``, from the children's ``whitened`` terms
    (:meth:`models.cpds.mixture.ParameterMixture.whitened`): the factors of
    ``log p(theta, evidence)`` that depend on the value (under the grid layout the value's
    cell is its cluster), in closed form. The other
    factors are a constant per row. None where that does not hold: a site other than the
    observed continuous ``children`` depends on the cluster or the value, the cluster has
    parents besides the action, or a child's other continuous inputs are not all given.
    """
    depends = {m.cluster.site, m.value.site}
    mine = {child.site for child in children}
    for spec in net.sites:
        if spec.name in depends or spec.name in mine:
            continue
        if depends & set(net.cpd(spec.name).parents):
            return None
    if tuple(net.cpd(m.cluster.site).parents) != (ACTION,):
        return None
    others = {q.value.site for q in acting}
    for child in children:
        for site in child.inputs:
            if site not in others and (site not in given or bool(torch.isnan(given[site]).any())):
                return None
    n, c, k = candidates.shape
    slope, target, log_norm = whitened  # the children's, per row and cluster c' (n or 1, C')
    mean, cov = m.belief(params, torch.arange(c))  # (C', k), (C', k, k)
    tril = torch.linalg.cholesky(cov)
    eye = torch.eye(k, dtype=cov.dtype).expand_as(cov)
    whiten = torch.linalg.solve_triangular(tril, eye, upper=False)  # (C', k, k)
    log_norm = (
        log_norm
        - tril.diagonal(dim1=-2, dim2=-1).log().sum(-1)
        - k / 2 * LOG_2PI
        + params[m.cluster.site].probs.clamp_min(0.0).log()[given[ACTION]]
    )  # (n, C')
    # The squared distances sum |b - A theta|^2 over the children's whitened rows and the
    # value's, per row and cluster c'. Completed to m0 + |U (theta - theta_hat)|^2 (H =
    # A^T A = U^T U; theta_hat: the value's posterior mean under c'), a sum of squares
    # without cancellation, evaluated one component at a time below.
    lead = target.shape[:-2]  # (n,): the observation is per row
    a = torch.cat([slope.expand(*lead, -1, -1, -1), whiten.expand(*lead, -1, -1, -1)], -2)
    prior = (whiten @ mean[..., None])[..., 0]
    b = torch.cat([target, prior.expand(*lead, -1, -1)], -1)  # (n, C', D + k)
    hessian = a.mT @ a  # (n, C', k, k), positive definite: the value's precision is in it
    upper = torch.linalg.cholesky(hessian).mT
    theta_hat = torch.cholesky_solve(a.mT @ b[..., None], upper.mT)[..., 0]  # (n, C', k)
    m0 = (b - (a @ theta_hat[..., None])[..., 0]).square().sum(-1)  # (n, C')
    base = log_norm - 0.5 * m0  # (n, C')
    shift = (upper @ theta_hat[..., None])[..., 0]  # (n, C', k)
    if not m.parameter.adaptive:  # grid: a value given alone comes with its cell
        cells = m.parameter.cluster_of(candidates)  # (n, C)
        rows = torch.arange(n)[:, None]
        z = (upper[rows, cells] @ candidates[..., None])[..., 0] - shift[rows, cells]
        return base[rows, cells] - 0.5 * z.square().sum(-1)
    out = []
    step = max(1, _SCORE_CHUNK // max(1, c * c))
    for start in range(0, n, step):
        part = slice(start, start + step)
        theta = candidates[part]  # (r, C, k)
        u, sh = upper[part], shift[part]
        total = torch.zeros(len(theta), c, c, dtype=theta.dtype)  # (r, C candidates, C')
        for row in range(k):
            z = torch.addcmul(-sh[:, None, :, row], theta[:, :, None, 0], u[:, None, :, row, 0])
            for col in range(1, k):
                z.addcmul_(theta[:, :, None, col], u[:, None, :, row, col])
            total.addcmul_(z, z)
        log = base[part][:, None, :] - 0.5 * total
        # logsumexp in place; terms below e^-700 of the largest, which change no float64
        # sum, are dropped before exp (its far tail, near the denormals, is slow)
        top = log.amax(-1, keepdim=True)
        top = torch.where(torch.isfinite(top), top, 0.0)
        log = log.sub_(top)
        log = log.masked_fill_(log < -700.0, -torch.inf)
        out.append(log.exp_().sum(-1).log_() + top[..., 0])
    return torch.cat(out, 0)


def _inverse_placeholder(m, enc: Evidence) -> Evidence:
    """A placeholder row for an empty inverse query, with an action using the parameter."""
    placeholder = placeholder_row(enc)
    if ACTION in placeholder:
        placeholder = placeholder.without(ACTION) | {ACTION: [m.parameter.actions[0]]}
    return placeholder


def _inverse_evidence(net, m, enc: Evidence, query: str) -> tuple[Evidence, list[str]]:
    """Check an inverse query's evidence: the parameter unknown, an effect of it observed,
    an action using it in every row (filled in when only one action does). Returns the
    evidence with the action, and the observed sites the parameter acts on."""
    p = m.parameter
    if param_site(p.name) in enc or cluster_site(p.name) in enc:
        raise ValueError(
            f"evidence gives {param_site(p.name)!r} or {cluster_site(p.name)!r}, which this query infers"
        )
    observed = [s for s in m.affected if s in enc]
    if not observed or m.child is not None and m.child not in enc and len(m.affected) == 1:
        y_site = m.child or m.affected[0]
        raise ValueError(
            f"{query} needs the observed end state {y_site!r} of the feature {p.name!r} acts on"
            + (f" (or one of {list(m.affected)})" if len(m.affected) > 1 else "")
        )
    if ACTION not in enc:
        if len(p.actions) != 1:
            raise ValueError(f"give the action (one of {list(p.actions)}) that used {p.name!r}")
        action = torch.full((enc.n_rows,), net.action_index(p.actions[0]))
        enc = Evidence(net, dict(enc) | {ACTION: action}, enc.n_rows)
    not_using = ~m.in_use(enc[ACTION])
    if not_using.any():
        row = int(not_using.nonzero()[0])
        raise ValueError(
            f"row {row}: action {net.actions[int(enc[ACTION][row])]!r} does not use {p.name!r}"
        )
    return enc, observed


def _given_others(net, m, enc: Evidence, children, query: str):
    """The other parameters acting on the same feature, which must be given in every row
    whose action uses them (elsewhere they are ignored, NaN or absent): the evidence with
    their cells as clusters, and every parameter acting on the feature (in input order).
    Checks that the observed children's discrete parents are given."""
    p = m.parameter
    acting = net.acting_on(m.child) if m.child is not None else (m,)
    for q in acting:
        if q is m:
            continue
        uses = q.in_use(enc[q.action])
        theta = enc.get(q.value.site)
        if theta is None:
            theta = torch.full((enc.n_rows, q.parameter.dim), float("nan"), dtype=DTYPE)
        unknown = torch.isnan(theta).any(-1) & uses
        if bool(unknown.any()):
            row = int(unknown.nonzero()[0])
            raise ValueError(
                f"{query}({p.name!r}) needs {q.value.site!r} in every row whose action uses "
                f"it: it acts on {m.child!r} too (row {row} leaves it unknown)"
            )
        enc = enc | net.encode_indices({q.cluster.site: q.cells(theta, enc[q.action])})
    for child in children:
        missing = [s for s in child.parents if s not in enc and s != m.cluster.site]
        if missing:
            raise ValueError(
                f"{query} needs the discrete parents {missing} of {child.site!r} as evidence"
            )
    return enc, acting


def _over_latent_parents(net, params, m, enc, children, latent, mixture) -> ParameterPosterior:
    """:func:`infer_parameter` where initial states the observed effects depend on are
    unknown: their states and the cluster enumerated jointly (their exact posterior), the
    parameter given the best cluster a mixture over those states (its mean and covariance
    returned, by the law of total covariance), each cluster's in ``mixture`` likewise."""
    p = m.parameter
    sites = [*latent, m.cluster.site]

    def joint(e: Enumerated, *_):
        w = e.log_weight
        keep = [w.dim() + e.dims[s] for s in sites]
        others = [d for d in range(w.dim() - 1) if d not in keep]
        w = w.logsumexp(others, keepdim=True) if others else w
        w = w.permute(w.dim() - 1, *keep, *others).reshape(w.shape[-1], -1)
        return (w - w.logsumexp(-1, keepdim=True)).exp()

    sizes = [net.site(s).size for s in latent]
    n, c = enc.n_rows, p.n_clusters
    weights = over_row_chunks(net, params, enc, set(), joint).reshape(n, -1, c)  # (n, S, C)
    probs = weights.sum(1)
    best = probs.argmax(-1)
    every = torch.arange(c).expand(n, -1)
    means, covs, unseen = [], [], []
    for states in itertools.product(*[range(k) for k in sizes]):
        given = enc | net.encode_indices(
            {s: torch.full((n,), i) for s, i in zip(latent, states, strict=True)}
        )
        given, acting = _given_others(net, m, given, children, "infer_parameter")
        mean, cov = m.posterior(params, children, given, every, acting=acting)
        means.append(mean)
        covs.append(cov)
        flag = torch.zeros(n, dtype=torch.bool)
        for child in children:
            index = tuple(given[s] if s != m.cluster.site else best for s in child.parents)
            flag = flag | ~child.seen(params[child.site])[index]
        unseen.append(flag)
    means, covs = torch.stack(means, 1), torch.stack(covs, 1)  # (n, S, C, k), (n, S, C, k, k)
    share = weights / probs.clamp_min(1e-300)[:, None, :]  # p(states | cluster, evidence)
    mean = (share[..., None] * means).sum(1)  # (n, C, k)
    spread = means - mean[:, None]
    cov = (share[..., None, None] * (covs + spread[..., :, None] * spread[..., None, :])).sum(1)
    rows = torch.arange(n)
    unseen = (share[rows, :, best] * torch.stack(unseen, 1).to(DTYPE)).sum(1)
    full = GaussianMixture(probs, mean, cov) if mixture else None
    answer, answer_cov = mean[rows, best], cov[rows, best]
    return ParameterPosterior(
        probs, best, answer, answer_cov, unseen, outside_range(p, answer), full
    )


def _parameter_from_cluster(net, params, m, enc, observed, mixture) -> ParameterPosterior:
    """The answer when only discrete features the parameter acts on are observed: they
    depend on its cell, so the parameter given its best cluster is that cluster's
    Gaussian."""

    def fn(e: Enumerated, *_):
        post = e.posterior()
        unseen = (post * _unseen_mass(net, params, e, observed)).reshape(-1, post.shape[-1])
        return e.marginal(m.cluster.site), unseen.sum(0)

    probs, unseen = over_row_chunks(net, params, enc, set(), fn)
    best = probs.argmax(-1)
    prior = params[m.value.site]
    mean, cov = prior.bias[best], prior.covariance[best]
    full = None
    if mixture:
        n = enc.n_rows
        every = (prior.bias.expand(n, *prior.bias.shape), prior.covariance.expand(n, -1, -1, -1))
        full = GaussianMixture(probs, *every)
    return ParameterPosterior(
        probs, best, mean, cov, unseen.clamp(0, 1), outside_range(m.parameter, mean), full
    )


def outside_range(p: Parameter, value: torch.Tensor) -> torch.Tensor:
    """``(n,)`` bool: a parameter value ``(n, d)`` outside ``[low, high]`` in some dim."""
    low, high = value.new_tensor(p.low), value.new_tensor(p.high)
    return ((value < low) | (value > high)).any(-1)
