"""A plan drawn by its states.

The policy as a grid (state x actions left) of the chosen actions, or the most likely path
to the goal as a line through the states.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from effect_networks.inference.plots._common import new_axes

#: what ``show=`` accepts
SHOWS = ("policy", "path")


def _labels(plan, states: Sequence | None, actions: Sequence[str] | None):
    """The state and action labels, and the name of the states' axis.

    A :class:`~inference.sequences.planner.Plan`'s own, or those given (default: indices).
    """
    space = getattr(plan, "space", None)
    s = plan.value.shape[1]
    if space is not None:  # a Plan: its own states (projected ones on the factored routes)
        states = [", ".join(map(str, state)) for state in space.states]
        axis = ", ".join(space.names)
        return states, list(plan.actions), axis
    if states is not None and len(states) != s:
        raise ValueError(f"states names {len(states)} states; the plan has {s}")
    chosen = [int(x) for x in np.unique(plan.policy.numpy()) if x >= 0]
    a = max(chosen, default=-1) + 1
    if actions is not None and len(actions) < a:
        raise ValueError(
            f"actions names {len(actions)} actions; the policy takes action index {a - 1}"
        )
    states = [str(x) for x in (range(s) if states is None else states)]
    return states, [str(x) for x in (range(a) if actions is None else actions)], "state"


def plot_plan(
    plan,
    ax=None,
    *,
    show: str = "policy",
    states: Sequence | None = None,
    actions: Sequence[str] | None = None,
):
    """Draw a plan: its policy as a grid of actions, or its most likely path.

    Parameters
    ----------
    plan : Plan or ExactPlan
        What :func:`inference.plan` (or :func:`~inference.sequences.planner.plan_on`)
        returned, drawn by its labels; or an
        :class:`~inference.sequences.dynamic_programming.ExactPlan` from
        :func:`~inference.sequences.dynamic_programming.exact_plan`, drawn by ``states`` and
        ``actions`` (indices by default).
    ax : matplotlib.axes.Axes, optional
        Where to draw; a new figure when ``None``.
    show : {"policy", "path"}
        ``"policy"``: one row per state and one column per number of actions left (the
        horizon on the left, 1 on the right), each cell coloured by the action chosen
        there and labelled with it and the probability of reaching the goal from it;
        ``"goal"`` in a goal state, ``"-"`` where no action is allowed. ``"path"``: the
        most likely path to the goal under the policy (a :class:`Plan`'s ``path``), one
        marker per state it passes, at its step, each step's action written on its
        segment, the path's probability in the title.
    states : sequence, optional
        An ``ExactPlan``'s state labels, one per state.
    actions : sequence of str, optional
        An ``ExactPlan``'s action labels, one per action index.

    Returns
    -------
    matplotlib.axes.Axes
        For ``"policy"``: an image ``(S, H)`` of action indices (masked where no action is
        chosen) and ``S * H`` cell texts; x-axis "actions left", y-axis the state
        features. For ``"path"``: one line whose markers are the path's states; x-axis
        "step", y-axis the state features.

    Raises
    ------
    ValueError
        If ``show`` is not one of ``"policy"``, ``"path"``; if ``"path"`` is asked of an
        ``ExactPlan`` (which has no path); if ``states`` or ``actions`` do not match the
        plan's sizes.
    """
    if show not in SHOWS:
        raise ValueError(f"show must be one of {SHOWS}, got {show!r}")
    if not hasattr(plan, "policy") or not hasattr(plan, "value"):
        raise ValueError(
            f"plan must be a Plan (inference.plan) or an ExactPlan, got {type(plan).__name__}"
        )
    state_names, action_names, axis = _labels(plan, states, actions)
    if show == "path":
        if not hasattr(plan, "path"):
            raise ValueError("show='path' needs a Plan (inference.plan): an ExactPlan has no path")
        return _path(plan, new_axes(ax), state_names, axis)
    return _policy(plan, new_axes(ax), state_names, action_names, axis)


def _policy(plan, ax, state_names, action_names, axis):
    from matplotlib.colors import ListedColormap

    horizon = plan.policy.shape[0] - 1
    policy = plan.policy[1:].flip(0).numpy().T  # (S, H): column 0 = the horizon left
    value = plan.value[1:].flip(0).double().numpy().T
    goal = plan.goal.numpy() if hasattr(plan, "goal") else np.zeros(len(state_names), bool)
    colours = ListedColormap([f"C{a % 10}" for a in range(max(len(action_names), 1))])
    shown = np.ma.masked_less(policy, 0)
    ax.imshow(
        shown,
        cmap=colours,
        vmin=-0.5,
        vmax=len(action_names) - 0.5,
        aspect="auto",
        alpha=0.45,
        interpolation="nearest",
    )
    for (i, j), a in np.ndenumerate(policy):
        if goal[i]:
            text = "goal"
        elif a < 0:
            text = "-"
        else:
            text = f"{action_names[a]}\n{value[i, j]:.2f}"
        ax.text(j, i, text, ha="center", va="center", fontsize=7)
    ax.set_xticks(range(horizon), [str(h) for h in range(horizon, 0, -1)])
    ax.set_yticks(range(len(state_names)), state_names)
    ax.set_xlabel("actions left")
    ax.set_ylabel(axis)
    return ax


def _path(plan, ax, state_names, axis):
    path = plan.path
    ax.set_yticks(range(len(state_names)), state_names)
    ax.set_ylim(len(state_names) - 0.5, -0.5)
    ax.set_xlabel("step")
    ax.set_ylabel(axis)
    if not path:
        ax.set_title(f"no path reaches the goal within {plan.horizon} actions", fontsize=9)
        return ax
    rows = [plan.space.index_of(state) for state in path[::2]]
    steps = np.arange(len(rows))
    ax.plot(steps, rows, "o-", color="C0", markersize=7)
    for t, action in enumerate(path[1::2]):
        ax.annotate(
            action,
            ((t + 0.5), (rows[t] + rows[t + 1]) / 2),
            ha="center",
            va="bottom",
            fontsize=8,
            xytext=(0, 4),
            textcoords="offset points",
        )
    ax.set_xticks(steps)
    ax.set_xlim(-0.5, max(len(rows) - 0.5, 1.5))
    ax.set_title(f"most likely path: p = {plan.path_probability:.3g}", fontsize=9)
    return ax
