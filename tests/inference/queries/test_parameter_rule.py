"""The parameter rules: an action that does not use a parameter ignores it; NaN = unknown.

Checked against a hand-written joint (tables and Gaussian densities read off the
parameters), not against the model's own code.
"""

import math

import numpy as np
import pytest
import torch
from effect_networks.inference import fit, imitation_check, infer_action, predict
from effect_networks.models import Continuous, Discrete, EffectNetwork, Parameter, random_params
from effect_networks.models.declaration import DTYPE

PUSH = EffectNetwork(
    (Discrete("contact", ("no", "yes")), Continuous("pos", 1)),
    ("wait", "push", "grasp"),
    (Parameter("force", 0.0, 10.0, 4, ("push",), "pos"),),
)
START = {"initial.contact": ["no"], "initial.pos": [[0.2]]}


def normal(x, mean, var):
    return math.exp(-0.5 * (x - mean) ** 2 / var) / math.sqrt(2 * math.pi * var)


def hand_posterior(params, force, y):
    """p(action | contact = no, pos = 0.2, force, end.pos = y) from the tables by hand."""
    cpd, prior = params["end.pos"], params["param.force"]
    post = []
    for a, name in enumerate(PUSH.actions):
        pa = float(params["action"].probs[a])
        if name == "push":
            c = min(int(force / 2.5), 3)
            pc = float(params["cluster.force"].probs[a, c])
            m, s = float(prior.bias[c, 0]), float(prior.covariance[c, 0, 0])
            w, b = cpd.weight[0, a, c, 0], float(cpd.bias[0, a, c, 0])
            mean = float(w[0]) * 0.2 + float(w[1]) * force + b
            like = pc * normal(force, m, s) * normal(y, mean, float(cpd.covariance[0, a, c, 0, 0]))
        else:  # the force is ignored: no weight on it, no density, cluster on cell 0
            w, b = cpd.weight[0, a, 0, 0], float(cpd.bias[0, a, 0, 0])
            like = normal(y, float(w[0]) * 0.2 + b, float(cpd.covariance[0, a, 0, 0, 0]))
        post.append(pa * like)
    post = torch.tensor(post, dtype=DTYPE)
    return post / post.sum()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_an_action_not_using_the_parameter_ignores_its_value(seed):
    params = random_params(PUSH, seed)  # random weights on the force for every action
    for action in ("wait", "grasp"):
        given = predict(PUSH, params, START | {"action": [action], "param.force": [[9.0]]})
        absent = predict(PUSH, params, START | {"action": [action]})
        torch.testing.assert_close(given.continuous["pos"].mean, absent.continuous["pos"].mean)
        torch.testing.assert_close(given.continuous["pos"].cov, absent.continuous["pos"].cov)


@pytest.mark.parametrize(("seed", "force", "y"), [(0, 4.0, 1.0), (1, 9.0, -0.5), (2, 1.0, 0.3)])
def test_action_posterior_with_a_given_force_is_the_hand_joint(seed, force, y):
    params = random_params(PUSH, seed)
    got = infer_action(PUSH, params, START | {"param.force": [[force]], "end.pos": [[y]]})
    torch.testing.assert_close(got.probs[0], hand_posterior(params, force, y), atol=1e-9, rtol=1e-7)


def test_a_pushed_object_is_not_explained_by_waiting():
    # The case: the force of a push given, the object moved; "wait" must not win.
    rng = np.random.default_rng(0)
    n = 2000
    action = rng.choice(PUSH.actions, n)
    force = np.where(action == "push", rng.uniform(0, 10, n), np.nan)[:, None]
    pos0 = rng.normal(0, 1, (n, 1))
    moved = np.where(action[:, None] == "push", 0.1 * np.nan_to_num(force), 0.0)
    data = {
        "initial.contact": rng.choice(["no", "yes"], n),
        "initial.pos": pos0,
        "action": action,
        "param.force": force,
        "end.contact": np.where(action == "push", "yes", "no"),
        "end.pos": pos0 + moved + rng.normal(0, 0.01, (n, 1)),
    }
    params = fit(PUSH, data).params
    ev = {"initial.contact": ["no"], "initial.pos": [[0.0]], "param.force": [[4.0]]}
    moved = infer_action(PUSH, params, ev | {"end.pos": [[0.4]]})
    assert moved.best_names == ("push",) and float(moved.prob("push")[0]) > 0.99
    wait = predict(PUSH, params, ev | {"action": ["wait"]})
    assert abs(float(wait.continuous["pos"].mean[0, 0])) < 0.01  # waiting moves nothing


def test_training_refuses_a_value_for_an_action_that_does_not_use_it():
    data = {
        "initial.contact": ["no", "no"],
        "initial.pos": [[0.0], [0.0]],
        "action": ["push", "wait"],
        "param.force": [[3.0], [5.0]],
        "end.contact": ["yes", "no"],
        "end.pos": [[0.3], [0.0]],
    }
    with pytest.raises(ValueError, match=r"row 1 has action 'wait', which does not use"):
        fit(PUSH, data)


def test_nan_parameter_is_unknown_row_by_row():
    params = random_params(PUSH, 3)
    rows = {"initial.contact": ["no"] * 3, "initial.pos": [[0.2]] * 3, "action": ["push"] * 3}
    batch = predict(PUSH, params, rows | {"param.force": [[6.0], [float("nan")], [2.0]]})
    unknown = predict(PUSH, params, START | {"action": ["push"]}).continuous["pos"]
    mix = batch.continuous["pos"]
    torch.testing.assert_close(mix.mean[1], unknown.mean[0])
    torch.testing.assert_close(mix.cov[1], unknown.cov[0])
    for row, force in ((0, 6.0), (2, 2.0)):
        one = predict(PUSH, params, START | {"action": ["push"], "param.force": [[force]]})
        torch.testing.assert_close(mix.mean[row], one.continuous["pos"].mean[0])
        torch.testing.assert_close(mix.cov[row], one.continuous["pos"].cov[0])
    # the action query and the imitation check read NaN the same way
    ev = {"initial.contact": ["no"] * 2, "initial.pos": [[0.2]] * 2, "end.pos": [[0.7]] * 2}
    both = infer_action(PUSH, params, ev | {"param.force": [[float("nan")], [5.0]]})
    torch.testing.assert_close(
        both.probs[0], infer_action(PUSH, params, START | {"end.pos": [[0.7]]}).probs[0]
    )
    torch.testing.assert_close(
        both.probs[1],
        infer_action(PUSH, params, START | {"end.pos": [[0.7]], "param.force": [[5.0]]}).probs[0],
    )
    check = imitation_check(
        PUSH, params, ev | {"action": ["push"] * 2, "param.force": [[float("nan")], [5.0]]}
    )
    alone = imitation_check(PUSH, params, START | {"action": ["push"], "end.pos": [[0.7]]})
    torch.testing.assert_close(check.log_likelihood[0], alone.log_likelihood[0])


def test_a_partly_nan_parameter_is_refused():
    net = EffectNetwork(
        (Continuous("pos", 2),), ("push",), (Parameter("f", (0, 0), (1, 1), (2, 2), "push", "pos"),)
    )
    with pytest.raises(ValueError, match=r"param.f.*whole row is NaN"):
        net.encode({"param.f": [[0.5, float("nan")]]})


# A push/wait world: the force acts on "push" only. "wait" leaves the object where it was
# (noise 5 mm); fitted P(cluster | wait) is exactly cell 0, the other cells of "wait"
# are configurations no row reached (the pooled, wide Gaussians of the pseudo-counts).
PUSH_WAIT = EffectNetwork(
    (Continuous("position", 1),),
    ("push", "wait"),
    (Parameter("force", 0.0, 10.0, 4, ("push",), "position"),),
)
STILL = EffectNetwork((Continuous("position", 1),), ("push", "wait"))


def push_wait_rows(n=2000, seed=0):
    rng = np.random.default_rng(seed)
    action = rng.choice(["push", "wait"], n)
    start = rng.uniform(-1.0, 1.0, (n, 1))
    force = np.where(action[:, None] == "push", rng.uniform(0.0, 10.0, (n, 1)), np.nan)
    end = start + 0.05 * np.nan_to_num(force) + rng.normal(0.0, 0.005, (n, 1))
    return {"initial.position": start, "action": action, "param.force": force, "end.position": end}


def wait_log_density(params, x0, y):
    """log p(end = y | start = x0, wait), read off the (wait, cell 0) linear Gaussian."""
    cpd = params["end.position"]
    w, b, var = cpd.weight[1, 0, 0], float(cpd.bias[1, 0, 0]), float(cpd.covariance[1, 0, 0, 0])
    mean = float(w[0]) * x0 + b
    return -0.5 * (y - mean) ** 2 / var - 0.5 * math.log(2 * math.pi * var)


def push_log_density(params, x0, y):
    """log p(end = y | start = x0, push), the force integrated out by hand: per cluster
    c the Gaussian of mean w_x x0 + w_p m_c + b and variance R + w_p^2 s_c."""
    cpd, prior = params["end.position"], params["param.force"]
    terms = []
    for c in range(4):
        (w_x, w_p), b = cpd.weight[0, c, 0].tolist(), float(cpd.bias[0, c, 0])
        m, s = float(prior.bias[c, 0]), float(prior.covariance[c, 0, 0])
        var = float(cpd.covariance[0, c, 0, 0]) + w_p**2 * s
        mean = w_x * x0 + w_p * m + b
        log_c = math.log(float(params["cluster.force"].probs[0, c]))
        terms.append(log_c - 0.5 * (y - mean) ** 2 / var - 0.5 * math.log(2 * math.pi * var))
    return float(np.logaddexp.reduce(terms))


def test_an_action_not_using_the_parameter_sits_on_its_one_configuration():
    data = push_wait_rows()
    params = fit(PUSH_WAIT, data).params
    still = fit(STILL, {k: v for k, v in data.items() if k != "param.force"}).params
    assert params["cluster.force"].probs[1].tolist() == [1.0, 0.0, 0.0, 0.0]
    # moved 0.2 m (40 noise sds) while waiting: scored by wait's own Gaussian only, as in
    # the same network without the parameter, and flagged
    ev = {"initial.position": [[0.0]], "action": ["wait"], "end.position": [[0.2]]}
    check = imitation_check(PUSH_WAIT, params, ev)
    truth = wait_log_density(params, 0.0, 0.2)
    assert truth < -700
    assert float(check.log_likelihood[0]) == pytest.approx(truth, rel=1e-12)
    assert float(check.log_likelihood[0]) == pytest.approx(
        float(imitation_check(STILL, still, ev).log_likelihood[0]), rel=1e-9
    )
    assert bool(check.implausible[0]) and float(check.unseen[0]) == 0.0
    # the action posterior: wait's likelihood is its own Gaussian's; wait was trained on
    # about 1,000 rows, so it is not unseen
    ev = {"initial.position": [[0.0]], "end.position": [[-0.3]]}
    post = infer_action(PUSH_WAIT, params, ev)
    log_wait = wait_log_density(params, 0.0, -0.3) + math.log(float(params["action"].probs[1]))
    log_push = math.log(float(params["action"].probs[0])) + push_log_density(params, 0.0, -0.3)
    assert float(post.prob("wait")[0]) == pytest.approx(
        math.exp(log_wait - np.logaddexp(log_wait, log_push)), rel=1e-9, abs=1e-300
    )
    assert float(post.prob("push")[0]) == pytest.approx(
        math.exp(log_push - np.logaddexp(log_wait, log_push)), rel=1e-9
    )
    assert float(post.unseen[0, 1]) == 0.0
    assert post.best_names == tuple(post.actions[i] for i in post.probs.argmax(-1).tolist())
    stay = infer_action(PUSH_WAIT, params, {"initial.position": [[0.0]], "end.position": [[0.0]]})
    assert stay.best_names == ("wait",) and float(stay.unseen[0, 1]) == 0.0
    # predict: one component for wait, its own
    wait = predict(PUSH_WAIT, params, {"initial.position": [[0.0]], "action": ["wait"]})
    assert wait.continuous["position"].weights.shape[-1] == 1
    assert float(wait.unseen[0]) == 0.0
