"""pgmpy interop: our queries against pgmpy's VariableElimination, hand-computed numbers,
round trips through pgmpy and BIF, and the structures that are refused."""

import itertools
import sys

import numpy as np
import pytest
import torch
from effect_networks.inference import infer_action, predict
from effect_networks.models import (
    Continuous,
    Discrete,
    DroppedSites,
    EffectNetwork,
    Parameter,
    from_pgmpy,
    random_params,
    read_bif,
    to_pgmpy,
    write_bif,
)
from effect_networks.models.declaration import DTYPE
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.networks import counts_of, declared_networks, discrete_networks, pgmpy_marginal

pytest.importorskip("pgmpy")
from pgmpy.factors.discrete import TabularCPD  # noqa: E402
from pgmpy.inference import VariableElimination  # noqa: E402
from pgmpy.models import DiscreteBayesianNetwork  # noqa: E402


def door_world():
    """A door: locked, shut or open; the robot waits, pushes or unlocks.

    The end CPD lists its parents as (action, initial.door), the reverse of ours, and
    its states in another order than the initial node's: from_pgmpy must rearrange both.
    """
    doors = ["locked", "shut", "open"]
    actions = ["wait", "push", "unlock"]
    end_states = ["open", "shut", "locked"]
    bn = DiscreteBayesianNetwork([("initial.door", "end.door"), ("action", "end.door")])
    bn.add_cpds(
        TabularCPD("initial.door", 3, [[0.2], [0.5], [0.3]], state_names={"initial.door": doors}),
        TabularCPD("action", 3, [[0.5], [0.3], [0.2]], state_names={"action": actions}),
    )
    # p(end | action, initial): one column per (action, initial), initial varying fastest
    end = {  # (action, initial) -> p(open), p(shut), p(locked)
        ("wait", "locked"): (0.0, 0.0, 1.0),
        ("wait", "shut"): (0.05, 0.95, 0.0),
        ("wait", "open"): (0.9, 0.1, 0.0),
        ("push", "locked"): (0.0, 0.1, 0.9),
        ("push", "shut"): (0.8, 0.2, 0.0),
        ("push", "open"): (1.0, 0.0, 0.0),
        ("unlock", "locked"): (0.0, 0.9, 0.1),
        ("unlock", "shut"): (0.1, 0.9, 0.0),
        ("unlock", "open"): (0.7, 0.3, 0.0),
    }
    columns = [end[a, d] for a in actions for d in doors]
    bn.add_cpds(
        TabularCPD(
            "end.door",
            3,
            np.array(columns).T,
            evidence=["action", "initial.door"],
            evidence_card=[3, 3],
            state_names={"end.door": end_states, "action": actions, "initial.door": doors},
        )
    )
    bn.check_model()
    return bn


# ----------------------------------------------------------------------------- to_pgmpy
@settings(max_examples=15, deadline=None)
@given(net=discrete_networks(), seed=st.integers(0, 10_000), data=st.data())
def test_pgmpy_answers_equal_ours(net, seed, data):
    params = random_params(net, seed)
    model, left_out = to_pgmpy(net, params)
    assert left_out == ()
    assert model.check_model()
    assert list(model.nodes()) == [s.name for s in net.sites]
    ve = VariableElimination(model)
    initial = {
        f"initial.{f.name}": data.draw(st.sampled_from(f.states)) for f in net.features if f.initial
    }
    action = data.draw(st.sampled_from(net.actions))
    ours = predict(net, params, {k: [v] for k, v in initial.items()} | {"action": [action]})
    for f in net.features:
        states, theirs = pgmpy_marginal(ve, f"end.{f.name}", initial | {"action": action})
        assert tuple(states) == f.states
        torch.testing.assert_close(ours.discrete[f.name][0], theirs, atol=1e-9, rtol=0)
    observed = data.draw(st.sampled_from(net.features))
    end = {f"end.{observed.name}": data.draw(st.sampled_from(observed.states))}
    post = infer_action(net, params, {k: [v] for k, v in (initial | end).items()})
    states, theirs = pgmpy_marginal(ve, "action", initial | end)
    assert tuple(states) == net.actions
    torch.testing.assert_close(post.probs[0], theirs, atol=1e-9, rtol=0)


LEFT_OUT = (
    "initial.position",
    "cluster.force",
    "param.force",
    "end.visible",  # a softmax: its parents include initial.position
    "end.position",
)


def continuous_network():
    return EffectNetwork(
        (Discrete("visible", (False, True)), Continuous("position", 1)),
        ("look", "remove", "tap"),
        (Parameter("force", 0.0, 20.0, 4, ("tap",), "position"),),
    )


def test_a_network_pgmpy_cannot_hold_whole_is_refused_naming_its_sites():
    net = continuous_network()
    with pytest.raises(ValueError) as refused:
        to_pgmpy(net, random_params(net, 0))
    message = str(refused.value)
    assert str(list(LEFT_OUT)) in message and "drop_continuous=True" in message
    for site, why in (
        ("initial.position", "a continuous feature"),
        ("param.force", "an action parameter's value is continuous"),
        ("end.visible", "a softmax CPD with continuous parents ['initial.position']"),
    ):
        assert f"{site}: {why}" in message
    with pytest.raises(ValueError, match=r"sites \['initial.position', 'cluster.force'"):
        write_bif("net.bif", net, random_params(net, 0))


def test_the_discrete_part_on_request_warns_naming_what_it_drops():
    net = continuous_network()
    with pytest.warns(DroppedSites) as caught:
        model, left_out = to_pgmpy(net, random_params(net, 0), drop_continuous=True)
    assert len(caught) == 1 and str(list(LEFT_OUT)) in str(caught[0].message)
    assert left_out == LEFT_OUT
    assert list(model.nodes()) == ["initial.visible", "action"]
    assert model.check_model()


def test_a_table_below_a_left_out_site_is_named_with_its_parent():
    net = EffectNetwork(
        (Discrete("door", ("shut", "open")), Continuous("x", 1), Discrete("lock", (0, 1))),
        ("push", "wait"),
        parents={
            "end.door": ("initial.door", "action", "initial.x"),  # a softmax
            "end.x": ("initial.x",),
            "end.lock": ("initial.lock", "end.door"),  # a table below the softmax
        },
    )
    with pytest.raises(ValueError, match=r"end.lock: a table whose parents \['end.door'\] are"):
        to_pgmpy(net, random_params(net, 0))


# ----------------------------------------------------------------------------- round trips
def assert_same(net, params, net2, params2):
    assert net2 == net
    assert params2.cpds.keys() == params.cpds.keys()
    for site, cpd in params.cpds.items():
        assert torch.equal(params2[site].probs, cpd.probs), site
        assert torch.equal(params2[site].n, cpd.n), site


@settings(max_examples=10, deadline=None)
@given(net=discrete_networks(), seed=st.integers(0, 10_000))
def test_from_pgmpy_gives_back_what_to_pgmpy_wrote(net, seed):
    params = random_params(net, seed, unseen=0.3)
    net2, params2 = from_pgmpy(to_pgmpy(net, params).model, n=counts_of(params))
    assert_same(net, params, net2, params2)
    assert params2.pseudo_count == 0.01


@settings(max_examples=15, deadline=None)
@given(net=declared_networks(), seed=st.integers(0, 10_000), data=st.data())
def test_declared_structures_round_trip_and_answer_as_pgmpy(net, seed, data):
    params = random_params(net, seed, unseen=0.3)
    model, left_out = to_pgmpy(net, params)
    assert left_out == ()
    order = [f.name for f in net.features]
    net2, params2 = from_pgmpy(model, n=counts_of(params), order=order)
    assert_same(net, params, net2, params2)
    ve = VariableElimination(model)
    given_initial = {
        f"initial.{f.name}": data.draw(st.sampled_from(f.states))
        for f in net.features
        if f.initial and data.draw(st.booleans())
    }
    action = data.draw(st.sampled_from(net.actions))
    ev = given_initial | {"action": action}
    ours = predict(net2, params2, {k: [v] for k, v in ev.items()})
    for f in net.features:
        _, theirs = pgmpy_marginal(ve, f"end.{f.name}", ev)
        torch.testing.assert_close(ours.discrete[f.name][0], theirs, atol=1e-9, rtol=0)
    observed = data.draw(st.sampled_from(net.features))
    end = {f"end.{observed.name}": data.draw(st.sampled_from(observed.states))}
    post = infer_action(net2, params2, {k: [v] for k, v in (given_initial | end).items()})
    _, theirs = pgmpy_marginal(ve, "action", given_initial | end)
    torch.testing.assert_close(post.probs[0], theirs, atol=1e-9, rtol=0)


@settings(max_examples=8, deadline=None)
@given(net=declared_networks(), seed=st.integers(0, 10_000))
def test_declared_structures_round_trip_through_bif(net, seed):
    import tempfile
    from pathlib import Path

    params = random_params(net, seed)
    with tempfile.TemporaryDirectory() as tmp:
        path = write_bif(Path(tmp) / "net.bif", net, params)
        states = {f.name: f.states for f in net.features}
        order = [f.name for f in net.features]
        net2, params2 = read_bif(path, n=counts_of(params), states=states, order=order)
    assert net2 == net
    for site in params.cpds:  # BIF writes rounded decimals
        torch.testing.assert_close(params2[site].probs, params[site].probs, atol=1e-6, rtol=0)


def test_bif_round_trip(tmp_path):
    net = EffectNetwork(  # not in name order: BIF sorts its variables
        (
            Discrete("lid", ("on", "off")),
            Discrete("full", (True, False)),
            Discrete("count", (0, 1, 2), initial=False),
        ),
        ("fill", "drink", "open lid"),
    )
    params = random_params(net, 3, unseen=0.3)
    path = write_bif(tmp_path / "cup.bif", net, params)
    states = {f.name: f.states for f in net.features}
    net2, params2 = read_bif(
        path, n=counts_of(params), states=states, order=["lid", "full", "count"]
    )
    assert_same(net, params, net2, params2)
    # without states= the labels are the file's texts, in name order of the features
    net3, params3 = read_bif(path, n=1)
    assert [f.name for f in net3.features] == ["count", "full", "lid"]
    assert net3.feature("full").states == ("True", "False")
    assert net3.feature("count").states == ("0", "1", "2") and not net3.feature("count").initial
    ev = {"initial.lid": ["off"], "action": ["open lid"]}
    torch.testing.assert_close(
        predict(net3, params3, ev | {"initial.full": ["True"]}).discrete["count"],
        predict(net, params, ev | {"initial.full": [True]}).discrete["count"],
        atol=0,
        rtol=0,
    )


def test_bif_refuses_labels_it_cannot_read_back(tmp_path):
    for states, match in [
        (("a,b", "c"), "cannot be written to BIF"),
        ((" a", "b"), "cannot be written to BIF"),
        ((1, "1"), "are both '1'"),
    ]:
        net = EffectNetwork((Discrete("f", states),), ("x", "y"))
        with pytest.raises(ValueError, match=match):
            write_bif(tmp_path / "f.bif", net, random_params(net, 0))
    net = EffectNetwork((Discrete("f", (0, 1)), Discrete("F", (0, 1))), ("x", "y"))
    with pytest.raises(ValueError, match="differ only in case"):
        write_bif(tmp_path / "f.bif", net, random_params(net, 0))


# ----------------------------------------------------------------------------- by hand
def test_door_world_queries_equal_numbers_from_its_cpds():
    n = {
        "initial.door": 40,
        "action": 40,
        "end.door": np.full((3, 3), 5.0),  # (initial.door, action), our parent order
    }
    n["end.door"][0, 1] = 0  # nobody ever pushed a locked door
    net, params = from_pgmpy(door_world(), n=n, kind="world")
    assert net.feature("door") == Discrete("door", ("locked", "shut", "open"), "world")
    assert net.actions == ("wait", "push", "unlock")
    assert net.discrete_parents("door") == ("initial.door", "action")

    pred = predict(net, params, {"initial.door": ["shut", "locked"], "action": ["push", "push"]})
    torch.testing.assert_close(
        pred.discrete["door"],
        torch.tensor([[0.0, 0.2, 0.8], [0.9, 0.1, 0.0]], dtype=DTYPE),
        atol=1e-12,
        rtol=0,
    )
    assert pred.unseen.tolist() == [0.0, 1.0]
    # a shut door ends open: wait 0.5 * 0.05, push 0.3 * 0.8, unlock 0.2 * 0.1 (sum 0.285)
    post = infer_action(net, params, {"initial.door": ["shut"], "end.door": ["open"]})
    torch.testing.assert_close(
        post.probs[0], torch.tensor([5 / 57, 48 / 57, 4 / 57], dtype=DTYPE), atol=1e-12, rtol=0
    )
    assert post.best_names == ("push",)
    # unknown initial state: p(open | unlock) = 0.2 * 0 + 0.5 * 0.1 + 0.3 * 0.7
    pred = predict(net, params, {"action": ["unlock"]})
    assert abs(float(pred.prob("door", "open")[0]) - 0.26) < 1e-12
    assert params.pseudo_count == 0.01 and params["end.door"].n[0, 1] == 0


def test_rounded_columns_are_renormalised_and_broken_ones_refused():
    bn = door_world()
    cpd = bn.get_cpds("initial.door")
    bn.remove_cpds(cpd)
    bn.add_cpds(
        TabularCPD("initial.door", 3, [[0.333], [0.333], [0.333]], state_names=cpd.state_names)
    )
    _, params = from_pgmpy(bn, n=1)
    torch.testing.assert_close(params["initial.door"].probs, torch.full((3,), 1 / 3, dtype=DTYPE))

    bn.remove_cpds(bn.get_cpds("initial.door"))
    bn.add_cpds(TabularCPD("initial.door", 3, [[0.5], [0.5], [0.5]], state_names=cpd.state_names))
    with pytest.raises(ValueError, match=r"check_model refuses.* node initial.door"):
        from_pgmpy(bn, n=1)
    # values changed after pgmpy's constructor checked them: the sum is 1, a value is not
    bn.get_cpds("initial.door").values[:] = [1.2, -0.1, -0.1]
    with pytest.raises(ValueError, match=r"node 'initial.door'.*non-negative probabilities"):
        from_pgmpy(bn, n=1)


# ----------------------------------------------------------------------------- refused
def edited(edges, nodes=()):
    """A bare graph, no CPDs: from_pgmpy checks the structure before any CPD."""
    bn = DiscreteBayesianNetwork(edges)
    bn.add_nodes_from(nodes)
    return bn


def two_feature_world(extra_edges=(), drop=()):
    nodes = ["initial.a", "initial.b", "action", "end.a", "end.b"]
    edges = [(p, e) for p in ("initial.a", "initial.b", "action") for e in ("end.a", "end.b")]
    edges = [e for e in edges if e not in drop] + list(extra_edges)
    bn = DiscreteBayesianNetwork()
    bn.add_nodes_from(nodes)
    bn.add_edges_from(edges)
    return bn


@pytest.mark.parametrize(
    ("bn", "match"),
    [
        (
            two_feature_world(extra_edges=[("initial.a", "action")]),
            r"node 'action' \(the action\) has parents \['initial.a'\]; .* the action is a root",
        ),
        (
            two_feature_world(extra_edges=[("end.a", "initial.b")], drop=[("initial.b", "end.a")]),
            r"node 'initial.b' has parents \['end.a'\]; an initial node's parents can only be",
        ),
        (
            two_feature_world(extra_edges=[("action", "initial.b")]),
            r"node 'initial.b' has parents \['action'\]; an initial node's parents can only be",
        ),
        (
            edited([("weather", "end.a"), ("action", "end.a")]),
            r"node 'weather' is not an effect-network site",
        ),
        (
            edited([("action", "cluster.force"), ("cluster.force", "end.a")]),
            r"node 'cluster.force': an action parameter has a continuous value",
        ),
        (edited([("initial.a", "end.a")]), r"no action node 'action'"),
        (edited([("action", "end.a")], ["initial.b"]), r"'initial.b' has no end node 'end.b'"),
    ],
)
def test_bad_structures_are_refused_naming_the_node(bn, match):
    with pytest.raises(ValueError, match=match):
        from_pgmpy(bn, n=1)


def test_missing_cpds_and_bad_counts_are_refused():
    bn = door_world()
    bn.remove_cpds(bn.get_cpds("end.door"))
    with pytest.raises(ValueError, match="node 'end.door' has no CPD"):
        from_pgmpy(bn, n=1)
    bn = door_world()
    with pytest.raises(ValueError, match=r"missing \['end.door'\], unknown \['end.dor'\]"):
        from_pgmpy(bn, n={"initial.door": 1, "action": 1, "end.dor": 1})
    with pytest.raises(ValueError, match=r"n\['end.door'\] has shape \(3,\); expected \(3, 3\)"):
        from_pgmpy(bn, n={"initial.door": 1, "action": 1, "end.door": np.ones(3)})
    with pytest.raises(ValueError, match=r"n\['action'\] must be finite and >= 0"):
        from_pgmpy(bn, n={"initial.door": 1, "action": -1, "end.door": 1})
    with pytest.raises(ValueError, match="no action node 'act'"):
        from_pgmpy(bn, n=1, actions_node="act")
    with pytest.raises(ValueError, match="pseudo_count must be a finite number >= 0, got -1"):
        from_pgmpy(bn, n=1, pseudo_count=-1)
    assert from_pgmpy(bn, n=1, pseudo_count=0.5)[1].pseudo_count == 0.5
    with pytest.raises(ValueError, match=r"kind names unknown features \['window'\]"):
        from_pgmpy(bn, n=1, kind={"window": "world"})
    with pytest.raises(ValueError, match=r"order \['window'\] must list every feature once"):
        from_pgmpy(bn, n=1, order=["window"])


def test_actions_node_by_another_name_and_int_states():
    """pgmpy's default state names are 0..K-1; the action's become the names '0', '1'."""
    bn = DiscreteBayesianNetwork([("initial.x", "end.x"), ("do", "end.x")])
    bn.add_cpds(
        TabularCPD("initial.x", 2, [[0.4], [0.6]]),
        TabularCPD("do", 2, [[0.5], [0.5]]),
        TabularCPD(
            "end.x", 2, [[1.0, 0.0, 0.3, 0.0], [0.0, 1.0, 0.7, 1.0]], ["initial.x", "do"], [2, 2]
        ),
    )
    net, params = from_pgmpy(bn, n=2, actions_node="do")
    assert net.actions == ("0", "1") and net.feature("x").states == (0, 1)
    pred = predict(net, params, {"initial.x": [1, 1], "action": ["0", "1"]})
    torch.testing.assert_close(
        pred.discrete["x"], torch.tensor([[0.3, 0.7], [0.0, 1.0]], dtype=DTYPE)
    )


def test_missing_pgmpy_says_how_to_install_it(monkeypatch):
    for name in ("pgmpy", "pgmpy.models", "pgmpy.factors.discrete"):
        monkeypatch.setitem(sys.modules, name, None)
    net = EffectNetwork((Discrete("f", (0, 1)),), ("x", "y"))
    with pytest.raises(ImportError, match="pip install pgmpy"):
        to_pgmpy(net, random_params(net, 0))


def test_every_column_of_pgmpy_matches_our_table_axis_order():
    """pgmpy's first evidence variable varies slowest, as our row-major table does."""
    net = EffectNetwork((Discrete("a", ("p", "q", "r")), Discrete("b", (1, 2))), ("u", "v"))
    params = random_params(net, 5)
    model, _ = to_pgmpy(net, params)
    cpd = model.get_cpds("end.a")
    assert cpd.variables == ["end.a", "initial.a", "initial.b", "action"]
    for (i, a), (j, b), (k, u) in itertools.product(
        enumerate(("p", "q", "r")), enumerate((1, 2)), enumerate(("u", "v"))
    ):
        for m, state in enumerate(("p", "q", "r")):  # pgmpy looks up by state name
            theirs = cpd.get_value(**{"end.a": state, "initial.a": a, "initial.b": b, "action": u})
            assert theirs == float(params["end.a"].probs[i, j, k, m])
