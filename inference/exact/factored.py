"""An evidence pattern of the compiled action tables answered by elimination, row by row.

Where the latent sites of a pattern are many and the network's structure splits their
joint (sparse parents), summing the pattern's factor tables into one table would hold
the joint: ``2^k`` configurations for ``k`` unknown binary initial values. Instead each
factor table is indexed at a row's observed states, which leaves a factor over the
latent sites it spans, and the latent sites are summed out one at a time
(:func:`inference.exact.elimination.contract`): the cost follows the largest factor
the elimination builds, not the joint. The factors are the tables the traced model's
log-probabilities are read from (:func:`inference.queries.action_tables.compile_discrete`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
from effect_networks.inference.exact.elimination import contract, contract_size
from effect_networks.models.declaration import ACTION
from effect_networks.models.evidence import Evidence

#: A pattern whose summed table (observed configurations times the latent joint) holds
#: at most this many values keeps that table: its answers are then computed once per
#: observed configuration and a query reads them.
SUMMED_TABLE = 1 << 22


@dataclass(frozen=True)
class _Part:
    """One factor table.

    Its axes of observed sites first and flattened (the rows' index), then the latent sites it
    spans, ``(prod observed sizes, latent sizes...)``.
    """

    table: torch.Tensor
    observed: tuple[str, ...]  # the observed sites it spans, slowest first
    sizes: tuple[int, ...]  # their sizes
    shape: tuple[int, ...]  # its shape in the pattern's latent layout (1 where not spanned)

    def at(self, enc: Evidence) -> torch.Tensor:
        """``(latent layout..., n)`` the factor at each row's observed states.

        Rows 1 where it spans no observed site.
        """
        if not self.observed:
            return self.table.reshape(*self.shape, 1)
        row = enc[self.observed[0]]
        for site, size in zip(self.observed[1:], self.sizes[1:], strict=True):
            row = row * size + enc[site]
        picked = self.table.index_select(0, row)  # (n, latent sizes...)
        return picked.movedim(0, -1).reshape(*self.shape, row.shape[0])


def _part(table: torch.Tensor, order: tuple[str, ...], observed, latent) -> _Part:
    """``table`` laid out for a pattern whose latent layout is ``latent``.

    ``table`` has one axis per site of ``order``.
    """
    obs_axes = [a for a, s in enumerate(order) if s in observed and table.shape[a] > 1]
    lat_axes = [a for a, s in enumerate(order) if s in latent and table.shape[a] > 1]
    rest = [a for a in range(len(order)) if a not in obs_axes and a not in lat_axes]
    sizes = tuple(table.shape[a] for a in obs_axes)
    moved = table.permute(*obs_axes, *lat_axes, *rest)
    moved = moved.reshape(math.prod(sizes), *(table.shape[a] for a in lat_axes)).contiguous()
    shape = tuple(table.shape[order.index(s)] for s in latent)
    return _Part(moved, tuple(order[a] for a in obs_axes), sizes, shape)


@dataclass(frozen=True)
class FactoredPlan:
    """A pattern's kept factors, each laid out by ``_Part``, over the latent sites ``latent``.

    The action is among the latent sites. ``unseen`` holds, where some configuration of an observed
    end site's parents was never seen in training, that site's indicator of a seen configuration as
    a log-factor (0 or ``-inf``).
    """

    observed: tuple[str, ...]
    latent: tuple[str, ...]
    parts: tuple[_Part, ...]
    unseen: tuple[_Part, ...] | None
    scopes: tuple[frozenset[tuple[int, int]], ...]  # the parts', then the unseen ones'
    answers = None  # no per-configuration answers: each row is summed when asked

    @staticmethod
    def of(
        order: tuple[str, ...],
        sizes: dict[str, int],
        observed: frozenset,
        kept: list[torch.Tensor],
        misses: list[torch.Tensor],
    ) -> FactoredPlan | None:
        """The plan of ``observed`` by elimination, where one summed table would serve worse.

        Where the summed table would exceed ``SUMMED_TABLE`` values and the latent sites' joint is
        larger than the elimination's steps by far (the rule
        :func:`~inference.exact.elimination.contract_size` applies); ``None`` where the table is
        small or the joint does not split, and one summed table serves better.
        """
        spanned = {s for t in kept for a, s in enumerate(order) if t.shape[a] > 1}
        latent = tuple(s for s in order if s not in observed and (s in spanned or s == ACTION))
        dim = {s: i - len(latent) - 1 for i, s in enumerate(latent)}  # rows last
        scopes = tuple(
            frozenset(
                (dim[s], t.shape[a]) for a, s in enumerate(order) if s in dim and t.shape[a] > 1
            )
            for t in kept
        )
        joint = math.prod(sizes[s] for s in latent)
        table = joint * math.prod(sizes[s] for s in spanned if s in observed)
        if table <= SUMMED_TABLE or contract_size(scopes) >= joint:
            return None
        parts = tuple(_part(t, order, observed, latent) for t in kept)
        unseen = None
        misses = [_part(m, order, observed, latent) for m in misses]  # fewer dims first
        scopes += tuple(_scope(m.shape) for m in misses)
        if any(bool(m.table.any()) for m in misses):
            dtype = kept[0].dtype
            unseen = tuple(
                replace(m, table=torch.where(m.table, -torch.inf, 0.0).to(dtype)) for m in misses
            )
        observed = tuple(s for s in order if s in observed)
        return FactoredPlan(observed, latent, parts, unseen, scopes)

    def _sum(self, factors: list[torch.Tensor], keep_action: bool, n: int) -> torch.Tensor:
        """``(n, A)`` the factors' log-sum over the latent sites.

        ``(n,)`` without ``keep_action``.
        """
        rank = len(self.latent) + 1
        eliminate = [i - rank for i, s in enumerate(self.latent) if not keep_action or s != ACTION]
        total = contract(factors, eliminate, self.scopes[: len(factors)])
        if not keep_action:
            return total.reshape(-1).expand(n)
        a = self.latent.index(ACTION) - rank + total.dim()
        total = total.movedim(a, 0)
        return total.reshape(total.shape[0], -1).expand(total.shape[0], n).T

    def log_evidence(self, enc: Evidence) -> torch.Tensor:
        """``(n,)`` log-probability of each row's observed states, every latent site summed out."""
        if any(p.observed for p in self.parts):
            return self._sum([p.at(enc) for p in self.parts], False, enc.n_rows)
        if "prior" not in self.__dict__:  # the same for every row: summed once
            self.__dict__["prior"] = self._sum([p.at(enc) for p in self.parts], False, 1)
        return self.__dict__["prior"].expand(enc.n_rows)

    def answer(self, enc: Evidence) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Per row: the action's posterior, the evidence's log-probability, and its unseen share.

        The action's posterior ``(n, A)``, the evidence's log-probability ``(n,)``, and the
        posterior probability, given each action, that an observed end site sits on a configuration
        unseen in training ``(n, A)``.
        """
        n = enc.n_rows
        factors = [p.at(enc) for p in self.parts]
        log_marginal = self._sum(factors, True, n)
        log_evidence = log_marginal.logsumexp(-1)
        probs = (log_marginal - log_evidence[:, None]).exp()
        if self.unseen is None:
            return probs, log_evidence, torch.zeros_like(probs)
        log_seen = self._sum(factors + [p.at(enc) for p in self.unseen], True, n)
        possible = log_marginal > -torch.inf
        p_seen = (log_seen - torch.where(possible, log_marginal, 0.0)).exp()
        unseen = torch.where(possible, 1.0 - p_seen, 0.0).clamp(0, 1)
        return probs, log_evidence, unseen


def _scope(shape: tuple[int, ...]) -> frozenset[tuple[int, int]]:
    """:func:`~inference.exact.elimination.scope` of a part laid out in ``shape`` (rows last)."""
    return frozenset((i - len(shape) - 1, k) for i, k in enumerate(shape) if k > 1)
