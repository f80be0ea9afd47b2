"""The parameter posterior: which parameter value an action used, given its effect.

Side by side, tested equal on the same cases:

* :func:`infer_parameter` -- the traced model (the paper's query): the cluster posterior
  by enumeration, the most probable cluster added to the evidence, then the parameter by
  closed-form Gaussian conditioning. Serves any evidence the model accepts (unknown
  initial states included).
* :func:`compile_parameter_query` -- the same answer without tracing:
  :class:`~inference.queries.parameter_tables.CompiledParameterQuery` (Gaussian tables
  precomputed) for a parameter acting on one continuous feature,
  :class:`CompiledJointParameterQuery` for one acting on several features. Both report
  ``implausible`` from the chi-square tail of the closest cluster's Gaussian
  (:mod:`inference.queries.implausibility`).

Users reach the compiled query through :func:`inference.compile` (its
``infer_parameter``).
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import torch
from effect_networks.inference.exact.enumeration import over_row_chunks
from effect_networks.inference.exact.traced import Enumerated
from effect_networks.inference.queries.batching import (
    check_parameter_evidence,
    given_other_parameters,
    no_rows,
    parameter_placeholder,
    placeholder_row,
    prepare,
    unseen_indicator,
    unseen_mass,
)
from effect_networks.inference.queries.implausibility import (
    IMPLAUSIBLE_BELOW,
    check_threshold,
    initial_tails,
    outside_training,
    plausibility,
)
from effect_networks.inference.queries.parameter_tables import (
    CompiledParameterQuery,
    refuse_impossible,
)
from effect_networks.inference.queries.results import (
    GaussianMixture,
    ParameterPosterior,
    outside_range,
)
from effect_networks.models.cpds import concat_inputs
from effect_networks.models.declaration import (
    ACTION,
    DTYPE,
    EffectNetwork,
    Parameter,
    cluster_site,
)
from effect_networks.models.evidence import is_partial
from effect_networks.models.gaussian import (
    mask_unobserved,
    partial_log_density,
    residual_of,
)
from effect_networks.models.params import NetworkParams, check_params


def infer_parameter(
    net: EffectNetwork,
    params: NetworkParams,
    parameter: str,
    evidence: Mapping[str, object],
    *,
    mixture: bool = False,
    implausible_below: float = IMPLAUSIBLE_BELOW,
) -> ParameterPosterior:
    """The parameter posterior (the paper's query): best cluster by enumeration, then the parameter.

    With ``mixture=True`` the result also holds the parameter's full posterior (every
    cluster's conditional Gaussian, weighted by the cluster posterior), whose mean is the
    posterior mean of the parameter; the paper's best-cluster answer stays in ``mean``.
    ``implausible`` flags rows whose observed end state has a probability below
    ``implausible_below`` given the action, the parameter integrated out
    (:mod:`inference.queries.implausibility`).

    Parameters
    ----------
    net, params
        The network and its fitted parameters.
    evidence
        ``n`` rows of what is known, by site name (labels, numbers, NaN where unknown):
        see :meth:`models.EffectNetwork.encode`.
    parameter
        The action parameter's name; unknown (NaN or left out) in ``evidence``.
    mixture
        Also give the parameter's full posterior over every cluster.
    implausible_below
        The probability under which a row's observed end state is flagged.

    Returns
    -------
    ParameterPosterior
        Per row, the cluster posterior and the parameter's Gaussian given the best
        cluster (and, with ``mixture=True``, the full posterior).
    """
    below = check_threshold(implausible_below)
    m = net.mixture(parameter)
    p = m.parameter
    enc = prepare(net, params, evidence)
    if enc.n_rows == 0:
        return no_rows(
            infer_parameter(
                net,
                params,
                parameter,
                parameter_placeholder(m, enc),
                mixture=mixture,
                implausible_below=below,
            )
        )
    enc, observed = check_parameter_evidence(net, m, enc, "infer_parameter")
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
    enc, acting = given_other_parameters(net, m, enc, children, "infer_parameter")
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


def _over_latent_parents(net, params, m, enc, children, latent, mixture) -> ParameterPosterior:
    """:func:`infer_parameter` where initial states the observed effects depend on are unknown.

    Their states and the cluster are enumerated jointly (their exact posterior), the parameter given
    the best cluster a mixture over those states (its mean and covariance returned, by the law of
    total covariance), each cluster's in ``mixture`` likewise.
    """
    p = m.parameter
    sites = [*latent, m.cluster.site]

    sizes = [net.site(s).size for s in latent]
    n, c = enc.n_rows, p.n_clusters
    weights = over_row_chunks(net, params, enc, set(), lambda e, *_: e.joint(sites))
    weights = weights.reshape(n, -1, c)  # (n, S, C)
    probs = weights.sum(1)
    best = probs.argmax(-1)
    every = torch.arange(c).expand(n, -1)
    means, covs, unseen = [], [], []
    for states in itertools.product(*[range(k) for k in sizes]):
        given = enc | net.encode_indices(
            {s: torch.full((n,), i) for s, i in zip(latent, states, strict=True)}
        )
        given, acting = given_other_parameters(net, m, given, children, "infer_parameter")
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
    """The answer when only discrete features the parameter acts on are observed.

    They depend on its cell, so the parameter given its best cluster is that cluster's Gaussian.
    """

    def fn(e: Enumerated, *_):
        if e.contracted:
            e.check_possible(e.log_norm)
            return e.marginal(m.cluster.site), unseen_mass(net, params, e, observed)
        post = e.posterior()
        unseen = (post * unseen_indicator(net, params, e, observed)).reshape(-1, post.shape[-1])
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


@dataclass(frozen=True)
class CompiledJointParameterQuery:
    """The parameter posterior of a parameter acting on several features, without tracing.

    The observed continuous features it acts on are jointly Gaussian given its cluster
    (its unknown value couples them); their joint density is taken in the model's own
    order, each feature given the value's Gaussian conditioned on those before it
    (:meth:`models.cpds.ParameterMixture.shared_gaussian` and ``update``, the rules the
    model samples with), batched over rows and clusters; the observed discrete features
    it acts on add their kind's log-probability per cluster. Same results as
    :func:`inference.infer_parameter` for evidence of the initial state, the action, the
    affected features and their parents.
    """

    net: EffectNetwork
    params: NetworkParams = field(repr=False)
    parameter: Parameter
    log_cluster: torch.Tensor  # (A, C)

    def serves(self, sites: set[str]) -> bool:
        """Whether evidence on ``sites`` gets the traced query's answer here.

        An affected feature observed, with the observed ones' discrete parents and continuous inputs
        besides the parameter (the action may be left out, as for
        :meth:`CompiledParameterQuery.serves`), and every other site an initial state (an observed
        end site outside the affected ones, whose own plausibility the traced query would weigh, is
        left to it).
        """
        m = self.net.mixture(self.parameter.name)
        observed = {s for s in m.affected if s in sites}
        needed = {
            q
            for s in observed
            for q in (*self.net.cpd(s).parents, *self.net.cpd(s).inputs)
            if q not in (m.cluster.site, m.value.site, ACTION)
        }
        return (
            bool(observed)
            and needed <= sites
            and sites - observed
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
        net, params, p = self.net, self.params, self.parameter
        m = net.mixture(p.name)
        enc = net.encode(evidence)
        observed = [s for s in m.affected if s in enc]
        if not observed:
            raise ValueError(f"the query needs an observed end state of one of {list(m.affected)}")
        n = enc.n_rows
        if ACTION not in enc:
            if len(p.actions) != 1:
                raise ValueError(f"give the action (one of {list(p.actions)}) that used {p.name!r}")
            enc = enc | net.encode_indices(
                {ACTION: torch.full((n,), net.action_index(p.actions[0]))}
            )
        not_using = ~m.in_use(enc[ACTION])
        if not_using.any():
            row = int(not_using.nonzero()[0])
            raise ValueError(
                f"row {row}: action {net.actions[int(enc[ACTION][row])]!r} does not use {p.name!r}"
            )
        depending = _depending_on(net, set(m.affected)) & set(enc)
        if depending:
            raise ValueError(
                f"evidence on {sorted(depending)}, which depend on features {p.name!r} acts "
                "on: use inference.infer_parameter"
            )
        for site in observed:
            missing = [q for q in net.cpd(site).parents if q not in enc and q != m.cluster.site]
            if missing:
                raise ValueError(
                    f"the query needs the discrete parents {missing} of {site!r} as evidence"
                )
        if n == 0:  # a placeholder row whose action uses the parameter
            placeholder = placeholder_row(enc).without(ACTION)
            placeholder |= net.encode_indices({ACTION: [net.action_index(p.actions[0])]})
            return no_rows(
                self.infer_parameter(placeholder, mixture=mixture, implausible_below=below)
            )
        clusters = torch.arange(p.n_clusters)  # (C,), broadcast against rows (n, 1)
        action = enc[ACTION][:, None]
        log_cluster = self.log_cluster[enc[ACTION]]  # (n, C)
        log_discrete = torch.zeros_like(log_cluster)
        cache: dict[str, torch.Tensor] = {}
        for site in (s for s in observed if net.site(s).discrete):
            cpd = net.cpd(site)
            index = [clusters if q == m.cluster.site else enc[q][:, None] for q in cpd.parents]
            x = [enc[q][:, None, :] for q in cpd.inputs]
            fn = cpd.distribution(params[site], index, concat_inputs(x), cache)
            log_discrete = log_discrete + fn.log_prob(enc[site][:, None])
        children = [s for s in m.continuous if s in enc]
        d2 = torch.zeros_like(log_cluster)
        log_lik = log_discrete.clone()
        dof = torch.zeros(n, dtype=DTYPE)
        belief = None
        known = torch.zeros(n, 1, dtype=torch.bool)
        unknown = torch.full((n, 1, p.dim), torch.nan, dtype=DTYPE)
        for site in sorted(children, key=lambda s: is_partial(enc[s])):  # as the model does
            cpd = net.cpd(site)
            index = [clusters if q == m.cluster.site else enc[q][:, None] for q in cpd.parents]
            x = [enc[q][:, None, :] for q in cpd.inputs if q != m.value.site] + [unknown]
            args = (params, cpd, index, x, action)
            fn = m.shared_gaussian(*args, known, belief)
            y = enc[site][:, None, :]
            # the residual first (exact where the mean is a pair), NaN where y is
            resid = residual_of(fn, y)
            zero, tril = torch.zeros_like(resid), fn.scale_tril
            log_lik = log_lik + partial_log_density(resid, zero, tril)
            resid_, _, cov_, seen = mask_unobserved(resid, zero, tril @ tril.mT)
            z = torch.linalg.solve_triangular(
                torch.linalg.cholesky(cov_), resid_[..., None], upper=False
            )
            d2 = d2 + z.square().sum((-2, -1))
            dof = dof + seen[:, 0].sum(-1)
            belief = m.update(*args, y, belief)
        refuse_impossible(log_lik + log_cluster)
        probs = (log_lik + log_cluster).softmax(-1)
        best = probs.argmax(-1)
        rows = torch.arange(n)
        prior = params[m.value.site]
        if belief is None:  # only discrete effects observed: each cluster's own Gaussian
            belief = (prior.bias.expand(n, -1, -1), prior.covariance.expand(n, -1, -1, -1))
        means, covs = belief
        mean, cov = means[rows, best], covs[rows, best]
        if children:
            unseen = torch.zeros(n, dtype=torch.bool)
            for site in children:
                cpd = net.cpd(site)
                index = tuple(best if q == m.cluster.site else enc[q] for q in cpd.parents)
                unseen = unseen | ~cpd.seen(params[site])[index]
            unseen = unseen.to(DTYPE)
        else:
            flag = torch.zeros_like(log_cluster, dtype=torch.bool)
            for site in observed:
                cpd = net.cpd(site)
                index = tuple(
                    clusters if q == m.cluster.site else enc[q][:, None] for q in cpd.parents
                )
                flag = flag | ~cpd.seen(params[site])[index]
            unseen = (probs * flag).sum(-1).clamp(0, 1)
        possible = torch.isfinite(log_cluster + log_discrete)
        closest = d2.masked_fill(~possible, torch.inf).min(-1).values
        tail = torch.special.gammaincc(dof.clamp_min(1) / 2, closest / 2)
        tail = torch.where(dof > 0, tail, 1.0)
        p_discrete = (log_cluster + log_discrete).logsumexp(-1).exp()
        implausible = (tail < below) | (p_discrete < below)
        implausible = implausible | outside_training(initial_tails(net, params, enc), below)
        mix = GaussianMixture(probs, means, covs) if mixture else None
        return ParameterPosterior(
            probs, best, mean, cov, unseen, outside_range(p, mean), mix, implausible
        )


def _depending_on(net: EffectNetwork, sites: set[str]) -> set[str]:
    """The end sites with one of ``sites`` among their ancestors (not ``sites`` themselves)."""
    out: set[str] = set()
    for spec in net.sites:  # parents before children
        if spec.role == "end" and spec.name not in sites:
            if any(q in sites or q in out for q in net.cpd(spec.name).parents):
                out.add(spec.name)
    return out


def shared_features(net: EffectNetwork, parameter: str) -> list[str]:
    """The continuous features ``parameter`` acts on that another parameter acts on too.

    Where there are any, :func:`compile_parameter_query` refuses (the traced :func:`infer_parameter`
    answers).
    """
    m = net.mixture(parameter)
    return [s for s in m.continuous if net.acting_on(s) != (m,)]


def compile_parameter_query(
    net: EffectNetwork, params: NetworkParams, parameter: str
) -> CompiledParameterQuery | CompiledJointParameterQuery:
    """Precompute the parameter posterior of ``parameter``.

    :class:`~inference.queries.parameter_tables.CompiledParameterQuery` (its tables) for a parameter
    acting on one continuous feature, :class:`CompiledJointParameterQuery` for one acting on several
    features. A continuous feature that several parameters act on is refused (use
    :func:`inference.infer_parameter`).
    """
    check_params(net, params)
    m = net.mixture(parameter)
    shared = shared_features(net, parameter)
    if shared:
        raise ValueError(
            f"the compiled query serves a parameter whose continuous features no other "
            f"parameter acts on; {parameter!r} shares {shared} with another parameter: use "
            "inference.infer_parameter"
        )
    if m.child is None or m.affected != (m.child,):
        log_cluster = params[m.cluster.site].probs.log()  # -inf: a cluster the action never takes
        return CompiledJointParameterQuery(net, params, m.parameter, log_cluster)
    child = net.cpd(m.child)
    tables = m.query_tables(params, child)
    return CompiledParameterQuery(
        net, m.parameter, child.parents, child.inputs, **tables, params=params
    )
