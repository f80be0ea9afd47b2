"""Chaining actions towards a goal exactly: finite-horizon dynamic programming.

With learned transition probabilities ``P(next state | state, action)`` the probability
of reaching the goal within ``H`` actions is maximised by finite-horizon dynamic
programming (every state, every action, exact sums): :func:`exact_plan`.
:func:`policy_value` evaluates a fixed policy under another transition model (e.g. a plan
made on one half of some simulations, scored on the other). The paper's round planner,
over sets of objects, is the experiments' :mod:`experiments.round_planner`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

#: The most backups run while the values still change: a longer horizon is answered only
#: where they stop changing before it (then every longer horizon has the same answer).
MAX_HORIZON = 10_000


@dataclass(frozen=True)
class ExactPlan:
    """The best probability of reaching the goal, and the action achieving it.

    ``value[h, s]``: the best probability of reaching the goal from state ``s`` with ``h`` actions
    left; ``policy[h, s]``: the action achieving it (``h >= 1``).
    """

    value: torch.Tensor  # (H + 1, S)
    policy: torch.Tensor  # (H + 1, S) long; row 0 unused (-1)
    converged: int | None = None  # rows from this one on are equal


def induction(
    backup: Callable[[torch.Tensor], torch.Tensor],
    goal: torch.Tensor,
    horizon: int,
    allowed: torch.Tensor | None = None,
    dtype: torch.dtype = torch.float64,
) -> ExactPlan:
    """Finite-horizon dynamic programming with any backup, stopping where values stop changing.

    ``backup(v)`` returns ``q[s, a]``, the probability of reaching the goal by taking ``a``
    in ``s`` when ``v`` is the value one action later; ``goal`` ``(S,)`` bool is absorbing;
    ``allowed`` ``(S, A)`` bool excludes actions. The rows are kept up to the first whose
    values equal the row before (``converged``): every later row is that row again, since
    the backup of equal values is equal. A horizon over :data:`MAX_HORIZON` whose values
    still change at :data:`MAX_HORIZON` is refused.
    """
    s = goal.shape[0]
    zero = torch.zeros(s, dtype=dtype).masked_fill(goal, 1.0)
    values, policies = [zero], [torch.full((s,), -1, dtype=torch.long)]
    for h in range(1, horizon + 1):
        q = backup(values[-1])
        if allowed is not None:
            q = q.masked_fill(~allowed, -1.0)
        v, p = q.max(-1)
        v = v.masked_fill(goal, 1.0).clamp_min(0.0)
        converged = torch.equal(v, values[-1])
        values.append(v)
        policies.append(p)
        if converged and h < horizon:
            return ExactPlan(torch.stack(values), torch.stack(policies), h)
        if h >= MAX_HORIZON and h < horizon:
            raise ValueError(
                f"horizon {horizon}: the values still change after {MAX_HORIZON} actions "
                "(they approach their limit step by step, each backup costing as much as the "
                f"first); ask for a horizon of at most {MAX_HORIZON}"
            )
    return ExactPlan(torch.stack(values), torch.stack(policies))


def exact_plan(
    transition: torch.Tensor,
    goal: int | torch.Tensor,
    horizon: int,
    *,
    allowed: torch.Tensor | None = None,
) -> ExactPlan:
    """Finite-horizon dynamic programming on ``transition[s, a, s'] = P(s' | s, a)``.

    The goal (a state's index, or an ``(S,)`` bool mask of goal states) is absorbing and
    counts as reached; ``allowed`` ``(S, A)`` bool excludes actions (e.g. ones the model
    never saw from that state). A row of ``transition`` may sum to less than one: the
    rest is a next state outside the modelled ones, from which the goal is never reached.
    """
    goal = _check_transition(transition, goal)
    if horizon < 1:
        raise ValueError(f"horizon must be >= 1, got {horizon}")
    s = transition.shape[0]
    if not isinstance(goal, torch.Tensor):
        goal = torch.zeros(s, dtype=torch.bool).index_fill(0, torch.tensor([goal]), True)
    out = induction(lambda v: transition @ v, goal, horizon, allowed, transition.dtype)
    if out.converged is None:
        return out
    more = horizon - out.converged  # every later row equals the last one kept
    value = torch.cat([out.value, out.value[-1:].expand(more, s)])
    policy = torch.cat([out.policy, out.policy[-1:].expand(more, s)])
    return ExactPlan(value, policy, out.converged)


def unseen_along(
    step: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    unseen: Callable[[torch.Tensor], torch.Tensor],
    policy: torch.Tensor,
    start: torch.Tensor,
    goal: torch.Tensor,
    horizon: int,
) -> float:
    """The probability that following ``policy`` from ``start`` takes an unseen step.

    ``step(mass, actions)``: the next states' mass ``(S,)`` from ``mass`` ``(S,)`` with each
    state taking ``actions[s]``; ``unseen(actions)``: ``(S,)`` the probability that each
    state's step under its action rests on an unseen configuration. The mass that reaches
    the goal, or a state with no action, stops; each step's unseen share is weighed by
    the mass in its state (the share taken as independent of where the step lands).
    """
    mass = torch.where(goal, 0.0, start.to(torch.float64))
    total = 0.0
    rows = policy.shape[0] - 1
    for t in range(horizon):
        acts = policy[min(horizon - t, rows)]
        mass = torch.where(acts >= 0, mass, 0.0)
        if not float(mass.sum()) > 1e-15:  # nothing left to take a step
            break
        u = unseen(acts.clamp_min(0))
        total += float((mass * u).sum())
        mass = step(mass * (1 - u), acts.clamp_min(0))
        mass = torch.where(goal, 0.0, mass)
    return min(max(total, 0.0), 1.0)


def policy_value(
    transition: torch.Tensor, policy: torch.Tensor, goal: int | torch.Tensor, horizon: int
) -> torch.Tensor:
    """The probability that following ``policy`` reaches the goal.

    ``value[h, s]``: the probability that following ``policy`` from ``s`` reaches the goal within
    ``h`` actions, under ``transition[s, a, s'] = P(s' | s, a)``.

    ``policy`` is ``(H + 1, S)`` as in :class:`ExactPlan` (``H >= horizon``); a state whose
    entry is ``-1`` has no action and never reaches the goal. Use it to evaluate a plan made
    on one transition model under another (e.g. held-out simulations). ``goal``: a
    state's index or an ``(S,)`` bool mask, as in :func:`exact_plan`.
    """
    goal = _check_transition(transition, goal)
    s = transition.shape[0]
    if policy.dim() != 2 or policy.shape[0] < horizon + 1 or policy.shape[1] != s:
        raise ValueError(
            f"policy must have shape (>= {horizon + 1}, {s}), got {tuple(policy.shape)}"
        )
    value = torch.zeros(horizon + 1, s, dtype=transition.dtype)
    value[0, goal] = 1.0
    rows = torch.arange(s)
    for h in range(1, horizon + 1):
        act = policy[h]
        q = transition[rows, act.clamp_min(0)] @ value[h - 1]
        value[h] = torch.where(act >= 0, q, torch.zeros_like(q))
        value[h, goal] = 1.0
    return value


def _check_transition(transition: torch.Tensor, goal: int | torch.Tensor) -> int | torch.Tensor:
    """The goal as an index or an ``(S,)`` bool mask, checked against ``transition``."""
    if transition.dim() != 3 or transition.shape[0] != transition.shape[2]:
        raise ValueError(f"transition must have shape (S, A, S), got {tuple(transition.shape)}")
    s = transition.shape[0]
    if isinstance(goal, torch.Tensor) and goal.dtype == torch.bool:
        if goal.shape != (s,):
            raise ValueError(f"a goal mask must have shape ({s},), got {tuple(goal.shape)}")
        return goal
    if not 0 <= goal < s:
        raise ValueError(f"goal index {goal} outside 0..{s - 1}")
    return goal
