"""predict_joint: the joint of the discrete end features, beside the joint transitions
(tables, no evidence traced) and predict's marginals."""

from __future__ import annotations

import numpy as np
import torch
from effect_networks.inference import fit, predict
from effect_networks.inference.queries.joint import predict_joint
from effect_networks.inference.sequences.transition_tables import transitions

from tests.networks import rich_net, rich_rows


def test_the_joint_equals_the_transitions_and_sums_to_the_marginals():
    net = rich_net()
    params = fit(net, rich_rows(net, 400, 1)).params
    t = transitions(net, params, given={"x": [0.5]})
    states = t.space.states
    rows = [(s, a) for s in range(len(states)) for a in range(len(t.actions))]
    evidence = {
        "initial.door": [states[s][0] for s, _ in rows],
        "initial.lock": [states[s][1] for s, _ in rows],
        "initial.x": np.full((len(rows), 1), 0.5),
        "action": [t.actions[a] for _, a in rows],
    }
    joint = predict_joint(net, params, evidence)
    assert joint.features == ("door", "lock", "noise")
    by_state = joint.probs.reshape(len(rows), 2, 2, 3).sum(-1).reshape(len(rows), 4)
    expected = torch.stack([t.probs[s, a] for s, a in rows])
    torch.testing.assert_close(by_state, expected, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(joint.unseen, torch.stack([t.unseen[s, a] for s, a in rows]))
    marginals = predict(net, params, evidence)
    for f in ("door", "lock", "noise"):
        torch.testing.assert_close(joint.marginal(f), marginals.discrete[f])
    torch.testing.assert_close(joint.unseen, marginals.unseen)
    assert joint.prob({"door": "open", "lock": "on", "noise": 2}).shape == (len(rows),)
    assert len(joint.most_likely()) == len(rows)


def test_no_rows_give_an_empty_joint():
    net = rich_net()
    params = fit(net, rich_rows(net, 200, 2)).params
    empty = predict_joint(net, params, {"initial.x": np.zeros((0, 1)), "action": []})
    assert empty.probs.shape == (0, 12) and empty.features == ("door", "lock", "noise")
