"""Discrete networks compiled to their factor tables, for fast repeated queries.

Tracing the Pyro model costs a fixed ~1 ms per call, which dominates a single small
query. For a network whose sites are all discrete, :func:`compile_discrete` traces the
model *once* with every site enumerated and no evidence, and keeps each site's
log-probability table (one dim per enumerated site). A query then indexes the tables at
the evidence (one gather per factor), adds them and normalises: the same numbers as
:mod:`inference.queries`, read from the same model, without re-tracing. The tests check
the two against each other.

Both compiled queries report ``implausible`` as the traced ones do
(:mod:`inference.queries.plausibility`): the discrete action query from the evidence
probability against the same query's table with the end sites left out, the parameter
query from the chi-square tail of the closest cluster's Gaussian.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import torch
from pyro import poutine

from inference.queries import (
    ActionPosterior,
    GaussianMixture,
    ParameterPosterior,
    allowed_actions,
    first_best,
    no_rows,
    outside_range,
    placeholder_row,
)
from inference.queries.plausibility import (
    IMPLAUSIBLE_BELOW,
    check_threshold,
    initial_tails,
    outside_training,
)
from models.cpds import concat_inputs
from models.declaration import (
    ACTION,
    DTYPE,
    EffectNetwork,
    Parameter,
    end_site,
)
from models.evidence import MAX_MAGNITUDE, Evidence, is_partial
from models.gaussian import chi_square_tail, mask_unobserved, partial_log_density
from models.model import effect_model
from models.params import NetworkParams, check_params


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
    """The posterior per observed configuration, for a pattern whose latent sites include
    the action: a query then gathers its answer instead of computing it per row.

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
        """Answers of a table ``(observed sizes..., latent sizes...)`` with ``k`` observed
        axes and the action at latent axis ``a``, the other latent sites summed out, in
        chunks of configurations of at most ``ANSWERS_CHUNK`` elements."""
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
        total = torch.zeros((), dtype=DTYPE)
        unseen = None
        needed = self.net.end_sites_needed(observed)
        for site, table in self.factors.items():
            role = self.net.site(site).role
            if role == "end" and site not in needed:
                continue  # no observed site depends on it: it sums to one
            if role == "end" and site not in observed:  # a latent parent of an observed one
                total = total + table
                continue
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
            raise ValueError("evidence names the action; infer_action infers it")
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
        if plan.answers is not None:  # gather the answers computed for the whole table
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
        """One row of a pattern with answers per configuration, read by its position in
        the flattened tables (slices, no index tensors): the same numbers as the batched
        gather, in a few small operations."""
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
        """``(1,)`` bool: :meth:`_evidence_below` for one row of a pattern with answers,
        from its table of ``log_evidence - log_prior`` per configuration (built once)."""
        pattern = frozenset(enc)
        if pattern not in self.surprises:
            ends = {end_site(f.name) for f in self.net.features}
            given = frozenset(s for s in enc if s not in ends)
            if len(given) == len(enc):
                self.surprises[pattern] = None  # no end site observed: never implausible
            else:
                self._evidence_below(enc, log_evidence, below)  # builds priors[given]
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
        """``(n,)`` bool: p(observed end sites | the rest of the evidence) below ``below``
        (``log_evidence``: ``(n,)``, or a float for one row)."""
        ends = {end_site(f.name) for f in self.net.features}
        given = frozenset(s for s in enc if s not in ends)
        if len(given) == len(enc):
            return torch.zeros(enc.n_rows, dtype=torch.bool)
        if given not in self.priors:
            plan = self.plans.get(given) or self._build_plan(given)
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
        # contiguous: an enumerated table's log_prob may be a strided view of its table
        factors[name] = lp.reshape(*[1] * (rank - lp.dim()), *lp.shape).contiguous()
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


@dataclass(frozen=True)
class CompiledParameterQuery:
    """The inverse parameter query with its Gaussian tables precomputed.

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
    # for the initial states' plausibility (inference.queries.plausibility.initial_tails)
    params: NetworkParams | None = field(default=None, repr=False, compare=False)
    # The one-row tables (:meth:`_one_row`), built on the first single query.
    _one: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def infer(
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
        others = [enc[s] for s in self.inputs[:-1]]
        x = torch.cat(others, -1) if others else None
        if x is not None:
            loc = loc + (self.w_x[gather] @ x[:, None, :, None]).squeeze(-1)
        if is_partial(y):
            return self._infer_partial(enc, y, index, loc, mixture, below)
        # log N(y; loc, L L^T) = log_norm - |L^-1 (y - loc)|^2 / 2, with L^-1 and log_norm
        # precomputed from the model's own marginal Cholesky factor L. The residual is
        # taken first and then whitened: a sum of squares without cancellation, where an
        # expanded form y'Ay - 2b'y + c with A ~ 1 / noise loses as many digits as A has.
        whiten = self.whiten[gather][0] if shared else self.whiten[index]  # (C or n, C, d, d)
        d2 = _whitened_distance(y, loc, whiten)  # (n, C) squared Mahalanobis distances
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
        _refuse_impossible(log_post)
        probs = torch.softmax(log_post, -1, out=log_post)  # in place: log_post is ours
        # numpy's argmax (the first maximum, as torch's) is several times faster here
        best = torch.from_numpy(probs.numpy().argmax(-1))
        rows = torch.arange(n)
        full = (*index, best)
        resid = y - loc.expand(n, *loc.shape[1:])[rows, best]
        mean = self.prior_mean[best] + (self.gain[full] @ resid[..., None]).squeeze(-1)
        unseen = (~self.seen[full]).to(DTYPE)
        mix = None
        if mixture:  # every cluster's conditional Gaussian, from the same tables
            resid_all = y[:, None, :] - loc  # (n, C, d)
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
        """Per action, the numpy views :meth:`_one_row` reads (``None``: no one-row path,
        the feature has discrete parents besides the action and the cluster, or
        continuous inputs besides the parameter)."""
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
        """The query of one fully observed hit (and perhaps the action, as a label) with
        numpy on per-action tables: a handful of small operations instead of some forty
        tensor ones. The same steps as the batched query on the same tables, so the same
        answers up to rounding. ``None`` where the evidence is anything else (several
        rows, a partial observation, encoded evidence, an error to report): the general
        path then serves it."""
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

    def _infer_partial(self, enc, y, index, loc, mixture, below) -> ParameterPosterior:
        """The query for ``y`` observed in some dimensions (NaN in the others): each
        cluster's marginal and conditioning restricted to the observed dimensions. The
        tables hold them for all dimensions; the marginal covariance ``L L^T``, the
        cross-covariance ``gain L L^T`` and the cluster covariance ``post_cov + gain L
        L^T gain^T`` are read back from them, then every observed-dimension quantity is
        taken from those (:func:`models.gaussian.mask_unobserved`)."""
        n = y.shape[0]
        eye = torch.eye(y.shape[-1], dtype=DTYPE)
        tril = torch.linalg.solve_triangular(self.whiten[index], eye, upper=False)
        marginal = tril @ tril.mT  # (n, C, d, d)
        gain = self.gain[index]
        cross = gain @ marginal  # (n, C, k, d)
        prior_cov = self.post_cov[index] + gain @ cross.mT
        y_, loc_, cov_, seen = mask_unobserved(y[:, None, :], loc, marginal)
        chol = torch.linalg.cholesky(cov_)
        resid = (y_ - loc_)[..., None]
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
        _refuse_impossible(log_lik + log_cluster)
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


@dataclass(frozen=True)
class CompiledJointParameterQuery:
    """The inverse query of a parameter acting on several features, without tracing.

    The observed continuous features it acts on are jointly Gaussian given its cluster
    (its unknown value couples them); their joint density is taken in the model's own
    order, each feature given the value's Gaussian conditioned on those before it
    (:meth:`models.cpds.ParameterMixture.shared_loc_tril` and ``update``, the rules the
    model samples with), batched over rows and clusters; the observed discrete features
    it acts on add their kind's log-probability per cluster. Same results as
    :func:`inference.infer_parameter` for evidence of the initial state, the action, the
    affected features and their parents.
    """

    net: EffectNetwork
    params: NetworkParams = field(repr=False)
    parameter: Parameter
    log_cluster: torch.Tensor  # (A, C)

    def infer(
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
            return no_rows(self.infer(placeholder, mixture=mixture, implausible_below=below))
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
            loc, tril = m.shared_loc_tril(*args, known, belief)
            y = enc[site][:, None, :]
            log_lik = log_lik + partial_log_density(y, loc, tril)
            y_, loc_, cov_, seen = mask_unobserved(y, loc, tril @ tril.mT)
            z = torch.linalg.solve_triangular(
                torch.linalg.cholesky(cov_), (y_ - loc_)[..., None], upper=False
            )
            d2 = d2 + z.square().sum((-2, -1))
            dof = dof + seen[:, 0].sum(-1)
            belief = m.update(*args, y, belief)
        _refuse_impossible(log_lik + log_cluster)
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


def compile_parameter_query(
    net: EffectNetwork, params: NetworkParams, parameter: str
) -> CompiledParameterQuery | CompiledJointParameterQuery:
    """Precompute the inverse query of ``parameter``: :class:`CompiledParameterQuery`
    (its tables) for a parameter acting on one continuous feature,
    :class:`CompiledJointParameterQuery` for one acting on several features. A
    continuous feature that several parameters act on is refused (use
    :func:`inference.infer_parameter`)."""
    check_params(net, params)
    m = net.mixture(parameter)
    shared = [s for s in m.continuous if net.acting_on(s) != (m,)]
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


def _refuse_impossible(log_post: torch.Tensor) -> None:
    """Refuse rows ``(n, C)`` whose every cluster has probability 0 (in float64): no
    posterior exists (as :class:`inference.queries.enumeration.Enumerated` refuses them)."""
    top = log_post.amax(-1)
    if not bool((top > -torch.inf).all()):
        row = int((top == -torch.inf).nonzero()[0])
        raise ValueError(
            f"evidence row {row} has probability 0 under every configuration of the model "
            "(every cluster): no posterior exists. A value too far from every component "
            "for float64 (rescale the feature)"
        )


def _whitened_distance(y: torch.Tensor, loc: torch.Tensor, whiten: torch.Tensor) -> torch.Tensor:
    """``(n, C)`` ``|whiten (y - loc)|^2`` for ``y`` ``(n, d)``, ``loc`` ``(n or 1, C, d)`` and
    lower triangular ``whiten`` ``(n or C, ..., d, d)``: the residual first, then whitened,
    one dimension at a time on ``(n, C)`` tensors (a sum of squares without cancellation,
    and no ``(n, C, d)`` temporaries)."""
    d = y.shape[-1]
    diff = [y[:, j, None] - loc[..., j] for j in range(d)]  # (n, C) each
    d2 = None
    for i in range(d):
        z = diff[0] * whiten[..., i, 0]
        for j in range(1, i + 1):
            z.addcmul_(diff[j], whiten[..., i, j])
        d2 = z.square_() if d2 is None else d2.add_(z.square_())
    return d2
