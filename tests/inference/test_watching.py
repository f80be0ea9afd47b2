"""Learning from demonstrations whose actions were not labelled.

Against a fit on the same steps fully labelled, one EM step written by hand from the
brute-force posterior over each step's action, and the true tables of a switch world.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from effect_networks.experiments.switch_worlds import switch_world
from effect_networks.inference import fit
from effect_networks.inference.sequences.demonstration import simulate_demonstrations
from effect_networks.inference.watching import fit_demonstrations
from effect_networks.models import Discrete, EffectNetwork, random_params

from tests.networks import tap_net


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


def test_hidden_state_values_and_parameters_are_refused_with_the_reason():
    world = switch_world(4, "sparse")
    demo = [dict.fromkeys(("f0", "f1", "f2", "f3"), "off") for _ in range(3)]
    demo[1] = {**demo[1], "f2": None}
    with pytest.raises(ValueError, match=r"time 1: 'f2' is not given.*hidden state"):
        fit_demonstrations(world.net, [demo])
    with pytest.raises(ValueError, match="not one of"):
        fit_demonstrations(world.net, [demo[:1] * 2], [["jump"]])
    with pytest.raises(ValueError, match="does not record an action's parameter"):
        fit_demonstrations(tap_net(), [[{"visible": 1}, {"visible": 0}]])
