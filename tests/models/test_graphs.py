"""to_networkx (models.graphs): every site a node with its role, kind and states or
dimension, an edge from each parent, checked against the declaration's parents."""

import networkx as nx
from effect_networks.models import Continuous, Discrete, to_networkx
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.networks import README_NET, declared_networks, networks_of_every_kind


@settings(max_examples=40, deadline=None)
@given(net=st.one_of(networks_of_every_kind(), declared_networks()))
def test_the_graph_is_the_declarations(net):
    graph = to_networkx(net)
    assert list(graph.nodes) == [s.name for s in net.sites]
    assert nx.is_directed_acyclic_graph(graph)
    for s in net.sites:
        cpd = net.cpd(s.name)
        assert set(graph.predecessors(s.name)) == {*cpd.parents, *cpd.inputs}
        for p in graph.predecessors(s.name):
            assert graph.edges[p, s.name]["discrete"] == net.site(p).discrete
        node = graph.nodes[s.name]
        assert node["role"] == s.role and node["cpd"] == cpd.name
        if s.role in ("initial", "end"):
            feature = net.feature(s.feature)
            assert node["kind"] == feature.kind and node["feature"] == feature.name
            if isinstance(feature, Discrete):
                assert node["states"] == feature.states
            else:
                assert isinstance(feature, Continuous) and node["dim"] == feature.dim
    assert graph.nodes["action"]["states"] == net.actions
    # a declared parent set is the site's parents, less what a parameter adds
    for site, declared in net.parents:
        added = set(graph.predecessors(site)) - set(declared)
        assert set(declared) <= set(graph.predecessors(site))
        assert all(net.site(q).role in ("cluster", "param") for q in added)
    # Fig. 1 where nothing is declared: every initial site and the action
    initial = {s.name for s in net.sites if s.role == "initial"}
    declared_sites = dict(net.parents)
    for f in net.features:
        site = f"end.{f.name}"
        if site not in declared_sites:
            assert initial | {"action"} <= set(graph.predecessors(site))


def test_the_quick_starts_graph():
    graph = to_networkx(README_NET)
    assert graph.nodes["cluster.force"] == {
        "role": "cluster",
        "cpd": "table",
        "discrete": True,
        "parameter": "force",
        "states": tuple(range(8)),
    }
    assert graph.nodes["param.force"]["dim"] == 1
    assert set(graph.predecessors("end.position")) == {
        "initial.visible",
        "initial.position",
        "action",
        "cluster.force",
        "param.force",
    }
    assert list(nx.topological_sort(graph))[0] in ("initial.visible", "initial.position", "action")
