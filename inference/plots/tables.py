"""A table site's probabilities as a heat map, rows and columns by their labels."""

from __future__ import annotations

import itertools

import numpy as np
from effect_networks.inference.plots._common import check_site, new_axes, state_labels
from effect_networks.models.declaration import EffectNetwork
from effect_networks.models.params import NetworkParams, check_params


def plot_table(net: EffectNetwork, params: NetworkParams, site: str, ax=None, *, annotate=None):
    """Draw a table site's probabilities as a heat map.

    Parameters
    ----------
    net : EffectNetwork
        The declaration ``params`` were fitted for.
    params : NetworkParams
        Fitted numbers; ``params[site]`` must be a
        :class:`~models.cpds.table.TableParams`.
    site : str
        A discrete site whose kind is ``"table"`` (a cluster's table too).
    ax : matplotlib.axes.Axes, optional
        Where to draw; a new figure when ``None``.
    annotate : bool, optional
        Write each probability in its cell; by default when the table has at most 120
        cells.

    Returns
    -------
    matplotlib.axes.Axes
        Rows: the parents' configurations (row-major, labelled by their states, the
        y-axis named by the parent sites), columns: the site's states. Each row sums to 1.

    Raises
    ------
    ValueError
        If ``site`` is not a site of ``net`` or not a table site, or ``params`` do not
        fit ``net`` (:func:`models.params.check_params`).
    """
    check_params(net, params)
    check_site(net, site)
    cpd = net.cpd(site)
    if not cpd.tabular:
        tables = [s.name for s in net.sites if net.cpd(s.name).tabular]
        raise ValueError(
            f"site {site!r} has kind {cpd.name!r}, not a table; plot_table draws the table "
            f"sites {tables}"
        )
    probs = np.asarray(params[site].probs.detach().cpu(), dtype=float).reshape(-1, cpd.size)
    rows = [
        ", ".join(map(str, config))
        for config in itertools.product(*(state_labels(net, p) for p in cpd.parents))
    ]
    ax = new_axes(ax)
    image = ax.imshow(probs, vmin=0.0, vmax=1.0, cmap="viridis", aspect="auto")
    ax.figure.colorbar(image, ax=ax, label="probability")
    ax.set_xticks(range(cpd.size), [str(s) for s in state_labels(net, site)])
    ax.set_yticks(range(len(rows)), rows if cpd.parents else ["(no parents)"])
    ax.set_xlabel(site)
    ax.set_ylabel(", ".join(cpd.parents))
    if annotate if annotate is not None else probs.size <= 120:
        for (i, j), p in np.ndenumerate(probs):
            colour = "black" if p > 0.5 else "white"
            ax.text(j, i, f"{p:.2f}", ha="center", va="center", fontsize=7, color=colour)
    return ax
