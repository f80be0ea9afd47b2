"""Learning which parents each end feature has, from complete training rows.

:func:`learn_structure` chooses the parent set of every end site among the sites a
declaration allows there (:class:`~models.declaration.EffectNetwork`): the initial
sites, the action and the *discrete* end sites (a continuous end site is no parent),
without a cycle among end sites. A parameter's cluster and value stay in the family of
every feature it is declared to affect, and the action stays a parent of those features
(it decides whether the parameter is used); initial sites stay roots. The criterion is a
decomposable score (:mod:`inference.fitting.family`: BIC by default, AIC, or BDeu for
all-discrete networks), the sum of one term per end site's family, maximised by

* **exhaustive search** where the candidate families are few: every admissible parent
  set of every end site (at most ``max_parents`` chosen parents) is scored; without
  edges among end sites each site takes its best family, and with them a dynamic
  programme over the orders of the discrete end sites (each site's best family among
  those whose end parents come before it, the best order by subsets) finds the best
  acyclic combination, the global optimum of the score;
* **greedy hill climbing** otherwise: from no chosen parents, the single edge added,
  removed or (between two discrete end sites) reversed that raises the score most, until
  none does; then ``restarts`` times from the best network with a few random edges
  changed (seeded), keeping the best.

Both search the same space and return the same optimum where the climb finds it.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable, Mapping

import numpy as np
from effect_networks.inference.fitting.family import Families, Family
from effect_networks.models.declaration import ACTION, EffectNetwork, Feature, Parameter
from effect_networks.models.sites import end_site

__all__ = ["EXHAUSTIVE_COST", "EXHAUSTIVE_ENDS", "SOFTMAX_COST", "learn_structure"]

#: ``search="auto"`` searches exhaustively when scoring every candidate family of every
#: end site costs at most this many table fits (:data:`SOFTMAX_COST` per softmax family)
#: and the discrete end sites that may be parents are at most :data:`EXHAUSTIVE_ENDS`
#: (the order search visits every subset of them).
EXHAUSTIVE_COST = 4000
#: The most discrete end sites that may be parents for which the order search runs (it
#: visits every subset of them): for exhaustive search and the climb's recombination.
EXHAUSTIVE_ENDS = 12
#: Scores this close (relative) are equal up to rounding: the choice between them goes
#: to the family with fewer end parents.
TIE = 1e-9
#: A softmax family's cost in table fits: Newton's method on the rows takes several
#: passes over them where a table takes one count.
SOFTMAX_COST = 50


def learn_structure(
    data: Mapping[str, object],
    features: Iterable[Feature],
    actions: Iterable[str],
    parameters: Iterable[Parameter] = (),
    *,
    score: str = "bic",
    max_parents: int | None = 4,
    end_parents: bool = True,
    required: Iterable[tuple[str, str]] = (),
    forbidden: Iterable[tuple[str, str]] = (),
    search: str = "auto",
    restarts: int = 5,
    seed: int = 0,
    min_variance: float = 1e-6,
    l2: float = 0.01,
    steps: int = 20,
    ess: float = 1.0,
) -> EffectNetwork:
    """The effect network whose end sites' parents maximise a decomposable score.

    Parameters
    ----------
    data
        Complete training rows by site, read as :func:`inference.fit` reads them
        (:func:`inference.fitting.reading.read_rows`: a mapping of labels, a ``DataFrame``
        or one read back from CSV; ``param.p`` NaN where the action does not use ``p``).
        Rows with missing values are refused, naming each site with gaps and how many
        rows miss it: learn from the complete rows (``frame.dropna(subset=...)``, the
        columns of the sites with gaps) and fit the
        learned network on all rows, or fit a declared structure with the gaps.
    features, actions, parameters
        The declaration (:class:`~models.declaration.EffectNetwork`); its end sites'
        parents are learned.
    score
        ``"bic"`` (default), ``"aic"`` or ``"bdeu"`` (networks of discrete features only,
        no parameters); see :mod:`inference.fitting.family`.
    max_parents
        The most chosen parents per end site (the action counts; a parameter's sites do
        not). ``None``: no bound.
    end_parents
        Whether discrete end sites may be parents of other end sites.
    required, forbidden
        ``(parent, child)`` site pairs every learned network has, or none has. The
        action is required for a feature a parameter affects.
    search
        ``"exhaustive"``, ``"greedy"`` or ``"auto"`` (exhaustive when scoring the
        candidate families costs at most :data:`EXHAUSTIVE_COST` and the discrete end sites
        that may be parents at most :data:`EXHAUSTIVE_ENDS`).
    restarts, seed
        The greedy search's random restarts and their seed.
    min_variance, l2, steps, ess
        The covariance floor and softmax prior of :func:`inference.fit`; the most
        Newton steps of a softmax family's fit (a state no row of a configuration shows
        sends its offset towards minus infinity, where the steps only crawl: the
        log-likelihood they leave is within a vanishing margin of the supremum); BDeu's
        equivalent sample size.

    Returns
    -------
    EffectNetwork
        The declaration with the learned parents (``parents=``); fit it with
        :func:`inference.fit`.

    Raises
    ------
    ValueError
        Naming the argument: rows with missing values, an unknown score or search, a pair that names no site or
        breaks the declaration's rules, required pairs that form a cycle, or an end site
        no admissible family fits (more parent configurations than rows).

    Examples
    --------
    >>> import numpy as np
    >>> from models import Discrete
    >>> rng = np.random.default_rng(0)
    >>> colour, lit = rng.integers(0, 2, 500), rng.integers(0, 2, 500)
    >>> rows = {"initial.colour": colour, "initial.lit": lit, "action": ["push"] * 500,
    ...         "end.colour": colour, "end.lit": 1 - lit}
    >>> net = learn_structure(rows, (Discrete("colour", (0, 1)), Discrete("lit", (0, 1))),
    ...                       ("push",))
    >>> dict(net.parents)
    {'end.colour': ('initial.colour',), 'end.lit': ('initial.lit',)}
    """
    if search not in ("auto", "exhaustive", "greedy"):
        raise ValueError(f"search must be 'auto', 'exhaustive' or 'greedy', got {search!r}")
    if max_parents is not None and (not isinstance(max_parents, int) or max_parents < 0):
        raise ValueError(f"max_parents must be an int >= 0 or None, got {max_parents!r}")
    if not isinstance(restarts, int) or restarts < 0:
        raise ValueError(f"restarts must be an int >= 0, got {restarts!r}")
    features, actions, parameters = tuple(features), tuple(actions), tuple(parameters)
    # the sites' encoding does not depend on the parents: the sparsest network serves
    bare = _network(features, actions, parameters, {})
    space = _Space(bare, max_parents, end_parents, required, forbidden)
    space.families = Families(
        bare,
        data,
        score=score,
        min_variance=min_variance,
        l2=l2,
        steps=steps,
        ess=ess,
        pooled=True,
    )
    if search == "auto":
        small = space.cost() <= EXHAUSTIVE_COST and len(space.movers) <= EXHAUSTIVE_ENDS
        search = "exhaustive" if small else "greedy"
    if search == "exhaustive":
        chosen = space.exhaustive()
    else:
        chosen = space.greedy(restarts, np.random.default_rng(seed))
    return _network(features, actions, parameters, chosen)


def _network(features, actions, parameters, chosen: Mapping[str, tuple[str, ...]]):
    """The declaration with ``chosen`` parents for every end site.

    None where absent, but the action for a feature a parameter affects.
    """
    affected = {end_site(f) for p in parameters for f in p.features}
    parents = {
        end_site(f.name): chosen.get(
            end_site(f.name), (ACTION,) if end_site(f.name) in affected else ()
        )
        for f in features
    }
    return EffectNetwork(features, actions, parameters, parents=parents)


class _Space:
    """The parent sets the declaration allows for each end site, and their search."""

    families: Families  # the rows' scores, set once the arguments are checked

    def __init__(self, net, max_parents, end_parents, required, forbidden):
        self.ends = [s.name for s in net.sites if s.role == "end"]
        initial = [s.name for s in net.sites if s.role == "initial"]
        # discrete end sites that may be parents: the only edges that can close a cycle
        self.movers = [s for s in self.ends if net.site(s).discrete] if end_parents else []
        self.max_parents = math.inf if max_parents is None else max_parents
        self.candidates = {
            s: [*initial, ACTION, *(q for q in self.movers if q != s)] for s in self.ends
        }
        affected = {end_site(f) for p in net.parameters for f in p.features}
        self.required = {s: {ACTION} if s in affected else set() for s in self.ends}
        for name, pairs, into in (("required", required, True), ("forbidden", forbidden, False)):
            for pair in pairs:
                parent, child = self._pair(name, pair)
                if into:
                    self.required[child].add(parent)
                else:
                    if parent in self.required[child]:
                        raise ValueError(
                            f"forbidden names {(parent, child)}, which is required"
                            + (" (a parameter affects it)" if parent == ACTION else "")
                        )
                    self.candidates[child].remove(parent)
        for s, needed in self.required.items():
            if len(needed) > self.max_parents:
                raise ValueError(
                    f"{s!r} requires the parents {sorted(needed)}, more than "
                    f"max_parents={max_parents}"
                )
        order = {s: i for i, s in enumerate(self.movers)}
        self.index = order
        if _cyclic({s: self.required[s] & set(order) for s in self.movers}):
            raise ValueError(f"the required pairs form a cycle among {self.movers}")

    def _pair(self, name: str, pair) -> tuple[str, str]:
        try:
            parent, child = pair
        except (TypeError, ValueError):
            raise ValueError(f"{name} must hold (parent, child) site pairs, got {pair!r}") from None
        if child not in self.candidates or parent not in self.candidates[child]:
            allowed = {s: c for s, c in self.candidates.items()}
            raise ValueError(
                f"{name} names {(parent, child)}, which is not an edge the declaration allows "
                f"(the parents an end site may have: {allowed})"
            )
        return parent, child

    # ------------------------------------------------------------------ exhaustive
    def _sets(self, site: str):
        """Every admissible parent set of ``site``.

        The required parents plus at most ``max_parents`` in all, in site order.
        """
        needed = self.required[site]
        free = [q for q in self.candidates[site] if q not in needed]
        room = min(len(free), self.max_parents - len(needed))
        for k in range(room + 1):
            for extra in itertools.combinations(free, k):
                chosen = (*needed, *extra)
                if self.families.admissible(site, chosen):
                    yield chosen

    def cost(self) -> int:
        """What exhaustive search would cost, in table fits.

        The parent sets it would score, a softmax family (a discrete site with a continuous parent:
        Newton's method on the rows) counting :data:`SOFTMAX_COST` (admissibility is not checked).
        """
        total = 0
        for s in self.ends:
            needed = self.required[s]
            free = [q for q in self.candidates[s] if q not in needed]
            room = int(min(len(free), self.max_parents - len(needed)))
            sets = _subsets(len(free), room)
            specs = self.families.specs
            if specs[s].discrete:
                continuous = sum(not specs[q].discrete for q in free)
                plain = 0
                if all(specs[q].discrete for q in needed):
                    plain = _subsets(len(free) - continuous, room)
                total += plain + SOFTMAX_COST * (sets - plain)
            else:
                total += sets
        return total

    def exhaustive(self) -> dict[str, tuple[str, ...]]:
        scored = {s: [self.families.family(s, ps) for ps in self._sets(s)] for s in self.ends}
        for s, options in scored.items():
            if not options:
                raise ValueError(self._no_family(s))
        chosen = {}
        for s in self.ends:
            if s not in self.index:  # not a parent of any end: no cycle through it
                chosen[s] = self._preferred(scored[s]).parents
        chosen.update(self._best_order({s: scored[s] for s in self.movers}))
        return chosen

    def _preferred(self, options: list[Family]) -> Family:
        """The best-scoring family.

        Among those within rounding (:data:`TIE`) of it, the first with the fewest end parents (an
        end feature the action leaves as it was copies its initial site, which then explains as
        much).
        """
        top = max(f.score for f in options)
        near = [f for f in options if f.score >= top - TIE * abs(top)]
        specs = self.families.specs
        return min(near, key=lambda f: sum(specs[q].role == "end" for q in f.parents))

    def _best_order(self, scored: Mapping[str, list[Family]]) -> dict[str, tuple[str, ...]]:
        """The best acyclic choice of families for the discrete end sites.

        For the end sites that may be each other's parents: over orders of them, by subsets (each
        site takes its best family among those whose end parents all come before it).
        """
        m = len(self.movers)
        if not m:
            return {}
        size = 1 << m
        best, pick = {}, {}
        for s, options in scored.items():
            # best[s][S]: the best score of s with end parents inside S (bit i: movers[i])
            value = np.full(size, -np.inf)
            which = np.full(size, -1)
            for i, f in enumerate(options):
                mask = sum(1 << self.index[q] for q in f.parents if q in self.index)
                if f.score > value[mask]:
                    value[mask], which[mask] = f.score, i
            for bit in range(m):  # every subset inherits its subsets' best
                step = 1 << bit
                shape = (size // (2 * step), 2, step)
                v, w = value.reshape(shape), which.reshape(shape)
                # within rounding, the family with fewer end parents
                better = v[:, 0, :] >= v[:, 1, :] - TIE * np.abs(v[:, 1, :])
                v[:, 1, :] = np.where(better, v[:, 0, :], v[:, 1, :])
                w[:, 1, :] = np.where(better, w[:, 0, :], w[:, 1, :])
            best[s], pick[s] = value, which
        total = np.full(size, -np.inf)
        last = np.full(size, -1)
        total[0] = 0.0
        for subset in range(1, size):
            for i, s in enumerate(self.movers):
                if subset >> i & 1:
                    rest = subset ^ (1 << i)
                    value = total[rest] + best[s][rest]
                    if value > total[subset]:
                        total[subset], last[subset] = value, i
        if not np.isfinite(total[size - 1]):
            raise ValueError(self._no_family(self.movers[0]))
        chosen, subset = {}, size - 1
        while subset:
            i = int(last[subset])
            s = self.movers[i]
            subset ^= 1 << i
            chosen[s] = scored[s][int(pick[s][subset])].parents
        return chosen

    def _no_family(self, site: str) -> str:
        return (
            f"no parent set of {site!r} can be fitted from {self.families.n} rows (each has "
            f"more parent configurations than rows, or holds more than MAX_CPD_ENTRIES "
            f"numbers, or breaks max_parents={self.max_parents}): give more rows or fewer "
            "required parents"
        )

    # ------------------------------------------------------------------ greedy
    def _score(self, site: str, parents) -> float:
        if not self.families.admissible(site, parents):
            return -math.inf
        return self.families.family(site, parents).score

    def _moves(self, state: dict[str, frozenset], rank: Mapping[str, float] | None = None):
        """Every legal single-edge change: ``(site, new parents)`` pairs, one or two.

        With ``rank``, an edge between end sites is added only from a lower rank to a higher one,
        and none is turned.
        """
        for s in self.ends:
            ps = state[s]
            for q in self.candidates[s]:
                if q in ps:
                    if q not in self.required[s]:
                        yield ((s, ps - {q}),)
                        if rank is not None:
                            continue
                        if q in self.index and s in self.index and s in self.candidates[q]:
                            if len(state[q]) < self.max_parents:
                                turned = ((s, ps - {q}), (q, state[q] | {s}))
                                if not _cyclic(_with(state, turned, self.index)):
                                    yield turned
                elif len(ps) < self.max_parents:
                    if rank is not None and rank.get(q, -1) > rank.get(s, math.inf):
                        continue
                    added = ((s, ps | {q}),)
                    if q not in self.index or not _cyclic(_with(state, added, self.index)):
                        yield added

    def _climb(self, state: dict[str, frozenset], rank=None) -> dict[str, frozenset]:
        current = {s: self._score(s, ps) for s, ps in state.items()}
        while True:
            # a gain within rounding is none, and a move beats an earlier one only by
            # more than rounding: initial parents come first, so a tie goes to them
            rounding = TIE * max(1.0, abs(sum(current.values())))
            best, gain = None, rounding
            for move in self._moves(state, rank):
                delta = sum(self._score(s, ps) - current[s] for s, ps in move)
                if delta > gain + (rounding if best is not None else 0.0):
                    best, gain = move, delta
            if best is None:
                return state
            for s, ps in best:
                state[s], current[s] = ps, self._score(s, ps)

    def greedy(self, restarts: int, rng: np.random.Generator) -> dict[str, tuple[str, ...]]:
        start = {s: frozenset(self.required[s]) for s in self.ends}
        for s, ps in start.items():
            if not math.isfinite(self._score(s, ps)):
                raise ValueError(self._no_family(s))
        best = self._settle(start)
        best_score = self._total(best)
        for restart in range(restarts):
            if restart % 2 == 0 and len(self.movers) > 1:
                # from no chosen parents, edges among end sites only along a random
                # order of them: another orientation of what they share
                rank = dict(zip(self.movers, rng.permutation(len(self.movers)), strict=True))
                state = self._climb(dict(start), rank)
            else:
                state = dict(best)
                for _ in range(max(2, len(self.ends))):  # a few random legal edge changes
                    moves = list(self._moves(state))
                    if not moves:
                        break
                    for s, ps in moves[int(rng.integers(len(moves)))]:
                        state[s] = ps
            state = self._settle(state)
            total = self._total(state)
            if total > best_score + TIE * max(1.0, abs(best_score)):
                best, best_score = state, total
        order = list(self.families.specs)
        return {s: tuple(q for q in order if q in ps) for s, ps in best.items()}

    def _total(self, state: Mapping[str, frozenset]) -> float:
        return sum(self._score(s, ps) for s, ps in state.items())

    def _settle(self, state: dict[str, frozenset]) -> dict[str, frozenset]:
        """Climb from ``state``; then, while it gains, recombine and climb again.

        Recombine: the best acyclic choice among every family scored so far (the exhaustive order
        search over them, which turns edges among end sites that the climb, one edge at a time,
        cannot), and climb from there.
        """
        state = self._climb(state)
        if len(self.movers) > EXHAUSTIVE_ENDS:
            return state
        while True:
            scored = {s: self.families.scored(s) for s in self.ends}
            chosen = {s: self._preferred(scored[s]).parents for s in self.ends}
            chosen.update(self._best_order({s: scored[s] for s in self.movers}))
            combined = {s: frozenset(ps) for s, ps in chosen.items()}
            total = self._total(state)
            if self._total(combined) <= total + 1e-9 * max(1.0, abs(total)):
                return state
            state = self._climb(combined)


def _subsets(n: int, most: int) -> int:
    """How many subsets of ``n`` things hold at most ``most``."""
    return sum(math.comb(n, k) for k in range(max(0, min(n, most)) + 1))


def _with(state, move, index) -> dict[str, set]:
    """The end-to-end edges of ``state`` after ``move``, as parents within ``index``."""
    out = {s: set(ps) & set(index) for s, ps in state.items() if s in index}
    for s, ps in move:
        if s in index:
            out[s] = set(ps) & set(index)
    return out


def _cyclic(parents: Mapping[str, set]) -> bool:
    """Whether the parent sets ``{site: parents}`` (within the keys) close a cycle."""
    state: dict[str, int] = {}

    def visit(s: str) -> bool:
        if state.get(s) == 2:
            return False
        if state.get(s) == 1:
            return True
        state[s] = 1
        if any(visit(q) for q in parents.get(s, ()) if q in parents):
            return True
        state[s] = 2
        return False

    return any(visit(s) for s in parents)
