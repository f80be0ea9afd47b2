"""The action posterior from tables: :class:`CompiledNetwork`, for all-discrete networks.

The same query as :func:`~inference.queries.action.infer_action` (tested equal on the
same cases), for a network whose sites are all discrete. Tracing the Pyro model costs a
fixed ~1 ms per call, which dominates a single small query. :func:`compile_discrete`
traces the model *once* with every site enumerated and no evidence, and keeps each
site's log-probability table (one dim per enumerated site). A query then indexes the
tables at the evidence (one gather per factor), adds them and normalises: the same
numbers, read from the same model, without re-tracing. It reports ``implausible`` as the
traced query does (:mod:`inference.queries.implausibility`), from the evidence
probability against the same query's table with the end sites left out.

Users reach the tables through :func:`inference.compile` (its ``infer_action``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import torch
from effect_networks.inference.exact.factored import FactoredPlan
from effect_networks.inference.queries.batching import (
    allowed_actions,
    first_best,
    no_rows,
    placeholder_row,
)
from effect_networks.inference.queries.implausibility import (
    IMPLAUSIBLE_BELOW,
    check_threshold,
)
from effect_networks.inference.queries.results import (
    ActionPosterior,
)
from effect_networks.models.declaration import (
    ACTION,
    DTYPE,
    EffectNetwork,
    end_site,
)
from effect_networks.models.evidence import Evidence
from effect_networks.models.model import effect_model
from effect_networks.models.params import NetworkParams, check_params
from pyro import poutine


@dataclass(frozen=True)
class _Plan:
    """One evidence pattern: the kept factors summed into one table, observed axes first."""

    observed: tuple[str, ...]
    latent: tuple[str, ...]  # latent axes the table keeps (size > 1)
    log_table: torch.Tensor  # (observed sizes..., latent sizes...)
    unseen: torch.Tensor | None  # bool, same shape: an observed end site's configuration unseen
    answers: _Answers | None = None  # when the action is the only latent axis


@dataclass(frozen=True)
class _Answers:
    """The posterior per observed configuration, for a pattern with the action latent.

    The pattern's latent sites include the action: a query then gathers its answer instead of
    computing it per row.

    Each is computed over the plan's table exactly as :meth:`CompiledNetwork.infer_action`
    computes it over gathered rows (row by row the same operations): with the action the
    only latent site, the same bits; with other latent sites (summed out), the same sums
    in chunks of configurations, equal to rounding.
    """

    probs: torch.Tensor  # (G, A), G the observed configurations flattened
    top: torch.Tensor | None  # (G,): the largest probability (the action alone latent)
    best: torch.Tensor  # (G,): first_best of probs
    log_evidence: torch.Tensor  # (G,)
    unseen_mass: torch.Tensor | None = None  # (G, A), where the plan has unseen configurations

    @staticmethod
    def of(log_joint: torch.Tensor) -> _Answers:
        flat = log_joint.reshape(-1, log_joint.shape[-1])
        probs = flat.softmax(-1)
        top, arg = probs.max(-1)
        log_evidence = flat.gather(-1, arg[:, None]).squeeze(-1) - top.log()
        return _Answers(probs, top, first_best(probs, top), log_evidence)

    @staticmethod
    def marginal(log_table: torch.Tensor, k: int, a: int, unseen: torch.Tensor | None) -> _Answers:
        """Answers of a table ``(observed sizes..., latent sizes...)``, in chunks.

        The table has ``k`` observed axes and the action at latent axis ``a``; the other latent
        sites are summed out, in chunks of configurations of at most ``ANSWERS_CHUNK`` elements.
        """
        n_actions = log_table.shape[k + a]
        latent_sizes = log_table.shape[k:]
        groups = math.prod(log_table.shape[:k])
        total = log_table.reshape(groups, *latent_sizes)  # views: chunks are copied singly
        miss = None if unseen is None else unseen.reshape(groups, *latent_sizes)

        def per_configuration(table: torch.Tensor) -> torch.Tensor:  # (g, others, A)
            return table.movedim(a + 1, -1).reshape(table.shape[0], -1, n_actions)

        step = max(1, ANSWERS_CHUNK // math.prod(latent_sizes))
        probs = torch.empty(groups, n_actions, dtype=log_table.dtype)
        log_evidence = torch.empty(groups, dtype=log_table.dtype)
        mass = None if miss is None else torch.empty(groups, n_actions, dtype=log_table.dtype)
        for start in range(0, groups, step):
            rows = slice(start, start + step)
            chunk = per_configuration(total[rows])
            log_marginal = chunk.logsumexp(1)
            log_evidence[rows] = log_marginal.logsumexp(-1)
            probs[rows] = (log_marginal - log_evidence[rows, None]).exp()
            if mass is not None:
                joint = (chunk - log_evidence[rows, None, None]).exp() * per_configuration(
                    miss[rows]
                )
                mass[rows] = (joint.sum(1) / probs[rows].clamp_min(1e-300)).clamp(0, 1)
        return _Answers(probs, None, first_best(probs), log_evidence, mass)

    @staticmethod
    def row(index: tuple[torch.Tensor, ...], sizes: tuple[int, ...]) -> torch.Tensor:
        """``(n,)`` row of the flattened tables for the observed state indices."""
        flat = index[0]
        for i, size in zip(index[1:], sizes[1:], strict=True):
            flat = flat * size + i
        return flat


# Per-configuration answers are kept while the table of them stays this small (elements).
ANSWERS_BUDGET = 1 << 22
# With latent sites besides the action, the answers are summed in chunks of configurations
# whose part of the table has at most this many elements.
ANSWERS_CHUNK = 1 << 22


# A pattern whose summed table would hold more elements than this (with an end site
# observed) keeps its factors instead, summed per queried row (:class:`_RowSums`).
PLAN_BUDGET = 1 << 24


class _RowSums:
    """A plan's table ``(observed sizes..., latent sizes...)`` that is never built.

    Indexed at the observed states of ``n`` rows it returns the rows' part, ``(n, latent
    sizes...)``, combining the factors' parts in their order exactly as the whole table combines
    them (the same additions, or logical ors, element by element: the same bits).
    """

    def __init__(self, parts: list[torch.Tensor], shape: tuple[int, ...], k: int, add: bool):
        self.parts, self.shape, self.k, self.add = parts, torch.Size(shape), k, add

    def __getitem__(self, index: tuple[torch.Tensor, ...]) -> torch.Tensor:
        n = index[0].shape[0]
        out = torch.zeros((), dtype=DTYPE) if self.add else None
        for part in self.parts:
            at = tuple(i if part.shape[a] > 1 else torch.zeros_like(i) for a, i in enumerate(index))
            rows = part[at]
            out = rows if out is None else (out + rows if self.add else out | rows)
        out = out.expand(n, *self.shape[self.k :])
        return out if self.add else out.to(DTYPE)


def _lazy_plan(net, order, observed, kept, misses) -> _Plan | None:
    """The plan of ``observed`` with its table and unseen indicator as :class:`_RowSums`.

    Where the table would exceed ``PLAN_BUDGET`` elements; None where it would not.
    """
    sizes = [net.site(s).size for s in order]
    shape = torch.broadcast_shapes(*(t.shape for t in kept))
    shape = [sizes[a] if s == ACTION else shape[a] for a, s in enumerate(order)]
    obs_axes = [a for a, s in enumerate(order) if s in observed]
    latent_axes = [
        a for a, s in enumerate(order) if s not in observed and (shape[a] > 1 or s == ACTION)
    ]
    drop = [a for a in range(len(order)) if a not in obs_axes and a not in latent_axes]
    full = [sizes[a] if a in obs_axes else shape[a] for a in obs_axes + latent_axes]
    if math.prod(full) <= PLAN_BUDGET:
        return None
    k = len(obs_axes)

    def moved(table: torch.Tensor) -> torch.Tensor:  # observed axes, latent axes
        table = table.permute(*obs_axes, *latent_axes, *drop)
        return table.reshape(table.shape[: k + len(latent_axes)])

    table = _RowSums([moved(t) for t in kept], tuple(full), k, add=True)
    unseen = None
    if misses and any(bool(m.any()) for m in misses):
        unseen = _RowSums([moved(m) for m in misses], tuple(full), k, add=False)
    latent = tuple(order[a] for a in latent_axes)
    return _Plan(tuple(order[a] for a in obs_axes), latent, table, unseen)


@dataclass(frozen=True)
class CompiledNetwork:
    """Log factor tables of an all-discrete network.

    ``factors[site]`` has one axis per enumerated site, in ``order`` (size 1 where the
    factor does not depend on that site). Per evidence pattern (which sites are
    observed) the kept factors are summed once into a single table, cached in ``plans``;
    where that table would be large and the latent sites' joint splits (sparse
    parents), the pattern keeps its factors and sums each row by elimination instead
    (:class:`~inference.exact.factored.FactoredPlan`).
    """

    net: EffectNetwork
    order: tuple[str, ...]
    factors: dict[str, torch.Tensor]
    seen: dict[str, torch.Tensor]  # end site -> bool table over ``order`` axes
    plans: dict[frozenset, _Plan] = field(default_factory=dict, repr=False)
    # per pattern without end sites: log p(evidence) per observed configuration
    priors: dict[frozenset, torch.Tensor] = field(default_factory=dict, repr=False)
    # per pattern with answers: log p(end sites | the rest) per observed configuration,
    # flattened as the answers (numpy), for the one-row query's implausible flag
    surprises: dict[frozenset, np.ndarray] = field(default_factory=dict, repr=False)

    def plan(self, observed: frozenset) -> _Plan:
        """The summed table for this evidence pattern (built once, then cached)."""
        if observed not in self.plans:
            self.plans[observed] = self._build_plan(observed)
        return self.plans[observed]

    def _build_plan(self, observed: frozenset) -> _Plan:
        kept, misses = [], []
        needed = self.net.end_sites_needed(observed)
        for site, table in self.factors.items():
            role = self.net.site(site).role
            if role == "end" and site not in needed:
                continue  # no observed site depends on it: it sums to one
            kept.append(table)
            if role == "end" and site in observed:
                misses.append(~self.seen[site])
        factored = FactoredPlan.of(
            self.order, {s: self.net.site(s).size for s in self.order}, observed, kept, misses
        )
        if factored is not None:
            return factored
        if any(self.net.site(s).role == "end" for s in observed):
            lazy = _lazy_plan(self.net, self.order, observed, kept, misses)
            if lazy is not None:
                return lazy
        total = torch.zeros((), dtype=DTYPE)
        for table in kept:
            total = total + table
        unseen = None
        for miss in misses:
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
        if unseen is not None and not bool(unseen.any()):
            unseen = None  # every configuration this pattern touches was seen
        latent = tuple(self.order[a] for a in latent_axes)
        answers = None
        k = len(obs_axes)
        configurations = math.prod(total.shape[:k])
        if latent == (ACTION,) and total.numel() <= ANSWERS_BUDGET:
            answers = _Answers.of(total)
        elif configurations * self.net.site(ACTION).size <= ANSWERS_BUDGET:
            # other latent sites too: their sums per configuration cost about as much as
            # building the table did, and every later query is a gather
            answers = _Answers.marginal(total, k, latent.index(ACTION), unseen)
        return _Plan(tuple(self.order[a] for a in obs_axes), latent, total, unseen, answers)

    @property
    def order_sizes(self) -> tuple[int, ...]:
        """The sizes of the sites of ``order``, in that order."""
        return tuple(self.net.site(s).size for s in self.order)

    def infer_action(
        self,
        evidence: Mapping[str, object],
        *,
        allowed: torch.Tensor | None = None,
        avoid_unseen: bool = True,
        implausible_below: float = IMPLAUSIBLE_BELOW,
    ) -> ActionPosterior:
        """Same contract and result as :func:`inference.infer_action`."""
        below = check_threshold(implausible_below)
        enc = self.net.encode(evidence)
        if ACTION in enc:
            raise ValueError(
                "evidence names the action; infer_action infers it (use predict or imitation_check)"
            )
        if not len(enc):
            raise ValueError("evidence is empty: give at least the initial state")
        n = enc.n_rows
        allowed = allowed_actions(self.net, allowed, n)
        if n == 0:
            return no_rows(
                self.infer_action(
                    placeholder_row(enc),
                    allowed=allowed,
                    avoid_unseen=avoid_unseen,
                    implausible_below=below,
                )
            )
        plan = self.plan(frozenset(enc))
        if n == 1 and plan.answers is not None and allowed is None and plan.unseen is None:
            return self._one_answer(enc, plan, below)
        index = tuple(enc[s] for s in plan.observed)
        a = plan.latent.index(ACTION) + 1
        top = None
        if isinstance(plan, FactoredPlan):  # summed per row by elimination
            probs, log_evidence, factored_unseen = plan.answer(enc)
        elif plan.answers is not None:  # gather the answers computed for the whole table
            row = _Answers.row(index, plan.log_table.shape[: len(plan.observed)])
            probs = plan.answers.probs.index_select(0, row)
            top = None if plan.answers.top is None else plan.answers.top[row]
            log_evidence = plan.answers.log_evidence[row]
        else:
            total = plan.log_table[index]  # (n, latent sizes...)
            if len(plan.latent) > 1:
                total = total.movedim(a, -1)
            total = total.reshape(n, -1, len(self.net.actions))  # (n, others, A)
            if total.shape[1] == 1:
                log_joint = total[:, 0]
                probs = log_joint.softmax(-1)
                # log p(e) = log p(a*, e) - log p(a* | e) at the most probable a*: exact,
                # and cheaper than a second pass (logsumexp)
                top, arg = probs.max(-1)
                log_evidence = log_joint.gather(-1, arg[:, None]).squeeze(-1) - top.log()
            else:
                log_marginal = total.logsumexp(1)
                log_evidence = log_marginal.logsumexp(-1)
                probs = (log_marginal - log_evidence[:, None]).exp()
        if plan.unseen is None:
            unseen_mass = torch.zeros_like(probs)
        elif isinstance(plan, FactoredPlan):
            unseen_mass = factored_unseen
        elif plan.answers is not None and plan.answers.unseen_mass is not None:
            unseen_mass = plan.answers.unseen_mass.index_select(0, row)
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
        if allowed is not None or plan.unseen is not None:
            top = None  # the maximum of the score, not of probs
        if allowed is not None:
            score = score.masked_fill(~allowed.expand_as(score), -1.0)
        if avoid_unseen and plan.unseen is not None and bool((unseen_mass >= 0.5).any()):
            seen_score = score.masked_fill(unseen_mass >= 0.5, -1.0)
            score = torch.where(seen_score.max(-1, keepdim=True).values >= 0, seen_score, score)
        if plan.answers is not None and allowed is None and plan.unseen is None:
            best = plan.answers.best[row]  # first_best(score, top), row by row
        else:
            best = first_best(score, top)
        names = tuple(self.net.actions[i] for i in best.tolist())
        flag = self._evidence_below(enc, log_evidence, below)
        return ActionPosterior(
            probs, best, names, log_evidence, unseen_mass, self.net.actions, flag
        )

    def _one_answer(self, enc: Evidence, plan: _Plan, below: float) -> ActionPosterior:
        """One row of a pattern with answers per configuration.

        Read by its position in the flattened tables (slices, no index tensors): the same numbers as
        the batched gather, in a few small operations.
        """
        row = 0
        for s, size in zip(plan.observed, plan.log_table.shape, strict=False):
            row = row * size + int(enc[s])
        answers = plan.answers
        # numpy copies wrapped as tensors: cheaper than torch's own small operations, and
        # the results own their memory (the answers stay the plan's)
        probs = answers.probs.numpy()[row : row + 1].copy()
        best = answers.best.numpy()[row : row + 1].copy()
        log_evidence = answers.log_evidence.numpy()[row : row + 1].copy()
        return ActionPosterior(
            torch.from_numpy(probs),
            torch.from_numpy(best),
            (self.net.actions[int(best[0])],),
            torch.from_numpy(log_evidence),
            torch.from_numpy(np.zeros_like(probs)),
            self.net.actions,
            self._one_below(enc, plan, row, float(log_evidence[0]), below),
        )

    def _one_below(
        self, enc: Evidence, plan: _Plan, row: int, log_evidence: float, below: float
    ) -> torch.Tensor:
        """``(1,)`` bool: :meth:`_evidence_below` for one row of a pattern with answers.

        From its table of ``log_evidence - log_prior`` per configuration (built once).
        """
        pattern = frozenset(enc)
        if pattern not in self.surprises:
            ends = {end_site(f.name) for f in self.net.features}
            given = frozenset(s for s in enc if s not in ends)
            if len(given) == len(enc):
                self.surprises[pattern] = None  # no end site observed: never implausible
            else:
                flag = self._evidence_below(enc, log_evidence, below)  # builds priors[given]
                if given not in self.priors:  # a prior summed per row (FactoredPlan)
                    return flag
                prior = self.priors[given]  # axes: the observed non-end sites, in order
                shape = [
                    size if s in given else 1
                    for s, size in zip(plan.observed, plan.log_table.shape, strict=False)
                ]
                log_evidence_all = plan.answers.log_evidence.reshape(
                    plan.log_table.shape[: len(plan.observed)]
                )
                self.surprises[pattern] = (
                    (log_evidence_all - prior.reshape(shape)).reshape(-1).numpy()
                )
        surprise = self.surprises[pattern]
        flag = surprise is not None and bool(surprise[row] < math.log(below))
        return torch.from_numpy(np.array([flag]))

    def _evidence_below(self, enc: Evidence, log_evidence: torch.Tensor | float, below: float):
        """``(n,)`` bool: p(observed end sites | the rest of the evidence) below ``below``.

        ``log_evidence``: ``(n,)``, or a float for one row.
        """
        ends = {end_site(f.name) for f in self.net.features}
        given = frozenset(s for s in enc if s not in ends)
        if len(given) == len(enc):
            return torch.zeros(enc.n_rows, dtype=torch.bool)
        if given not in self.priors:
            plan = self.plans.get(given) or self._build_plan(given)
            if isinstance(plan, FactoredPlan):  # the prior summed per row by elimination
                self.plans[given] = plan
                log_prior = plan.log_evidence(enc)
                return torch.as_tensor(log_evidence - log_prior < math.log(below)).reshape(-1)
            table = plan.log_table
            k = len(plan.observed)
            self.priors[given] = table.reshape(*table.shape[:k], -1).logsumexp(-1)
        order = [s for s in self.order if s in given]  # the plan's observed axes
        if enc.n_rows == 1:  # Python numbers: the same subtraction and comparison
            log_prior = float(self.priors[given].numpy()[tuple(int(enc[s]) for s in order)])
            flag = float(log_evidence) - log_prior < math.log(below)
            return torch.from_numpy(np.array([flag]))
        log_prior = self.priors[given][tuple(enc[s] for s in order)]
        return (log_evidence - log_prior) < math.log(below)


def compile_discrete(net: EffectNetwork, params: NetworkParams) -> CompiledNetwork:
    """Trace ``effect_model`` once with every site enumerated and keep its log tables."""
    check_params(net, params)
    continuous = [s.name for s in net.sites if not s.discrete]
    if continuous:
        raise ValueError(
            f"compile_discrete needs an all-discrete network; continuous sites: {continuous}"
        )
    trace = poutine.trace(poutine.enum(effect_model, first_available_dim=-2)).get_trace(
        net, params, n_rows=1
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
        # an enumerated table's log_prob may be a strided view of its log table: kept as
        # a view (no copy of a large table that a pattern may never read)
        factors[name] = lp.reshape(*[1] * (rank - lp.dim()), *lp.shape)
    seen = {}
    for spec in net.sites:
        if spec.role != "end":
            continue
        cpd = net.cpd(spec.name)
        n = cpd.seen(params[spec.name])  # over the discrete parents, in table-axis order
        # move the parents' axes to their positions in ``order``
        perm = sorted(range(len(cpd.parents)), key=lambda i: order.index(cpd.parents[i]))
        n = n.permute(perm)
        shape = [net.site(s).size if s in cpd.parents else 1 for s in order]
        seen[spec.name] = n.reshape(shape)
    return CompiledNetwork(net, order, factors, seen)
