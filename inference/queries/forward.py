"""Forward questions: what an action does, and whether an observed outcome fits it.

* :func:`predict` -- the end-state distribution given the initial state and an action
  (and its parameter). Discrete end features: probabilities. Continuous ones: a Gaussian
  mixture over whatever discrete sites stay unknown (one component when the action and
  the parameter are given).
* :func:`imitation_check` -- the log-likelihood of an observed end state under the
  executed action, and a surprise score: the predictive probability of an outcome
  strictly more likely than the one observed, over the joint of all observed end
  features (exact for discrete end states and where one Gaussian predicts the continuous
  ones; a deterministic quadrature where a mixture does: :mod:`inference.queries.surprise`).
  Near 1: the action did not do what it usually does.

Both are answered from the traced model only (:func:`inference.compile`'s methods of the
same names call them).
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
from effect_networks.inference.exact.enumeration import conditional_log_evidence, over_row_chunks
from effect_networks.inference.exact.traced import Enumerated
from effect_networks.inference.queries.batching import (
    no_rows,
    placeholder_row,
    prepare,
    unseen_indicator,
    unseen_mass,
)
from effect_networks.inference.queries.implausibility import (
    IMPLAUSIBLE_BELOW,
    check_threshold,
    plausibility,
)
from effect_networks.inference.queries.results import (
    GaussianMixture,
    ImitationCheck,
    Prediction,
)
from effect_networks.inference.queries.surprise import QUADRATURE_POINTS, continuous_surprise
from effect_networks.models.declaration import (
    ACTION,
    EffectNetwork,
    end_site,
)
from effect_networks.models.evidence import Evidence, is_partial
from effect_networks.models.gaussian import (
    condition_on_observed,
)
from effect_networks.models.params import NetworkParams


def predict(
    net: EffectNetwork,
    params: NetworkParams,
    evidence: Mapping[str, object],
    *,
    implausible_below: float = IMPLAUSIBLE_BELOW,
) -> Prediction:
    """End-state distribution of every end feature not in ``evidence``.

    ``implausible`` flags rows whose observed end features (if any are given) have a
    probability below ``implausible_below`` (:mod:`inference.queries.implausibility`).

    Parameters
    ----------
    net, params
        The network and its fitted parameters.
    evidence
        ``n`` rows of what is known, by site name (labels, numbers, NaN where unknown):
        see :meth:`models.EffectNetwork.encode`.
    implausible_below
        The probability under which a row's observed end features are flagged.

    Returns
    -------
    Prediction
        Per row, each unobserved discrete end feature's probabilities and each continuous
        one's Gaussian mixture.
    """
    below = check_threshold(implausible_below)
    enc = prepare(net, params, evidence)
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
                net, params, enc, {site}, lambda e, *_, s=site: e.marginal(s), contracted=True
            )
        else:
            continuous[f] = _mixture(net, params, enc, site)

    def unseen(e, *_):
        if e.contracted:
            e.check_possible(e.log_norm)
            return unseen_mass(net, params, e, unseen_sites)
        post = e.posterior()
        return (
            (post * unseen_indicator(net, params, e, unseen_sites))
            .reshape(-1, post.shape[-1])
            .sum(0)
        )

    states = {f: net.feature(f).states for f in discrete}
    # the unseen flag reads the targets' parents: latent end parents must be traced
    end_parents = {q for s in unseen_sites for q in net.cpd(s).parents if net.site(q).role == "end"}
    mass = over_row_chunks(net, params, enc, end_parents, unseen, contracted=True).clamp(0, 1)
    flag = plausibility(net, params, enc).implausible(below)
    return Prediction(discrete, continuous, mass, states, flag)


def _mixture(net, params, enc, site) -> GaussianMixture:
    """The site's mixture over the enumerated sites.

    A partly observed site's components are conditioned on its observed dimensions (which hold their
    value, variance 0).
    """
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


def imitation_check(
    net: EffectNetwork,
    params: NetworkParams,
    evidence: Mapping[str, object],
    *,
    n_samples: int = QUADRATURE_POINTS,
    seed: int = 0,
    implausible_below: float = IMPLAUSIBLE_BELOW,
) -> ImitationCheck:
    """How surprising each observed end state is under the executed action.

    The fields are defined in :class:`~inference.queries.results.ImitationCheck`. Discrete end states are summed
    exactly; with a continuous end feature observed, the surprise is exact where each
    discrete outcome has one Gaussian component (the action and the parameter given, say)
    and a deterministic quadrature where it has several (an unknown parameter's clusters):
    ``n_samples`` points per component (directions times radii), ``seed`` fixing the
    quasi-random directions beyond two continuous dimensions (:mod:`inference.queries.surprise`).
    The same row gets the same answer in any batch. ``implausible`` flags rows whose
    observed end state has a probability below ``implausible_below`` given the executed
    action (:mod:`inference.queries.implausibility`).

    Parameters
    ----------
    net, params
        The network and its fitted parameters.
    evidence
        ``n`` rows of what is known, by site name (labels, numbers, NaN where unknown):
        see :meth:`models.EffectNetwork.encode`.
        Each row gives the executed action and the observed end state.
    n_samples
        Quadrature points per Gaussian component (several components only).
    seed
        Fixes the quadrature's directions beyond two continuous dimensions.
    implausible_below
        The probability under which a row's observed end state is flagged.

    Returns
    -------
    ImitationCheck
        Per row, how surprising the observed end state is under the executed action.
    """
    below = check_threshold(implausible_below)
    enc = prepare(net, params, evidence)
    if ACTION not in enc:
        raise ValueError(
            "imitation_check needs the executed action in the evidence (site 'action')"
        )
    unknown = [
        s.name for s in net.sites if s.role == "initial" and not s.discrete and s.name not in enc
    ]
    if unknown:  # its surprise reads each observed feature's own density given the rest
        raise ValueError(f"imitation_check needs the initial state of {unknown}")
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
    log_joint = over_row_chunks(
        net, params, enc, set(), lambda e, *_: e.log_evidence, contracted=True
    )
    log_prior = over_row_chunks(
        net, params, prior, set(), lambda e, *_: e.log_evidence, contracted=True
    )
    log_lik = conditional_log_evidence(net, params, enc, prior, log_joint, log_prior)
    if all(net.site(s).discrete for s in observed):
        surprise = _discrete_surprise(net, params, prior, observed, log_lik)
    else:
        surprise = continuous_surprise(net, params, enc, observed, n_points=n_samples, seed=seed)

    def unseen(e, *_):
        if e.contracted:  # an impossible outcome rests on no configuration: 0
            return unseen_mass(net, params, e, observed)
        post = e.posterior(strict=False)  # an impossible outcome rests on no configuration
        return (
            (post * unseen_indicator(net, params, e, observed)).reshape(-1, post.shape[-1]).sum(0)
        )

    flag = plausibility(net, params, enc, log_evidence=log_joint, log_prior=log_prior)
    flag = flag.implausible(below)
    mass = over_row_chunks(net, params, enc, set(), unseen, contracted=True).clamp(0, 1)
    return ImitationCheck(log_lik, surprise, mass, flag)


def _discrete_surprise(net, params, prior, observed, log_lik) -> torch.Tensor:
    """P(outcome strictly more likely than the observed one), by enumerating outcomes."""

    def fn(e: Enumerated, *_):
        if e.contracted:  # the outcomes' joint, the latents summed out by contraction
            joint = e.log_sum(observed) - e.log_norm
            return joint.reshape(-1, joint.shape[-1]).T
        w = e.log_weight - e.log_norm  # joint over outcomes and latents, (E..., n)
        outcome_dims = [w.dim() + e.dims[s] for s in observed]
        latent_dims = [d for d in range(w.dim() - 1) if d not in outcome_dims]
        joint = w.logsumexp(latent_dims, keepdim=True) if latent_dims else w
        return joint.reshape(-1, w.shape[-1]).T  # (n, outcomes)

    joint = over_row_chunks(net, params, prior, set(observed), fn, contracted=True)
    more_likely = joint > log_lik[:, None] + 1e-9
    return (joint.exp() * more_likely).sum(-1).clamp(0, 1)
