"""Chaining actions towards a goal: the paper's round planner and an exact planner.

States are sets of objects still present (``frozenset``); the goal is a state to reach by
removing objects. Nothing here knows what an object or an action is: the caller passes
functions that propose actions and play them.

* :func:`paper_planner` (paper §IV-C): in a round, take every action proposed to reach
  the goal from the round's state; if none, add objects back to the goal (intermediate
  goals, fewest added first) until some action is proposed. Play every action and
  classify the outcome: success (the goal), too many removed (an object of the goal is
  gone), nothing hit (the state is unchanged), or an intermediate state (more objects
  than the goal, all goal objects kept), which becomes the start of a new round,
  evaluated once however often it is reached. A round's success rate is its success
  share plus, for each intermediate state, its share times that state's success rate:
  a linear system, solved exactly (rounds can lead back to one another).
* :func:`exact_plan` -- beyond the paper: with learned transition probabilities
  ``P(next state | state, action)`` the probability of reaching the goal within ``H``
  actions is maximised by finite-horizon dynamic programming (every state, every
  action, exact sums). :func:`policy_value` evaluates a fixed policy under another
  transition model (e.g. a plan made on one half of some simulations, scored on the other).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass, field

import torch

State = frozenset
Action = Hashable

SUCCESS, TOO_MANY, NO_HIT, INTERMEDIATE = "success", "too_many", "no_hit", "intermediate"


def classify(start: State, goal: State, outcome: State) -> str:
    """Which of the paper's four cases an outcome is."""
    if outcome == goal:
        return SUCCESS
    if not goal <= outcome:
        return TOO_MANY
    if outcome == start:
        return NO_HIT
    return INTERMEDIATE


@dataclass
class Round:
    """One state's round: the actions played from it and what they did."""

    name: str
    state: State
    to_remove: int
    actions: list[Action] = field(default_factory=list)
    outcomes: dict[str, int] = field(default_factory=lambda: {SUCCESS: 0, TOO_MANY: 0, NO_HIT: 0})
    intermediate: dict[State, int] = field(default_factory=dict)
    success_rate: float = float("nan")

    def as_dict(self, names: dict[State, str]) -> dict:
        """The round as JSON-ready data, states written by their ``names``."""
        return {
            "round": self.name,
            "state": sorted(self.state),
            "cans_to_throw": self.to_remove,
            "actions": len(self.actions),
            "success": self.outcomes[SUCCESS],
            "fail_too_many": self.outcomes[TOO_MANY],
            "fail_no_hit": self.outcomes[NO_HIT],
            "intermediate": {names[s]: k for s, k in self.intermediate.items()},
            "success_rate": self.success_rate,
        }


def success_rates(rounds: Sequence[Round]) -> list[float]:
    """Solve ``r_s = (success_s + sum_t n_st r_t) / actions_s`` for every round at once."""
    index = {r.state: i for i, r in enumerate(rounds)}
    n = len(rounds)
    a = torch.eye(n, dtype=torch.float64)
    b = torch.zeros(n, dtype=torch.float64)
    for i, r in enumerate(rounds):
        total = len(r.actions)
        if total == 0:
            continue  # no action found: rate 0
        b[i] = r.outcomes[SUCCESS] / total
        for state, k in r.intermediate.items():
            a[i, index[state]] -= k / total
    return torch.linalg.solve(a, b).tolist()


def intermediate_goals(state: State, goal: State) -> list[State]:
    """Goals between ``goal`` and ``state``: add 1, 2, ... objects of ``state`` back."""
    extra = sorted(state - goal, key=repr)
    return [
        goal | frozenset(c) for k in range(1, len(extra)) for c in itertools.combinations(extra, k)
    ]


def paper_planner(
    start: State,
    goal: State,
    propose: Callable[[State, State], Sequence[Action]],
    play: Callable[[State, Action], State],
    *,
    max_rounds: int = 50,
) -> tuple[list[Round], float]:
    """Run the paper's planner from ``start`` to ``goal``.

    Parameters
    ----------
    propose
        ``propose(state, goal)`` -> the actions the model expects to turn ``state`` into
        ``goal`` in one step (empty if none).
    play
        ``play(state, action)`` -> the state the action actually produces.

    Returns
    -------
    rounds, success_rate
        Every round in the order reached, and the start round's success rate.
    """
    if not goal <= start:
        raise ValueError(f"the goal {sorted(goal)} must be a subset of the start {sorted(start)}")
    rounds: dict[State, Round] = {}
    queue = [start]
    while queue:
        state = queue.pop(0)
        if state in rounds:
            continue
        if len(rounds) >= max_rounds:
            raise RuntimeError(f"more than {max_rounds} rounds: raise max_rounds or check `play`")
        r = Round(f"round {len(rounds) + 1}", state, len(state - goal))
        rounds[state] = r
        actions = list(propose(state, goal))
        if not actions:
            for sub in intermediate_goals(state, goal):
                actions = list(propose(state, sub))
                if actions:
                    break
        r.actions = actions
        for action in actions:
            outcome = play(state, action)
            kind = classify(state, goal, outcome)
            if kind == INTERMEDIATE:
                r.intermediate[outcome] = r.intermediate.get(outcome, 0) + 1
                if outcome not in rounds and outcome not in queue:
                    queue.append(outcome)
            else:
                r.outcomes[kind] += 1
    ordered = list(rounds.values())
    for r, rate in zip(ordered, success_rates(ordered), strict=True):
        r.success_rate = rate
    return ordered, ordered[0].success_rate


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
