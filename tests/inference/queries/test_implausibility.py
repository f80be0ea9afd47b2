"""The ``implausible`` flag against brute-force enumeration and closed-form Gaussian tails."""

import math

import mpmath
import numpy as np
import pytest
import torch
from effect_networks.inference import fit, imitation_check, infer_action, infer_parameter, predict
from effect_networks.inference.queries.implausibility import IMPLAUSIBLE_BELOW, plausibility
from effect_networks.models import Continuous, Discrete, EffectNetwork, Parameter
from effect_networks.models.declaration import DTYPE
from hypothesis import given, settings
from hypothesis import strategies as st

from effect_networks import inference
from tests.helpers import brute_joint, discrete_network, random_params
from tests.networks import README_NET, softmax_oracle


def brute_evidence_prob(net, params, init, end, action=None):
    """p(end | init[, action]) from the joint enumerated over every full assignment;
    ``end`` maps a feature index to its observed state, the others are summed out."""
    given_init = [
        (k, p)
        for k, p in brute_joint(net, params).items()
        if k[0] == tuple(init) and (action is None or k[1] == action)
    ]
    match = sum(p for (_, _, e), p in given_init if all(e[i] == v for i, v in end.items()))
    return match / sum(p for _, p in given_init)


@settings(max_examples=25, deadline=None)
@given(
    cards=st.lists(st.integers(2, 3), min_size=1, max_size=3),
    n_actions=st.integers(1, 3),
    seed=st.integers(0, 10_000),
    data=st.data(),
)
def test_discrete_plausibility_is_the_evidence_probability(cards, n_actions, seed, data):
    net = discrete_network(cards, n_actions)
    params = random_params(net, seed)
    init = [data.draw(st.integers(0, k - 1)) for k in cards]
    observed = data.draw(st.sets(st.integers(0, len(cards) - 1), min_size=1))
    end = {i: data.draw(st.integers(0, cards[i] - 1)) for i in sorted(observed)}
    action = data.draw(st.none() | st.integers(0, n_actions - 1))
    evidence = {f"initial.f{i}": [v] for i, v in enumerate(init)}
    evidence |= {f"end.f{i}": [v] for i, v in end.items()}
    if action is not None:
        evidence["action"] = [net.actions[action]]
    got = plausibility(net, params, net.encode(evidence))
    want = brute_evidence_prob(net, params, init, end, action)
    assert float(got.discrete[0]) == pytest.approx(want, rel=1e-9, abs=1e-15)
    assert float(got.tail[0]) == 1.0  # nothing continuous observed
    # the flag is that probability against the threshold, in every query
    cases = [(want * 0.99, False)] + ([(want * 1.01, True)] if want * 1.01 < 1 else [])
    for below, flagged in cases:
        if action is None:
            answer = infer_action(net, params, evidence, implausible_below=below)
        else:
            answer = imitation_check(net, params, evidence, implausible_below=below)
        assert bool(answer.implausible[0]) is flagged


def door_rows(n: int, seed: int) -> dict:
    """A door that no action opens while it is locked (a door that stays locked)."""
    rng = np.random.default_rng(seed)
    doors = rng.choice(["locked", "shut", "open"], n)
    actions = rng.choice(["wait", "push", "unlock"], n)
    end = []
    for d, a in zip(doors, actions, strict=True):
        if d == "locked":
            end.append("shut" if a == "unlock" and rng.random() < 0.9 else "locked")
        elif d == "shut":
            end.append("open" if a == "push" and rng.random() < 0.8 else "shut")
        else:
            end.append("open")
    return {"initial.door": doors, "action": actions, "end.door": np.array(end)}


DOOR = EffectNetwork((Discrete("door", ("locked", "shut", "open")),), ("wait", "push", "unlock"))


def test_a_locked_door_that_ends_open_is_flagged_and_still_answered():
    params = fit(DOOR, door_rows(3000, 0)).params
    evidence = {"initial.door": ["locked", "shut"], "end.door": ["open", "open"]}
    posterior = infer_action(DOOR, params, evidence)
    assert posterior.implausible.tolist() == [True, False]
    assert posterior.best_names[1] == "push"
    torch.testing.assert_close(posterior.probs.sum(-1), torch.ones(2, dtype=DTYPE))
    check = imitation_check(DOOR, params, evidence | {"action": ["unlock", "push"]})
    assert check.implausible.tolist() == [True, False]
    forward = predict(DOOR, params, {"initial.door": ["locked"], "action": ["wait"]})
    assert forward.implausible.tolist() == [False]  # no end state observed


def test_a_lenient_threshold_lets_the_locked_door_through():
    params = fit(DOOR, door_rows(3000, 0)).params
    evidence = {"initial.door": ["locked"], "end.door": ["open"]}
    p = float(plausibility(DOOR, params, DOOR.encode(evidence)).discrete[0])
    assert 0 < p < IMPLAUSIBLE_BELOW
    assert not bool(infer_action(DOOR, params, evidence, implausible_below=p / 2).implausible[0])


@pytest.mark.parametrize("below", [0, 1, -0.1, 2.0, "0.1"])
def test_a_threshold_outside_zero_one_is_refused(below):
    params = random_params(DOOR, 0)
    with pytest.raises(ValueError, match="implausible_below"):
        infer_action(
            DOOR, params, {"initial.door": ["shut"], "end.door": ["open"]}, implausible_below=below
        )


def mahalanobis(x, mean, cov):
    diff = x - mean
    return float(diff @ torch.linalg.solve(cov, diff))


@pytest.mark.parametrize("dim", [1, 2])
def test_continuous_tail_is_the_closed_form_gaussian_tail(dim):
    """With the action given there is one component: tail = P(χ²_d > D²), which is
    erfc(|z| / √2) in one dimension and exp(-D² / 2) in two."""
    net = EffectNetwork(
        (Discrete("visible", (False, True)), Continuous("pos", dim)), ("remove", "tap")
    )
    params = random_params(net, 3)
    g = torch.Generator().manual_seed(1)
    cpd = params["end.pos"]
    for scale in (0.5, 2.0, 6.0, 20.0):
        pos0 = torch.randn(dim, generator=g, dtype=DTYPE)
        vis0 = 1
        d2 = {}
        for a in range(2):
            mean = cpd.weight[vis0, a] @ pos0 + cpd.bias[vis0, a]
            d2[a] = mean, cpd.covariance[vis0, a]
        mean, cov = d2[0]
        pos1 = mean + scale * torch.linalg.cholesky(cov) @ torch.ones(dim, dtype=DTYPE)
        evidence = {
            "initial.visible": [True],
            "initial.pos": pos0[None],
            "action": ["remove"],
            "end.pos": pos1[None],
        }
        got = plausibility(net, params, net.encode(evidence))
        dist2 = mahalanobis(pos1, mean, cov)
        want = math.erfc(math.sqrt(dist2 / 2)) if dim == 1 else math.exp(-dist2 / 2)
        assert float(got.tail[0]) == pytest.approx(want, rel=1e-8, abs=1e-300)
        assert float(got.discrete[0]) == 1.0
        check = imitation_check(net, params, evidence)
        assert bool(check.implausible[0]) is (want < IMPLAUSIBLE_BELOW)
        # without the action: the closest of the two actions' components
        closest = min(mahalanobis(pos1, *d2[a]) for a in range(2))
        want = math.erfc(math.sqrt(closest / 2)) if dim == 1 else math.exp(-closest / 2)
        unknown = {k: v for k, v in evidence.items() if k != "action"}
        got = plausibility(net, params, net.encode(unknown))
        assert float(got.tail[0]) == pytest.approx(want, rel=1e-8, abs=1e-300)
        posterior = infer_action(net, params, unknown)
        assert bool(posterior.implausible[0]) is (want < IMPLAUSIBLE_BELOW)
        torch.testing.assert_close(posterior.probs.sum(-1), torch.ones(1, dtype=DTYPE))


NET = EffectNetwork(
    (Discrete("visible", (False, True)), Continuous("pos", 2)),
    ("remove", "tap", "push"),
    (Parameter("force", (0.0,), (10.0,), (3,), ("tap", "push"), "pos"),),
)


def test_far_out_evidence_is_flagged_by_every_query():
    params = random_params(NET, 5)
    near = torch.zeros(1, 2, dtype=DTYPE)
    evidence = {"initial.visible": [True], "initial.pos": near, "end.visible": [True]}
    far = evidence | {"end.pos": torch.full((1, 2), 1e4, dtype=DTYPE)}
    for query in (
        lambda ev: infer_action(NET, params, ev),
        lambda ev: imitation_check(NET, params, ev | {"action": ["tap"]}),
        lambda ev: infer_parameter(NET, params, "force", ev | {"action": ["tap"]}),
        lambda ev: predict(NET, params, ev | {"action": ["tap"]}),
    ):
        assert query(far).implausible.tolist() == [True]


@settings(max_examples=20, deadline=None)
@given(
    cards=st.lists(st.integers(2, 3), min_size=1, max_size=3),
    n_actions=st.integers(1, 4),
    seed=st.integers(0, 1000),
    data=st.data(),
)
def test_compiled_action_query_flags_what_the_traced_one_flags(cards, n_actions, seed, data):
    net = discrete_network(cards, n_actions)
    params = random_params(net, seed, unseen=0.3)
    compiled = inference.compile(net, params).action_tables
    g = torch.Generator().manual_seed(seed)
    ev = {}
    for i, k in enumerate(cards):
        for role in ("initial", "end"):
            if data.draw(st.booleans()):
                ev[f"{role}.f{i}"] = torch.randint(0, k, (9,), generator=g)
    if not ev:
        ev["end.f0"] = torch.randint(0, cards[0], (9,), generator=g)
    ev = net.encode_indices(ev)
    p = plausibility(net, params, ev).discrete
    for below in (0.5 * float(p.min()), float(p.median()), 0.999):
        if not any(abs(float(x) / below - 1) < 1e-6 for x in p):  # no row on the threshold
            a = compiled.infer_action(ev, implausible_below=below)
            b = infer_action(net, params, ev, implausible_below=below)
            assert torch.equal(a.implausible, b.implausible)
            assert torch.equal(a.implausible, p < below)


def test_compiled_parameter_query_flags_what_the_traced_one_flags():
    params = random_params(NET, 21)
    query = inference.compile(NET, params).parameter_query("force")
    g = torch.Generator().manual_seed(1)
    n = 40
    ev = {
        "initial.visible": torch.randint(0, 2, (n,), generator=g).bool().tolist(),
        "initial.pos": torch.randn(n, 2, generator=g, dtype=DTYPE),
        "action": ["tap", "push"] * (n // 2),
        "end.pos": torch.randn(n, 2, generator=g, dtype=DTYPE) * torch.logspace(0, 3, n)[:, None],
    }
    a = query.infer_parameter(ev)
    b = infer_parameter(NET, params, "force", ev)
    assert torch.equal(a.implausible, b.implausible)
    assert 0 < int(a.implausible.sum()) < n


def _distance_world(n=2000, seed=0):
    """Initial distances trained on 0.1-1.2 m; push (with a force) moves the object."""
    net = EffectNetwork(
        (Continuous("distance", 1), Continuous("pos", 1)),
        ("push", "wait"),
        (Parameter("force", 0.0, 10.0, 4, ("push",), "pos"),),
    )
    rng = np.random.default_rng(seed)
    action = rng.choice(net.actions, n)
    distance = rng.uniform(0.1, 1.2, (n, 1))
    pos = rng.uniform(-1.0, 1.0, (n, 1))
    force = np.where(action[:, None] == "push", rng.uniform(0.0, 10.0, (n, 1)), np.nan)
    data = {
        "initial.distance": distance,
        "initial.pos": pos,
        "action": action,
        "param.force": force,
        "end.distance": distance + rng.normal(0.0, 0.01, (n, 1)),
        "end.pos": pos + 0.05 * np.nan_to_num(force) + rng.normal(0.0, 0.01, (n, 1)),
    }
    return net, fit(net, data).params, distance[:, 0]


def test_an_initial_state_far_outside_the_training_data_is_flagged_by_name():
    """A distance of 1e6 m where training covered 0.1-1.2 m: every query flags the row
    and names the field; inside the range nothing is flagged. The tail is the chi-square
    tail of the value under the training rows' own mean and spread."""
    from effect_networks.inference.queries.implausibility import OutsideTrainingData

    net, params, trained = _distance_world()
    rows = {"initial.distance": [[0.6], [1e6], [1.3]], "initial.pos": [[0.0]] * 3}
    z = (np.array([0.6, 1e6, 1.3]) - trained.mean()) / trained.std()
    want = [math.erfc(abs(v) / math.sqrt(2)) for v in z]
    got = plausibility(net, params, net.encode(rows)).initial["initial.distance"]
    torch.testing.assert_close(got, torch.tensor(want, dtype=DTYPE), rtol=1e-3, atol=1e-300)
    push = rows | {"action": ["push"] * 3}
    ends = {"end.distance": [[0.6], [1e6], [1.3]], "end.pos": [[0.25]] * 3}
    queries = {
        "predict": lambda: predict(net, params, push | {"param.force": [[5.0]] * 3}),
        "infer_action": lambda: infer_action(net, params, rows | ends),
        "imitation_check": lambda: imitation_check(net, params, push | ends),
        "infer_parameter": lambda: infer_parameter(net, params, "force", push | ends),
        "compiled": lambda: (
            inference.compile(net, params).parameter_query("force").infer_parameter(push | ends)
        ),
    }
    for name, query in queries.items():
        with pytest.warns(
            OutsideTrainingData, match=r"initial\.distance: 1 row\(s\), the first row 1"
        ):
            answer = query()
        assert answer.implausible.tolist() == [False, True, False], name


def test_the_discrete_flag_and_the_imitation_likelihood_hold_at_a_large_initial_state():
    """log p(end | rest) is a ratio whose shared factors cancel: with the initial position
    at 1e8 (its own density near -1e16) the imitation log-likelihood is the observed end
    position's Gaussian density, computed by hand in 50 digits."""
    import warnings

    from effect_networks.inference.queries.implausibility import OutsideTrainingData

    net, params, _ = _distance_world()
    x = 1e8
    lg = params["end.pos"]  # parents: action, cluster.force; inputs: distance, pos, force
    assert net.cpd("end.pos").parents == ("action", "cluster.force")
    w, b, tril = lg.weight[1, 0], lg.bias[1, 0], lg.scale_tril[1, 0]  # wait: cluster 0
    mean = float(w[0, 0]) * 0.5 + float(w[0, 1]) * x + float(b[0])
    y = mean + 0.7 * float(tril[0, 0])
    ev = {"initial.distance": [[0.5]], "initial.pos": [[x]], "action": ["wait"]}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutsideTrainingData)  # 1e8: far outside, flagged
        check = imitation_check(net, params, ev | {"end.pos": [[y]]})
    assert bool(check.implausible[0])
    with mpmath.workdps(50):
        r = (
            mpmath.mpf(y)
            - mpmath.mpf(float(w[0, 0])) * mpmath.mpf(0.5)
            - mpmath.mpf(float(w[0, 1])) * mpmath.mpf(x)
            - mpmath.mpf(float(b[0]))
        )
        s = mpmath.mpf(float(tril[0, 0]))
        want = float(-((r / s) ** 2) / 2 - mpmath.log(s) - mpmath.log(2 * mpmath.pi) / 2)
    assert abs(float(check.log_likelihood[0]) - want) < 1e-6


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 50), exponent=st.floats(0.0, 150.0), end=st.booleans())
def test_the_discrete_plausibility_is_right_at_any_accepted_initial_magnitude(seed, exponent, end):
    """p(end.visible | initial) of README's network, every action summed out, against a
    60-digit oracle, with the initial position anywhere up to the magnitude limit."""
    params = random_params(README_NET, seed)
    x = 10.0**exponent
    ev = README_NET.encode(
        {"initial.visible": [True], "initial.position": [[x]], "end.visible": [end]}
    )
    prior = params["action"].probs.tolist()
    want = sum(prior[a] * softmax_oracle(params, (1, a), x)[int(end)] for a in range(3))
    got = plausibility(README_NET, params, ev).discrete
    assert abs(float(got[0]) - float(want)) < 1e-12
