"""EM over demonstrations that hide state values, against the brute-force joint.

The brute force enumerates every joint completion of a demonstration (each hidden state
value at each time, each unlabelled step's action, each hidden outcome) with
``itertools.product``, weights it by the product of the network's table entries over
every step's row (the module's model: every step's start drawn from the initial tables),
and accumulates each completion's counts.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch
from effect_networks.experiments.switch_worlds import switch_world
from effect_networks.inference.hidden_demonstrations import completed_steps, fit_hidden_states
from effect_networks.inference.sequences.demonstration import simulate_demonstrations
from effect_networks.inference.watching import fit_demonstrations
from effect_networks.models import Discrete, EffectNetwork, random_params
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.networks import declared_networks, drawn_demonstrations

ALPHA = 0.01  # fit_demonstrations' pseudo-count


def _brute_force(net, params, demos, labels):
    """Per site the expected counts, and the summed log-likelihood, by enumeration."""
    sites = [s.name for s in net.sites]
    counts = {s: torch.zeros_like(params[s].probs) for s in sites}
    log_lik = 0.0
    for demo, marks in zip(demos, labels, strict=True):
        # the unknowns: (time, feature) of a hidden value, each unlabelled step's action
        unknowns = []
        for t, state in enumerate(demo):
            for f in net.features:
                if (f.initial or t) and state.get(f.name) is None:
                    unknowns.append(((t, f.name), f.cardinality))
        for t, mark in enumerate(marks):
            if mark is None:
                unknowns.append(((t, "action"), len(net.actions)))
        completions, weights = [], []
        for values in itertools.product(*(range(k) for _, k in unknowns)):
            chosen = {key: v for (key, _), v in zip(unknowns, values, strict=True)}

            def value(t, f, chosen=chosen, demo=demo):
                given = demo[t].get(f.name)
                return chosen[(t, f.name)] if given is None else f.states.index(given)

            rows, w = [], 1.0
            for t in range(len(demo) - 1):
                row = {"action": chosen.get((t, "action"), marks[t])}
                for f in net.features:
                    if f.initial:
                        row[f"initial.{f.name}"] = value(t, f)
                    row[f"end.{f.name}"] = value(t + 1, f)
                for s in sites:
                    w *= float(
                        params[s].probs[tuple(row[q] for q in net.cpd(s).parents) + (row[s],)]
                    )
                rows.append(row)
            completions.append(rows)
            weights.append(w)
        total = sum(weights)
        log_lik += math.log(total)
        for rows, w in zip(completions, weights, strict=True):
            for row in rows:
                for s in sites:
                    counts[s][tuple(row[q] for q in net.cpd(s).parents) + (row[s],)] += w / total
    return counts, log_lik


def _normalised(counts):
    return {s: (c + ALPHA) / (c + ALPHA).sum(-1, keepdim=True) for s, c in counts.items()}


@pytest.mark.filterwarnings("ignore::effect_networks.inference.fitting.result.ConvergenceWarning")
@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(declared_networks(), st.integers(0, 2**16), st.data())
def test_one_em_step_is_the_brute_force_over_every_hidden_value_and_action(net, seed, data):
    """One EM step from drawn tables equals the counts of every joint completion of each
    demonstration (hidden state values carried from step to step, hidden outcomes,
    unlabelled actions), weighted by its posterior; the log-likelihood too."""
    init = random_params(net, seed)
    demos, labels = drawn_demonstrations(net, np.random.default_rng(seed), data)
    counts, log_lik = _brute_force(net, init, demos, labels)
    got = fit_hidden_states(net, demos, labels, init=init, steps=1, tol=1e-300, pseudo_count=ALPHA)
    assert got.log_likelihoods[0] == pytest.approx(log_lik, rel=1e-10, abs=1e-10)
    if len(got.log_likelihoods) < 2:
        return  # the step would have lowered the likelihood (a pseudo-count's pull): not taken
    for s, want in _normalised(counts).items():
        torch.testing.assert_close(got.params[s].probs, want, rtol=0, atol=1e-10)


def _switches():
    return EffectNetwork(
        (
            Discrete("a", ("off", "on")),
            Discrete("b", ("off", "on")),
            Discrete("lamp", ("dark", "lit"), initial=False),
        ),
        ("flip_a", "flip_b", "wait"),
    )


def test_fit_demonstrations_with_hidden_state_values_is_the_brute_force_step():
    net = _switches()
    init = random_params(net, 3)
    demos = [
        [
            {"a": "off", "b": None},
            {"a": None, "b": "on", "lamp": "lit"},
            {"a": "on", "b": None, "lamp": None},
        ],
        [{"a": None, "b": "off"}, {"a": "on", "b": "off", "lamp": None}],
    ]
    labels = [[None, "wait"], [None]]
    got = fit_demonstrations(net, demos, labels, init=init, steps=1, tol=1e-300)
    index = [[None if x is None else net.actions.index(x) for x in marks] for marks in labels]
    counts, log_lik = _brute_force(net, init, demos, index)
    assert got.log_likelihoods[0] == pytest.approx(log_lik, rel=1e-12)
    assert len(got.log_likelihoods) == 2
    for s, want in _normalised(counts).items():
        torch.testing.assert_close(got.params[s].probs, want, rtol=0, atol=1e-10)


@pytest.mark.filterwarnings("ignore::effect_networks.inference.fitting.result.ConvergenceWarning")
def test_the_log_likelihood_never_falls_over_a_run():
    net = _switches()
    g = np.random.default_rng(0)
    demos = []
    for _ in range(12):
        demo = []
        for t in range(4):
            state = {f: (None if g.random() < 0.3 else ("off", "on")[g.integers(2)]) for f in "ab"}
            if t:
                state["lamp"] = None if g.random() < 0.3 else ("dark", "lit")[g.integers(2)]
            demo.append(state)
        demos.append(demo)
    labels = [[None] * 3 for _ in demos]
    got = fit_hidden_states(net, demos, labels, init=random_params(net, 1), steps=40, tol=1e-300)
    curve = got.log_likelihoods
    assert len(curve) > 5
    assert all(b >= a for a, b in zip(curve, curve[1:], strict=False))
    # the returned tables score the last value
    last = completed_steps(net, got.params, demos, labels).log_likelihood
    assert last == pytest.approx(curve[-1], rel=1e-12)


@pytest.mark.filterwarnings("ignore::effect_networks.inference.fitting.result.ConvergenceWarning")
def test_fully_shown_demonstrations_fit_as_today_s_per_step_em():
    net = _switches()
    g = np.random.default_rng(2)
    demos = []
    for _ in range(6):
        demo = [{f: ("off", "on")[g.integers(2)] for f in "ab"} for _ in range(4)]
        for state in demo[1:]:
            state["lamp"] = None if g.random() < 0.3 else ("dark", "lit")[g.integers(2)]
        demos.append(demo)
    labels = [[None, "wait", None] for _ in demos]
    init = random_params(net, 4)
    today = fit_demonstrations(net, demos, labels, init=init, steps=5, tol=1e-300)
    index = [[None if x is None else net.actions.index(x) for x in marks] for marks in labels]
    got = fit_hidden_states(net, demos, index, init=init, steps=5, tol=1e-300)
    np.testing.assert_allclose(got.log_likelihoods, today.log_likelihoods, rtol=1e-12)
    for s in today.params.cpds:
        torch.testing.assert_close(got.params[s].probs, today.params[s].probs, rtol=0, atol=1e-10)


def test_a_switch_world_with_hidden_state_values_learns_the_fully_shown_fit_s_tables():
    """A fifth of the state values hidden and a tenth of the steps labelled: the tables come
    close to the fit on the same steps fully shown and labelled, and the labels given are
    the labels used (the starts do not relabel the steps)."""
    world = switch_world(4, "sparse")
    states, actions = simulate_demonstrations(world.net, world.params, 150, 5, seed=1)
    g = np.random.default_rng(0)
    shown = {f: np.where(g.random(v.shape) < 0.2, None, v) for f, v in states.items()}
    labels = np.where(g.random(actions.shape) < 0.1, actions, None)
    full = fit_demonstrations(world.net, states, actions).params
    got = fit_demonstrations(world.net, shown, labels, restarts=0)
    assert got.identifiable and got.converged and 0 < got.confidence <= 1
    curve = got.log_likelihoods
    assert all(b >= a for a, b in zip(curve, curve[1:], strict=False))
    for site, want in full.cpds.items():
        d = (got.params[site].probs - want.probs).abs().sum(-1) / 2
        assert float((d * want.n).sum() / want.n.sum()) < 0.1, site
