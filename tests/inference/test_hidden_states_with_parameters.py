"""Demonstrations that hide a discrete state value in a network with an action parameter.

Against a brute force written out here: every hidden state value, every unlabelled
action, every cluster, and the unrecorded force integrated in closed form (the model's
own joint with everything given is a Gaussian in the force: three evaluations fix it, a
fourth checks it). One EM step's tables, cluster means and variances, and the
log-likelihood; the log-likelihood never falling over a fit.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch
from effect_networks.inference import fit, simulate
from effect_networks.inference.exact.enumeration import enumerate_model
from effect_networks.inference.hidden_demonstrations import MIN_VARIANCE
from effect_networks.inference.watching import fit_demonstrations

from tests.networks import tap_data, tap_net

CLUSTERS = 3


@pytest.fixture(scope="module")
def world():
    net = tap_net(bins=CLUSTERS, affects="pos", layout="grid")
    true = fit(net, tap_data(net, 400)).params
    return net, true


def _log_joint(net, params, v0, action, v1, pos, cluster=None, force=None):
    """The model's joint of one step with everything given (the force NaN: not used)."""
    evidence = {"initial.visible": [v0], "action": [action], "end.visible": [v1]}
    if pos is not None:
        evidence["end.pos"] = [pos]
    if cluster is not None:
        evidence |= {"cluster.force": [cluster], "param.force": [[force]]}
    else:
        evidence |= {"param.force": [[math.nan]]}
    return float(enumerate_model(net, params, net.encode(evidence)).log_evidence[0])


def _integrated(net, params, v0, v1, pos, cluster):
    """The joint integrated over the force, and its first and second moments' integrals.

    Its log is a quadratic ``q(x) = q0 + b x + a x^2`` in the force (``a < 0``).
    """
    xs = (1.0, 3.0, 5.0)
    ys = [_log_joint(net, params, v0, "tap", v1, pos, cluster, x) for x in xs]
    a, b, q0 = np.polyfit(xs, ys, 2)
    check = _log_joint(net, params, v0, "tap", v1, pos, cluster, 7.5)
    assert check == pytest.approx(q0 + b * 7.5 + a * 7.5**2, abs=1e-9)
    assert a < 0
    variance, mean = -1 / (2 * a), -b / (2 * a)
    mass = math.exp(q0 + mean**2 / (2 * variance)) * math.sqrt(2 * math.pi * variance)
    return mass, mass * mean, mass * (variance + mean**2)


def _step_entries(net, params, v0, v1, pos, label, force):
    """Per (action, cluster): the step's mass and the force's moments (zero where unused)."""
    out = {}
    if force is not None:  # recorded: tap alone, its cluster the value's cell
        cell = int(net.mixture("force").parameter.cluster_of(torch.tensor([[force]])))
        mass = math.exp(_log_joint(net, params, v0, "tap", v1, pos, cell, force))
        return {("tap", cell): (mass, force * mass, force**2 * mass)}
    for action in [label] if label else net.actions:
        if action == "remove":
            out[action, None] = (math.exp(_log_joint(net, params, v0, action, v1, pos)), 0, 0)
            continue
        for c in range(CLUSTERS):
            out[action, c] = _integrated(net, params, v0, v1, pos, c)
    return out


def _brute_force(net, params, demos, labels, records):
    """Log-likelihood and expected statistics by every completion of every demonstration."""
    log_lik = 0.0
    counts = {"visible0": np.zeros(2), "action": np.zeros(2), "end": np.zeros((2, 2, 2))}
    weight, first, second = np.zeros(CLUSTERS), np.zeros(CLUSTERS), np.zeros(CLUSTERS)
    for demo, marks, rec in zip(demos, labels, records, strict=True):
        hidden = [t for t, s in enumerate(demo) if s.get("visible") is None]
        paths = []
        for values in itertools.product((0, 1), repeat=len(hidden)):
            vis = [s.get("visible") for s in demo]
            for t, v in zip(hidden, values, strict=True):
                vis[t] = v
            tables = [
                _step_entries(
                    net, params, vis[t], vis[t + 1], demo[t + 1].get("pos"), marks[t], rec[t]
                )
                for t in range(len(demo) - 1)
            ]
            for choice in itertools.product(*(t.items() for t in tables)):
                paths.append((vis, choice, math.prod(m for _, (m, _, _) in choice)))
        total = sum(p for *_, p in paths)
        log_lik += math.log(total)
        for vis, choice, p in paths:
            w = p / total
            for t, ((action, c), (m, f, g)) in enumerate(choice):
                a = net.action_index(action)
                counts["visible0"][vis[t]] += w
                counts["action"][a] += w
                counts["end"][vis[t], a, vis[t + 1]] += w
                if c is not None:
                    weight[c] += w
                    first[c] += w * f / m
                    second[c] += w * g / m
    return log_lik, counts, weight, first, second


DEMOS = [
    [{"visible": 1}, {"visible": None, "pos": [1.9]}, {"visible": 0, "pos": [2.4]}],
    [{"visible": None}, {"visible": 1, "pos": [0.1]}, {"visible": None, "pos": [3.1]}],
    [{"visible": 1}, {"visible": None}, {"visible": 0, "pos": [0.05]}],
    [{"visible": 0}, {"visible": None, "pos": [2.2]}, {"visible": 1, "pos": [-0.1]}],
]
# every force either recorded or unused and every outcome shown: the step tables' other
# route (no value integrated)
RECORDED = [
    [{"visible": 1}, {"visible": None, "pos": [1.9]}, {"visible": 0, "pos": [2.4]}],
    [{"visible": None}, {"visible": 1, "pos": [3.0]}, {"visible": None, "pos": [0.0]}],
]


@pytest.mark.parametrize(
    ("demos", "labels", "records"),
    [
        (
            DEMOS,
            [[None, None], ["tap", None], [None, "remove"], [None, None]],
            [[None, 6.0], [None, None], [None, None], [3.5, None]],
        ),
        (RECORDED, [[None, None], [None, "remove"]], [[2.5, 6.0], [8.0, None]]),
    ],
    ids=["unrecorded", "recorded"],
)
def test_one_em_step_over_hidden_states_and_forces_is_the_brute_force(
    world, demos, labels, records
):
    net, true = world
    parameters = [[None if f is None else {"force": [f]} for f in r] for r in records]
    got = fit_demonstrations(
        net,
        demos,
        labels,
        parameters=parameters,
        init=true,
        steps=1,
        tol=1e-300,
        pseudo_count=0.0,
    )
    log_lik, counts, weight, first, second = _brute_force(net, true, demos, labels, records)
    assert got.log_likelihoods[0] == pytest.approx(log_lik, rel=1e-10, abs=1e-10)
    assert len(got.log_likelihoods) == 2 and got.log_likelihoods[1] >= got.log_likelihoods[0]
    params = got.params

    def close(got_, want, atol=1e-9):
        torch.testing.assert_close(got_, torch.as_tensor(want), rtol=0, atol=atol)

    close(params["initial.visible"].probs, counts["visible0"] / counts["visible0"].sum())
    close(params["action"].probs, counts["action"] / counts["action"].sum())
    seen = counts["end"].sum(-1, keepdims=True)  # a row no step reaches: uniform
    table = np.where(seen > 0, counts["end"] / np.where(seen > 0, seen, 1), 0.5)
    close(params["end.visible"].probs, table)
    close(params["cluster.force"].probs[net.action_index("tap")], weight / weight.sum())
    mean = first / weight
    close(params["param.force"].bias[:, 0], mean, atol=1e-8)
    variance = np.maximum(second / weight - mean**2, MIN_VARIANCE)  # one value: the floor
    close(params["param.force"].scale_tril[:, 0, 0] ** 2, variance, atol=1e-8)


def test_hidden_states_with_unrecorded_forces_never_lower_the_likelihood(world):
    net, true = world
    rows = simulate(net, true, 120, seed=3)
    demos, labels, records = [], [], []
    for i in range(0, 120, 3):
        states = [{"visible": rows["initial.visible"][i]}]
        for j in range(i, i + 3):  # chained: each step starts where the last ended
            states.append({"visible": rows["end.visible"][j], "pos": rows["end.pos"][j].tolist()})
        states[1]["visible"] = None
        demos.append(states)
        labels.append([rows["action"][i] if i % 12 == 0 else None, None, None])
        records.append([None, None, {"force": [3.0]} if rows["action"][i + 2] == "tap" else None])
    got = fit_demonstrations(net, demos, labels, parameters=records, restarts=1, steps=15)
    curve = got.log_likelihoods
    assert len(curve) > 2
    assert all(b >= a - 1e-9 for a, b in zip(curve, curve[1:], strict=False))


def test_a_hidden_continuous_state_stays_refused_and_says_why():
    net = tap_net(bins=3, affects="pos", layout="grid")
    with pytest.raises(ValueError, match="adaptive layout"):
        fit_demonstrations(tap_net(), [[{"visible": None}, {"visible": 0}, {"visible": 1}]])
    hidden = [{"visible": None}, {"visible": 0, "pos": [0.1]}, {"visible": 0, "pos": [0.1]}]
    got = fit_demonstrations(net, [hidden], [["tap", "remove"]], steps=2)
    assert got.steps == 2 and got.labelled == 2
