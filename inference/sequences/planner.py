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
import warnings
from collections.abc import Iterable, Mapping, Sequence

import torch
from effect_networks.inference.sequences.dynamic_programming import induction, unseen_along
from effect_networks.inference.sequences.factored_planning import (
    EPISODES,
    KEEP_ROWS,
    MAX_RELEVANT_STATES,
    factored_plan,
)
from effect_networks.inference.sequences.factored_steps import step_model
from effect_networks.inference.sequences.plans import Plan, allowed_mask
from effect_networks.inference.sequences.states import Selection, StateLike, state_features
from effect_networks.inference.sequences.transition_tables import Transitions, transitions
from effect_networks.models.declaration import DTYPE, EffectNetwork
from effect_networks.models.params import NetworkParams

#: ``route="auto"`` plans on the dense tensor when it holds at most this many numbers
#: (states x actions x states), and factor by factor beyond.
DENSE_ENTRIES = 1 << 18
#: A plan warns when following it takes a step no training row reached with at least
#: this probability (``unseen``).
UNSEEN_WARNING = 0.5


class RestsOnUnseen(UserWarning):
    """A plan's policy likely takes steps that no training row reached."""


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
    route: str = "auto",
    budget: int = MAX_RELEVANT_STATES,
    episodes: int = EPISODES,
    seed: int = 0,
) -> Plan:
    """The policy maximising the probability of reaching ``goal`` within ``horizon`` actions.

    By exact finite-horizon dynamic programming: over the network's states where they are
    few (``route="dense"``), factor by factor over the features the goal depends on
    otherwise (``"projected"``, the same answers), and approximately, with a certified
    lower bound on its success, where even those exceed ``budget`` (``"approximate"``):
    :mod:`inference.sequences.factored_planning`.

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
    route
        ``"auto"`` (default): ``"dense"`` where the ``(S, A, S)`` tensor holds at most
        :data:`DENSE_ENTRIES` numbers or ``states=``, ``normalise=``, a per-state
        ``allowed`` mask or a predicate start asks for it; the factored routes otherwise
        (``"projected"`` when the goal's relevant features have at most ``budget`` joint
        states, ``"approximate"`` beyond). ``"dense"`` or ``"factored"`` forces one.
    budget
        The most joint states of the relevant features the factored route plans over
        exactly.
    episodes, seed
        The approximate route's simulated runs of its policy and their seed.

    Returns
    -------
    Plan
        The best action per state and step (``policy``), the probability of reaching the
        goal within ``horizon`` actions from ``start`` (``success``), the most likely
        path of states and actions (``path``), the route, the features the policy reads
        and the probability that it takes steps no training row reached (``unseen``;
        :class:`RestsOnUnseen` warns at :data:`UNSEEN_WARNING` or more).

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
    if route not in ("auto", "dense", "factored"):
        raise ValueError(f"route must be 'auto', 'dense' or 'factored', got {route!r}")
    if route == "auto":
        route = "dense" if dense_wanted(net, states, normalise, allowed, start) else "factored"
    if route == "factored":
        if states is not None or normalise:
            raise ValueError("states= and normalise= read the dense tensor: use route='dense'")
        model = step_model(
            net,
            params,
            parameter_values=parameter_values,
            given=given,
            features=_read_by(net, start, goal),
        )
        out = factored_plan(
            model,
            start,
            goal,
            horizon,
            allowed,
            avoid_unseen=avoid_unseen,
            budget=budget,
            episodes=episodes,
            seed=seed,
        )
        _warn_unseen(out)
        return out
    model = transitions(
        net,
        params,
        states=states,
        parameter_values=parameter_values,
        given=given,
        normalise=normalise,
    )
    return plan_on(model, start, goal, horizon, allowed, avoid_unseen=avoid_unseen)


def _read_by(net: EffectNetwork, start, goal) -> list[str] | None:
    """The features whose steps a factored plan reads (``None``: all).

    The goal's, where the start is a full state; a partial one is weighed by every
    initial table.
    """
    names = {f.name for f in state_features(net)}
    full = isinstance(start, Sequence) and not isinstance(start, str | bytes)
    full |= isinstance(start, Mapping) and names <= set(start)
    if not full or not isinstance(goal, Mapping) or not set(goal) <= names or not goal:
        return None
    return list(goal)


def dense_wanted(net: EffectNetwork, states, normalise, allowed, start) -> bool:
    """Whether ``route="auto"`` plans on the dense tensor (see ``plan``'s ``route``)."""
    if states is not None or normalise:
        return True
    if isinstance(allowed, torch.Tensor) and allowed.dim() == 2:
        return True
    if callable(start) and not isinstance(start, Mapping):
        return True
    s = math.prod(f.cardinality for f in state_features(net))
    return s * s * len(net.actions) <= DENSE_ENTRIES


def _warn_unseen(out: Plan) -> None:
    if out.unseen >= UNSEEN_WARNING:
        warnings.warn(
            RestsOnUnseen(
                f"following this plan takes a step that no training row reached with "
                f"probability {out.unseen:.3g}: its success is the pseudo-count prior's "
                "answer there (avoid_unseen=True plans around such steps)"
            ),
            stacklevel=3,
        )


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
    mask = allowed_mask(allowed, len(space), len(model.actions), model.action_index)
    if avoid_unseen:
        seen = mask & (model.unseen <= 0.5)
        mask = torch.where(seen.any(-1, keepdim=True), seen, mask)
    probs = model.probs
    exact = induction(lambda v: probs @ v, goal_mask, horizon, mask, probs.dtype)
    policy = exact.policy.clone()
    policy[:, goal_mask] = -1
    policy[:, ~mask.any(-1)] = -1  # no allowed action: none is taken
    value = exact.value
    rows = value.shape[0] - 1
    if rows < horizon and (horizon + 1) * len(space) <= KEEP_ROWS:  # converged: repeat
        value = torch.cat([value, value[-1:].expand(horizon - rows, -1)])
        policy = torch.cat([policy, policy[-1:].expand(horizon - rows, -1)])
    success = float(start_dist @ value[min(horizon, value.shape[0] - 1)])
    steps = _path_steps(horizon, exact.converged, len(space))
    path, p = _most_likely_path(probs, policy, goal_mask, start_dist, horizon, steps)
    labelled = tuple(
        space.states[x] if i % 2 == 0 else model.actions[x] for i, x in enumerate(path)
    )
    states = torch.arange(len(space))
    unseen = unseen_along(
        lambda mass, acts: mass @ probs[states, acts],
        lambda acts: model.unseen[states, acts],
        policy,
        start_dist,
        goal_mask,
        horizon,
    )
    out = Plan(
        model,
        goal_mask,
        start_dist,
        horizon,
        value,
        policy,
        success,
        labelled,
        p,
        unseen=unseen,
        converged=exact.converged,
    )
    _warn_unseen(out)
    return out


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


def _path_steps(horizon: int, converged: int | None, n_states: int) -> int:
    """The actions a most likely path is searched within.

    Past the rows where the policy stopped changing it is the same in every step, and a
    most likely path under one policy repeats no state: ``converged + S`` actions hold it.
    """
    return horizon if converged is None else min(horizon, converged + n_states)


def _most_likely_path(
    probs: torch.Tensor,
    policy: torch.Tensor,
    goal: torch.Tensor,
    start: torch.Tensor,
    horizon: int,
    steps: int | None = None,
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
    last = policy.shape[0] - 1
    steps = horizon if steps is None else steps
    for t in range(steps + 1):
        in_goal = torch.where(goal, delta, -torch.inf)
        top, at = in_goal.max(0)
        if top > best:
            best, best_t, best_s = float(top), t, int(at)
        if t == steps:
            break
        act = policy[min(horizon - t, last)]
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
        path = [prev, int(policy[min(horizon - t + 1, last), prev]), *path]
        state = prev
    return path, math.exp(best)
