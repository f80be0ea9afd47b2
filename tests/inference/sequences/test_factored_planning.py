"""Plans by the network's structure against the dense planner and brute force.

The projected route must give the dense planner's values at every state (1e-12), the
best any policy achieves (brute force over every policy on small networks), and the
approximate route a lower bound that holds for its policy evaluated exactly.
"""

from __future__ import annotations

import itertools
import time
import warnings

import pytest
import torch
from effect_networks.experiments.switch_worlds import switch_world
from effect_networks.inference import fit
from effect_networks.inference.sequences import dynamic_programming
from effect_networks.inference.sequences.dynamic_programming import policy_value
from effect_networks.inference.sequences.planner import RestsOnUnseen, plan
from effect_networks.inference.sequences.states import StateSpace, state_features
from effect_networks.inference.sequences.transition_tables import transitions
from effect_networks.models import Discrete, EffectNetwork, random_params
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.networks import declared_networks, rich_net, rich_rows


def _quiet(fn, *args, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RestsOnUnseen)
        return fn(*args, **kw)


@st.composite
def planning_questions(draw):
    net = draw(declared_networks())
    features = state_features(net)
    params = random_params(net, draw(st.integers(0, 2**16)), unseen=0.3)
    names = [f.name for f in features]
    chosen = draw(st.lists(st.sampled_from(names), min_size=1, max_size=len(names), unique=True))
    goal = {n: draw(st.sampled_from(net.feature(n).states)) for n in chosen}
    start = tuple(draw(st.sampled_from(f.states)) for f in features)
    horizon = draw(st.integers(1, 4))
    return net, params, start, goal, horizon


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(planning_questions(), st.booleans())
def test_the_projected_plan_has_the_dense_values_at_every_state(question, avoid):
    net, params, start, goal, horizon = question
    dense = _quiet(plan, net, params, start, goal, horizon, route="dense")
    factored = _quiet(plan, net, params, start, goal, horizon, route="factored")
    assert factored.route == "projected"
    assert factored.success == pytest.approx(dense.success, abs=1e-12)
    for h in range(1, horizon + 1):
        for state in dense.space.states:
            assert factored.probability(state, h) == pytest.approx(
                dense.probability(state, h), abs=1e-12
            )
    assert 0.0 <= factored.unseen <= 1.0
    if set(factored.features) == set(dense.features):  # nothing projected away
        # the same states in the same order: where both choose the same actions (ties may
        # be broken apart by rounding), the same unseen share
        if torch.equal(factored.policy, dense.policy):
            assert factored.unseen == pytest.approx(dense.unseen, abs=1e-12)
        a = _quiet(plan, net, params, start, goal, horizon, route="dense", avoid_unseen=avoid)
        b = _quiet(plan, net, params, start, goal, horizon, route="factored", avoid_unseen=avoid)
        assert b.success == pytest.approx(a.success, abs=1e-12)


def test_the_projected_plan_is_the_best_of_every_policy():
    net = EffectNetwork(
        (Discrete("door", ("shut", "open")), Discrete("lock", ("on", "off"))),
        ("push", "unlock", "wait"),
        parents={"end.door": ("initial.door", "initial.lock", "action")},
    )
    params = random_params(net, 7)
    t = transitions(net, params)
    goal = {"door": "open"}
    mask = t.space.mask(goal)
    start = ("shut", "on")
    best = 0.0
    s, a = len(t.space), len(t.actions)
    for rows in itertools.product(itertools.product(range(a), repeat=s), repeat=2):
        policy = torch.tensor([[-1] * s, *rows])
        value = policy_value(t.probs, policy, mask, 2)
        best = max(best, float(value[2, t.space.index_of(start)]))
    factored = plan(net, params, start, goal, 2, route="factored")
    assert factored.success == pytest.approx(best, abs=1e-12)


def test_a_partial_start_is_weighed_by_the_initial_tables_as_the_dense_route_weighs_it():
    net = EffectNetwork(
        (Discrete("a", (0, 1, 2)), Discrete("b", (0, 1)), Discrete("c", (0, 1))),
        ("x", "y"),
        parents={
            "initial.b": ("initial.a",),
            "end.a": ("initial.a", "initial.b", "action"),
            "end.b": ("initial.b", "action"),
            "end.c": ("initial.c", "action"),
        },
    )
    params = random_params(net, 11)
    dense = _quiet(plan, net, params, {"c": 1}, {"a": 2}, 3, route="dense")
    factored = _quiet(plan, net, params, {"c": 1}, {"a": 2}, 3, route="factored")
    assert factored.features == ("a", "b")
    assert factored.success == pytest.approx(dense.success, abs=1e-12)


def test_the_sparse_world_plans_by_its_structure_as_the_dense_planner_does():
    world = switch_world(8, "sparse")
    dense = plan(world.net, world.params, world.start, world.goal, 5, route="dense")
    auto = plan(world.net, world.params, world.start, world.goal, 5)
    assert auto.route == "projected" and auto.model is None
    assert auto.features == ("f0", "f1", "f2", "f3")
    assert auto.success == pytest.approx(dense.success, abs=1e-12)
    assert auto.action(world.start) in {"flip_0", "flip_1", "flip_2"}
    assert auto.path[0] == ("off",) * 4 and auto.path[-1][:3] == ("on",) * 3
    assert len(auto.to_dict()) > 0


def test_sixty_four_features_plan_in_a_blink():
    world = switch_world(64, "sparse")
    t0 = time.perf_counter()
    out = plan(world.net, world.params, world.start, world.goal, 6)
    assert time.perf_counter() - t0 < 30  # a refusal or a dense tensor would never end
    small = plan(*(lambda w: (w.net, w.params, w.start, w.goal))(switch_world(8, "sparse")), 6)
    assert out.success == pytest.approx(small.success, abs=1e-12)  # the same four features


def test_the_approximate_plan_certifies_a_lower_bound_for_its_own_policy():
    world = switch_world(9, "coupled")
    out = plan(world.net, world.params, world.start, world.goal, 8, budget=1 << 8, seed=3)
    assert out.route == "approximate" and out.certificate is not None
    assert out.features == tuple(f"f{i}" for i in range(8))
    again = plan(world.net, world.params, world.start, world.goal, 8, budget=1 << 8, seed=3)
    assert again.certificate == out.certificate  # the seed reproduces it
    # the policy, read on the full states, evaluated exactly
    t = transitions(world.net, world.params)
    policy = torch.stack(
        [
            torch.tensor(
                [
                    out.policy[min(h, out.policy.shape[0] - 1), out.space.index_of(s)]
                    for s in t.space.states
                ]
            )
            for h in range(9)
        ]
    )
    mask = t.space.mask(world.goal)
    exact = float(policy_value(t.probs, policy, mask, 8)[8, t.space.index_of(world.start)])
    c = out.certificate
    sigma = (exact * (1 - exact) / c.episodes) ** 0.5
    assert abs(c.estimate - exact) < 5 * sigma + 1e-9
    assert out.success == c.lower <= exact + 1e-9
    best = plan(world.net, world.params, world.start, world.goal, 8, route="factored")
    assert best.route == "projected" and exact <= best.success + 1e-12


def test_a_huge_horizon_is_answered_where_the_values_stop_changing():
    net = EffectNetwork((Discrete("door", ("shut", "open")),), ("push", "wait"))
    params = random_params(net, 1)
    t0 = time.perf_counter()
    far = plan(net, params, ("shut",), {"door": "open"}, 10**6)
    assert time.perf_counter() - t0 < 30
    assert far.converged is not None and far.converged < 200
    near = plan(net, params, ("shut",), {"door": "open"}, far.converged)
    assert far.success == near.success
    assert far.action(("shut",), 10**6) == near.action(("shut",))


def test_a_horizon_whose_values_keep_changing_past_the_limit_is_refused(monkeypatch):
    monkeypatch.setattr(dynamic_programming, "MAX_HORIZON", 3)
    net = EffectNetwork((Discrete("door", ("shut", "open")),), ("push", "wait"))
    params = random_params(net, 1)
    with pytest.raises(ValueError, match="still change after 3"):
        dynamic_programming.exact_plan(transitions(net, params).probs, 1, 50)


@pytest.mark.parametrize("route", ["dense", "factored"])
def test_a_plan_through_steps_no_row_reached_says_so(route):
    world = switch_world(4, "sparse", unseen=("flip_0",))
    with pytest.warns(RestsOnUnseen, match="no training row reached"):
        bold = plan(world.net, world.params, world.start, {"f0": "on"}, 3, route=route)
    assert bold.action(world.start) == "flip_0" and bold.unseen == pytest.approx(1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RestsOnUnseen)
        careful = plan(
            world.net, world.params, world.start, {"f0": "on"}, 3, route=route, avoid_unseen=True
        )
    assert careful.unseen == 0.0 and careful.success < bold.success


def test_factored_routes_refuse_what_only_the_dense_tensor_answers():
    world = switch_world(4, "sparse")
    space = StateSpace.of(world.net)
    with pytest.raises(ValueError, match="route='dense'"):
        plan(
            world.net,
            world.params,
            world.start,
            world.goal,
            2,
            states=space.states,
            route="factored",
        )
    with pytest.raises(ValueError, match="dense route"):
        plan(world.net, world.params, lambda s: True, world.goal, 2, route="factored")
    with pytest.raises(ValueError, match="route must be"):
        plan(world.net, world.params, world.start, world.goal, 2, route="fast")
    big = switch_world(20, "sparse")
    with pytest.raises(ValueError, match="a predicate goal reads every feature"):
        plan(big.net, big.params, big.start, lambda s: s["f0"] == "on", 2)


@pytest.mark.parametrize("mode", ["integrate", "clusters"])
def test_a_network_with_clusters_a_context_and_an_outcome_plans_alike_on_both_routes(mode):
    net = rich_net()
    params = fit(net, rich_rows(net, 400, 0)).params
    kw = {"given": {"x": [0.3]}, "parameter_values": mode}
    for goal in ({"door": "open"}, {"lock": "on"}, {"door": "open", "lock": "off"}):
        dense = _quiet(plan, net, params, ("shut", "off"), goal, 3, route="dense", **kw)
        factored = _quiet(plan, net, params, ("shut", "off"), goal, 3, route="factored", **kw)
        assert factored.success == pytest.approx(dense.success, abs=1e-12)
        assert factored.actions == dense.actions
        for state in dense.space.states:
            assert factored.probability(state) == pytest.approx(dense.probability(state), abs=1e-12)
