"""Learning from demonstrations whose actions were not labelled.

Against a fit on the same steps fully labelled, one EM step written by hand from the
brute-force posterior over each step's action, and the true tables of a switch world.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch
from effect_networks.experiments.switch_worlds import switch_world
from effect_networks.inference import fit
from effect_networks.inference.sequences.demonstration import simulate_demonstrations
from effect_networks.inference.watching import fit_demonstrations
from effect_networks.models import Continuous, Discrete, EffectNetwork, random_params
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.networks import declared_networks, tap_net


@pytest.fixture(scope="module")
def watched():
    world = switch_world(4, "sparse")
    states, actions = simulate_demonstrations(world.net, world.params, 200, 5, seed=1)
    return world, states, actions


def _weighted_tv(a, b, site):
    d = (a[site].probs - b[site].probs).abs().sum(-1) / 2
    n = b[site].n
    return float((d * n).sum() / n.sum())


def test_fully_labelled_demonstrations_fit_as_their_steps_do(watched):
    world, states, actions = watched
    got = fit_demonstrations(world.net, states, actions)
    names = [f.name for f in world.net.features]
    rows = {f"initial.{f}": states[f][:, :-1].reshape(-1) for f in names}
    rows |= {f"end.{f}": states[f][:, 1:].reshape(-1) for f in names}
    rows["action"] = actions.reshape(-1)
    want = fit(world.net, rows).params
    for site in want.cpds:
        torch.testing.assert_close(got.params[site].probs, want[site].probs, rtol=0, atol=1e-9)
    assert got.identifiable and got.labelled == got.steps == 1000


def test_a_tenth_labelled_learns_the_labelled_fit_s_tables(watched):
    world, states, actions = watched
    labels = np.where(np.random.default_rng(0).random(actions.shape) < 0.1, actions, None)
    full = fit_demonstrations(world.net, states, actions).params
    got = fit_demonstrations(world.net, states, labels)
    assert got.identifiable and 50 < got.labelled < 150
    curve = got.log_likelihoods
    assert all(b >= a - 1e-9 for a, b in zip(curve, curve[1:], strict=False))
    for site in full.cpds:
        assert _weighted_tv(got.params, full, site) < 0.06, site
    assert got.agreement > 0.8 and 0 < got.confidence <= 1


def test_one_em_step_is_the_brute_force_posterior_s_counts():
    net = EffectNetwork((Discrete("door", ("shut", "open")),), ("push", "wait"))
    init = random_params(net, 5)
    demos = [
        [{"door": "shut"}, {"door": "open"}, {"door": "open"}],
        [{"door": "shut"}, {"door": "shut"}, {"door": "open"}],
        [{"door": "open"}, {"door": "open"}, {"door": "open"}],
    ]
    got = fit_demonstrations(net, demos, init=init, steps=1, pseudo_count=0.0).params
    # by hand: each step's posterior over the action, then the weighted counts
    index = {"shut": 0, "open": 1}
    counts = torch.zeros(2, 2, 2, dtype=torch.float64)  # (initial, action, end)
    prior = torch.zeros(2, dtype=torch.float64)
    for demo in demos:
        for a, b in zip(demo, demo[1:], strict=False):
            s, e = index[a["door"]], index[b["door"]]
            joint = init["action"].probs * init["end.door"].probs[s, :, e]
            post = joint / joint.sum()
            counts[s, :, e] += post
            prior += post
    want = counts / counts.sum(-1, keepdim=True)
    torch.testing.assert_close(got["end.door"].probs, want, rtol=0, atol=1e-12)
    torch.testing.assert_close(got["action"].probs, prior / prior.sum(), rtol=0, atol=1e-12)


def test_without_labels_the_actions_are_named_by_a_reference(watched):
    world, states, actions = watched
    with pytest.warns(UserWarning, match="up to a relabelling"):
        blind = fit_demonstrations(world.net, states)
    assert not blind.identifiable and np.isnan(blind.confidence)
    named = fit_demonstrations(world.net, states, reference=world.params)
    assert named.identifiable
    full = fit_demonstrations(world.net, states, actions).params
    for site in ("end.f0", "end.f1", "end.f2", "end.f3"):
        assert _weighted_tv(named.params, full, site) < 0.1, site


def test_hidden_state_values_beside_what_their_em_does_not_cover_are_refused():
    world = switch_world(4, "sparse")
    demo = [dict.fromkeys(("f0", "f1", "f2", "f3"), "off") for _ in range(3)]
    demo[1] = {**demo[1], "f2": None}
    got = fit_demonstrations(world.net, [demo], [["wait", None]], steps=3)
    assert got.steps == 2 and got.labelled == 1
    rows = {s.name: ["off"] for s in world.net.sites if s.name != "action"} | {"action": ["wait"]}
    beside = fit_demonstrations(world.net, [demo], rows=rows, steps=3)  # rows join the fit
    curve = beside.log_likelihoods
    assert beside.identifiable and all(b >= a for a, b in zip(curve, curve[1:], strict=False))
    # the default structure reads x into end.door: a softmax, which has no closed form
    net = EffectNetwork((Discrete("door", ("shut", "open")), Continuous("x", 1)), ("push", "wait"))
    hidden = [{"door": None, "x": [0.0]}, {"door": "open", "x": [1.0]}]
    with pytest.raises(ValueError, match=r"sites without a closed form \['end.door'\]"):
        fit_demonstrations(net, [hidden])
    with pytest.raises(ValueError, match=r"time 1 hides continuous 'x'"):
        fit_demonstrations(net, [[hidden[0], {"door": "open", "x": None}]])
    with pytest.raises(ValueError, match="not one of"):
        fit_demonstrations(world.net, [demo[:1] * 2], [["jump"]])
    with pytest.raises(ValueError, match="adaptive layout"):
        fit_demonstrations(tap_net(), [[{"visible": 1}, {"visible": 0}]])


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(declared_networks(), st.integers(0, 2**16), st.data())
def test_one_em_step_is_brute_force_over_every_action_and_hidden_outcome(net, seed, data):
    """On drawn networks (end -> end parents, outcome features): one EM step from drawn
    tables equals the counts of every step's every action and hidden outcome, weighted by
    their posterior, written out by hand."""
    init = random_params(net, seed)
    g = np.random.default_rng(seed)
    states = [f for f in net.features if f.initial]
    outcomes = [f for f in net.features if not f.initial]
    demos, labels = [], []
    for _ in range(3):
        demo = []
        for t in range(3):
            state = {f.name: f.states[g.integers(f.cardinality)] for f in states}
            if t:
                for f in outcomes:
                    hide = data.draw(st.booleans())
                    state[f.name] = None if hide else f.states[g.integers(f.cardinality)]
            demo.append(state)
        demos.append(demo)
        labels.append([data.draw(st.sampled_from([None, *net.actions])) for _ in range(2)])
    got = fit_demonstrations(net, demos, labels, init=init, steps=1, tol=1e-300)
    if len(got.log_likelihoods) < 2:
        return  # the step would have lowered the likelihood (a pseudo-count's pull): not taken
    sites = [s.name for s in net.sites]
    counts = {s: torch.zeros_like(init[s].probs) for s in sites}
    for demo, marks in zip(demos, labels, strict=True):
        for t in range(2):
            fixed = {f"initial.{f.name}": f.states.index(demo[t][f.name]) for f in states}
            fixed |= {f"end.{f.name}": f.states.index(demo[t + 1][f.name]) for f in states}
            open_ = [f for f in outcomes if demo[t + 1][f.name] is None]
            for f in outcomes:
                if demo[t + 1][f.name] is not None:
                    fixed[f"end.{f.name}"] = f.states.index(demo[t + 1][f.name])
            actions = range(len(net.actions)) if marks[t] is None else [net.actions.index(marks[t])]
            completions, weights = [], []
            for a in actions:
                for values in itertools.product(*(range(f.cardinality) for f in open_)):
                    row = {**fixed, "action": a}
                    row |= {f"end.{f.name}": v for f, v in zip(open_, values, strict=True)}
                    w = 1.0
                    for s in sites:
                        parents = net.cpd(s).parents
                        w *= float(init[s].probs[tuple(row[q] for q in parents) + (row[s],)])
                    completions.append(row)
                    weights.append(w)
            total = sum(weights)
            for row, w in zip(completions, weights, strict=True):
                for s in sites:
                    parents = net.cpd(s).parents
                    counts[s][tuple(row[q] for q in parents) + (row[s],)] += w / total
    for s in sites:
        c = counts[s]
        alpha = 0.01  # fit_demonstrations' pseudo-count
        want = (c + alpha) / (c + alpha).sum(-1, keepdim=True)
        torch.testing.assert_close(got.params[s].probs, want, rtol=0, atol=1e-10)
