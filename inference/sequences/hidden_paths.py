"""Forward-backward and Viterbi over each step's hidden configurations only.

The step tables of :mod:`inference.sequences.hidden_steps` are ragged: step ``t`` of
demonstration ``i`` pairs the ``m_t`` configurations of time ``t`` with the ``m_{t+1}``
of time ``t + 1``. The sums run over those pairs, flat over the batch, one time at a
time (a time's steps of every demonstration at once), in log space: a message into a
configuration is the log-sum (or the maximum) over the pairs that end in it::

    alpha_{t+1}[c'] = logsumexp over pairs (c, c') of step t:  alpha_t[c] + log sum_a T[c, a, c']
    beta_t[c]       = logsumexp over pairs (c, c') of step t:  beta_{t+1}[c'] + log sum_a T[c, a, c']
    delta_{t+1}[c'] = max over pairs (c, c') of step t:        delta_t[c] + max_a T[c, a, c']

A fully observed demonstration has one configuration per time and one pair per step, so
its posterior over each step's action is the step's own ``p(a | s_t, s_{t+1})`` and its
Viterbi sequence the per-step argmax.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from effect_networks.inference.sequences.hidden_steps import (
    HiddenConfigurations,
    StepPairs,
    StepTables,
)
from effect_networks.models.declaration import DTYPE


def segment_logsumexp(values: torch.Tensor, index: torch.Tensor, size: int) -> torch.Tensor:
    """``(size,)`` ``log sum exp`` of ``values`` ``(m,)`` grouped by ``index`` (``-inf`` if none)."""
    top = torch.full((size,), -torch.inf, dtype=values.dtype)
    top = top.scatter_reduce(0, index, values, "amax")
    safe = torch.where(torch.isfinite(top), top, 0.0)
    total = torch.zeros(size, dtype=values.dtype).index_add_(0, index, (values - safe[index]).exp())
    return total.log() + safe


def _logsumexp(values: torch.Tensor, top: torch.Tensor) -> torch.Tensor:
    """``log sum exp`` of ``values`` ``(P, A)`` along its last axis, its maxima ``top`` given."""
    safe = torch.where(torch.isfinite(top), top, 0.0)
    return (values - safe[:, None]).exp().sum(-1).log() + safe


def segment_argmax(values: torch.Tensor, index: torch.Tensor, size: int):
    """Per group of ``index``: the largest of ``values`` and the first position holding it."""
    top = torch.full((size,), -torch.inf, dtype=values.dtype)
    top = top.scatter_reduce(0, index, values, "amax")
    position = torch.arange(len(values))
    hit = torch.where(values == top[index], position, len(values))
    first = torch.full((size,), len(values), dtype=torch.long)
    first = first.scatter_reduce(0, index, hit, "amin")
    return top, first


@dataclass(frozen=True)
class PathAnswers:
    """What the passes answer.

    ``probs`` ``(n, T, A)``, ``best`` ``(n, T)``, ``path`` ``(n, T + 1)`` (state indices),
    ``config_probs`` ``(M,)`` each configuration's posterior, ``log_likelihood`` ``(n,)``,
    ``flags`` ``(n, T)``, ``initial`` ``{site: (n, T)}`` (continuous initial tails).
    """

    probs: torch.Tensor
    best: torch.Tensor
    path: torch.Tensor
    config_probs: torch.Tensor
    log_likelihood: torch.Tensor
    flags: torch.Tensor
    initial: dict[str, torch.Tensor]


def over_hidden_paths(
    configs: HiddenConfigurations,
    pairs: StepPairs,
    tables: StepTables,
    shape: tuple[int, int],
    below: float,
) -> PathAnswers:
    """Forward-backward, Viterbi and the plausibility flags over the pairs."""
    n, steps = shape
    a = tables.log_step.shape[-1]
    m = len(configs.state)
    demo_of = configs.owner // (steps + 1)  # (M,) each configuration's demonstration
    time_of = configs.owner % (steps + 1)
    at = step_order(pairs, steps)
    top, act = tables.log_step.max(-1)  # (P,): the action maximised (Viterbi)
    summed = _logsumexp(tables.log_step, top)  # (P,): the action summed out
    # the start given state 0: the initial distribution over time 0's configurations
    first = time_of == 0
    log_start = torch.full((m,), -torch.inf, dtype=DTYPE)
    log_start.index_put_((pairs.start[at[0]],), tables.log_start[at[0]])
    start = torch.where(first, log_start, -torch.inf)
    norm = segment_logsumexp(start[first], demo_of[first], n)
    alpha, beta, log_likelihood = forward_backward(
        configs, pairs, summed, torch.where(first, start - norm[demo_of], -torch.inf), shape, at
    )
    z = log_likelihood[demo_of]
    config_probs = (alpha + beta - z).exp()
    # each step's action: the pairs' joint with the action kept, summed per step
    pair_z = log_likelihood[pairs.step // steps]
    joint = alpha[pairs.start, None] + tables.log_step + beta[pairs.end, None] - pair_z[:, None]
    probs = torch.zeros(n * steps, a, dtype=DTYPE).index_add_(0, pairs.step, joint.exp())
    best, path = _viterbi(configs, pairs, top, act, at, alpha, (n, steps))
    flags, initial = _flags(configs, pairs, tables, at, (alpha, beta, summed), (n, steps), below)
    return PathAnswers(
        probs.reshape(n, steps, a),
        best,
        path,
        config_probs,
        log_likelihood,
        flags,
        initial,
    )


def step_order(pairs: StepPairs, steps: int) -> list[torch.Tensor]:
    """Per time ``t``, the positions of the pairs of every demonstration's step ``t``."""
    return [(pairs.step % steps == t).nonzero().squeeze(-1) for t in range(steps)]


def forward_backward(
    configs: HiddenConfigurations,
    pairs: StepPairs,
    summed: torch.Tensor,
    first: torch.Tensor,
    shape: tuple[int, int],
    at: list[torch.Tensor] | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The forward and backward messages over the pairs, and each demonstration's log-sum.

    ``summed`` ``(P,)``: each pair's log-factor (the action summed out); ``first`` ``(M,)``:
    the log-weight of each time-0 configuration (``-inf`` at the other times). Returns
    ``alpha``, ``beta`` ``(M,)`` and ``(n,)`` the log-sum over every path of the product of
    its start weight and its pairs' factors; ``alpha + beta`` at a configuration, less that
    sum, is its log-posterior.
    """
    n, steps = shape
    m = len(configs.state)
    demo_of = configs.owner // (steps + 1)
    time_of = configs.owner % (steps + 1)
    at = step_order(pairs, steps) if at is None else at
    alpha = torch.where(time_of == 0, first, -torch.inf)
    for t in range(steps):
        p = at[t]
        into = segment_logsumexp(alpha[pairs.start[p]] + summed[p], pairs.end[p], m)
        alpha = torch.where(time_of == t + 1, into, alpha)
    last = time_of == steps
    log_sum = segment_logsumexp(alpha[last], demo_of[last], n)
    beta = torch.where(last, 0.0, -torch.inf).to(DTYPE)
    for t in reversed(range(steps)):
        p = at[t]
        back = segment_logsumexp(beta[pairs.end[p]] + summed[p], pairs.start[p], m)
        beta = torch.where(time_of == t, back, beta)
    return alpha, beta, log_sum


def _viterbi(configs, pairs, top, act, at, alpha, shape):
    """The most probable (actions, states) path jointly: the action maximised in each step."""
    n, steps = shape
    m = len(configs.state)
    time_of = configs.owner % (steps + 1)
    delta = torch.where(time_of == 0, alpha, -torch.inf)
    back = torch.zeros(m, dtype=torch.long)  # the pair that reaches each configuration best
    for t in range(steps):
        p = at[t]
        value, pick = segment_argmax(delta[pairs.start[p]] + top[p], pairs.end[p], m)
        ends = time_of == t + 1
        delta = torch.where(ends, value, delta)
        back = torch.where(ends, p[pick.clamp(max=len(p) - 1)], back)
    last = (time_of == steps).nonzero().squeeze(-1)
    _, pick = segment_argmax(delta[last], configs.owner[last] // (steps + 1), n)
    config = last[pick]
    path = torch.empty(n, steps + 1, dtype=torch.long)
    best = torch.empty(n, steps, dtype=torch.long)
    path[:, -1] = configs.state[config]
    for t in reversed(range(steps)):
        pair = back[config]
        best[:, t] = act[pair]
        config = pairs.start[pair]
        path[:, t] = configs.state[config]
    return best, path


def _flags(configs, pairs, tables, at, passes, shape, below):
    """``(n, T)`` implausible steps and ``{site: (n, T)}`` continuous initial tails.

    The discrete ends given all before the step; the continuous ends' tail at the closest
    possible pair; the initial tails at the closest possible start.
    """
    n, steps = shape
    alpha, beta, summed = passes
    time_of = configs.owner % (steps + 1)
    demo_of = configs.owner // (steps + 1)
    if tables.log_discrete is tables.log_step:  # no continuous end: the same sums
        discrete = summed
    else:
        discrete = tables.log_discrete.logsumexp(-1)
    continuous = bool(tables.initial) or bool((tables.tail < 1).any())
    flags = torch.zeros(n * steps, dtype=torch.bool)
    initial = {site: torch.ones(n * steps, dtype=DTYPE) for site in tables.initial}
    for t in range(steps):
        now = time_of == t
        norm = segment_logsumexp(alpha[now], demo_of[now], n)
        p = at[t]
        filtered = alpha[pairs.start[p]] - norm[pairs.step[p] // steps]
        ends = segment_logsumexp(filtered + discrete[p], pairs.step[p], n * steps)[pairs.step[p]]
        flags[pairs.step[p]] = ends.exp() < below
        if continuous:
            possible = torch.isfinite(alpha[pairs.start[p]] + summed[p] + beta[pairs.end[p]])
            worst = torch.zeros(n * steps, dtype=DTYPE)
            tail = torch.where(possible, tables.tail[p], 0.0)
            worst = worst.scatter_reduce(0, pairs.step[p], tail, "amax")
            flags[pairs.step[p]] |= worst[pairs.step[p]] < below
            for site, value in tables.initial.items():
                most = torch.zeros(n * steps, dtype=DTYPE)
                most = most.scatter_reduce(
                    0, pairs.step[p], torch.where(possible, value[p], 0.0), "amax"
                )
                initial[site][pairs.step[p]] = most[pairs.step[p]]
    return flags.reshape(n, steps), {s: v.reshape(n, steps) for s, v in initial.items()}
