"""The hidden part of a demonstration's steps: its configurations and their step tables.

:func:`~inference.sequences.explanation.explain` reads a demonstration as a hidden Markov
model whose variable at time ``t`` is what time ``t`` does not show of the network's
state: the configurations of the state features hidden at ``t``, every observed feature
fixed to its observed value (or, over a listed state space, the listed states that agree
with what ``t`` shows). A fully observed time has one configuration; a time that hides
``h`` binary features has ``2^h``, whatever the number of features it shows::

    time t:   f0 f1 f2 f3 f4 ...        time t + 1:   f0 f1 f2 f3 f4 ...
              1  ?  0  1  ?                           1  1  ?  1  0
              -> 4 configurations                     -> 2 configurations

    step t's table: 4 x A x 2 entries, each read off the model at (start, action, end)

:func:`hidden_configurations` numbers every time's configurations (flat over the batch),
:func:`step_pairs` pairs each step's start configurations with its end ones, and
:func:`read_step_tables` reads each pair's ``log p(a) + log p(end, observations | start,
observations, a)`` off the traced model, exactly as the dense route does for a pair of
states (:mod:`inference.sequences.dense_explanation`), once per distinct (observation,
start, end). A state is named by its index in the network's state space (the product of
the state features' states, the last one fastest, or the listed states), so that paths
and posteriors read as the dense route's.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from effect_networks.inference.exact.enumeration import (
    enumerate_model,
    enumeration_size,
    row_chunks,
)
from effect_networks.inference.queries.implausibility import plausibility
from effect_networks.inference.sequences.demonstration import (
    Demonstrations,
    key_columns,
    key_evidence,
)
from effect_networks.inference.sequences.states import StateSpace
from effect_networks.models.declaration import ACTION, DTYPE, Discrete, EffectNetwork
from effect_networks.models.evidence import Evidence
from effect_networks.models.params import NetworkParams
from effect_networks.models.sites import end_site, initial_site

#: The most entries one step's table may hold: (configurations at its start) x actions x
#: (configurations at its end). Past it :func:`step_pairs` refuses, naming the step.
MAX_STEP_TABLE = 1 << 22
#: (start, end) pairs read off the traced model at once, times the actions.
ROW_CHUNK = 1 << 20


class ProductStates(Sequence):
    """Every combination of the state features' states, as label tuples, made on demand.

    The last feature varies fastest (:class:`~inference.sequences.states.StateSpace`'s
    order); item ``i`` is the state of index ``i``. Stands for ``states`` where the
    product is too large to list.
    """

    def __init__(self, features: Sequence[Discrete]):
        self.features = tuple(features)
        self._size = math.prod(f.cardinality for f in self.features)

    def __len__(self) -> int:
        return self._size

    def __getitem__(self, i):
        if isinstance(i, slice):
            return tuple(self[j] for j in range(*i.indices(len(self))))
        i = int(i)
        if i < 0:
            i += len(self)
        if not 0 <= i < len(self):
            raise IndexError(f"state index {i} outside 0..{len(self) - 1}")
        labels = []
        for f in reversed(self.features):
            i, digit = divmod(i, f.cardinality)
            labels.append(f.states[digit])
        return tuple(reversed(labels))

    def __eq__(self, other: object) -> bool:
        if isinstance(other, ProductStates):
            return self.features == other.features
        return NotImplemented

    def __hash__(self) -> int:
        return hash(self.features)

    def __repr__(self) -> str:
        return f"ProductStates({[f.name for f in self.features]}, {len(self)} states)"


@dataclass(frozen=True)
class StateCodes:
    """A state's index and its state features' digits, both ways.

    ``cards`` ``(F,)`` the state features' numbers of states; ``strides`` ``(F,)`` the index
    step of each (the product's mixed radix); ``listed`` ``(S, F)`` the digits of a listed
    space's states (``None`` over the product).
    """

    cards: torch.Tensor
    strides: torch.Tensor
    listed: torch.Tensor | None

    @staticmethod
    def of(features: Sequence[Discrete], space: StateSpace | None) -> StateCodes:
        """The codes of the product of ``features`` (``space`` ``None``) or of a listed space."""
        if space is None and math.prod(f.cardinality for f in features) >= 1 << 62:
            raise ValueError(
                f"the state of {len(features)} features has "
                f"{math.prod(f.cardinality for f in features):.4g} configurations, past the "
                "2**62 a state's index can number: name the states that occur (state_space=)"
            )
        cards = torch.tensor([f.cardinality for f in features], dtype=torch.long)
        after = torch.ones_like(cards)
        if len(cards) > 1:
            after[:-1] = cards.flip(0).cumprod(0).flip(0)[1:]
        return StateCodes(cards, after, None if space is None else space.index)

    @property
    def size(self) -> int:
        """The number of states."""
        return len(self.listed) if self.listed is not None else math.prod(self.cards.tolist())

    def digits(self, state: torch.Tensor) -> torch.Tensor:
        """``(m, F)`` the state features' indices of the states ``state`` ``(m,)``."""
        if self.listed is not None:
            return self.listed[state]
        return (state[:, None] // self.strides) % self.cards


@dataclass(frozen=True)
class HiddenConfigurations:
    """Every time's configurations, flat over the batch.

    Time ``t`` of demonstration ``i`` is ``p = i * (T + 1) + t``; its configurations are
    ``state[offset[p]:offset[p + 1]]`` (state indices, increasing), ``owner`` ``(M,)``
    gives each configuration's ``p``.
    """

    offset: torch.Tensor
    state: torch.Tensor
    owner: torch.Tensor

    @property
    def counts(self) -> torch.Tensor:
        """``(N,)`` the number of configurations of each time."""
        return self.offset[1:] - self.offset[:-1]


def configuration_counts(demo: Demonstrations, codes: StateCodes) -> torch.Tensor:
    """``(n, T + 1)`` the number of states each time of ``demo`` allows.

    Refuses (``ValueError``) a time whose configurations alone exceed :data:`MAX_STEP_TABLE`,
    naming the demonstration, the time and the number.
    """
    n, steps = demo.shape
    if codes.listed is not None:
        return demo.allowed.sum(-1)
    hidden = demo.shown < 0
    cards = torch.where(hidden, codes.cards, 1)  # (n, T + 1, F): 1 where shown
    log_counts = cards.to(DTYPE).log2().sum(-1)
    past = log_counts > math.log2(MAX_STEP_TABLE)
    if bool(past.any()):
        i, t = (int(x) for x in past.nonzero()[0])
        raise ValueError(
            f"demonstration {i} at time {t} hides {int(hidden[i, t].sum())} state features, "
            f"{2 ** float(log_counts[i, t]):.4g} configurations: more than MAX_STEP_TABLE = "
            f"{MAX_STEP_TABLE} entries a step; observe more of the state at that time or "
            "name the states that occur (state_space=)"
        )
    return cards.prod(-1) if cards.shape[-1] else torch.ones(n, steps + 1, dtype=torch.long)


def hidden_configurations(demo: Demonstrations, codes: StateCodes) -> HiddenConfigurations:
    """The states each time of ``demo`` allows: its hidden features enumerated.

    Refuses as :func:`configuration_counts` does.
    """
    n, steps = demo.shape
    counts = configuration_counts(demo, codes).reshape(-1)
    if codes.listed is not None:
        owner, state = demo.allowed.reshape(n * (steps + 1), -1).nonzero(as_tuple=True)
        return HiddenConfigurations(_offsets(counts), state, owner)
    shown = demo.shown.reshape(n * (steps + 1), -1)
    hidden = shown < 0
    cards = torch.where(hidden, codes.cards, 1)
    offset = _offsets(counts)
    owner = torch.repeat_interleave(torch.arange(len(counts)), counts)
    local = torch.arange(len(owner)) - offset[owner]
    inner = torch.ones_like(cards)  # each hidden feature's stride among its time's
    if cards.shape[-1] > 1:
        inner[:, :-1] = cards.flip(-1).cumprod(-1).flip(-1)[:, 1:]
    digits = torch.where(
        hidden[owner], (local[:, None] // inner[owner]) % codes.cards, shown[owner]
    )
    state = (digits * codes.strides).sum(-1)
    return HiddenConfigurations(offset, state, owner)


def unique_rows(rows: torch.Tensor, bounds: Sequence[int]) -> tuple[torch.Tensor, torch.Tensor]:
    """The distinct rows of ``rows`` ``(m, c)``, in order, and each row's index among them.

    Column ``j`` holds numbers in ``0 .. bounds[j] - 1``. One number per row where the bounds' product fits an int64 (a sort of ``m`` numbers),
    else :func:`torch.unique` over the rows.
    """
    if not len(rows):
        return rows, torch.zeros(0, dtype=torch.long)
    if math.prod(bounds) >= 1 << 62:
        return torch.unique(rows, dim=0, return_inverse=True)
    scale = torch.tensor([math.prod(bounds[j + 1 :]) for j in range(len(bounds))])
    distinct, where = torch.unique((rows * scale).sum(-1), return_inverse=True)
    first = torch.zeros(len(distinct), dtype=torch.long)
    first[where] = torch.arange(len(rows))
    return rows[first], where


def _offsets(counts: torch.Tensor) -> torch.Tensor:
    offset = torch.zeros(len(counts) + 1, dtype=torch.long)
    offset[1:] = counts.cumsum(0)
    return offset


@dataclass(frozen=True)
class StepPairs:
    """Every step's (start configuration, end configuration) pairs, flat over the batch.

    ``step`` ``(P,)``: the step ``g = i * T + t``; ``start``, ``end`` ``(P,)``: indices
    into :class:`HiddenConfigurations`' flat configurations, at time ``t`` and ``t + 1``.
    Ordered by step, then start, then end.
    """

    step: torch.Tensor
    start: torch.Tensor
    end: torch.Tensor


def step_pairs(configs: HiddenConfigurations, shape: tuple[int, int], actions: int) -> StepPairs:
    """Each step's start configurations times its end ones.

    Refuses (``ValueError``) a step whose table (start configurations x ``actions`` x end
    configurations) exceeds :data:`MAX_STEP_TABLE`, naming the demonstration, the step and
    the number.
    """
    n, steps = shape
    counts = configs.counts.reshape(n, steps + 1)
    before, after = counts[:, :-1].reshape(-1), counts[:, 1:].reshape(-1)
    size = before * after * actions
    if bool((size > MAX_STEP_TABLE).any()):
        g = int((size > MAX_STEP_TABLE).nonzero()[0])
        raise ValueError(
            f"demonstration {g // steps} step {g % steps}: {int(before[g])} x {actions} x "
            f"{int(after[g])} = {int(size[g])} entries of hidden configurations, more than "
            f"MAX_STEP_TABLE = {MAX_STEP_TABLE}; observe more of the state at its start or "
            "end, or name the states that occur (state_space=)"
        )
    per_step = before * after
    step = torch.repeat_interleave(torch.arange(n * steps), per_step)
    local = torch.arange(len(step)) - _offsets(per_step)[step]
    width = after[step]
    first = torch.arange(n)[:, None] * (steps + 1) + torch.arange(steps)  # p of each start
    p = first.reshape(-1)[step]
    start = configs.offset[p] + local // width
    end = configs.offset[p + 1] + local % width
    return StepPairs(step, start, end)


@dataclass(frozen=True)
class StepTables:
    """Per pair (:class:`StepPairs`), the step's entries.

    ``log_step`` ``(P, A)``: ``log p(a) + log p(end state and observations | start state and
    observations, a)``; ``log_discrete`` the same without the continuous end observations
    (the discrete plausibility's numerator; ``log_step`` itself where the network has no
    continuous end); ``log_start`` ``(P,)``: ``log p(start state, start observations)``
    under the initial distribution; ``tail`` ``(P,)`` and ``initial`` ``{site: (P,)}`` the
    plausibility tails (1 where not needed).
    """

    log_step: torch.Tensor
    log_discrete: torch.Tensor
    log_start: torch.Tensor
    tail: torch.Tensor
    initial: dict[str, torch.Tensor]


def read_step_tables(
    net: EffectNetwork,
    params: NetworkParams,
    codes: StateCodes,
    demo: Demonstrations,
    configs: HiddenConfigurations,
    pairs: StepPairs,
    *,
    tails: bool = True,
) -> StepTables:
    """Each pair's step entries, read off the traced model once per distinct row.

    A row is (the step's observation, start state, end state): the continuous values at
    both ends and the outcomes observed set the observation (:meth:`Demonstrations.step_keys`).
    Without ``tails`` the plausibility tails are not read (``tail`` 1, ``initial`` empty):
    what a fit needs is the entries alone.
    """
    a = len(net.actions)
    key, keys = demo.step_keys()
    step_key = torch.from_numpy(key.reshape(-1))[pairs.step]
    triples = torch.stack(
        [step_key, configs.state[pairs.start], configs.state[pairs.end]], 1
    )  # (P, 3)
    size = codes.size
    triples, where = unique_rows(triples, (max(1, len(keys)), size, size))
    u = len(triples)
    log_step = torch.full((u, a), -torch.inf, dtype=DTYPE)
    log_discrete = log_step.clone()
    log_start = torch.full((u,), -torch.inf, dtype=DTYPE)
    tail = torch.ones(u, dtype=DTYPE)
    initial: dict[str, torch.Tensor] = {}
    columns = key_columns(net, demo)
    observed = ~np.isnan(keys) if keys.size else np.zeros((len(keys), 0), dtype=bool)
    # one evidence pattern per set of observed outcomes
    _, pattern = np.unique(observed, axis=0, return_inverse=True)
    pattern = torch.from_numpy(pattern.reshape(-1))[triples[:, 0]]
    continuous = any(not x.discrete for x in net.sites if x.role in ("initial", "end"))
    chunk = max(1, ROW_CHUNK // a)
    for kind in torch.unique(pattern).tolist():
        rows_of = (pattern == kind).nonzero().squeeze(-1)
        for i in range(0, len(rows_of), chunk):
            rows = rows_of[i : i + chunk]
            ev = _pair_evidence(net, codes, keys, columns, triples[rows])
            step, discrete, start = _read_rows(net, params, triples[rows], ev, a, size)
            log_step[rows], log_discrete[rows], log_start[rows] = step, discrete, start
            if continuous and tails:
                told = plausibility(net, params, net.encode_indices(ev))
                tail[rows] = told.tail
                for site, value in told.initial.items():
                    initial.setdefault(site, torch.ones(u, dtype=DTYPE))[rows] = value
    # the model keeps a zero probability finite (its tables' logs are clamped): an action
    # the prior rules out is ruled out exactly
    impossible = params[ACTION].probs == 0
    log_step[:, impossible] = -torch.inf
    log_discrete[:, impossible] = -torch.inf
    step = log_step[where]
    continuous_ends = any(not x.discrete for x in net.sites if x.role == "end")
    return StepTables(
        step,
        log_discrete[where] if continuous_ends else step,  # without them: the same table
        log_start[where],
        tail[where],
        {site: value[where] for site, value in initial.items()},
    )


def _read_rows(net, params, triples: torch.Tensor, ev: dict[str, torch.Tensor], a: int, bound: int):
    """Step entries for rows ``triples`` ``(m, 3)`` (key, start, end) of evidence ``ev``.

    ``(m, A)`` the step's ``log p(a) + log p(end, observations | start, observations, a)``,
    ``(m, A)`` the same without the continuous ends, ``(m,)`` the start's ``log p(start,
    start observations)``. The action is enumerated with the other latent sites and kept
    (one row per pair, not per pair and action); the start's evidence is summed once per
    distinct (key, start). The ratio's per-site offsets cancel exactly
    (:func:`~inference.exact.enumeration.log_ratio`).
    """
    enc = net.encode_indices(ev)
    ends = [x for x in enc if x.startswith("end.")]
    starts, where = unique_rows(triples[:, :2], (int(triples[:, 0].max()) + 1, bound))
    one = torch.zeros(len(starts), dtype=torch.long)
    one[where] = torch.arange(len(triples))  # a row of each start (any: they read alike)
    start, start_offsets = _summed(net, params, enc.without(*ends).rows(one), None)
    start, start_offsets = start[where], {k: v[where] for k, v in start_offsets.items()}
    joint, offsets = _summed(net, params, enc, a)
    values = _ratio(joint, offsets, start, start_offsets)
    discrete = values
    continuous_ends = [x for x in ends if not net.site(x).discrete]
    if continuous_ends:
        joint, offsets = _summed(net, params, enc.without(*continuous_ends), a)
        discrete = _ratio(joint, offsets, start, start_offsets)
    return values, discrete, start[:, 0] + sum(start_offsets.values(), 0.0)


def _summed(net, params, enc: Evidence, a: int | None):
    """The evidence's ``log sum`` over its latent sites, and its offsets by name.

    ``(n, a)`` with the action kept (``a`` actions), ``(n, 1)`` where ``a`` is ``None``
    (every site summed); offsets ``{name: (n,)}``.
    """
    n = enc.n_rows
    out = torch.empty(n, a or 1, dtype=DTYPE)
    offsets: dict[str, torch.Tensor] = {}
    size = enumeration_size(net, enc, contracted=True)
    for rows in row_chunks(n, size):
        e = enumerate_model(net, params, enc.rows(rows))
        if a is not None:
            w = e.log_sum([ACTION]).movedim(e.dims[ACTION], -1)
            out[rows] = w.reshape(-1, a).expand(rows.stop - rows.start, a)
        else:
            out[rows, 0] = e.log_norm
        for name, value in e.offsets.items():
            offsets.setdefault(name, torch.zeros(n, dtype=DTYPE))[rows] = value
    return out, offsets


def _ratio(joint, offsets, start, start_offsets) -> torch.Tensor:
    """``log p(joint's evidence) - log p(start's evidence)``, offsets cancelled by name."""
    ratio = joint - start
    for name in offsets.keys() | start_offsets.keys():
        ratio = ratio + (offsets.get(name, 0.0) - start_offsets.get(name, 0.0))[:, None]
    return ratio


def _pair_evidence(net, codes: StateCodes, keys, columns, triples) -> dict[str, torch.Tensor]:
    """Evidence by site (indices, numbers) for rows ``(key, start state, end state)``.

    The start and end states and the key's observations, its unobserved outcomes left out
    (the rows share one pattern).
    """
    k = triples[:, 0]
    start, end = codes.digits(triples[:, 1]), codes.digits(triples[:, 2])
    ev: dict[str, torch.Tensor] = {}
    state = [f for f in net.features if isinstance(f, Discrete) and f.initial]
    for j, f in enumerate(state):
        ev[initial_site(f.name)] = start[:, j]
        ev[end_site(f.name)] = end[:, j]
    return ev | key_evidence(net, keys, columns, k)
