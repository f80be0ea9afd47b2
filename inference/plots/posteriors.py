"""Posteriors over actions.

One evidence row's as bars, a demonstration's per step as a heat map.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from effect_networks.inference.plots._common import new_axes


def plot_action_posterior(posterior, ax=None, actions: Sequence[str] | None = None, row: int = 0):
    """Draw one row of an action posterior as bars, one per action.

    Parameters
    ----------
    posterior : ActionPosterior
        What :func:`inference.infer_action` (or its compiled method) returned.
    ax : matplotlib.axes.Axes, optional
        Where to draw; a new figure when ``None``.
    actions : sequence of str, optional
        The actions to draw, in this order; all of them by default.
    row : int
        The evidence row to draw.

    Returns
    -------
    matplotlib.axes.Axes
        One bar per action, its height the action's posterior probability; the row's
        best action drawn darker.

    Raises
    ------
    ValueError
        If ``row`` or an action is not in the posterior.
    """
    names = tuple(posterior.actions)
    n = posterior.probs.shape[0]
    if not -n <= row < n:
        raise ValueError(f"row {row} is not a row of this posterior, which has {n} rows")
    chosen = names if actions is None else tuple(actions)
    unknown = [a for a in chosen if a not in names]
    if unknown:
        raise ValueError(f"unknown actions {unknown}; the posterior's actions are {list(names)}")
    probs = posterior.probs[row].detach().cpu().double().numpy()
    heights = [float(probs[names.index(a)]) for a in chosen]
    best = posterior.best_names[row]
    ax = new_axes(ax)
    ax.bar(range(len(chosen)), heights, color=["C0" if a == best else "#9ecae1" for a in chosen])
    ax.set_xticks(range(len(chosen)), list(chosen))
    ax.set_ylim(0.0, 1.0)
    ax.set_ylabel("P(action | evidence)")
    return ax


def plot_demonstration(explanation, ax=None, row: int = 0):
    """Draw one demonstration's per-step action posterior as a heat map.

    Parameters
    ----------
    explanation : Explanation
        What :func:`inference.explain` returned.
    ax : matplotlib.axes.Axes, optional
        Where to draw; a new figure when ``None``.
    row : int
        The demonstration to draw.

    Returns
    -------
    matplotlib.axes.Axes
        One column per step and one row per action, the cell's shade the action's
        posterior probability at that step (0 white, 1 dark); a dot marks each step's
        action in the most probable sequence.
    """
    n = explanation.probs.shape[0]
    if not -n <= row < n:
        raise ValueError(f"row {row} is not a demonstration of this explanation, which has {n}")
    probs = explanation.probs[row].detach().cpu().double().numpy().T  # (A, T)
    ax = new_axes(ax)
    ax.imshow(probs, cmap="Blues", vmin=0.0, vmax=1.0, aspect="auto", origin="upper")
    steps = np.arange(probs.shape[1])
    ax.plot(steps, explanation.best[row].numpy(), "o", color="C1", label="most probable sequence")
    ax.set_xticks(steps, [f"{t} → {t + 1}" for t in steps])
    ax.set_yticks(range(len(explanation.actions)), list(explanation.actions))
    ax.set_xlabel("step (state → state)")
    ax.set_ylabel("P(action | demonstration)")
    return ax
