"""An unknown continuous initial feature in a query: integrated out in closed form,
against numerical integration over it (scipy's quad on the densities written out here),
and refused naming the site where no closed form exists."""

import math

import numpy as np
import pytest
import torch
from effect_networks.inference import infer_action, predict
from effect_networks.models import Continuous, Discrete, EffectNetwork, random_params
from scipy import integrate

# initial.x (1-D, a Gaussian prior) is read by end.x and the 2-D end.y
NET = EffectNetwork(
    (Discrete("shape", ("box", "ball")), Continuous("x", 1), Continuous("y", 2, initial=False)),
    ("push", "lift"),
    parents={
        "end.shape": ("initial.shape", "action"),
        "end.x": ("initial.x", "action"),
        "end.y": ("initial.shape", "initial.x", "action"),
    },
)
PARAMS = random_params(NET, 3)


def normal(v, mean, cov):
    v, mean, cov = np.atleast_1d(v), np.atleast_1d(mean), np.atleast_2d(cov)
    r = v - mean
    return math.exp(-0.5 * r @ np.linalg.solve(cov, r)) / math.sqrt(
        np.linalg.det(2 * math.pi * cov)
    )


def numbers(site):
    p = PARAMS[site]
    return p.weight.numpy(), p.bias.numpy(), p.covariance.numpy()


def density(x, shape, action, end_x=None, end_y=None):
    """p(x) p(end.x | x, a) p(end.y | shape, x, a) for the given end values."""
    _, m0, v0 = numbers("initial.x")
    out = normal(x, m0, v0)
    if end_x is not None:
        w, b, c = numbers("end.x")
        out *= normal(end_x, w[action] @ [x] + b[action], c[action])
    if end_y is not None:
        w, b, c = numbers("end.y")
        out *= normal(end_y, w[shape, action] @ [x] + b[shape, action], c[shape, action])
    return out


def quad(fn):
    return integrate.quad(fn, -40, 40, epsabs=1e-13, epsrel=1e-11, limit=400)[0]


def test_infer_action_integrates_the_unknown_initial_value_out():
    end_x, end_y = [[0.1], [0.4]], [[0.3, -0.2], [1.0, 0.5]]
    posterior = infer_action(
        NET, PARAMS, {"initial.shape": ["box", "ball"], "end.x": end_x, "end.y": end_y}
    )
    prior = PARAMS["action"].probs.numpy()
    for row, shape in enumerate((0, 1)):
        joint = np.array(
            [
                prior[a] * quad(lambda x, a=a, s=shape, r=row: density(x, s, a, end_x[r], end_y[r]))
                for a in range(2)
            ]
        )
        np.testing.assert_allclose(posterior.probs[row].numpy(), joint / joint.sum(), atol=1e-9)
        # the evidence's probability, the shape's prior and the actions' summed
        p_shape = PARAMS["initial.shape"].probs[shape].item()
        assert posterior.log_evidence[row].item() == pytest.approx(
            math.log(p_shape * joint.sum()), rel=1e-9
        )


@pytest.mark.parametrize("observed_x", [None, [0.7]])
def test_predict_integrates_the_unknown_initial_value_out(observed_x):
    # end.y's mean and covariance with x unknown (given end.x, where observed), by
    # quadrature: E[y] = E[W x + b], Cov[y] = C + Var[W x + b], x's posterior weights
    evidence = {"initial.shape": ["ball"], "action": ["lift"]}
    if observed_x is not None:
        evidence["end.x"] = [observed_x]
    out = predict(NET, PARAMS, evidence).continuous["y"]
    w, b, c = (t[1, 1] for t in numbers("end.y"))

    def weight(x):
        return density(x, 1, 1, observed_x)

    total = quad(weight)
    mx = quad(lambda x: x * weight(x)) / total
    vx = quad(lambda x: (x - mx) ** 2 * weight(x)) / total
    np.testing.assert_allclose(out.mean[0].numpy(), w[:, 0] * mx + b, atol=1e-8)
    np.testing.assert_allclose(out.cov[0].numpy(), c + np.outer(w[:, 0], w[:, 0]) * vx, atol=1e-8)


def test_an_unknown_value_read_by_a_discrete_site_is_refused_by_name():
    net = EffectNetwork(
        (Discrete("shape", ("box", "ball")), Continuous("x", 1)),
        ("push", "lift"),
        parents={"end.shape": ("initial.x", "action"), "end.x": ("initial.x",)},
    )
    params = random_params(net, 0)
    with pytest.raises(ValueError, match=r"initial\.x.*'end\.shape' \(softmax\)"):
        infer_action(net, params, {"initial.shape": ["box"], "end.shape": ["ball"]})


def test_known_initial_values_give_the_same_answers_as_before():
    # with x given, nothing changes: the same posterior as the query always gave
    ev = {"initial.shape": ["box"], "initial.x": [[0.2]], "end.y": [[0.3, -0.2]]}
    probs = infer_action(NET, PARAMS, ev).probs[0].numpy()
    prior = PARAMS["action"].probs.numpy()
    w, b, c = numbers("end.y")
    joint = np.array(
        [prior[a] * normal([0.3, -0.2], w[0, a] @ [0.2] + b[0, a], c[0, a]) for a in range(2)]
    )
    np.testing.assert_allclose(probs, joint / joint.sum(), atol=1e-12)
    assert torch.isfinite(torch.as_tensor(probs)).all()


def test_queries_that_read_each_density_alone_still_need_the_initial_state():
    # simulate given an end state would draw x from its prior, ignoring that state;
    # imitation_check's surprise reads each observed feature's own density
    from effect_networks.inference import imitation_check, simulate

    ev = {"initial.shape": ["box"], "end.x": [[0.1]]}
    with pytest.raises(ValueError, match=r"simulate .*\['initial.x'\]"):
        simulate(NET, PARAMS, 1, ev)
    with pytest.raises(
        ValueError, match=r"imitation_check needs the initial state of \['initial.x'\]"
    ):
        imitation_check(NET, PARAMS, ev | {"action": ["push"]})


def test_an_unknown_parameter_beside_it_is_integrated_out_too():
    # tap's force (two clusters) acts on end.pos; initial.pos and the force unknown: the
    # posterior over actions by a double integral over both
    from effect_networks.models import Parameter

    net = EffectNetwork(
        (Discrete("visible", (0, 1)), Continuous("pos", 1)),
        ("remove", "tap"),
        (Parameter("force", 0.0, 10.0, 2, ("tap",), "pos"),),
        parents={"end.visible": ("initial.visible", "action")},
    )
    params = random_params(net, 5)
    y = 0.8

    def arr(site):
        p = params[site]
        return p.weight.numpy(), p.bias.numpy(), p.covariance.numpy()

    _, m0, v0 = arr("initial.pos")
    w, b, r = arr("end.pos")  # (visible, action, cluster, 1, 2): inputs [pos, force]
    _, mf, vf = arr("param.force")
    clusters = params["cluster.force"].probs.numpy()
    prior = params["action"].probs.numpy()

    # Gauss-Hermite nodes of N(0, 1): E[f(z)] = sum_i weight_i f(node_i), exact to
    # float64 here for the smooth Gaussian integrands
    nodes, weights = np.polynomial.hermite_e.hermegauss(80)
    weights = weights / weights.sum()
    xs = m0[0] + math.sqrt(v0[0, 0]) * nodes

    def joint(action):
        if action == 0:  # remove ignores the force (cluster 0, its weight unused)
            return sum(
                q * normal(y, w[1, 0, 0, :, 0] * x + b[1, 0, 0], r[1, 0, 0])
                for q, x in zip(weights, xs, strict=True)
            )
        total = 0.0
        for c in range(2):
            thetas = mf[c, 0] + math.sqrt(vf[c, 0, 0]) * nodes
            for q, x in zip(weights, xs, strict=True):
                for u, theta in zip(weights, thetas, strict=True):
                    mean = w[1, 1, c, :, 0] * x + w[1, 1, c, :, 1] * theta + b[1, 1, c]
                    total += clusters[1, c] * q * u * normal(y, mean, r[1, 1, c])
        return total

    want = np.array([prior[a] * joint(a) for a in range(2)])
    got = infer_action(net, params, {"initial.visible": [1], "end.pos": [[y]]}).probs[0]
    np.testing.assert_allclose(got.numpy(), want / want.sum(), atol=1e-7)


def test_plausibility_measures_the_joint_distance_of_the_observed_end_state():
    # end.x and end.y observed, x unknown: they are dependent through x, and the squared
    # Mahalanobis distance the flag reads is that of their joint Gaussian (by hand)
    from effect_networks.inference.queries.implausibility import plausibility
    from scipy import stats

    ex, ey = [0.9], [2.0, -1.5]
    evidence = NET.encode(
        {"initial.shape": ["ball"], "action": ["push"], "end.x": [ex], "end.y": [ey]}
    )
    tail = plausibility(NET, PARAMS, evidence).tail[0].item()
    _, m0, v0 = numbers("initial.x")
    wx, bx, cx = (t[0] for t in numbers("end.x"))
    wy, by, cy = (t[1, 0] for t in numbers("end.y"))
    lift = np.vstack([wx, wy])  # (3, 1): [end.x, end.y] = lift x + offset + noise
    mean = lift @ m0 + np.concatenate([bx, by])
    cov = lift @ v0 @ lift.T
    cov[:1, :1] += cx
    cov[1:, 1:] += cy
    r = np.concatenate([ex, ey]) - mean
    d2 = r @ np.linalg.solve(cov, r)
    assert tail == pytest.approx(stats.chi2.sf(d2, 3), rel=1e-9)
