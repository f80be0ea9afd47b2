"""The paper's round planner (§IV-C): chaining actions towards a goal, round by round.

States are sets of objects still present (``frozenset``); the goal is a state to reach by
removing objects. Nothing here knows what an object or an action is: the caller passes
functions that propose actions and play them.

:func:`paper_planner`: in a round, take every action proposed to reach the goal from the
round's state; if none, add objects back to the goal (intermediate goals, fewest added
first) until some action is proposed. Play every action and classify the outcome:
success (the goal), too many removed (an object of the goal is gone), nothing hit (the
state is unchanged), or an intermediate state (more objects than the goal, all goal
objects kept), which becomes the start of a new round, evaluated once however often it
is reached. A round's success rate is its success share plus, for each intermediate
state, its share times that state's success rate: a linear system, solved exactly
(rounds can lead back to one another).

Beyond the paper, the exact planner over learned transition probabilities is
:func:`inference.sequences.dynamic_programming.exact_plan`.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass, field

import torch

__all__ = [
    "INTERMEDIATE",
    "NO_HIT",
    "SUCCESS",
    "TOO_MANY",
    "Round",
    "classify",
    "intermediate_goals",
    "paper_planner",
    "success_rates",
]

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
