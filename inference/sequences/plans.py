"""What a plan answers: :class:`Plan`, and the certificate of an approximate one.

Every planning route returns a :class:`Plan`: the closed-loop policy (state, actions
left -> action), the probability of reaching the goal from the start, the path it most
likely takes, and what the answer rests on: the route that computed it, the features
its policy reads, the probability that following it passes through steps no training
row reached, and, for an approximate plan, a :class:`Certificate` for its success.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Iterable
from dataclasses import dataclass, field

import torch
from effect_networks.inference.sequences.states import ProjectedSpace, StateLike, StateSpace
from effect_networks.inference.sequences.transition_tables import Transitions

#: The routes a plan is computed by (:func:`~inference.sequences.planner.plan`).
ROUTES = ("dense", "projected", "approximate")


def allowed_mask(
    allowed: Iterable[str] | torch.Tensor | None,
    n_states: int,
    n_actions: int,
    action_index: Callable[[str], int],
    *,
    per_state: bool = True,
) -> torch.Tensor:
    """``(S, A)`` bool: the actions a plan may take, from labels or a mask.

    ``allowed``: action labels (read by ``action_index``), an ``(A,)`` bool mask, or, with
    ``per_state``, an ``(S, A)`` one; ``None``: every action.
    """
    s, a = n_states, n_actions
    if allowed is None:
        return torch.ones(s, a, dtype=torch.bool)
    if isinstance(allowed, torch.Tensor) and allowed.dtype == torch.bool:
        shapes = ((a,), (s, a)) if per_state else ((a,),)
        if allowed.shape not in shapes:
            wanted = f"a ({a},) or ({s}, {a})" if per_state else f"an ({a},)"
            where = (
                ""
                if per_state
                else " on the factored routes (a per-state mask needs the dense route)"
            )
            raise ValueError(
                f"allowed must be {wanted} bool mask{where}, got {tuple(allowed.shape)}"
            )
        return allowed.expand(s, a).clone()
    if isinstance(allowed, str) or not isinstance(allowed, Iterable):
        raise ValueError(f"allowed must be action labels or a bool mask, got {allowed!r}")
    mask = torch.zeros(a, dtype=torch.bool)
    for label in allowed:
        mask[action_index(label)] = True
    if not bool(mask.any()):
        raise ValueError("allowed names no action")
    return mask.expand(s, a).clone()


@dataclass(frozen=True)
class Certificate:
    """A Monte Carlo evaluation of a policy in the full model, with its lower bound.

    Attributes
    ----------
    estimate : float
        The fraction of ``episodes`` simulated runs of the policy that reached the goal.
    lower : float
        A lower bound on the policy's true success that holds with probability
        ``confidence`` (Hoeffding: ``estimate - sqrt(log(1 / (1 - confidence)) / (2 n))``).
    episodes : int
        The simulated runs.
    confidence : float
        The bound's confidence level.
    seed : int
        The seed of the simulations (the same seed gives the same figures).
    projected : float
        The success the policy's own reduced model promises (not a bound).
    """

    estimate: float
    lower: float
    episodes: int
    confidence: float
    seed: int
    projected: float


@dataclass(frozen=True)
class Plan:
    """A finite-horizon plan over a network's states and actions.

    Attributes
    ----------
    model : Transitions or None
        The dense transitions planned on (states, action labels, ``probs``); ``None`` on
        the factored routes, which never build them.
    goal : (S,) bool
        The goal states (of ``space``).
    start : (S,) float64
        The start distribution (over ``space``).
    horizon : int
        The most actions the plan takes.
    value : (H + 1, S) float64
        ``value[h, s]``: the probability of reaching the goal from ``s`` within ``h``
        actions under the policy (the best any policy achieves). Where the values stopped
        changing before the horizon (``converged``) and the table would be large, only
        the rows up to ``converged`` are kept: every later row equals the last.
    policy : (H + 1, S) long
        ``policy[h, s]``: the action to take in ``s`` with ``h`` actions left; ``-1`` in
        a goal state, where no action is allowed, and in row 0. Rows kept as ``value``'s.
    success : float
        The probability of reaching the goal within ``horizon`` actions from ``start``:
        exact on the ``"dense"`` and ``"projected"`` routes, the certified lower bound on
        the ``"approximate"`` one (``certificate``).
    path : tuple
        The most likely path to the goal under the policy: ``(state, action, state,
        ..., goal state)`` by labels (the start alone if it is a goal; empty if no path
        reaches the goal), and ``path_probability`` its probability. On the factored
        routes the states are the projected features' labels and the path is the
        greedy one (the most likely next state at each step).
    space : StateSpace or ProjectedSpace
        The states the policy reads: every state (dense) or the combinations of
        ``features`` (factored routes), which read a full state by those features.
    route : str
        ``"dense"`` (the ``(S, A, S)`` tensor), ``"projected"`` (exact, factor by factor,
        on the features the goal depends on) or ``"approximate"`` (see ``certificate``).
    features : tuple of str
        The state features the policy reads.
    unseen : float
        The probability that following the policy from the start takes a step resting on
        a configuration no training row reached (answered by the pseudo-count prior
        alone), each step's share weighted by the probability of being there.
    certificate : Certificate or None
        The approximate route's Monte Carlo evaluation in the full model.
    converged : int or None
        The number of actions left from which the values stopped changing (every larger
        horizon has the same answer); ``None`` if they changed up to the horizon.
    """

    model: Transitions | None
    goal: torch.Tensor = field(repr=False)
    start: torch.Tensor = field(repr=False)
    horizon: int
    value: torch.Tensor = field(repr=False)
    policy: torch.Tensor = field(repr=False)
    success: float
    path: tuple = ()
    path_probability: float = 0.0
    space: StateSpace | ProjectedSpace | None = field(repr=False, default=None)
    route: str = "dense"
    features: tuple[str, ...] = ()
    unseen: float = 0.0
    certificate: Certificate | None = None
    converged: int | None = None
    actions: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.space is None:
            object.__setattr__(self, "space", self.model.space)
        if not self.actions:
            object.__setattr__(self, "actions", self.model.actions)
        if not self.features:
            object.__setattr__(self, "features", tuple(self.space.names))

    def _row(self, steps_left: int | None) -> int:
        h = self.horizon if steps_left is None else steps_left
        if not isinstance(h, int) or isinstance(h, bool) or not 1 <= h <= self.horizon:
            raise ValueError(f"steps_left must be an int in 1..{self.horizon}, got {steps_left!r}")
        return min(h, self.value.shape[0] - 1)

    def action(self, state: StateLike | int, steps_left: int | None = None) -> str | None:
        """The action label to take in ``state`` with ``steps_left`` actions left.

        ``steps_left`` defaults to the horizon; ``None`` in a goal state or where no action is
        allowed.
        """
        a = int(self.policy[self._row(steps_left), self.space.index_of(state)])
        return None if a < 0 else self.actions[a]

    def probability(self, state: StateLike | int, steps_left: int | None = None) -> float:
        """The probability of reaching the goal from ``state`` within ``steps_left`` actions.

        ``steps_left`` defaults to the horizon.
        """
        return float(self.value[self._row(steps_left), self.space.index_of(state)])

    def to_dict(self) -> dict[tuple[tuple[Hashable, ...], int], str]:
        """``{(state, steps left): action}`` by labels.

        For every non-goal state with an allowed action (on the factored routes, the
        states of the projected features).
        """
        out = {}
        for h in range(1, self.horizon + 1):
            row = self.policy[self._row(h)]
            for i, s in enumerate(self.space.states):
                a = int(row[i])
                if a >= 0:
                    out[(s, h)] = self.actions[a]
        return out

    def __repr__(self) -> str:
        return (
            f"Plan(success={self.success:.4g} within {self.horizon} actions ({self.route}), "
            f"{int(self.goal.sum())} goal states of {len(self.space)} over {self.features}, "
            f"unseen {self.unseen:.3g}, most likely path {self.path!r} "
            f"(p={self.path_probability:.3g}))"
        )
