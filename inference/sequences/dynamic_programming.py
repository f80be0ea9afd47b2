"""Chaining actions towards a goal exactly: finite-horizon dynamic programming.

With learned transition probabilities ``P(next state | state, action)`` the probability
of reaching the goal within ``H`` actions is maximised by finite-horizon dynamic
programming (every state, every action, exact sums): :func:`exact_plan`.
:func:`policy_value` evaluates a fixed policy under another transition model (e.g. a plan
made on one half of some simulations, scored on the other). The paper's round planner,
over sets of objects, is the experiments' :mod:`experiments.round_planner`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class ExactPlan:
    """The best probability of reaching the goal, and the action achieving it.

    ``value[h, s]``: the best probability of reaching the goal from state ``s`` with ``h`` actions
    left; ``policy[h, s]``: the action achieving it (``h >= 1``).
    """

    value: torch.Tensor  # (H + 1, S)
    policy: torch.Tensor  # (H + 1, S) long; row 0 unused (-1)


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
    value = torch.zeros(horizon + 1, s, dtype=transition.dtype)
    policy = torch.full((horizon + 1, s), -1, dtype=torch.long)
    value[0, goal] = 1.0
    for h in range(1, horizon + 1):
        q = transition @ value[h - 1]  # (S, A)
        if allowed is not None:
            q = q.masked_fill(~allowed, -1.0)
        value[h], policy[h] = q.max(-1)
        value[h, goal] = 1.0
        value[h] = value[h].clamp_min(0.0)
    return ExactPlan(value, policy)


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
