"""Queries with continuous features and a parameter, against independent numerics."""

import math

import pytest
import torch
from effect_networks.inference import imitation_check, infer_action, infer_parameter, predict
from effect_networks.models import Continuous, Discrete, EffectNetwork
from effect_networks.models.declaration import DTYPE
from effect_networks.models.gaussian import condition_linear_gaussian
from hypothesis import example, given, settings
from hypothesis import strategies as st

from tests.helpers import random_params
from tests.networks import NET, README_NET, softmax_oracle


def normal_pdf(x, mean, cov):
    """Density of N(mean, cov) at x; mean may carry a leading batch dim."""
    d = x.shape[-1]
    diff = x - mean
    quad = (diff * torch.linalg.solve(cov, diff.T).T).sum(-1)
    return torch.exp(-0.5 * quad) / math.sqrt((2 * math.pi) ** d * float(torch.det(cov)))


def brute_action_posterior(params, vis0, pos0, pos1):
    """p(action | initial, end.pos) by trapezoid integration over the 1-D force."""
    theta = torch.linspace(-40, 50, 9001, dtype=DTYPE)
    post = []
    for a in range(3):
        uses = a in (1, 2)
        total = 0.0
        for c in range(3) if uses else [0]:
            pc = float(params["cluster.force"].probs[a, c])
            cpd = params["end.pos"]
            w, b, cov = cpd.weight[vis0, a, c], cpd.bias[vis0, a, c], cpd.covariance[vis0, a, c]
            if not uses:
                total += pc * float(normal_pdf(pos1, (w[:, :2] @ pos0 + b)[None], cov)[0])
                continue
            m, s = params["param.force"].bias[c, 0], params["param.force"].covariance[c, 0, 0]
            means = (w[:, :2] @ pos0 + b)[None] + theta[:, None] * w[:, 2][None]
            dens = normal_pdf(pos1, means, cov)
            prior = torch.exp(-0.5 * (theta - m) ** 2 / s) / torch.sqrt(2 * math.pi * s)
            total += pc * float(torch.trapezoid(dens * prior, theta))
        post.append(float(params["action"].probs[a]) * total)
    post = torch.tensor(post, dtype=DTYPE)
    return post / post.sum()


def test_action_posterior_integrates_parameter_out():
    params = random_params(NET, 5)
    for seed in range(3):
        g = torch.Generator().manual_seed(seed)
        pos0 = torch.randn(2, generator=g, dtype=DTYPE)
        pos1 = torch.randn(2, generator=g, dtype=DTYPE) * 2
        got = infer_action(
            NET,
            params,
            {"initial.visible": [True], "initial.pos": pos0[None], "end.pos": pos1[None]},
        )
        want = brute_action_posterior(params, 1, pos0, pos1)
        torch.testing.assert_close(got.probs[0], want, atol=1e-6, rtol=1e-5)


def test_predict_given_parameter_is_one_gaussian():
    params = random_params(NET, 8)
    pos0 = torch.tensor([[0.3, -0.2]], dtype=DTYPE)
    force = torch.tensor([[7.5]], dtype=DTYPE)  # cluster 2
    pred = predict(
        NET,
        params,
        {"initial.visible": [False], "initial.pos": pos0, "action": ["tap"], "param.force": force},
    )
    mix = pred.continuous["pos"]
    assert mix.weights.shape[1] == 1
    cpd = params["end.pos"]
    x = torch.cat([pos0[0], force[0]])
    torch.testing.assert_close(mix.mean[0], cpd.weight[0, 1, 2] @ x + cpd.bias[0, 1, 2])
    torch.testing.assert_close(mix.cov[0], cpd.covariance[0, 1, 2])


def test_inverse_parameter_query_matches_joint_gaussian_conditioning():
    params = random_params(NET, 13)
    pos0 = torch.tensor([[0.1, 0.4]], dtype=DTYPE)
    pos1 = torch.tensor([[3.0, 1.0]], dtype=DTYPE)
    out = infer_parameter(
        NET,
        params,
        "force",
        {"initial.visible": [True], "initial.pos": pos0, "action": ["push"], "end.pos": pos1},
    )
    c = int(out.best_cluster[0])
    # joint Gaussian of (theta, y) by hand, then the block formula
    m, s = params["param.force"].bias[c], params["param.force"].covariance[c]
    cpd = params["end.pos"]
    w, b, r = cpd.weight[1, 2, c], cpd.bias[1, 2, c], cpd.covariance[1, 2, c]
    wp = w[:, 2:]
    mu_y = w[:, :2] @ pos0[0] + wp @ m + b
    s_yy = wp @ s @ wp.T + r
    s_ty = s @ wp.T
    mean = m + s_ty @ torch.linalg.solve(s_yy, pos1[0] - mu_y)
    cov = s - s_ty @ torch.linalg.solve(s_yy, s_ty.T)
    torch.testing.assert_close(out.mean[0], mean)
    torch.testing.assert_close(out.cov[0], cov)
    assert abs(float(out.cluster_probs.sum()) - 1) < 1e-9


def test_condition_linear_gaussian_batch_shapes():
    g = torch.Generator().manual_seed(0)
    mean = torch.randn(4, 3, generator=g, dtype=DTYPE)
    a = torch.randn(4, 3, 3, generator=g, dtype=DTYPE)
    cov = a @ a.mT + torch.eye(3, dtype=DTYPE)
    w = torch.randn(4, 2, 3, generator=g, dtype=DTYPE)
    m, c = condition_linear_gaussian(
        mean,
        cov,
        w,
        torch.zeros(4, 2, dtype=DTYPE),
        torch.eye(2, dtype=DTYPE),
        torch.ones(4, 2, dtype=DTYPE),
    )
    assert m.shape == (4, 3) and c.shape == (4, 3, 3)
    assert (torch.linalg.eigvalsh(c) > 0).all()


def test_joint_surprise_of_discrete_and_continuous_end_features():
    # end.visible (softmax on the initial position) and end.pos are independent given the
    # initial state and the action: the tail probability by a large hand-made sample.
    net = EffectNetwork((Discrete("visible", (False, True)), Continuous("pos", 1)), ("a", "b"))
    params = random_params(net, 7)
    gen = torch.Generator().manual_seed(0)
    for vis0, pos0, action, vis1, pos1 in [(1, 0.3, 0, 0, 0.5), (0, -1.0, 1, 1, -2.0)]:
        soft = params["end.visible"]
        logits = soft.weight[vis0, action, :, 0] * pos0 + soft.bias[vis0, action]
        p_vis = logits.softmax(-1)
        g = params["end.pos"]
        mean = float(g.weight[vis0, action, 0, 0] * pos0 + g.bias[vis0, action, 0])
        sd = float(g.scale_tril[vis0, action, 0, 0])

        def log_density(v, x, p_vis=p_vis, mean=mean, sd=sd):
            return p_vis[v].log() - 0.5 * ((x - mean) / sd) ** 2 - math.log(sd)

        m = 200_000
        v = torch.multinomial(p_vis, m, replacement=True, generator=gen)
        x = mean + sd * torch.randn(m, generator=gen, dtype=DTYPE)
        want = float(
            (log_density(v, x) > log_density(vis1, torch.tensor(pos1, dtype=DTYPE))).double().mean()
        )
        got = imitation_check(
            net,
            params,
            {
                "initial.visible": [bool(vis0)],
                "initial.pos": [[pos0]],
                "action": [net.actions[action]],
                "end.visible": [bool(vis1)],
                "end.pos": [[pos1]],
            },
            n_samples=4000,
        )
        assert abs(float(got.surprise[0]) - want) < 0.03
        want_ll = float(log_density(vis1, torch.tensor(pos1, dtype=DTYPE))) - 0.5 * math.log(
            2 * math.pi
        )
        assert abs(float(got.log_likelihood[0]) - want_ll) < 1e-9


def test_full_parameter_posterior_is_the_integral_over_the_force():
    from effect_networks import inference

    params = random_params(NET, 6)
    vis0, action = 1, 2  # push
    pos0 = torch.tensor([0.2, -0.4], dtype=DTYPE)
    pos1 = torch.tensor([1.5, 0.5], dtype=DTYPE)
    ev = {"initial.visible": [True], "initial.pos": pos0[None], "action": ["push"]}
    ev |= {"end.pos": pos1[None]}
    got = infer_parameter(NET, params, "force", ev, mixture=True)
    # p(theta | y) by brute force over a grid: sum over clusters of
    # p(c | push) N(theta; m_c, s_c) N(y; W [x, theta] + b, R)
    theta = torch.linspace(-40, 50, 20001, dtype=DTYPE)
    density = torch.zeros_like(theta)
    for c in range(3):
        pc = float(params["cluster.force"].probs[action, c])
        cpd = params["end.pos"]
        w, b, cov = (
            cpd.weight[vis0, action, c],
            cpd.bias[vis0, action, c],
            cpd.covariance[vis0, action, c],
        )
        m, s = params["param.force"].bias[c, 0], params["param.force"].covariance[c, 0, 0]
        means = (w[:, :2] @ pos0 + b)[None] + theta[:, None] * w[:, 2][None]
        prior = torch.exp(-0.5 * (theta - m) ** 2 / s) / torch.sqrt(2 * math.pi * s)
        density += pc * normal_pdf(pos1, means, cov) * prior
    z = torch.trapezoid(density, theta)
    mean = torch.trapezoid(theta * density, theta) / z
    var = torch.trapezoid((theta - mean) ** 2 * density, theta) / z
    mix = got.mixture
    torch.testing.assert_close(mix.mean[0, 0], mean, atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(mix.cov[0, 0, 0], var, atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(mix.weights, got.cluster_probs)
    best = int(got.best_cluster[0])
    torch.testing.assert_close(mix.means[0, best], got.mean[0])  # the paper's answer inside
    compiled = (
        inference.compile(NET, params)
        .parameter_query("force")
        .infer_parameter(ev, mixture=True)
        .mixture
    )
    torch.testing.assert_close(compiled.means, mix.means)
    torch.testing.assert_close(compiled.covs, mix.covs)
    assert infer_parameter(NET, params, "force", ev).mixture is None  # the paper's default


def test_inferred_parameter_outside_its_range_is_flagged():
    params = random_params(NET, 6)
    ev = {"initial.visible": [True, True], "initial.pos": [[0.0, 0.0]] * 2}
    ev |= {"action": ["push", "push"]}
    inside = infer_parameter(NET, params, "force", ev | {"end.pos": [[0.0, 0.0]] * 2})
    means = inside.mean[:, 0]
    assert inside.outside.tolist() == ((means < 0) | (means > 10)).tolist()
    # an effect the declared forces cannot make: far along the force's direction
    w = params["end.pos"].weight[1, 2, 2, :, 2]
    far = (1e4 * w / w.norm())[None].expand(2, 2)
    flagged = infer_parameter(NET, params, "force", ev | {"end.pos": far})
    assert flagged.outside.all()


@settings(max_examples=30, deadline=None)
@given(
    seed=st.integers(0, 50),
    exponent=st.floats(0.0, 150.0),
    sign=st.sampled_from([1.0, -1.0]),
    where=st.sampled_from(["initial.position", "param.force"]),
)
@example(seed=0, exponent=10.0, sign=1.0, where="initial.position")
@example(seed=0, exponent=150.0, sign=-1.0, where="param.force")
def test_answers_are_normalised_and_right_at_every_accepted_magnitude(seed, exponent, sign, where):
    """From ordinary values to the magnitude limit, on an initial state or a parameter:
    every distribution sums to 1 within 1e-12, never NaN, and equals a 60-digit oracle."""
    params = random_params(README_NET, seed)
    big = sign * 10.0**exponent
    position = big if where == "initial.position" else 0.3
    force = big if where == "param.force" else 10.0
    ev = {"initial.visible": [True], "initial.position": [[position]]}
    visible = README_NET.site("end.visible")
    parents = README_NET.cpd(visible.name).parents
    assert parents == ("initial.visible", "action")

    tapped = predict(README_NET, params, ev | {"action": ["tap"], "param.force": [[force]]})
    p = tapped.discrete["visible"][0]
    assert abs(float(p.sum()) - 1.0) < 1e-12
    want = [float(v) for v in softmax_oracle(params, (1, 2), position)]
    torch.testing.assert_close(p, torch.tensor(want, dtype=DTYPE), atol=1e-12, rtol=0)

    # p(action | initial, end.visible = False): the table of actions times the softmax
    post = infer_action(README_NET, params, ev | {"end.visible": [False]})
    prior = params["action"].probs.tolist()
    joint = [prior[a] * softmax_oracle(params, (1, a), position)[0] for a in range(3)]
    want = torch.tensor([float(v / sum(joint)) for v in joint], dtype=DTYPE)
    assert abs(float(post.probs.sum()) - 1.0) < 1e-12
    torch.testing.assert_close(post.probs[0], want, atol=1e-9, rtol=0)
    assert float(want[int(post.best[0])]) >= float(want.max()) - 1e-9


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 50), exponent=st.floats(0.0, 150.0), sign=st.sampled_from([1.0, -1.0]))
def test_an_end_state_far_from_every_component_leaves_distributions_normalised(
    seed, exponent, sign
):
    """An observed end position far from every Gaussian component: the action posterior
    and the prediction of the other feature still sum to 1 within 1e-12, and no NaN."""
    params = random_params(README_NET, seed)
    ev = {"initial.visible": [True], "initial.position": [[0.1]]}
    far = {"end.position": [[sign * 10.0**exponent]]}
    post = infer_action(README_NET, params, ev | far)
    assert not post.probs.isnan().any()
    assert abs(float(post.probs.sum()) - 1.0) < 1e-12
    assert float(post.probs[0, int(post.best[0])]) == float(post.probs.max()) or bool(
        post.unseen[0].max() >= 0.5
    )
    pred = predict(README_NET, params, ev | far)
    assert abs(float(pred.discrete["visible"].sum()) - 1.0) < 1e-12
    weights = pred.continuous if pred.continuous else {}
    for mixture in weights.values():
        assert abs(float(mixture.weights.sum()) - 1.0) < 1e-12


def test_beyond_the_magnitude_limit_queries_refuse_by_name():
    params = random_params(README_NET, 0)
    ev = {"initial.visible": [True], "initial.position": [[1e160]]}
    with pytest.raises(ValueError, match=r"site 'initial\.position': row 0 .* beyond \+-1e\+150"):
        infer_action(README_NET, params, ev | {"end.visible": [False]})


def test_evidence_with_no_probability_in_float64_is_refused_not_nan():
    """Within the magnitude limit, a value ~1e156 noise standard deviations from every
    component has a density that underflows to 0 in float64 under every configuration:
    the queries say so, naming the row and the site, instead of answering NaN."""
    import dataclasses

    from effect_networks.models.params import NetworkParams

    net = EffectNetwork((Continuous("x"),), ("a", "b"))
    params = random_params(net, 0)
    cpd = params["end.x"]
    tiny = dataclasses.replace(cpd, scale_tril=torch.full_like(cpd.scale_tril, 1e-6))
    params = NetworkParams(params.cpds | {"end.x": tiny}, params.pseudo_count)
    ordinary = infer_action(net, params, {"initial.x": [[0.0]], "end.x": [[1e3]]})
    assert abs(float(ordinary.probs.sum()) - 1.0) < 1e-12
    far = {"initial.x": [[0.0], [0.0]], "end.x": [[0.0], [1e150]]}
    with pytest.raises(ValueError, match=r"row 1 has probability 0 .*'end\.x'"):
        infer_action(net, params, far)
    with pytest.raises(ValueError, match=r"row 1 has probability 0 .*'end\.x'"):
        predict(net, params, far)  # no posterior over the action to predict with
    # imitation asks how surprising the outcome is: certainly, and nothing is NaN
    check = imitation_check(net, params, far | {"action": ["a", "a"]}, n_samples=50)
    assert float(check.log_likelihood[1]) == -math.inf and float(check.surprise[1]) == 1.0
    assert not check.unseen.isnan().any() and bool(check.implausible[1])
