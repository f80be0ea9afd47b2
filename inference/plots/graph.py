"""The network's graph drawn with matplotlib (no graphviz).

Sites in columns by role, one arrow per parent link.
"""

from __future__ import annotations

from effect_networks.inference.plots._common import new_axes, site_parents
from effect_networks.models.declaration import EffectNetwork

#: Column of each role in :func:`plot_network` (end sites with end parents move right).
_COLUMN = {"initial": 0.0, "action": 1.0, "cluster": 1.0, "param": 1.0, "end": 2.0}


# ------------------------------------------------------------------------------ the graph
def _positions(net: EffectNetwork) -> dict[str, tuple[float, float]]:
    """Where each site sits.

    A column per role, end sites shifted right by their depth among end sites; the middle
    column (the action, the parameters' sites) above the rows of the initial and end
    sites.
    """
    column: dict[str, float] = {}
    for spec in net.sites:  # parents before children
        x = _COLUMN[spec.role]
        if spec.role == "end":
            ends = [column[p] for p in site_parents(net, spec.name) if net.site(p).role == "end"]
            x = max([x, *(c + 0.8 for c in ends)])
        column[spec.name] = x
    where = {}
    for x in sorted(set(column.values())):
        names = [s for s, c in column.items() if c == x]
        for i, name in enumerate(names):
            # The middle column stands above the others, so that no link from an initial
            # to an end site passes through its boxes, as a staircase down to the left,
            # so that the links leaving a box run down to the right clear of those below.
            if x == _COLUMN["action"]:
                where[name] = (2 * x - 0.3 * i, len(names) - i)
            else:
                where[name] = (2 * x, -i)
    return where


def plot_network(net: EffectNetwork, ax=None):
    """Draw the network's graph: its sites and one arrow per parent link.

    Parameters
    ----------
    net : EffectNetwork
        The declaration to draw (its fitted numbers play no part).
    ax : matplotlib.axes.Axes, optional
        Where to draw; a new figure when ``None``.

    Returns
    -------
    matplotlib.axes.Axes
        The axes, with one text per site (its name; discrete sites in square boxes,
        continuous ones in round boxes) and one
        :class:`~matplotlib.patches.FancyArrowPatch` per parent link, whose ``gid`` is
        ``"<parent>-><site>"``.
    """
    from matplotlib.patches import FancyArrowPatch

    ax = new_axes(ax)
    where = _positions(net)
    boxes = {}
    for spec in net.sites:
        style = "square,pad=0.4" if spec.discrete else "round,pad=0.4"
        colour = "#dbe8f5" if spec.discrete else "#f5e6d3"
        boxes[spec.name] = ax.text(
            *where[spec.name],
            spec.name,
            ha="center",
            va="center",
            fontsize=9,
            bbox={"boxstyle": style, "facecolor": colour, "edgecolor": "0.3"},
            zorder=3,
        )
    for spec in net.sites:
        for parent in site_parents(net, spec.name):
            (x0, y0), (x1, y1) = where[parent], where[spec.name]
            # a link past boxes of its own column curves around them
            bend = 0.4 if abs(y1 - y0) > 1 and abs(x1 - x0) < 1 else 0.0
            ax.add_patch(
                FancyArrowPatch(
                    (x0, y0),
                    (x1, y1),
                    arrowstyle="-|>",
                    mutation_scale=10,
                    connectionstyle=f"arc3,rad={bend}",
                    patchA=boxes[parent].get_bbox_patch(),
                    patchB=boxes[spec.name].get_bbox_patch(),
                    color="0.35",
                    linewidth=0.8,
                    zorder=4,  # after the boxes, which place themselves as they are drawn
                    gid=f"{parent}->{spec.name}",
                )
            )
    xs = [x for x, _ in where.values()]
    ys = [y for _, y in where.values()]
    ax.set_xlim(min(xs) - 0.9, max(xs) + 0.9)
    ax.set_ylim(min(ys) - 0.8, max(ys) + 0.8)
    ax.set_axis_off()
    return ax
