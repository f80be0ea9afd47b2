"""Parameters beyond one continuous feature: a parameter acting on a discrete feature
(through its cell), on several features, and several parameters on one feature.

Answers are compared with sums written out over the clusters and with Gaussian
identities computed here by hand (numpy), not by the toolkit's own conditioning.
"""

import math

import numpy as np
import pytest
import torch
from effect_networks.inference import (
    fit,
    imitation_check,
    infer_action,
    infer_parameter,
    predict,
    simulate,
)
from effect_networks.inference.queries.parameter import compile_parameter_query
from effect_networks.models import (
    Continuous,
    Discrete,
    EffectNetwork,
    Parameter,
    load,
    random_params,
    save,
)

from tests.networks import PUSH_ACTIONS, joint_by_hand, sliding, throwing


def normal_pdf(y, mean, cov):
    """Multivariate normal density by hand."""
    y, mean, cov = (np.asarray(v, dtype=float) for v in (y, mean, cov))
    diff = y - mean
    d = diff.shape[-1]
    quad = diff @ np.linalg.solve(cov, diff)
    return math.exp(-0.5 * quad) / math.sqrt((2 * math.pi) ** d * np.linalg.det(cov))


# ---------------------------------------------------------------- a discrete feature
def tipping():
    force = Parameter("force", 0.0, 9.0, 3, ("push",), "upright")
    net = EffectNetwork((Discrete("upright", (True, False)),), PUSH_ACTIONS, (force,))
    return net, random_params(net, 4)


def test_a_discrete_feature_depends_on_the_cell():
    net, params = tipping()
    assert net.cpd("end.upright").parents == ("initial.upright", "action", "cluster.force")
    table = params["end.upright"].probs  # (initial, action, cluster, end)
    clusters = params["cluster.force"].probs  # (action, cluster)
    ev = {"initial.upright": [True], "action": ["push"]}
    given = predict(net, params, ev | {"param.force": [[4.0]]})  # cell 1 of [0, 3, 6, 9]
    torch.testing.assert_close(given.discrete["upright"][0], table[0, 0, 1])
    unknown = predict(net, params, ev)
    torch.testing.assert_close(unknown.discrete["upright"][0], clusters[0] @ table[0, 0])
    waited = predict(net, params, {"initial.upright": [True], "action": ["wait"]})
    torch.testing.assert_close(waited.discrete["upright"][0], table[0, 1, 0])  # cell 0


def test_the_cell_is_inferred_from_a_discrete_outcome():
    net, params = tipping()
    table = params["end.upright"].probs
    clusters = params["cluster.force"].probs
    ev = {"initial.upright": [True], "action": ["push"], "end.upright": [False]}
    answer = infer_parameter(net, params, "force", ev, mixture=True)
    joint = clusters[0] * table[0, 0, :, 1]
    torch.testing.assert_close(answer.cluster_probs[0], joint / joint.sum())
    best = int(joint.argmax())
    torch.testing.assert_close(answer.mean[0], params["param.force"].bias[best])
    expected_mean = (joint / joint.sum()) @ params["param.force"].bias
    torch.testing.assert_close(answer.mixture.mean[0], expected_mean)
    # the action: p(a) sum_c p(c | a) p(end | a, c)
    posterior = infer_action(net, params, {"initial.upright": [True], "end.upright": [False]})
    actions = params["action"].probs
    likelihood = torch.stack([clusters[a] @ table[0, a, :, 1] for a in range(2)])
    torch.testing.assert_close(posterior.probs[0], actions * likelihood / (actions @ likelihood))


def closed_form(params, x, clusters, known):
    """Mean and covariance of end.pos for action push, given cluster indices, with the
    parameters in ``known`` (name -> value) given and the others integrated out."""
    cpd = params["end.pos"]
    index = (0, *clusters)  # action push, cluster force, cluster angle
    w = cpd.weight[index].numpy()  # (1, 3): [pos, force, angle]
    mean = cpd.bias[index].numpy() + w[:, :1] @ x
    cov = cpd.covariance[index].numpy()
    for j, (name, c) in enumerate(zip(("force", "angle"), clusters, strict=True)):
        wj = w[:, 1 + j : 2 + j]
        if name in known:
            mean = mean + wj @ np.atleast_1d(known[name])
        else:
            prior = params[f"param.{name}"]
            mean = mean + wj @ prior.bias[c].numpy()
            cov = cov + wj @ prior.covariance[c].numpy() @ wj.T
    return mean, cov


def test_two_unknown_parameters_add_their_spreads():
    net, params = sliding()
    assert net.cpd("end.pos").inputs == ("initial.pos", "param.force", "param.angle")
    x = np.array([0.3])
    pred = predict(net, params, {"initial.pos": [x], "action": ["push"]}).continuous["pos"]
    pf, pa = params["cluster.force"].probs[0], params["cluster.angle"].probs[0]
    mean, second = 0.0, 0.0
    for cf in range(2):
        for ca in range(2):
            m, c = closed_form(params, x, (cf, ca), {})
            weight = float(pf[cf] * pa[ca])
            mean, second = mean + weight * m, second + weight * (c + np.outer(m, m))
    np.testing.assert_allclose(pred.mean[0].numpy(), mean, rtol=1e-10)
    np.testing.assert_allclose(pred.cov[0].numpy(), second - np.outer(mean, mean), rtol=1e-9)
    # one given (its cell fixes its cluster), the other integrated out
    ev = {"initial.pos": [x], "action": ["push"], "param.force": [[3.0]]}
    pred = predict(net, params, ev).continuous["pos"]
    mean, second = 0.0, 0.0
    for ca in range(2):
        m, c = closed_form(params, x, (1, ca), {"force": 3.0})
        mean, second = mean + float(pa[ca]) * m, second + float(pa[ca]) * (c + np.outer(m, m))
    np.testing.assert_allclose(pred.mean[0].numpy(), mean, rtol=1e-10)
    np.testing.assert_allclose(pred.cov[0].numpy(), second - np.outer(mean, mean), rtol=1e-9)


def test_one_parameter_is_inferred_given_the_other():
    net, params = sliding()
    x, y, angle = np.array([0.3]), np.array([1.1]), 0.4  # angle in cell 1
    ev = {"initial.pos": [x], "action": ["push"], "param.angle": [[angle]], "end.pos": [y]}
    answer = infer_parameter(net, params, "force", ev)
    weights = []
    for cf in range(2):
        m, c = closed_form(params, x, (cf, 1), {"angle": angle})
        weights.append(float(params["cluster.force"].probs[0, cf]) * normal_pdf(y, m, c))
    weights = np.array(weights) / sum(weights)
    np.testing.assert_allclose(answer.cluster_probs[0].numpy(), weights, rtol=1e-9)
    best = int(weights.argmax())
    cpd, prior = params["end.pos"], params["param.force"]
    w = cpd.weight[0, best, 1].numpy()  # (1, 3)
    s, m0 = prior.covariance[best].numpy(), prior.bias[best].numpy()
    r = cpd.covariance[0, best, 1].numpy()
    offset = cpd.bias[0, best, 1].numpy() + w[:, :1] @ x + w[:, 2:] @ [angle]
    gain = s @ w[:, 1:2].T @ np.linalg.inv(w[:, 1:2] @ s @ w[:, 1:2].T + r)
    expected = m0 + gain @ (y - offset - w[:, 1:2] @ m0)
    np.testing.assert_allclose(answer.mean[0].numpy(), expected, rtol=1e-9)
    with pytest.raises(ValueError, match=r"needs 'param.angle' in every row"):
        infer_parameter(net, params, "force", {k: v for k, v in ev.items() if k != "param.angle"})
    with pytest.raises(ValueError, match=r"shares \[.end.pos.\] with another parameter"):
        compile_parameter_query(net, params, "force")


def test_fit_recovers_two_parameters_slopes():
    force = Parameter("force", 0.0, 4.0, 1, ("push",), "pos")
    angle = Parameter("angle", -1.0, 1.0, 1, ("push",), "pos")
    net = EffectNetwork((Continuous("pos", 1),), PUSH_ACTIONS, (force, angle))
    g = np.random.default_rng(0)
    n = 4000
    action = g.choice(PUSH_ACTIONS, n)
    push = action == "push"
    f = np.where(push, g.uniform(0, 4, n), np.nan)[:, None]
    a = np.where(push, g.uniform(-1, 1, n), np.nan)[:, None]
    x = g.normal(size=(n, 1))
    y = x + np.nan_to_num(0.5 * f - 2.0 * a) + 0.01 * g.normal(size=(n, 1))
    rows = {
        "initial.pos": x,
        "action": action,
        "param.force": f,
        "param.angle": a,
        "end.pos": y,
    }
    cpd = fit(net, rows).params["end.pos"]
    np.testing.assert_allclose(cpd.weight[0, 0, 0, 0].numpy(), [1.0, 0.5, -2.0], atol=0.01)
    np.testing.assert_allclose(cpd.weight[1, 0, 0, 0].numpy(), [1.0, 0.0, 0.0], atol=0.01)


# ---------------------------------------------------------------- several features
def test_one_parameter_on_a_continuous_and_a_discrete_feature(tmp_path):
    force = Parameter("force", 0.0, 6.0, 3, ("push",), ("pos", "upright"))
    net = EffectNetwork(
        (Discrete("upright", (True, False)), Continuous("pos", 1)),
        PUSH_ACTIONS,
        (force,),
        parents={
            "end.upright": ("initial.upright", "action"),
            "end.pos": ("initial.pos", "action"),
        },
    )
    params = random_params(net, 2)
    x, y = np.array([0.0]), np.array([0.8])
    ev = {"initial.upright": [True], "initial.pos": [x], "action": ["push"]}
    answer = infer_parameter(net, params, "force", ev | {"end.pos": [y], "end.upright": [False]})
    cpd, prior = params["end.pos"], params["param.force"]
    weights = []
    for c in range(3):
        w = cpd.weight[0, c].numpy()  # (1, 2): [pos, force]
        mean = cpd.bias[0, c].numpy() + w[:, :1] @ x + w[:, 1:] @ prior.bias[c].numpy()
        cov = cpd.covariance[0, c].numpy() + w[:, 1:] @ prior.covariance[c].numpy() @ w[:, 1:].T
        tipped = float(params["end.upright"].probs[0, 0, c, 1])
        weights.append(
            float(params["cluster.force"].probs[0, c]) * normal_pdf(y, mean, cov) * tipped
        )
    np.testing.assert_allclose(answer.cluster_probs[0].numpy(), np.array(weights) / sum(weights))
    save(tmp_path / "net.pt", net, params)
    assert load(tmp_path / "net.pt")[0] == net
    rows = simulate(net, params, 200, seed=0)  # fit reads what the model generates
    assert fit(net, rows).params["end.upright"].probs.shape == (2, 2, 3, 2)


def test_a_shared_parameter_couples_its_features():
    net, params = throwing()
    x_land, x_roll, y_land = np.array([0.1, -0.2]), np.array([0.3]), np.array([0.5, 1.0])
    ev = {"initial.land": [x_land], "initial.roll": [x_roll], "action": ["throw"]}
    clusters = params["cluster.aim"].probs[0].numpy()
    # end.roll given end.land: Gaussian conditioning of the joint, per cluster
    pred = predict(net, params, ev | {"end.land": [y_land]}).continuous["roll"]
    weights, means, covs = [], [], []
    for c in range(2):
        mu, cov, *_ = joint_by_hand(params, x_land, x_roll, c)
        weights.append(clusters[c] * normal_pdf(y_land, mu[:2], cov[:2, :2]))
        gain = cov[2:, :2] @ np.linalg.inv(cov[:2, :2])
        means.append(mu[2:] + gain @ (y_land - mu[:2]))
        covs.append(cov[2:, 2:] - gain @ cov[:2, 2:])
    weights = np.array(weights) / sum(weights)
    mean = sum(w * m for w, m in zip(weights, means, strict=True))
    spread = sum(w * (c + np.outer(m, m)) for w, m, c in zip(weights, means, covs, strict=True))
    np.testing.assert_allclose(pred.mean[0].numpy(), mean, rtol=1e-9)
    np.testing.assert_allclose(pred.cov[0].numpy(), spread - np.outer(mean, mean), rtol=1e-9)
    # both observed: the joint likelihood, and the aim given both
    y_roll = np.array([0.7])
    both = ev | {"end.land": [y_land], "end.roll": [y_roll]}
    answer = infer_parameter(net, params, "aim", both)
    y = np.concatenate([y_land, y_roll])
    joint = [
        clusters[c] * normal_pdf(y, *joint_by_hand(params, x_land, x_roll, c)[:2]) for c in range(2)
    ]
    np.testing.assert_allclose(answer.cluster_probs[0].numpy(), np.array(joint) / sum(joint))
    best = int(np.argmax(joint))
    mu, cov, w, m, s = joint_by_hand(params, x_land, x_roll, best)
    expected = m + s @ w.T @ np.linalg.solve(cov, y - mu)
    np.testing.assert_allclose(answer.mean[0].numpy(), expected, rtol=1e-9)
    check = imitation_check(net, params, both, n_samples=10)
    total = np.log(sum(joint))
    np.testing.assert_allclose(float(check.log_likelihood[0]), total, rtol=1e-9)


def test_a_shared_parameter_is_drawn_from_its_posterior():
    net, params = throwing()
    ev = {"initial.land": [[0.1, -0.2]], "initial.roll": [[0.3]], "action": ["throw"]}
    ev |= {"end.land": [[0.5, 1.0]], "end.roll": [[0.7]]}
    drawn = simulate(net, params, 4000, ev, seed=0)["param.aim"]
    exact = infer_parameter(net, params, "aim", ev, mixture=True).mixture
    torch.testing.assert_close(drawn.mean(0), exact.mean[0], atol=0.02, rtol=0)


def test_a_parameter_on_several_continuous_features_acts_alone():
    aim = Parameter("aim", 0.0, 1.0, 2, ("push",), ("a", "b"))
    spin = Parameter("spin", 0.0, 1.0, 2, ("push",), "a")
    with pytest.raises(ValueError, match=r"only parameter acting on each; \['a'\] have others"):
        EffectNetwork((Continuous("a"), Continuous("b")), PUSH_ACTIONS, (aim, spin))
