"""A network's graph as a networkx ``DiGraph``, for graph algorithms and drawing tools.

networkx comes with torch (and with the ``graph`` extra); it is imported when
:func:`to_networkx` runs.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from effect_networks.models.declaration import ACTION, Continuous, Discrete, EffectNetwork

if TYPE_CHECKING:
    import networkx as nx


def to_networkx(net: EffectNetwork) -> nx.DiGraph:
    """The declaration's graph: one node per site, an edge from every parent to its child.

    Parameters
    ----------
    net : EffectNetwork
        The declaration (no fitted numbers are needed).

    Returns
    -------
    networkx.DiGraph
        Nodes named by site, added in the network's site order (parents before
        children), each with the attributes

        * ``role``: ``"initial"``, ``"action"``, ``"cluster"``, ``"param"`` or ``"end"``;
        * ``cpd``: the name of the site's conditional-distribution kind (``"table"``,
          ``"softmax"``, ``"linear_gaussian"``, a user kind's name);
        * ``discrete``: whether the site takes states;
        * ``states``: a discrete site's labels (the action names for ``action``, the
          cluster numbers ``0..C-1`` for ``cluster.<p>``), or ``dim``: a continuous
          site's dimension;
        * ``feature`` and ``kind`` (``"object"``, ``"meta"``, ``"world"``) for a
          feature's sites, ``parameter`` for a parameter's.

        Edges run from each of ``net.cpd(site).parents`` (discrete parents) and
        ``net.cpd(site).inputs`` (continuous parents) to ``site``, with the attribute
        ``discrete`` saying which.

    Raises
    ------
    ImportError
        If networkx is not installed, naming the extra that installs it.
    """
    try:
        import networkx as nx
    except ImportError as exc:
        raise ImportError(
            "models.to_networkx needs networkx, the `graph` extra of effect-networks: install "
            "it with `pip install 'effect-networks[graph]'` (or `pip install networkx`)"
        ) from exc
    graph = nx.DiGraph()
    for s in net.sites:
        attributes: dict[str, object] = {"role": s.role, "cpd": net.cpd(s.name).name}
        attributes["discrete"] = s.discrete
        if s.feature is not None:
            feature = net.feature(s.feature)
            attributes |= {"feature": feature.name, "kind": feature.kind}
        if s.role in ("cluster", "param"):
            attributes["parameter"] = s.name.partition(".")[2]
        if s.name == ACTION:
            attributes["states"] = net.actions
        elif s.role == "cluster":
            attributes["states"] = tuple(range(s.size))
        elif s.discrete:
            feature = net.feature(s.feature)
            assert isinstance(feature, Discrete)
            attributes["states"] = feature.states
        else:
            assert s.role == "param" or isinstance(net.feature(s.feature), Continuous)
            attributes["dim"] = s.size
        graph.add_node(s.name, **attributes)
    for s in net.sites:
        cpd = net.cpd(s.name)
        graph.add_edges_from(((p, s.name) for p in cpd.parents), discrete=True)
        graph.add_edges_from(((p, s.name) for p in cpd.inputs), discrete=False)
    return graph
