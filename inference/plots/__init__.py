"""Pictures of a network and its fitted numbers, drawn into the caller's axes.

Each function takes ``ax=None`` (a new figure is made when it is ``None``) and returns the
:class:`matplotlib.axes.Axes` it drew on, so pictures compose into the caller's own
figures; nothing is shown or saved here. matplotlib is imported when a function runs,
so importing this package costs nothing.

* :func:`plot_network` (:mod:`inference.plots.graph`) -- the graph of a declaration
  (matplotlib only, no graphviz): initial sites on the left, the action and each
  parameter's cluster and value in the middle, end sites on the right; discrete sites in
  square boxes, continuous ones in round boxes, one arrow per parent link.
* :func:`plot_table` (:mod:`inference.plots.tables`) -- a table site's probabilities as a
  heat map, one row per parent configuration and one column per state, both by their
  labels.
* :func:`plot_clusters` (:mod:`inference.plots.clusters`) -- a parameter's clusters as
  their Gaussians: ellipses over the value (two dimensions of it) or over the value and an
  affected feature, intervals for a one-dimensional value, over the training rows when
  given.
* :func:`plot_action_posterior` (:mod:`inference.plots.posteriors`) -- an
  :class:`~inference.queries.ActionPosterior` row as bars by action name.
* :func:`plot_demonstration` (:mod:`inference.plots.posteriors`) -- an
  :class:`~inference.sequences.explanation.Explanation` row: the per-step action posterior as
  a heat map, the most probable sequence marked.
* :func:`plot_plan` (:mod:`inference.plots.plans`) -- a :class:`~inference.Plan`: its
  policy as a grid of the actions chosen per state and actions left, or its most likely
  path to the goal.
"""

from effect_networks.inference.plots._common import site_parents, state_labels
from effect_networks.inference.plots.clusters import plot_clusters
from effect_networks.inference.plots.graph import plot_network
from effect_networks.inference.plots.plans import plot_plan
from effect_networks.inference.plots.posteriors import plot_action_posterior, plot_demonstration
from effect_networks.inference.plots.tables import plot_table

__all__ = [
    "plot_network",
    "plot_table",
    "plot_clusters",
    "plot_action_posterior",
    "plot_demonstration",
    "plot_plan",
    "site_parents",
    "state_labels",
]
