"""Plan with any network.

The actions that reach a goal within a horizon, over the network's own states.

:func:`~inference.sequences.planner.plan` builds the network's joint transitions
(:func:`~inference.sequences.transition_tables.transitions`) and runs finite-horizon dynamic
programming on them (:func:`~inference.sequences.dynamic_programming.exact_plan`): with ``h`` actions
left, each state takes the action that maximises the probability of reaching the goal
within ``h`` actions, every next state's probability summed exactly. The goal is
absorbing (reached once is reached). :func:`plan_on` does the same on transitions already
built (another model's, a compiled one's, a subset of states).

The answer, a :class:`Plan`, is a closed-loop policy (state, actions left -> action), the
probability of success from the start (a state, or a distribution over the states a
partial start allows, weighted by the network's initial-state tables), and the most
likely path to the goal under the policy, all readable by labels. Scoring the policy
under another transition model is :func:`~inference.sequences.dynamic_programming.policy_value`
(``plan.policy`` is its ``(H + 1, S)`` tensor).
"""

from __future__ import annotations

import math
from collections.abc import Hashable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import torch
from effect_networks.inference.sequences.dynamic_programming import exact_plan
from effect_networks.inference.sequences.states import Selection, StateLike
from effect_networks.inference.sequences.transition_tables import Transitions, transitions
from effect_networks.models.declaration import DTYPE, EffectNetwork
from effect_networks.models.params import NetworkParams


@dataclass(frozen=True)
class Plan:
    """A finite-horizon plan over ``model``'s states and actions.

    Attributes
    ----------
    model : Transitions
        The transitions planned on (states, action labels, ``probs``).
    goal : (S,) bool
        The goal states.
    start : (S,) float64
        The start distribution.
    horizon : int
        The most actions the plan takes.
    value : (H + 1, S) float64
        ``value[h, s]``: the probability of reaching the goal from ``s`` within ``h``
        actions under the policy (the best any policy achieves).
    policy : (H + 1, S) long
        ``policy[h, s]``: the action to take in ``s`` with ``h`` actions left; ``-1`` in
        a goal state, where no action is allowed, and in row 0.
    success : float
        The probability of reaching the goal within ``horizon`` actions from ``start``.
    path : tuple
        The most likely path to the goal under the policy: ``(state, action, state,
        ..., goal state)`` by labels (the start alone if it is a goal; empty if no path
        reaches the goal), and ``path_probability`` its probability.
    """

    model: Transitions
    goal: torch.Tensor = field(repr=False)
    start: torch.Tensor = field(repr=False)
    horizon: int
    value: torch.Tensor = field(repr=False)
    policy: torch.Tensor = field(repr=False)
    success: float
    path: tuple = ()
    path_probability: float = 0.0

    def action(self, state: StateLike | int, steps_left: int | None = None) -> str | None:
        """The action label to take in ``state`` with ``steps_left`` actions left.

        ``steps_left`` defaults to the horizon; ``None`` in a goal state or where no action is
        allowed.
        """
        h = self.horizon if steps_left is None else steps_left
        if not isinstance(h, int) or not 1 <= h <= self.horizon:
            raise ValueError(f"steps_left must be an int in 1..{self.horizon}, got {steps_left!r}")
        a = int(self.policy[h, self.model.space.index_of(state)])
        return None if a < 0 else self.model.actions[a]

    def probability(self, state: StateLike | int, steps_left: int | None = None) -> float:
        """The probability of reaching the goal from ``state`` within ``steps_left`` actions.

        ``steps_left`` defaults to the horizon.
        """
        h = self.horizon if steps_left is None else steps_left
        return float(self.value[h, self.model.space.index_of(state)])

    def to_dict(self) -> dict[tuple[tuple[Hashable, ...], int], str]:
        """``{(state, steps left): action}`` by labels.

        For every non-goal state with an allowed action.
        """
        out = {}
        for h in range(1, self.horizon + 1):
            for i, s in enumerate(self.model.space.states):
                a = int(self.policy[h, i])
                if a >= 0:
                    out[(s, h)] = self.model.actions[a]
        return out

    def __repr__(self) -> str:
        return (
            f"Plan(success={self.success:.4g} within {self.horizon} actions, "
            f"{int(self.goal.sum())} goal states of {len(self.model.space)}, "
            f"most likely path {self.path!r} (p={self.path_probability:.3g}))"
        )


def plan(
    net: EffectNetwork,
    params: NetworkParams,
    start: Selection | StateLike,
    goal: Selection,
    horizon: int,
    allowed: Iterable[str] | torch.Tensor | None = None,
    *,
    states: Iterable[StateLike] | None = None,
    parameter_values: str = "integrate",
    given: Mapping[str, object] | None = None,
    normalise: bool = False,
    avoid_unseen: bool = False,
) -> Plan:
    """The policy maximising the probability of reaching ``goal`` within ``horizon`` actions.

    By exact finite-horizon dynamic programming over the network's states.

    Parameters
    ----------
    net, params
        The network and its fitted tables; its state is its discrete features with an
        initial and an end node (:mod:`inference.sequences.states`).
    start
        A full state (a label tuple, or ``{feature: label}`` naming every state feature)
        or a partial one (``{feature: label}`` for some features, or a predicate on a
        state's labels): the states it allows, weighted by the network's initial-state
        tables (``Transitions.prior``), normalised.
    goal
        Labels of some features (``{"door": "open"}``) or a predicate called with each
        state's ``{feature: label}``.
    horizon
        The most actions, ``>= 1``.
    allowed
        The actions the plan may take: action labels, or an ``(A,)`` or ``(S, A)`` bool
        mask over the transitions' actions.
    states, parameter_values, given, normalise
        As :func:`~inference.sequences.transition_tables.transitions` takes them: the states to
        plan over, how an action's parameter is chosen (``"integrate"``: drawn from the
        action's clusters; ``"clusters"``: one action per cluster, which the plan
        chooses), the continuous initial features' values, whether the next state is
        conditioned on being one of ``states`` (otherwise a step leaving them fails).
    avoid_unseen
        Never take an action whose step rests mostly (``unseen > 0.5``) on configurations
        no training row reached, unless a state has no other.


    Returns
    -------
    Plan
        The best action per state and step (``policy``), the probability of reaching the
        goal within ``horizon`` actions from ``start`` (``success``) and the most likely
        path of states and actions (``path``).

    Examples
    --------
    >>> from models import Discrete, EffectNetwork
    >>> from inference import fit
    >>> net = EffectNetwork(
    ...     features=(Discrete("door", ("shut", "open")), Discrete("lock", ("on", "off"))),
    ...     actions=("unlock", "push", "wait"),
    ... )
    >>> rows = {
    ...     "initial.door": ["shut"] * 6, "initial.lock": ["on", "on", "off", "off", "on", "off"],
    ...     "action": ["unlock", "push", "push", "unlock", "wait", "wait"],
    ...     "end.door": ["shut", "shut", "open", "shut", "shut", "shut"],
    ...     "end.lock": ["off", "on", "off", "off", "on", "off"],
    ... }
    >>> p = plan(net, fit(net, rows).params, ("shut", "on"), {"door": "open"}, horizon=2)
    >>> p.path[1::2], p.success > 0.9
    (('unlock', 'push'), True)
    """
    model = transitions(
        net,
        params,
        states=states,
        parameter_values=parameter_values,
        given=given,
        normalise=normalise,
    )
    return plan_on(model, start, goal, horizon, allowed, avoid_unseen=avoid_unseen)


def plan_on(
    model: Transitions,
    start: Selection | StateLike,
    goal: Selection,
    horizon: int,
    allowed: Iterable[str] | torch.Tensor | None = None,
    *,
    avoid_unseen: bool = False,
) -> Plan:
    """:func:`~inference.sequences.planner.plan` on transitions already built (``model``); the same arguments."""
    if not isinstance(horizon, int) or isinstance(horizon, bool) or horizon < 1:
        raise ValueError(f"horizon must be an int >= 1, got {horizon!r}")
    space = model.space
    start_dist = _start(model, start)
    goal_mask = space.mask(goal)
    if not bool(goal_mask.any()):
        raise ValueError(f"goal {goal!r} picks no state of the {len(space)} planned over")
    mask = _allowed(model, allowed)
    if avoid_unseen:
        seen = mask & (model.unseen <= 0.5)
        mask = torch.where(seen.any(-1, keepdim=True), seen, mask)
    exact = exact_plan(model.probs, goal_mask, horizon, allowed=mask)
    policy = exact.policy.clone()
    policy[:, goal_mask] = -1
    policy[:, ~mask.any(-1)] = -1  # no allowed action: none is taken
    success = float(start_dist @ exact.value[horizon])
    path, p = _most_likely_path(model.probs, policy, goal_mask, start_dist, horizon)
    labelled = tuple(
        space.states[x] if i % 2 == 0 else model.actions[x] for i, x in enumerate(path)
    )
    return Plan(model, goal_mask, start_dist, horizon, exact.value, policy, success, labelled, p)


def _start(model: Transitions, start) -> torch.Tensor:
    space = model.space
    if isinstance(start, int) and not isinstance(start, bool):
        return space.distribution(space.states[space.index_of(start)])
    prior = model.prior
    if not bool((prior > 0).any()):
        prior = None
    try:
        return space.distribution(start, prior)
    except ValueError:
        if prior is None:
            raise
        return space.distribution(start)  # the allowed states have no prior weight


def _allowed(model: Transitions, allowed) -> torch.Tensor:
    s, a = len(model.space), len(model.actions)
    if allowed is None:
        return torch.ones(s, a, dtype=torch.bool)
    if isinstance(allowed, torch.Tensor) and allowed.dtype == torch.bool:
        if allowed.shape not in ((a,), (s, a)):
            raise ValueError(
                f"allowed must be a ({a},) or ({s}, {a}) bool mask, got {tuple(allowed.shape)}"
            )
        return allowed.expand(s, a).clone()
    if isinstance(allowed, str) or not isinstance(allowed, Iterable):
        raise ValueError(f"allowed must be action labels or a bool mask, got {allowed!r}")
    mask = torch.zeros(a, dtype=torch.bool)
    for label in allowed:
        mask[model.action_index(label)] = True
    if not bool(mask.any()):
        raise ValueError("allowed names no action")
    return mask.expand(s, a).clone()


def _most_likely_path(
    probs: torch.Tensor,
    policy: torch.Tensor,
    goal: torch.Tensor,
    start: torch.Tensor,
    horizon: int,
) -> tuple[Sequence[int], float]:
    """The most probable state sequence under the policy that ends in the goal.

    Within ``horizon`` actions (Viterbi over the policy's chain, the goal absorbing), as ``(s0, a0,
    s1, a1, ..., goal)`` indices, and its probability.
    """
    s = probs.shape[0]
    rows = torch.arange(s)
    log_t = probs.to(DTYPE).log()
    delta = start.log()
    back = []
    best, best_t, best_s = -torch.inf, -1, -1
    for t in range(horizon + 1):
        in_goal = torch.where(goal, delta, -torch.inf)
        top, at = in_goal.max(0)
        if top > best:
            best, best_t, best_s = float(top), t, int(at)
        if t == horizon:
            break
        act = policy[horizon - t]
        step = log_t[rows, act.clamp_min(0)]  # (S, S'): from each state under its action
        moving = ~goal & (act >= 0)
        step = torch.where(moving[:, None], step + delta[:, None], -torch.inf)
        delta, came = step.max(0)
        back.append(came)
    if best_t < 0:
        return (), 0.0
    path = [best_s]
    state = best_s
    for t in range(best_t, 0, -1):
        prev = int(back[t - 1][state])
        path = [prev, int(policy[horizon - t + 1, prev]), *path]
        state = prev
    return path, math.exp(best)
