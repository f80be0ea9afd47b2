"""Active exploration: which (initial state, action) pairs to try next, and learning from them.

A robot cannot afford to play every action from every initial state many times. Given a
network whose sites are all tables, a *pool* of candidate pairs and an *oracle* that
plays candidates and reports their end states, :func:`explore` repeatedly chooses a
batch of candidates, plays them and updates the tables in closed form, until it has
used ``budget`` candidates.

Bayesian view of the fit. With pseudo-count ``alpha`` (:mod:`inference.fitting.sufficient_statistics`), a
table row fitted on counts ``c`` is ``(c + alpha) / (n + K alpha)``: the posterior mean of
the row's probabilities ``theta`` under a ``Dirichlet(alpha, ..., alpha)`` prior. Every
row (a configuration of an end site's discrete parents) has its own independent
posterior ``Dirichlet(c + alpha)``; one more row's outcome adds one to one count. So the
update is closed form, and ``ExplorationResult.params`` is exactly what
:func:`inference.fit` gives on the chosen rows with the same pseudo-count.

Strategies (``STRATEGIES``), each scoring a candidate by the end-site rows it would
fill (a candidate fixes every initial site and the action, hence one row per end site):

* ``"eig"`` -- the expected information gain about the rows' parameters from one play.
  For a Dirichlet-categorical row with parameters ``a`` (``a0 = sum a``) it is, in
  closed form, ``I(theta; y) = H[a / a0] - E[H[Cat(theta)]]`` with
  ``E[H[Cat(theta)]] = psi(a0 + 1) - sum_k a_k / a0 psi(a_k + 1)``
  (:func:`dirichlet_eig`). The rows of different end sites are independent a priori and
  each play draws one value per site, so the candidate's gain is the sum of its rows'
  gains (``sites`` restricts the sum to the end sites one cares about).
* ``"uncertainty"`` -- the entropy of the predictive distribution ``a / a0`` summed the
  same way (uncertainty sampling; it cannot tell "unknown" from "known to be random").
* ``"random"`` -- uniformly among the candidates not chosen yet.

How a batch of ``k`` is chosen (``eig``, ``uncertainty``): greedily, one candidate at a
time; after each pick its rows' parameters get the *expected* count of the pending play
(the predictive ``a / a0`` added to ``a``), and their scores are recomputed before the
next pick. Candidates whose rows differ are independent, so for them this is the ``k``
best distinct candidates; candidates that share a row (the same pair listed twice, or an
end site whose parents leave some initial site out) see the diminishing return of a
second play of the same row instead of all being chosen at once. Ties (every unseen
row scores the same) are broken uniformly at random with the run's generator, so the
order of the pool does not steer the choice.

``prior_strength`` (``s``, default 0) changes the *selection* only: a row's parameters
are scored as ``Dirichlet(c + alpha + s m)``, where ``m`` is the pseudo-count policy's
distribution of the counts pooled over the rows that share the row's parents except
the action (what this initial state's outcome usually is, whatever the action). With
``s > 0`` an unplayed row of an initial state whose plays mostly agree scores low, and
a row whose outcome departed from the usual scores high. The returned parameters stay
those of :func:`inference.fit` with ``alpha``.

The run is resumable: with ``checkpoint`` the state (counts, chosen candidates and their
outcomes, the generator's state) is saved after every batch, and a later call with the
same arguments continues from it and makes the same choices as a run that was never
interrupted.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
import torch
from effect_networks.inference.fitting.rows import check_settings
from effect_networks.models.cpds.table import TableCPD, normalised
from effect_networks.models.declaration import ACTION, EffectNetwork
from effect_networks.models.evidence import DTYPE, Evidence
from effect_networks.models.params import NetworkParams, check_params
from tqdm.auto import tqdm

__all__ = [
    "STRATEGIES",
    "ExplorationResult",
    "ExplorationState",
    "dirichlet_eig",
    "explore",
    "predictive_entropy",
    "with_pool_prior",
]

STRATEGIES = ("eig", "uncertainty", "random")
#: Relative tolerance within which two scores count as tied.
TIE = 1e-9


def predictive_entropy(alpha: torch.Tensor) -> torch.Tensor:
    """``(...)`` nats: the entropy of ``Dirichlet(alpha)``'s predictive ``alpha / alpha0``.

    ``alpha`` ``(..., K)``, positive.
    """
    p = alpha / alpha.sum(-1, keepdim=True)
    return -(p * p.log()).sum(-1)


def dirichlet_eig(alpha: torch.Tensor) -> torch.Tensor:
    """``(...)`` nats: the information one categorical draw gives about ``theta``.

    ``theta ~ Dirichlet(alpha)`` (``alpha`` ``(..., K)``, positive), in closed form (see the
    module).

    It is the mutual information ``I(theta; y)``: 0 for a row known exactly (huge
    counts), at most ``log K``.
    """
    alpha = alpha.to(DTYPE)
    a0 = alpha.sum(-1)
    expected_entropy = torch.special.digamma(a0 + 1) - (
        alpha / a0[..., None] * torch.special.digamma(alpha + 1)
    ).sum(-1)
    return (predictive_entropy(alpha) - expected_entropy).clamp_min(0.0)


_SCORES = {"eig": dirichlet_eig, "uncertainty": predictive_entropy}


@dataclass
class ExplorationState:
    """Where a run of :func:`explore` stands: everything needed to continue it.

    ``chosen`` ``(m,)`` pool indices in the order they were chosen; ``scores`` ``(m,)``
    their scores when chosen (NaN for ``random``); ``outcomes`` per end site ``(m,)`` the
    state indices the oracle returned; ``counts`` per site ``(rows, K)`` int64, the
    counts of the rows the pool can reach (see :func:`explore`); ``rng`` the generator's
    state; ``settings`` the arguments the run was started with.
    """

    chosen: np.ndarray
    scores: np.ndarray
    outcomes: dict[str, np.ndarray]
    counts: dict[str, np.ndarray]
    rng: dict
    settings: dict

    def save(self, path) -> Path:
        """Write the state to ``path`` (atomically: a crash leaves the previous file)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        torch.save(
            {
                "chosen": torch.as_tensor(self.chosen),
                "scores": torch.as_tensor(self.scores),
                "outcomes": {k: torch.as_tensor(v) for k, v in self.outcomes.items()},
                "counts": {k: torch.as_tensor(v) for k, v in self.counts.items()},
                "rng": self.rng,
                "settings": self.settings,
            },
            tmp,
        )
        os.replace(tmp, path)
        return path

    @classmethod
    def load(cls, path) -> ExplorationState:
        """The state :meth:`save` wrote to ``path``.

        Nothing in the file is executed: it is read as tensors, numbers, strings and
        containers of them (``torch.load(weights_only=True)``), and a file holding
        anything else, or not laid out as :meth:`save` lays it out, is a ``ValueError``.
        """
        path = Path(path)
        try:
            raw = torch.load(path, weights_only=True)
            return cls(
                chosen=raw["chosen"].numpy(),
                scores=raw["scores"].numpy(),
                outcomes={str(k): v.numpy() for k, v in raw["outcomes"].items()},
                counts={str(k): v.numpy() for k, v in raw["counts"].items()},
                rng=dict(raw["rng"]),
                settings=dict(raw["settings"]),
            )
        except FileNotFoundError:
            raise
        except Exception as exc:  # torch and pickle raise several types for a foreign file
            raise ValueError(
                f"checkpoint {str(path)!r} is not a state saved by explore ({type(exc).__name__}: "
                f"{exc}); remove it or pass another checkpoint"
            ) from exc


@dataclass(frozen=True)
class ExplorationResult:
    """What :func:`explore` returns.

    ``chosen`` ``(m,)`` pool indices in order of choice; ``scores`` ``(m,)`` their scores
    when chosen (NaN for ``random``); ``rows`` the chosen training rows (the pool's
    initial sites and action with the oracle's end sites, encoded: :func:`inference.fit`
    reads them); ``state`` the state to resume from; :attr:`params` the tables from the
    closed-form counts.
    """

    chosen: np.ndarray
    scores: np.ndarray
    rows: Evidence
    state: ExplorationState
    _tables: dict = field(repr=False, compare=False)
    _pseudo_count: float = field(repr=False, compare=False)
    _net: EffectNetwork = field(repr=False, compare=False)

    @cached_property
    def params(self) -> NetworkParams:
        """The tables from the closed-form counts, equal to ``fit(net, rows, pseudo_count=...)``.

        Built on first access (a table over every parent configuration can be large, and a caller
        that refits on prefixes of ``rows`` never reads them).
        """
        alpha = self._pseudo_count
        return NetworkParams({s: t.table(alpha) for s, t in self._tables.items()}, alpha, self._net)


def explore(
    net: EffectNetwork,
    pool: Mapping[str, object],
    oracle: Callable[[np.ndarray], Mapping[str, object]],
    budget: int,
    *,
    batch_size: int = 1,
    strategy: str = "eig",
    pseudo_count: float = 0.01,
    prior_strength: float = 0.0,
    sites: tuple[str, ...] | None = None,
    seed: int = 0,
    checkpoint: str | os.PathLike | None = None,
    progress: bool = False,
) -> ExplorationResult:
    """Choose ``budget`` candidates of ``pool`` batch by batch, play them and learn from them.

    The candidates are played with ``oracle`` and the tables learnt from their outcomes in closed
    form.

    Parameters
    ----------
    net
        A network whose sites are all tables (discrete children of discrete parents) and
        whose end sites' parents are initial sites and the action.
    pool
        The candidates, ``n`` rows of every initial site and the action, as labels (the
        row format of :func:`inference.fit`) or encoded :class:`Evidence`. A pair may be
        listed several times (then it can be played that many times).
    oracle
        ``oracle(index)`` plays the candidates ``pool[index]`` (``index`` ``(b,)`` int)
        and returns their end states: a mapping from every end site to ``b`` labels (or
        encoded Evidence).
    budget
        Candidates to choose in all, ``1..n``; each is chosen at most once.
    batch_size
        Candidates chosen before the oracle plays them (the last batch may be smaller).
    strategy
        One of ``STRATEGIES`` (see the module).
    pseudo_count
        The Dirichlet prior of every row and the fit's pseudo-count policy (> 0 unless
        ``strategy`` is ``"random"``).
    prior_strength
        Weight ``s >= 0`` of the prior shared by an initial state's rows in the scores.
    sites
        End sites whose parameters the scores are about (default every end site).
    seed
        Seeds the generator that breaks ties and draws the ``random`` choices.
    checkpoint
        A file: the state is saved there after every batch, and a run that finds it
        (started with the same arguments) continues from it.
    progress
        A tqdm bar over the candidates chosen.

    Returns
    -------
    ExplorationResult
        The candidates chosen, in order, their scores, the training rows they gave and the
        parameters fitted to them.
    """
    _check_network(net)
    check_settings(pseudo_count=pseudo_count, prior_strength=prior_strength)
    if strategy not in STRATEGIES:
        raise ValueError(f"strategy must be one of {STRATEGIES}, got {strategy!r}")
    if strategy != "random" and pseudo_count == 0:
        raise ValueError(
            f"pseudo_count must be > 0 for strategy={strategy!r}: it is the Dirichlet prior "
            "the scores are computed under (0 is improper for an unplayed row)"
        )
    ends = [s.name for s in net.sites if s.role == "end"]
    sites = tuple(ends) if sites is None else tuple(sites)
    bad = [s for s in sites if s not in ends]
    if bad or not sites:
        raise ValueError(f"sites must be a non-empty subset of the end sites {ends}, got {sites}")
    enc = _encode_pool(net, pool)
    n = enc.n_rows
    for name, value in (("budget", budget), ("batch_size", batch_size), ("seed", seed)):
        if not isinstance(value, int) or isinstance(value, bool) or value < (name != "seed"):
            raise ValueError(f"{name} must be an int >= {int(name != 'seed')}, got {value!r}")
    if budget > n:
        raise ValueError(f"budget={budget} exceeds the pool's {n} candidates")

    settings = {
        "n_pool": n,
        "batch_size": batch_size,
        "strategy": strategy,
        "pseudo_count": float(pseudo_count),
        "prior_strength": float(prior_strength),
        "sites": list(sites),
        "seed": seed,
    }
    tables = {s.name: _Rows(net, s.name, enc) for s in net.sites}
    path = None if checkpoint is None else Path(checkpoint)
    rng = np.random.default_rng(seed)
    if path is not None and path.exists():
        state = ExplorationState.load(path)
        if state.settings != settings:
            raise ValueError(
                f"checkpoint {str(path)!r} belongs to a run with settings {state.settings}, "
                f"not {settings}; remove it or pass another checkpoint"
            )
        rng.bit_generator.state = state.rng
    else:
        state = ExplorationState(
            chosen=np.zeros(0, np.int64),
            scores=np.zeros(0),
            outcomes={s: np.zeros(0, np.int64) for s in ends},
            counts={s: t.empty_counts() for s, t in tables.items()},
            rng=rng.bit_generator.state,
            settings=settings,
        )
    if len(state.chosen) > budget:
        raise ValueError(
            f"the checkpoint has already chosen {len(state.chosen)} candidates, more than "
            f"budget={budget}"
        )
    for s, t in tables.items():
        t.counts = state.counts[s].copy()
    scorer = None
    if strategy != "random":
        scorer = _Scorer(
            {s: tables[s] for s in sites}, _SCORES[strategy], pseudo_count, prior_strength
        )
    available = np.ones(n, dtype=bool)
    available[state.chosen] = False
    chosen, scores = list(state.chosen), list(state.scores)
    outcomes = {s: list(v) for s, v in state.outcomes.items()}

    def current() -> ExplorationState:
        return ExplorationState(
            chosen=np.asarray(chosen, np.int64),
            scores=np.asarray(scores, np.float64),
            outcomes={s: np.asarray(v, np.int64) for s, v in outcomes.items()},
            counts={s: t.counts.copy() for s, t in tables.items()},
            rng=rng.bit_generator.state,
            settings=settings,
        )

    bar = tqdm(
        total=budget, initial=len(chosen), desc=f"explore ({strategy})", disable=not progress
    )
    while len(chosen) < budget:
        k = min(batch_size, budget - len(chosen))
        if scorer is None:
            batch = rng.choice(np.flatnonzero(available), size=k, replace=False)
            gains = np.full(k, np.nan)
            available[batch] = False
        else:
            batch, gains = scorer.pick(k, available, rng)
        played = net.encode(oracle(np.asarray(batch)))
        missing = [s for s in ends if s not in played]
        if missing or played.n_rows != k:
            raise ValueError(
                f"the oracle must return {k} rows of every end site {ends}; got "
                f"{played.n_rows} rows of {sorted(played)}"
            )
        for s, t in tables.items():  # initial sites and the action: the pool's values
            value = played[s].numpy() if s in ends else t.pool_value[batch]
            t.add(batch, value)
        for s in ends:
            outcomes[s] += played[s].tolist()
        chosen += list(map(int, batch))
        scores += list(map(float, gains))
        if scorer is not None:
            scorer.refresh(batch)
        if path is not None:  # the state is built (its counts copied) only to be saved
            current().save(path)
        bar.update(k)
    bar.close()
    state = current()

    index = torch.as_tensor(state.chosen)
    rows = enc.rows(index) | net.encode_indices(
        {s: torch.as_tensor(v) for s, v in state.outcomes.items()}
    )
    return ExplorationResult(state.chosen, state.scores, rows, state, tables, pseudo_count, net)


def with_pool_prior(
    net: EffectNetwork, params: NetworkParams, pool: Mapping[str, object]
) -> NetworkParams:
    """``params`` with the tables of the initial sites and the action refitted on ``pool``.

    Every candidate is counted once, with ``params``' pseudo-count; the end sites' tables are kept.

    Tables fitted on the rows :func:`explore` chose (or on any designed experiment) learn
    the chooser's frequencies as ``p(action)`` and ``p(initial state)``: a design that
    played one action ten times more often than another makes
    :func:`inference.infer_action` prefer it ten to one where both cause the effect
    alike. The pool says which (initial state, action) pairs exist without playing any, so its frequencies are
    the design-free prior. Works on ``params`` of any fit (:func:`inference.fit`,
    :func:`inference.fit_pooled`, ``explore``'s own) whose initial and action sites are
    tables.
    """
    for spec in net.sites:
        cpd = net.cpd(spec.name)
        if spec.role in ("initial", "action") and not isinstance(cpd, TableCPD):
            raise ValueError(
                f"with_pool_prior refits tables; site {spec.name!r} is a {cpd.name} CPD"
            )
    check_params(net, params)
    enc = _encode_pool(net, pool)
    cpds = dict(params.cpds)
    every = np.arange(enc.n_rows)
    for spec in net.sites:
        if spec.role in ("initial", "action"):
            t = _Rows(net, spec.name, enc)
            t.add(every, t.pool_value)
            cpds[spec.name] = t.table(params.pseudo_count)
    return NetworkParams(cpds, params.pseudo_count, net)


# ------------------------------------------------------------------------------ internals
class _Rows:
    """One table site's rows that the pool can reach, and their counts.

    ``row[i]`` is candidate ``i``'s row among ``parents`` (the distinct flat parent
    configurations of the pool); ``counts`` ``(rows, K)`` int64. For an initial site the
    candidate's own value is known (``pool_value``); an end site's comes from the oracle.
    """

    def __init__(self, net: EffectNetwork, site: str, enc: Evidence):
        cpd = net.cpd(site)
        self.site, self.card, self.size = site, cpd.card, cpd.size
        flat = torch.zeros(enc.n_rows, dtype=torch.long)
        for s, k in zip(cpd.parents, cpd.card, strict=True):
            flat = flat * k + enc[s]
        self.parents, self.row = np.unique(flat.numpy(), return_inverse=True)
        self.row = self.row.reshape(-1)
        self.pool_value = enc[site].numpy() if site in enc else None
        # rows sharing every parent but the action: the groups of the shared prior
        group = torch.zeros(enc.n_rows, dtype=torch.long)
        for s, k in zip(cpd.parents, cpd.card, strict=True):
            if s != ACTION:
                group = group * k + enc[s]
        first = np.unique(self.row, return_index=True)[1]
        _, self.group = np.unique(group.numpy()[first], return_inverse=True)
        self.group = self.group.reshape(-1)
        self.counts = self.empty_counts()

    def empty_counts(self) -> np.ndarray:
        return np.zeros((len(self.parents), self.size), dtype=np.int64)

    def add(self, candidates: np.ndarray, value: np.ndarray) -> None:
        np.add.at(self.counts, (self.row[candidates], value), 1)

    def table(self, alpha: float):
        full = torch.zeros(math.prod(self.card), self.size, dtype=torch.long)
        full[torch.as_tensor(self.parents)] = torch.as_tensor(self.counts)
        return normalised(full.reshape(*self.card, self.size), alpha)


class _Scorer:
    """Per-row scores of the end sites of interest, and the greedy batch choice."""

    def __init__(self, tables: dict[str, _Rows], score, alpha: float, strength: float):
        self.tables, self.score, self.alpha, self.strength = tables, score, alpha, strength
        # each row's candidates, ascending: ``order[start[r]:start[r + 1]]``
        self.members = {}
        for s, t in tables.items():
            order = np.argsort(t.row, kind="stable")
            start = np.searchsorted(t.row[order], np.arange(len(t.parents) + 1))
            self.members[s] = (order, start)
        self.pooled: dict[str, np.ndarray] = {}  # per site, the groups' counts (see _prior)
        self.gain = {s: self._row_scores(t, np.arange(len(t.parents))) for s, t in tables.items()}

    def _prior(self, t: _Rows, rows: np.ndarray) -> torch.Tensor:
        """``(len(rows), K)``: the Dirichlet prior of ``rows`` (pseudo-count and shared part).

        The groups' pooled counts change only when a batch is played: they are summed once
        per batch (:meth:`refresh` forgets them), not once per row scored.
        """
        prior = torch.full((len(rows), t.size), self.alpha, dtype=DTYPE)
        if self.strength:
            if t.site not in self.pooled:
                pooled = np.zeros((t.group.max() + 1, t.size), dtype=np.int64)
                np.add.at(pooled, t.group, t.counts)
                self.pooled[t.site] = pooled
            m = normalised(torch.as_tensor(self.pooled[t.site][t.group[rows]]), self.alpha).probs
            prior = prior + self.strength * m
        return prior

    def _row_scores(self, t: _Rows, rows: np.ndarray, extra=None) -> torch.Tensor:
        alpha = self._prior(t, rows) + torch.as_tensor(t.counts[rows], dtype=DTYPE)
        return self.score(alpha if extra is None else alpha + extra)

    def candidate_scores(self) -> torch.Tensor:
        return sum(self.gain[s][torch.as_tensor(t.row)] for s, t in self.tables.items())

    def pick(self, k: int, available: np.ndarray, rng) -> tuple[np.ndarray, np.ndarray]:
        """``k`` candidates by greedy choice with expected counts (marks them unavailable)."""
        pending: dict[tuple[str, int], torch.Tensor] = {}  # expected counts of pending plays
        current: dict[tuple[str, int], float] = {}  # row scores with those counts
        batch, gains = [], []
        score = self.candidate_scores().numpy().copy()
        score[~available] = -np.inf
        for _ in range(k):
            best = score.max()
            if not np.isfinite(best):
                raise ValueError("no candidate left in the pool")
            ties = np.flatnonzero(score >= best - TIE * max(1.0, abs(best)))
            pick = int(ties[rng.integers(len(ties))]) if len(ties) > 1 else int(ties[0])
            batch.append(pick)
            gains.append(float(best))
            available[pick] = False
            score[pick] = -np.inf
            for s, t in self.tables.items():
                r = int(t.row[pick])
                rows = np.array([r])
                alpha = self._prior(t, rows) + torch.as_tensor(t.counts[rows], dtype=DTYPE)
                extra = pending.get((s, r), torch.zeros(1, t.size, dtype=DTYPE))
                a = alpha + extra
                pending[s, r] = extra + a / a.sum(-1, keepdim=True)  # this play's expected count
                new = float(self.score(alpha + pending[s, r])[0])
                delta = new - current.get((s, r), float(self.gain[s][r]))
                current[s, r] = new
                order, start = self.members[s]
                same = order[start[r] : start[r + 1]]  # the candidates of row r
                score[same[available[same]]] += delta
        return np.asarray(batch, np.int64), np.asarray(gains)

    def refresh(self, batch: np.ndarray) -> None:
        """Recompute the scores of the rows the played ``batch`` changed.

        With the shared prior: every row of their groups.
        """
        self.pooled.clear()  # the played batch changed the counts
        for s, t in self.tables.items():
            rows = np.unique(t.row[batch])
            if self.strength:
                rows = np.flatnonzero(np.isin(t.group, np.unique(t.group[rows])))
            self.gain[s][torch.as_tensor(rows)] = self._row_scores(t, rows)


def _check_network(net: EffectNetwork) -> None:
    """Refuse networks :func:`explore` cannot learn.

    Non-table sites, pinned tables, end sites with end parents.
    """
    for spec in net.sites:
        cpd = net.cpd(spec.name)
        if not isinstance(cpd, TableCPD) or cpd.pinned is not None:
            raise ValueError(
                f"explore learns tables only; site {spec.name!r} is a {cpd.name} CPD"
                + (" (an action parameter's cluster)" if spec.role == "cluster" else "")
                + ". Use a network whose sites are all discrete with discrete parents"
            )
        if spec.role == "end":
            late = [p for p in cpd.parents if net.site(p).role == "end"]
            if late:
                raise ValueError(
                    f"site {spec.name!r} has end sites {late} as parents: a candidate does "
                    "not fix its table row before it is played. explore needs every end "
                    "site's parents among the initial sites and the action"
                )


def _encode_pool(net: EffectNetwork, pool: Mapping[str, object]) -> Evidence:
    enc = net.encode(pool)
    need = [s.name for s in net.sites if s.role in ("initial", "action")]
    missing = [s for s in need if s not in enc]
    extra = [s for s in enc if s not in need]
    if missing or extra:
        raise ValueError(
            f"pool must give exactly the initial sites and the action {need}; missing "
            f"{missing}, extra {extra}"
        )
    if enc.n_rows == 0:
        raise ValueError("pool is empty: give at least one candidate")
    return enc
