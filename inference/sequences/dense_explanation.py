"""A demonstration read over the whole state space: :func:`explain_dense`.

:func:`~inference.sequences.explanation.explain`'s question answered the slow, obviously
correct way, kept beside it as its tests' and benchmark's twin: the hidden Markov model's
variable at every time ranges over *every* state of the network (its observed features
only mask it), so each step table is (states x actions x states), ``2^k`` squared for
``k`` binary state features however much a demonstration observes. The step tables are
read off the traced model once per distinct observation of a step; forward-backward and
Viterbi run over the dense tables in log space.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from effect_networks.inference.exact.enumeration import conditional_log_evidence, over_row_chunks
from effect_networks.inference.exact.paths import LogTables, log_matvec, max_matvec
from effect_networks.inference.queries.implausibility import (
    IMPLAUSIBLE_BELOW,
    check_threshold,
    plausibility,
)
from effect_networks.inference.sequences.demonstration import (
    Demonstrations,
    key_columns,
    key_evidence,
    with_action_prior,
)
from effect_networks.inference.sequences.explanation import Explanation, outside_flags
from effect_networks.inference.sequences.hidden_steps import MAX_STEP_TABLE
from effect_networks.inference.sequences.states import StateSpace
from effect_networks.models.declaration import ACTION, DTYPE, EffectNetwork
from effect_networks.models.evidence import Evidence
from effect_networks.models.params import NetworkParams, check_params
from effect_networks.models.sites import end_site, initial_site

#: Elements of the step tables held at once (distinct steps x states x actions x states).
TABLE_ELEMENTS = 1 << 24
#: Elements of the per-demonstration tensors one pass over the batch holds at once.
CHUNK_ELEMENTS = 1 << 22


def explain_dense(
    net: EffectNetwork,
    params: NetworkParams,
    states: Sequence[Mapping[str, object]] | Mapping[str, object],
    *,
    prior: Mapping[str, float] | Sequence[float] | None = None,
    state_space: Sequence | None = None,
    implausible_below: float = IMPLAUSIBLE_BELOW,
) -> Explanation:
    """:func:`~inference.sequences.explanation.explain`'s question over the whole state space.

    Per-step posterior, most probable sequence, log-likelihood: the same arguments and the
    same answer as :func:`~inference.sequences.explanation.explain` (its docstring says
    what each one means), with the hidden variable at every time ranging over every state
    of ``state_space``; refused where one step's table (states x actions x states) would
    hold more than ``MAX_STEP_TABLE`` numbers. The tests' twin of the structured route.
    """
    check_params(net, params)
    below = check_threshold(implausible_below)
    space = StateSpace.of(net, state_space, stateless=True)
    demo = Demonstrations.read(net, space, states)
    params = with_action_prior(net, params, prior)
    a = len(net.actions)
    if len(space) ** 2 * a > MAX_STEP_TABLE:
        raise ValueError(
            f"the network's state has {len(space)} configurations and {a} actions: a step "
            f"table of {len(space) ** 2 * a} entries exceeds {MAX_STEP_TABLE}; explain needs "
            "fewer discrete state features or states"
        )
    n, steps = demo.shape
    if n == 0:
        return _no_demonstrations(net, space, steps)
    per_key = len(space) ** 2 * a
    key, keys = demo.step_keys()
    if len(keys) * per_key <= TABLE_ELEMENTS:
        parts = [(demo, key, keys)]
    else:  # many distinct steps (continuous values): the tables part by part
        size = max(1, TABLE_ELEMENTS // (steps * per_key))
        parts = [(d, *d.step_keys()) for d in demo.split(size)]
    answers = [
        _over_paths(part, key, _step_tables(net, params, space, part, key, keys), below)
        for part, key, keys in parts
    ]
    fields = zip(*[x[:6] for x in answers], strict=True)
    probs, best, path, state_probs, log_likelihood, flags = (torch.cat(x, 0) for x in fields)
    initial = {site: torch.cat([x[6][site] for x in answers], 0) for site in answers[0][6]}
    implausible = flags | outside_flags(initial, (n, steps), below)
    names = tuple(map(tuple, np.array(net.actions, dtype=object)[best.numpy()].tolist()))
    return Explanation(
        probs,
        best,
        names,
        path,
        state_probs,
        log_likelihood,
        implausible,
        net.actions,
        tuple(f.name for f in space.features),
        space.states,
    )


@dataclass(frozen=True)
class _StepTables:
    """Per distinct step observation ``k``, the step's tables.

    ``log_step`` ``(K, S, A, S)`` the step's ``log p(a) + log p(end state and observations | start
    state and observations, a)``; ``log_discrete`` the same without the continuous end observations
    (the discrete plausibility's numerator); ``log_start`` ``(K, S)`` the initial distribution's
    ``log p(start state, start observations)``; ``tail`` ``(K, S, S)`` and ``initial`` ``{site: (K,
    S)}`` the plausibility tails; ``-inf`` / 1 where never needed.
    """

    log_step: torch.Tensor
    log_discrete: torch.Tensor
    log_start: torch.Tensor
    tail: torch.Tensor
    initial: dict[str, torch.Tensor]


def _log_evidence(net: EffectNetwork, params: NetworkParams, enc: Evidence) -> torch.Tensor:
    return over_row_chunks(net, params, enc, (), lambda e, *_: e.log_evidence, contracted=True)


def _step_tables(net, params, space, demo, key, keys) -> _StepTables:
    """The step tables, from the traced model.

    For the (start, end) state pairs some step of each distinct observation allows.
    """
    s, a, k = len(space), len(net.actions), len(keys)
    # the (start, end) pairs some step of each distinct observation allows, summed over
    # the steps in chunks (a batch's pairs at once would be (n, T, S, S))
    before = demo.allowed[:, :-1].reshape(-1, s)
    after = demo.allowed[:, 1:].reshape(-1, s)
    flat = torch.from_numpy(key.reshape(-1))
    need = torch.zeros(k, s * s, dtype=DTYPE)
    step = max(1, CHUNK_ELEMENTS // (s * s))
    for i in range(0, len(flat), step):
        pairs = before[i : i + step, :, None] & after[i : i + step, None, :]
        need.index_add_(0, flat[i : i + step], pairs.reshape(-1, s * s).to(DTYPE))
    triples = (need > 0).reshape(k, s, s).nonzero()  # (k, start, end) rows
    log_step = torch.full((k, s, a, s), -torch.inf, dtype=DTYPE)
    log_discrete = log_step.clone()
    log_start = torch.full((k, s), -torch.inf, dtype=DTYPE)
    tail = torch.ones(k, s, s, dtype=DTYPE)
    initial: dict[str, torch.Tensor] = {}
    columns = key_columns(net, demo)
    observed = ~np.isnan(keys) if keys.size else np.zeros((k, 0), dtype=bool)
    # one evidence pattern per set of observed outcomes
    patterns = {}
    for row, (kk, _, _) in enumerate(triples.tolist()):
        patterns.setdefault(tuple(observed[kk]), []).append(row)
    digits = space.index.T
    for rows in patterns.values():
        t = triples[rows]
        ev = _pair_evidence(net, space, digits, keys, columns, t)
        n_rows = len(rows)
        with_action = {site: v.repeat_interleave(a, 0) for site, v in ev.items()}
        with_action[ACTION] = torch.arange(a).repeat(n_rows)
        enc = net.encode_indices(with_action)
        ends = [x for x in enc if x.startswith("end.")]
        given = enc.without(ACTION, *ends)
        starts, where = torch.unique(t[:, :2], dim=0, return_inverse=True)
        one = torch.zeros(len(starts), dtype=torch.long)
        one[where] = torch.arange(n_rows)  # a row of each start (any: they read alike)
        start_enc = given.rows(one * a)
        log_given_start = _log_evidence(net, params, start_enc)
        log_start[starts[:, 0], starts[:, 1]] = log_given_start
        log_given = log_given_start[where].repeat_interleave(a)
        log_joint = _log_evidence(net, params, enc)
        values = conditional_log_evidence(net, params, enc, given, log_joint, log_given)
        log_step[t[:, 0], t[:, 1], :, t[:, 2]] = values.reshape(n_rows, a)
        continuous_ends = [x for x in ends if not net.site(x).discrete]
        if continuous_ends:
            discrete = enc.without(*continuous_ends)
            log_joint = _log_evidence(net, params, discrete)
            values = conditional_log_evidence(net, params, discrete, given, log_joint, log_given)
        log_discrete[t[:, 0], t[:, 1], :, t[:, 2]] = values.reshape(n_rows, a)
        if any(not x.discrete for x in net.sites if x.role in ("initial", "end")):
            told = plausibility(net, params, net.encode_indices(ev))
            tail[t[:, 0], t[:, 1], t[:, 2]] = told.tail
            for site, value in told.initial.items():
                initial.setdefault(site, torch.ones(k, s, dtype=DTYPE))
                initial[site][t[:, 0], t[:, 1]] = value
    # the model keeps a zero probability finite (its tables' logs are clamped): an action
    # the prior rules out is ruled out exactly
    impossible = params[ACTION].probs == 0
    log_step[:, :, impossible] = -torch.inf
    log_discrete[:, :, impossible] = -torch.inf
    return _StepTables(log_step, log_discrete, log_start, tail, initial)


def _pair_evidence(net, space, digits, keys, columns, triples) -> dict[str, torch.Tensor]:
    """Evidence by site (indices, numbers) for rows ``(key, start state, end state)``.

    The start and end states and the key's observations, its unobserved outcomes left out (the rows
    share one pattern).
    """
    k, start, end = triples[:, 0], triples[:, 1], triples[:, 2]
    ev: dict[str, torch.Tensor] = {}
    for f, digit in zip(space.features, digits, strict=True):
        ev[initial_site(f.name)] = digit[start]
        ev[end_site(f.name)] = digit[end]
    return ev | key_evidence(net, keys, columns, k)


def _over_paths(demo: Demonstrations, key: np.ndarray, tables: _StepTables, below: float):
    """Forward-backward and Viterbi over a batch, in chunks of demonstrations."""
    n, steps = demo.shape
    k, s, a, _ = tables.log_step.shape
    summed = tables.log_step.logsumexp(2)  # (K, S, S): the action summed out
    top, act = tables.log_step.max(2)  # the action maximised (Viterbi)
    shared = _Shared(
        LogTables(summed),
        LogTables(summed.transpose(1, 2)),
        LogTables(tables.log_step.permute(0, 1, 3, 2).reshape(k, s * s, a)),
        LogTables(tables.log_discrete.logsumexp(2)),
        top,
        act,
    )
    size = max(1, CHUNK_ELEMENTS // (s * s * steps))
    parts = [
        _chunk(
            tables, shared, demo.allowed[i : i + size], torch.from_numpy(key[i : i + size]), below
        )
        for i in range(0, n, size)
    ]
    out = [torch.cat(x, 0) for x in zip(*[p[:6] for p in parts], strict=True)]
    initial = {site: torch.cat([p[6][site] for p in parts], 0) for site in parts[0][6]}
    return (*out, initial)


@dataclass(frozen=True)
class _Shared:
    """A batch's step tables in the forms the passes read.

    The action summed out (``forward``; ``backward`` transposed), pairs of states by action
    (``pairs`` ``(K, S * S, A)``), the discrete plausibility's with the action summed out
    (``discrete``), and the action maximised (``top``, ``act`` ``(K, S, S)``).
    """

    forward: LogTables
    backward: LogTables
    pairs: LogTables
    discrete: LogTables
    top: torch.Tensor
    act: torch.Tensor


def _chunk(tables: _StepTables, shared: _Shared, allowed, key, below: float):
    """One chunk of demonstrations: ``allowed`` ``(n, T + 1, S)``, ``key`` ``(n, T)``."""
    n, steps = key.shape
    s = allowed.shape[-1]
    mask = torch.where(allowed, 0.0, -torch.inf).to(DTYPE)  # (n, T + 1, S)
    start = tables.log_start[key[:, 0]] + mask[:, 0]
    alpha = [start - start.logsumexp(-1, keepdim=True)]  # the start given state 0
    for t in range(steps):
        forward = log_matvec(alpha[t], shared.forward, key[:, t], allowed[:, t + 1])
        alpha.append(forward + mask[:, t + 1])
    log_likelihood = alpha[-1].logsumexp(-1)
    beta = [torch.zeros_like(start)]  # beta[t] + mask[t]: the evidence after time t
    for t in reversed(range(steps)):
        beta.insert(
            0, log_matvec(beta[0] + mask[:, t + 1], shared.backward, key[:, t], allowed[:, t])
        )
    ahead = [b + m for b, m in zip(beta, mask.unbind(1), strict=True)]
    z = log_likelihood[:, None]
    state_probs = torch.stack([(x + y - z).exp() for x, y in zip(alpha, beta, strict=True)], 1)
    probs = []
    for t in range(steps):
        pair = (alpha[t][:, :, None] + ahead[t + 1][:, None, :]).reshape(n, s * s)
        probs.append((log_matvec(pair, shared.pairs, key[:, t], total=True) - z).exp())
    # Viterbi over (state, action) jointly: the action maximised inside each step
    delta, back = alpha[0], []
    for t in range(steps):
        delta, arg = max_matvec(delta, shared.top, key[:, t])
        delta = delta + mask[:, t + 1]
        back.append(arg)
    path = torch.empty(n, steps + 1, dtype=torch.long)
    best = torch.empty(n, steps, dtype=torch.long)
    path[:, -1] = delta.argmax(-1)
    for t in reversed(range(steps)):
        path[:, t] = back[t].gather(1, path[:, t + 1, None]).squeeze(1)
        best[:, t] = shared.act[key[:, t], path[:, t], path[:, t + 1]]
    # implausible: the discrete ends given all before the step; the continuous ends'
    # tail at the closest possible pair of states; the initial tails at the closest
    # possible start
    flags, initial = [], {}
    continuous = bool(tables.initial) or bool((tables.tail < 1).any())
    for t in range(steps):
        filtered = alpha[t] - alpha[t].logsumexp(-1, keepdim=True)
        ends = log_matvec(filtered, shared.discrete, key[:, t], allowed[:, t + 1])
        flag = (ends + mask[:, t + 1]).logsumexp(-1).exp() < below
        if continuous:
            possible = torch.isfinite(
                alpha[t][:, :, None] + shared.forward.log[key[:, t]] + ahead[t + 1][:, None, :]
            )
            tail = torch.where(possible, tables.tail[key[:, t]], 0.0).amax((1, 2))
            flag |= tail < below
            starts = possible.any(2)
            for site, value in tables.initial.items():
                at = torch.where(starts, value[key[:, t]], 0.0).amax(1)
                initial.setdefault(site, []).append(at)
        flags.append(flag)
    initial = {site: torch.stack(v, 1) for site, v in initial.items()}
    probs = torch.stack(probs, 1)
    return probs, best, path, state_probs, log_likelihood, torch.stack(flags, 1), initial


def _no_demonstrations(net: EffectNetwork, space: StateSpace, steps: int) -> Explanation:
    """The answer to a batch of no demonstrations: every field with its shape, ``n = 0``."""
    a, s = len(net.actions), len(space)
    return Explanation(
        torch.zeros(0, steps, a, dtype=DTYPE),
        torch.zeros(0, steps, dtype=torch.long),
        (),
        torch.zeros(0, steps + 1, dtype=torch.long),
        torch.zeros(0, steps + 1, s, dtype=DTYPE),
        torch.zeros(0, dtype=DTYPE),
        torch.zeros(0, steps, dtype=torch.bool),
        net.actions,
        tuple(f.name for f in space.features),
        space.states,
    )
