"""Which action was executed: the posterior over actions given a (partial) end state.

:func:`infer_action` -- the traced model: the exact posterior over actions given the
initial state and a full or partial end state, and the best action: the argmax of the
action's marginal posterior with every other unobserved discrete site summed out (a
marginal MAP, as pgmpy's ``map_query``; not the joint MAP ``infer_discrete`` returns).

Its compiled answer, from tables read once off the same model for a network whose sites
are all discrete, is :class:`~inference.queries.action_tables.CompiledNetwork`; both are
tested equal on the same cases. Users reach the tables through :func:`inference.compile`
(its ``infer_action``); the free function itself answers a query of a few rows on an
all-discrete network from tables it keeps per (network, parameters)
(:mod:`inference.queries.kept_tables`), and larger batches by the traced model.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
from effect_networks.inference.exact.enumeration import (
    enumeration_size,
    one_thread_below,
    over_row_chunks,
)
from effect_networks.inference.exact.traced import Enumerated
from effect_networks.inference.queries.batching import (
    allowed_actions,
    first_best,
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
from effect_networks.inference.queries.kept_tables import FEW_ROWS, tables_for
from effect_networks.inference.queries.results import (
    ActionPosterior,
)
from effect_networks.models.cpds.table import broadcast_shapes
from effect_networks.models.declaration import (
    ACTION,
    EffectNetwork,
    end_site,
)
from effect_networks.models.params import NetworkParams


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
        under the model, every action summed out (:mod:`inference.queries.implausibility`); such a
        row still gets its posterior and ``best``.

    Returns
    -------
    ActionPosterior
        Per row, the posterior over the actions and the best allowed one.
    """
    below = check_threshold(implausible_below)
    enc = prepare(net, params, evidence)
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
    # small work on one torch thread throughout (the sums, the masses, the check), so that a
    # busy other core cannot stall it
    work = enumeration_size(net, enc, set(), contracted=True) * enc.n_rows
    if enc.n_rows <= FEW_ROWS:
        tables = tables_for(net, params)
        if tables is not None:
            with one_thread_below(work):
                return tables.infer_action(
                    enc, allowed=allowed, avoid_unseen=avoid_unseen, implausible_below=below
                )
    observed_end = [end_site(f.name) for f in net.features if end_site(f.name) in enc]

    def fn(e: Enumerated, *_):
        if e.contracted:  # by contraction: the joint is never built
            probs = e.marginal(ACTION)
            if not observed_end:
                return probs, torch.zeros_like(probs), e.log_evidence
            unseen = unseen_mass(net, params, e, observed_end, (ACTION,)).expand_as(probs)
            # an action of posterior probability 0 (in float64) rests on nothing: 0
            return probs, torch.where(probs > 0, unseen, 0.0), e.log_evidence
        post = e.posterior()
        dim = e.dims[ACTION]
        others = [d for d in range(post.dim() - 1) if d != post.dim() + dim]
        if post.shape[dim] == 1:  # no kept factor depends on the action (see marginal)
            probs = e.marginal(ACTION)
        else:  # the joint posterior summed over the other sites: one pass, not three
            probs = (post.sum(others) if others else post).T
        flag = unseen_indicator(net, params, e, observed_end) if observed_end else torch.zeros(())
        if not bool(flag.any()):
            return probs, torch.zeros_like(probs), e.log_evidence
        if others and broadcast_shapes(post.shape, flag.shape) == post.shape:
            joint = post.mul_(flag)  # post is this call's own and probs a sum of it
        else:
            joint = (post * flag).expand_as(post)
        per_action = joint.sum(others).T if others else joint.T
        return probs, per_action / probs.clamp_min(1e-300), e.log_evidence

    with one_thread_below(work):
        probs, unseen, log_evidence = over_row_chunks(net, params, enc, set(), fn, contracted=True)
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
