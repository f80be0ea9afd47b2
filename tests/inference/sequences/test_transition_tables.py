"""Joint transitions against a brute force over the traced model's full joint.

The oracle traces :func:`models.model.effect_model` with every discrete site observed,
one row per configuration (initial states, action, cluster, end states, end-only
features), and sums the rows' joint probabilities by hand: it shares no code with the
tables, gathers and eliminations :func:`inference.sequences.transition_tables.transitions` runs.
"""

from __future__ import annotations

import itertools

import pytest
import torch
from effect_networks.inference import compile as compile_queries
from effect_networks.inference import fit, plan
from effect_networks.inference.sequences.states import StateSpace
from effect_networks.inference.sequences.transition_tables import model_tables, transitions
from effect_networks.models import Continuous, Discrete, EffectNetwork, Parameter, random_params
from effect_networks.models.model import effect_model
from hypothesis import given, settings
from hypothesis import strategies as st
from pyro import poutine

from tests.networks import DOOR, LOCK, NOISE, rich_net, rich_rows


def brute_force(net, params, given, clusters: bool):
    """``(probs (S, A, S), unseen (S, A))`` over the product state space, by one trace of
    the model per configuration of every discrete site (observed)."""
    space = StateSpace.of(net)
    discrete = [s for s in net.sites if s.discrete]
    sizes = [s.size for s in discrete]
    configs = torch.tensor(list(itertools.product(*(range(k) for k in sizes))))
    n = len(configs)
    data = {s.name: configs[:, i] for i, s in enumerate(discrete)}
    for f, v in given.items():
        data[f"initial.{f}"] = torch.tensor(v, dtype=torch.float64).expand(n, -1)
    enc = net.encode_indices(data)
    trace = poutine.trace(effect_model).get_trace(net, params, enc, collapse=True)
    trace.compute_log_prob()
    log_joint = torch.zeros(n, dtype=torch.float64)
    for name, node in trace.nodes.items():
        if node["type"] == "sample" and name != "rows":
            if net.site(name).role in ("end", "cluster", "param"):
                if name.startswith("cluster.") and clusters:
                    continue  # the cluster is chosen, not drawn
                log_joint = log_joint + node["log_prob"].expand(n)
    unseen = torch.zeros(n, dtype=torch.bool)
    for s in net.sites:
        if s.role == "end" and s.discrete:
            cpd = net.cpd(s.name)
            seen = cpd.seen(params[s.name])
            unseen |= ~seen[tuple(data[q] for q in cpd.parents)]
    names = [s.name for s in discrete]
    col = {q: names.index(q) for q in names}
    feats = space.names
    s_of = lambda prefix: [  # noqa: E731
        space.index_of(tuple(net.feature(f).states[int(c[col[f"{prefix}.{f}"]])] for f in feats))
        for c in configs
    ]
    s0, s1 = torch.tensor(s_of("initial")), torch.tensor(s_of("end"))
    action = configs[:, col["action"]]
    if clusters:
        m = net.mixtures[0]
        c = configs[:, col[m.cluster.site]]
        offered = []
        for a in range(len(net.actions)):
            offered += [(a, k) for k in range(m.parameter.n_clusters)] if m.uses[a] else [(a, 0)]
        pairs = [(int(x), int(y)) for x, y in zip(action, c, strict=True)]
        possible = torch.tensor([p in offered for p in pairs])  # unused parameter: cell 0
        a_of = torch.tensor([offered.index(p) if p in offered else 0 for p in pairs])
        log_joint = torch.where(possible, log_joint, -torch.inf)
    else:
        a_of = action
    w = log_joint.exp()
    s, a = len(space), int(a_of.max()) + 1
    probs = torch.zeros(s, a, s, dtype=torch.float64).index_put_((s0, a_of, s1), w, accumulate=True)
    bad = torch.zeros(s, a, dtype=torch.float64).index_put_((s0, a_of), w * unseen, accumulate=True)
    total = probs.sum(-1, keepdim=True)
    return probs / total, bad / total[..., 0]


@pytest.fixture(scope="module")
def fitted():
    net = rich_net()
    return net, fit(net, rich_rows(net, 400, 0)).params


@pytest.mark.parametrize("mode", ["integrate", "clusters"])
def test_transitions_equal_the_brute_force_joint(fitted, mode):
    net, params = fitted
    given = {"x": [0.3]}
    t = transitions(net, params, given=given, parameter_values=mode)
    probs, unseen = brute_force(net, params, given, mode == "clusters")
    assert t.probs.shape == probs.shape
    torch.testing.assert_close(t.probs, probs, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(t.unseen, unseen, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(t.outside, torch.zeros_like(t.outside), rtol=0, atol=1e-12)
    if mode == "clusters":
        assert t.actions == ("push[force=0]", "push[force=1]", "push[force=2]", "unlock", "wait")
        assert t.choices[1]["cluster.force"] == 1 and len(t.choices[1]["param.force"]) == 1


def test_the_joint_is_not_the_product_of_the_marginals(fitted):
    """The lock's end reads the door's end: a product of marginals would be wrong."""
    net, params = fitted
    t = transitions(net, params, given={"x": [0.3]})
    p = t.probs.reshape(4, 3, 2, 2)  # next state = (door, lock)
    product = p.sum(-1, keepdim=True) * p.sum(-2, keepdim=True)
    assert (p - product).abs().max() > 1e-3


def test_unseen_pairs_are_reported_and_a_subset_reports_its_outside_mass():
    net = EffectNetwork(
        features=(Discrete("door", DOOR), Discrete("lock", LOCK)), actions=("push", "wait")
    )
    rows = {
        "initial.door": ["shut"] * 6,
        "initial.lock": ["off"] * 6,
        "action": ["push"] * 3 + ["wait"] * 3,
        "end.door": ["open"] * 3 + ["shut"] * 3,
        "end.lock": ["off"] * 6,
    }
    params = fit(net, rows).params
    t = transitions(net, params)
    start = t.space.index_of(("shut", "off"))
    assert t.unseen[start].tolist() == [0.0, 0.0]
    others = [i for i in range(4) if i != start]
    assert bool((t.unseen[others] == 1).all())
    assert t.prob(("shut", "off"), "push", ("open", "off")) > 0.9
    sub = transitions(net, params, states=[("shut", "off"), ("open", "off")])
    assert sub.probs.shape == (2, 2, 2)
    full = t.probs[:, :, [start, t.space.index_of(("open", "off"))]][[start, 2]]
    torch.testing.assert_close(sub.probs, full)
    torch.testing.assert_close(sub.outside, 1 - full.sum(-1))
    assert sub.next_states(("shut", "off"), "push")  # labels, most likely first
    within = transitions(net, params, states=[("shut", "off"), ("open", "off")], normalise=True)
    torch.testing.assert_close(within.probs, full / full.sum(-1, keepdim=True))
    torch.testing.assert_close(within.outside, sub.outside)
    assert "2 states" in repr(sub)


def test_a_continuous_initial_feature_must_be_given(fitted):
    net, params = fitted
    with pytest.raises(ValueError, match="'x'"):
        transitions(net, params)
    with pytest.raises(ValueError, match="given\\['x'\\]"):
        transitions(net, params, given={"x": [0.1, 0.2]})
    with pytest.raises(ValueError, match="parameter_values"):
        transitions(net, params, given={"x": [0.0]}, parameter_values="mean")


def test_the_door_changes_with_the_given_context(fitted):
    from effect_networks.inference import OutsideTrainingData

    net, params = fitted
    with pytest.warns(OutsideTrainingData, match="initial.x"):
        transitions(net, params, given={"x": [40.0]})
    a = transitions(net, params, given={"x": [-2.0]})
    b = transitions(net, params, given={"x": [2.0]})
    assert not torch.allclose(a.probs, b.probs)
    tables = model_tables(net, params, {"x": [2.0]})
    torch.testing.assert_close(transitions(net, params, tables=tables).probs, b.probs)


@st.composite
def small_networks(draw):
    """One or two state features, maybe an end-only feature and a parameter acting on
    the first, maybe end -> end parents; random tables, some configurations unseen."""
    features = [Discrete("f", ("a", "b", "c")[: draw(st.integers(2, 3))])]
    parents = {}
    if draw(st.booleans()):
        features.append(Discrete("g", ("x", "y")))
        g_parents = draw(st.sampled_from([None, ("initial.g", "action", "end.f"), ()]))
        if g_parents is not None:  # an end -> end parent, or none at all
            parents["end.g"] = g_parents
    if draw(st.booleans()):
        features.append(Discrete("h", ("lo", "hi"), initial=False))
        parents["end.f"] = ("initial.f", "action", "end.h")
    parameters = ()
    if draw(st.booleans()):
        parameters = (Parameter("p", low=0.0, high=1.0, bins=2, actions=("a1",), affects="f"),)
    net = EffectNetwork(
        features=tuple(features), actions=("a0", "a1"), parameters=parameters, parents=parents
    )
    seed = draw(st.integers(0, 2**16))
    return (
        net,
        random_params(net, seed, unseen=0.3),
        draw(st.sampled_from(["integrate", "clusters"])),
    )


@settings(max_examples=10, deadline=None)
@given(small_networks())
def test_transitions_of_drawn_networks_equal_the_brute_force(drawn):
    net, params, mode = drawn
    if mode == "clusters" and not net.mixtures:
        mode = "integrate"
    t = transitions(net, params, parameter_values=mode)
    probs, unseen = brute_force(net, params, {}, mode == "clusters")
    torch.testing.assert_close(t.probs, probs, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(t.unseen, unseen, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(t.probs.sum(-1), torch.ones_like(t.outside))


def test_transitions_equal_pgmpy_variable_elimination():
    """An all-discrete network with an end -> end parent and an end-only feature, beside
    pgmpy's VariableElimination on the same tables (no Pyro model involved)."""
    pytest.importorskip("pgmpy")
    from effect_networks.models.interop import to_pgmpy
    from pgmpy.inference import VariableElimination

    net = EffectNetwork(
        features=(
            Discrete("door", DOOR),
            Discrete("lock", LOCK),
            Discrete("noise", NOISE, initial=False),
        ),
        actions=("push", "unlock", "wait"),
        parents={
            "end.lock": ("initial.lock", "action", "end.door", "end.noise"),
            "end.door": ("initial.door", "action", "end.noise"),
        },
    )
    params = random_params(net, 7)
    t = transitions(net, params)
    ve = VariableElimination(to_pgmpy(net, params).model)
    sites = ["initial.door", "initial.lock", "action", "end.door", "end.lock"]
    joint = ve.query(sites, show_progress=False)  # one query: the joint of the five
    for s, state in enumerate(t.space.states):
        for a, action in enumerate(t.actions):
            given = {"initial.door": state[0], "initial.lock": state[1], "action": action}
            cells = [
                joint.get_value(**given, **{"end.door": door, "end.lock": lock})
                for door, lock in t.space.states
            ]
            expected = torch.tensor(cells, dtype=torch.float64) / sum(cells)
            torch.testing.assert_close(t.probs[s, a], expected, rtol=1e-9, atol=1e-12)


def test_the_compiled_transitions_and_plan_keep_their_tables(fitted):
    from effect_networks import inference

    net, params = fitted
    compiled = inference.compile(net, params)
    direct = transitions(net, params, given={"x": [0.3]}, parameter_values="clusters")
    first = compiled.transitions(given={"x": [0.3]}, parameter_values="clusters")
    torch.testing.assert_close(first.probs, direct.probs)
    torch.testing.assert_close(first.unseen, direct.unseen)
    again = compiled.transitions(given={"x": [0.3]}, states=[("open", "on"), ("shut", "off")])
    assert again.probs.shape == (2, 3, 2)
    assert sum(1 for k in compiled._built if k[0] == "tables") == 1
    p = compiled.plan(("shut", "off"), {"door": "open"}, 2, given={"x": [0.3]})
    q = inference.plan(net, params, ("shut", "off"), {"door": "open"}, 2, given={"x": [0.3]})
    assert p.success == pytest.approx(q.success, abs=1e-12) and p.path == q.path
    sub = [("shut", "off"), ("open", "off")]
    r = compiled.plan(sub[0], {"door": "open"}, 1, states=sub, normalise=True, given={"x": [0.3]})
    within = transitions(net, params, states=sub, normalise=True, given={"x": [0.3]})
    assert r.success == pytest.approx(float(within.probs[0, :, 1].max()), abs=1e-12)


def test_a_state_space_too_large_to_hold_is_refused_with_advice():
    many = tuple(range(60))
    net = EffectNetwork(  # 3,600 states x 20 actions x 3,600 next states
        features=(Discrete("a", many), Discrete("b", many)),
        actions=tuple(f"act{i}" for i in range(20)),
    )
    with pytest.raises(ValueError, match="pass states="):
        transitions(net, random_params(net, 0))
    few = transitions(net, random_params(net, 0), states=[(0, 0), (1, 2)])
    assert few.probs.shape == (2, 20, 2)


# ------------------------------------------------ a context value that is not a number
def _context_network():
    net = EffectNetwork(
        features=(Discrete("visible", (False, True)), Continuous("position", 1)),
        actions=("look", "remove"),
    )
    return net, random_params(net, 0)


BAD_CONTEXTS = st.one_of(
    st.none(),
    st.text(max_size=3),
    st.lists(st.text(min_size=1, max_size=2), min_size=1, max_size=2),
    st.lists(st.booleans(), min_size=1, max_size=1),
    st.lists(st.none(), min_size=1, max_size=1),
    st.sampled_from([[float("nan")], [float("inf")], [1e200], [[1.0, 2.0]], [], [1.0, 2.0]]),
)


@settings(max_examples=60, deadline=None)
@given(bad=BAD_CONTEXTS, route=st.sampled_from(["transitions", "plan", "compiled"]))
def test_a_context_that_is_not_one_number_is_named_with_what_it_should_be(bad, route):
    """Text, None, labels, non-finite or huge numbers, the wrong length: each refused with
    an error naming given['position'] and what it must be, by every sequence question."""
    net, params = _context_network()
    ask = {
        "transitions": lambda: transitions(net, params, given={"position": bad}),
        "plan": lambda: plan(
            net,
            params,
            {"visible": True},
            {"visible": False},
            horizon=1,
            given={"position": bad},
        ),
        "compiled": lambda: compile_queries(net, params).transitions(given={"position": bad}),
    }[route]
    with pytest.raises(ValueError, match=r"given\['position'\] must be 1 finite number"):
        ask()
