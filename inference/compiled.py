"""Discrete networks compiled to their factor tables, for fast repeated queries.

Tracing the Pyro model costs a fixed ~1 ms per call, which dominates a single small
query. For a network whose sites are all discrete, :func:`compile_discrete` traces the
model *once* with every site enumerated and no evidence, and keeps each site's
log-probability table (one dim per enumerated site). A query then indexes the tables at
the evidence (one gather per factor), adds them and normalises: the same numbers as
:mod:`inference.queries`, read from the same model, without re-tracing. The tests check
the two against each other.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import torch
from pyro import poutine

from inference.queries import ActionPosterior
from models.declaration import ACTION, DTYPE, EffectNetwork
from models.model import effect_model
from models.params import NetworkParams, check_params


@dataclass(frozen=True)
class _Plan:
    """One evidence pattern: the kept factors summed into one table, observed axes first."""

    observed: tuple[str, ...]
    latent: tuple[str, ...]  # latent axes the table keeps (size > 1)
    log_table: torch.Tensor  # (observed sizes..., latent sizes...)
    unseen: torch.Tensor | None  # bool, same shape: an observed end site's configuration unseen


@dataclass(frozen=True)
class CompiledNetwork:
    """Log factor tables of an all-discrete network.

    ``factors[site]`` has one axis per enumerated site, in ``order`` (size 1 where the
    factor does not depend on that site). Per evidence pattern (which sites are
    observed) the kept factors are summed once into a single table, cached in ``plans``.
    """

    net: EffectNetwork
    order: tuple[str, ...]
    factors: dict[str, torch.Tensor]
    seen: dict[str, torch.Tensor]  # end site -> bool table over ``order`` axes
    plans: dict[frozenset, _Plan] = field(default_factory=dict, repr=False)

    def plan(self, observed: frozenset) -> _Plan:
        """The summed table for this evidence pattern (built once, then cached)."""
        if observed in self.plans:
            return self.plans[observed]
        total = torch.zeros((), dtype=DTYPE)
        unseen = None
        for site, table in self.factors.items():
            role = self.net.site(site).role
            if role == "end" and site not in observed:
                continue  # a leaf nobody asked about sums to one
            total = total + table
            if role == "end":
                miss = ~self.seen[site]
                unseen = miss if unseen is None else unseen | miss
        total = total.expand(
            *[
                self.net.site(s).size if s == ACTION else total.shape[a]
                for a, s in enumerate(self.order)
            ]
        )
        obs_axes = [a for a, s in enumerate(self.order) if s in observed]
        latent_axes = [
            a
            for a, s in enumerate(self.order)
            if s not in observed and (total.shape[a] > 1 or s == ACTION)
        ]
        drop = [a for a in range(len(self.order)) if a not in obs_axes and a not in latent_axes]
        total = total.permute(*obs_axes, *latent_axes, *drop)
        total = total.reshape(total.shape[: len(obs_axes) + len(latent_axes)]).contiguous()
        if unseen is not None:
            unseen = unseen.expand(
                *[
                    self.order_sizes[a] if a in obs_axes or a in latent_axes else 1
                    for a in range(len(self.order))
                ]
            )
            unseen = unseen.permute(*obs_axes, *latent_axes, *drop)
            unseen = (
                unseen.reshape(unseen.shape[: len(obs_axes) + len(latent_axes)])
                .to(DTYPE)
                .contiguous()
            )
        plan = _Plan(
            tuple(self.order[a] for a in obs_axes),
            tuple(self.order[a] for a in latent_axes),
            total,
            unseen,
        )
        self.plans[observed] = plan
        return plan

    @property
    def order_sizes(self) -> tuple[int, ...]:
        return tuple(self.net.site(s).size for s in self.order)

    def infer_action(
        self,
        evidence: Mapping[str, object],
        *,
        allowed: torch.Tensor | None = None,
        avoid_unseen: bool = True,
    ) -> ActionPosterior:
        """Same contract and result as :func:`inference.infer_action`."""
        enc = self.net.encode(evidence)
        if ACTION in enc:
            raise ValueError("evidence names the action; infer_action infers it")
        if not enc:
            raise ValueError("evidence is empty: give at least the initial state")
        n = next(iter(enc.values())).shape[0]
        plan = self.plan(frozenset(enc))
        index = tuple(enc[s] for s in plan.observed)
        total = plan.log_table[index]  # (n, latent sizes...)
        a = plan.latent.index(ACTION) + 1
        if len(plan.latent) > 1:
            total = total.movedim(a, -1)
        total = total.reshape(n, -1, len(self.net.actions))  # (n, others, A)
        if total.shape[1] == 1:
            log_joint = total[:, 0]
            log_evidence = log_joint.logsumexp(-1)
            probs = (log_joint - log_evidence[:, None]).exp()
        else:
            log_marginal = total.logsumexp(1)
            log_evidence = log_marginal.logsumexp(-1)
            probs = (log_marginal - log_evidence[:, None]).exp()
        if plan.unseen is None:
            unseen_mass = torch.zeros_like(probs)
        else:
            miss = plan.unseen[index]
            if len(plan.latent) > 1:
                miss = miss.movedim(a, -1)
            miss = miss.reshape(n, -1, len(self.net.actions))
            if miss.shape[1] == 1:
                unseen_mass = miss[:, 0]
            else:
                joint = (total - log_evidence[:, None, None]).exp() * miss
                unseen_mass = (joint.sum(1) / probs.clamp_min(1e-300)).clamp(0, 1)
        score = probs
        if allowed is not None:
            score = score.masked_fill(
                ~torch.as_tensor(allowed, dtype=torch.bool).expand_as(score), -1.0
            )
        if avoid_unseen and bool((unseen_mass >= 0.5).any()):
            seen_score = score.masked_fill(unseen_mass >= 0.5, -1.0)
            score = torch.where(seen_score.max(-1, keepdim=True).values >= 0, seen_score, score)
        best = score.argmax(-1)
        names = tuple(self.net.actions[i] for i in best.tolist())
        return ActionPosterior(probs, best, names, log_evidence, unseen_mass)


def compile_discrete(net: EffectNetwork, params: NetworkParams) -> CompiledNetwork:
    """Trace ``effect_model`` once with every site enumerated and keep its log tables."""
    check_params(net, params)
    continuous = [s.name for s in net.sites if not s.discrete]
    if continuous:
        raise ValueError(
            f"compile_discrete needs an all-discrete network; continuous sites: {continuous}"
        )
    trace = poutine.trace(poutine.enum(effect_model, first_available_dim=-2)).get_trace(
        net, params, {}, n_rows=1
    )
    trace.compute_log_prob()
    sites = [
        name
        for name, s in trace.nodes.items()
        if s["type"] == "sample" and name in {x.name for x in net.sites}
    ]
    dims = {name: trace.nodes[name]["infer"]["_enumerate_dim"] for name in sites}
    order = tuple(sorted(sites, key=lambda s: dims[s]))  # leftmost axis first
    rank = len(order)
    factors = {}
    for name in sites:
        lp = trace.nodes[name]["log_prob"].squeeze(-1)  # drop the rows plate (size 1)
        factors[name] = lp.reshape(*[1] * (rank - lp.dim()), *lp.shape)
    seen = {}
    for spec in net.sites:
        if spec.role != "end":
            continue
        n = params[spec.name].n > 0  # over the discrete parents, in discrete_parents order
        parents = net.discrete_parents(spec.feature)
        # move the parents' axes to their positions in ``order``
        perm = sorted(range(len(parents)), key=lambda i: order.index(parents[i]))
        n = n.permute(*perm)
        shape = [net.site(s).size if s in parents else 1 for s in order]
        seen[spec.name] = n.reshape(shape)
    return CompiledNetwork(net, order, factors, seen)
