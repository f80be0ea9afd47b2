"""The imitation surprise with continuous end features (inference.queries.surprise), against
oracles built by hand from the parameters: scipy's chi-square CDF where one Gaussian
component predicts the outcome, numerical integration of the predictive mixture where
several do.

The surprise of an observation ``y*`` is ``P_{Y ~ p}(p(Y) > p(y*))`` for the predictive
``p`` given the rest of the evidence."""

import time
import warnings
from dataclasses import replace

import numpy as np
import pytest
import torch
from effect_networks.inference import imitation_check, predict
from effect_networks.inference.queries.implausibility import OutsideTrainingData
from effect_networks.inference.queries.surprise import _joint_gaussians
from effect_networks.models import (
    Continuous,
    Discrete,
    EffectNetwork,
    Parameter,
    Partial,
    random_params,
)
from effect_networks.models.declaration import DTYPE
from scipy import stats

TAP = EffectNetwork(  # README's network
    features=(Discrete("visible", (False, True)), Continuous("position", 1)),
    actions=("look", "remove", "tap"),
    parameters=(
        Parameter("force", low=0.0, high=20.0, bins=8, actions=("tap",), affects="position"),
    ),
)

SHARED = EffectNetwork(  # one unknown value acting on two continuous features
    features=(Continuous("a", 1), Continuous("b", 1)),
    actions=("push", "wait"),
    parameters=(
        Parameter("force", low=0.0, high=3.0, bins=3, actions=("push",), affects=("a", "b")),
    ),
)


def grid_surprise(log_density, grid_points, cell, observations, levels=None):
    """``P(p(Y) > p(y*))`` for each ``y*`` by a Riemann sum over a fine grid (``levels``:
    the ``log p(y*)`` to compare with, if not the observations' own)."""
    log_p = np.sort(log_density(grid_points))
    mass = np.cumsum(np.exp(log_p)[::-1])[::-1] * cell  # mass[i]: of the points from i up
    levels = log_density(observations) if levels is None else levels
    first = np.searchsorted(log_p, levels, side="right")
    return np.append(mass, 0.0)[first]


@pytest.mark.parametrize("dim", [1, 2, 3])
def test_one_gaussian_is_the_chi_square_cdf_of_the_mahalanobis_distance(dim):
    net = EffectNetwork((Continuous("pos", dim),), ("a", "b"))
    params = random_params(net, dim)
    rng = np.random.default_rng(dim)
    n = 200
    x0 = rng.normal(size=(n, dim))
    action = rng.integers(0, 2, n)
    y = rng.normal(size=(n, dim)) * rng.uniform(0.1, 5.0, (n, 1))
    evidence = {
        "initial.pos": x0,
        "action": [net.actions[a] for a in action],
        "end.pos": y,
    }
    got = imitation_check(net, params, evidence).surprise.numpy()
    g = params["end.pos"]
    want = []
    for i in range(n):
        w = g.weight[action[i]].numpy()
        mean = w @ x0[i] + g.bias[action[i]].numpy()
        cov = g.covariance[action[i]].numpy()
        diff = y[i] - mean
        want.append(stats.chi2.cdf(diff @ np.linalg.solve(cov, diff), dim))
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


def test_partial_evidence_counts_the_observed_dimensions_only():
    net = EffectNetwork((Continuous("pos", 2),), ("a",))
    params = random_params(net, 4)
    y = np.array([[0.7, -1.3]] * 3)
    seen = np.array([[True, False], [False, True], [True, True]])
    x0 = np.zeros((3, 2))
    evidence = {"initial.pos": x0, "action": ["a"] * 3, "end.pos": Partial(y, observed=seen)}
    got = imitation_check(net, params, evidence)
    g = params["end.pos"]
    mean, cov = g.bias[0].numpy(), g.covariance[0].numpy()
    want = [
        stats.chi2.cdf((0.7 - mean[0]) ** 2 / cov[0, 0], 1),
        stats.chi2.cdf((-1.3 - mean[1]) ** 2 / cov[1, 1], 1),
        stats.chi2.cdf((y[2] - mean) @ np.linalg.solve(cov, y[2] - mean), 2),
    ]
    np.testing.assert_allclose(got.surprise.numpy(), want, rtol=0, atol=1e-12)


def test_discrete_and_continuous_end_features_together_are_exact():
    # each visible state has one Gaussian for the position: the surprise sums, over the
    # visible states v, p(v) P(chi2_1 < r_v^2) with r_v^2 = D_v^2(y*) + 2 log(p(v, y*)/p(o*))
    net = EffectNetwork((Discrete("visible", (False, True)), Continuous("pos", 1)), ("a", "b"))
    params = random_params(net, 7)
    for vis0, pos0, action, vis1, pos1 in [(1, 0.3, 0, 0, 0.5), (0, -1.0, 1, 1, -2.0)]:
        soft = params["end.visible"]
        logits = soft.weight[vis0, action, :, 0] * pos0 + soft.bias[vis0, action]
        p_vis = logits.softmax(-1).numpy()
        g = params["end.pos"]
        mean = float(g.weight[vis0, action, 0, 0] * pos0 + g.bias[vis0, action, 0])
        sd = float(g.scale_tril[vis0, action, 0, 0])
        # the position does not depend on the end state of visible: one Gaussian
        log_star = np.log(p_vis[vis1]) + stats.norm.logpdf(pos1, mean, sd)
        want = 0.0
        for v in (0, 1):
            # p(v) N(Y) > p(o*)  <=>  |Y - mean| / sd < r
            r2 = 2 * (np.log(p_vis[v]) - np.log(sd) - 0.5 * np.log(2 * np.pi) - log_star)
            want += p_vis[v] * stats.chi2.cdf(max(r2, 0.0), 1)
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
        )
        assert abs(float(got.surprise[0]) - want) < 1e-12


def tap_mixture(params, visible, position):
    """The predictive of end.position after a tap with the force unknown, by hand:
    weights p(c | tap), means W_x x + W_f mu_c + b, variances R + W_f S_c W_f^T."""
    tap = TAP.actions.index("tap")
    weights = params["cluster.force"].probs[tap].numpy()
    prior = params["param.force"]
    g = params["end.position"]
    w = g.weight[visible, tap, :, 0].numpy()  # (C, 2): position, force
    mean = (
        w[:, 0] * position + w[:, 1] * prior.bias[:, 0].numpy() + g.bias[visible, tap, :, 0].numpy()
    )
    var = (
        g.covariance[visible, tap, :, 0, 0].numpy()
        + w[:, 1] ** 2 * prior.covariance[:, 0, 0].numpy()
    )
    return weights, mean, np.sqrt(var)


def test_mixture_surprise_equals_numerical_integration():
    params = random_params(TAP, 1)
    weights, mean, sd = tap_mixture(params, 1, 0.0)
    ys = np.linspace(-4.0, 4.0, 17)
    evidence = {
        "initial.visible": [True] * len(ys),
        "initial.position": [[0.0]] * len(ys),
        "action": ["tap"] * len(ys),
        "end.position": ys[:, None],
    }
    got = imitation_check(TAP, params, evidence).surprise.numpy()
    grid = np.linspace(mean.min() - 12 * sd.max(), mean.max() + 12 * sd.max(), 1_000_001)

    def log_density(y):
        return np.log((weights * stats.norm.pdf(y[:, None], mean, sd)).sum(1))

    cell = grid[1] - grid[0]
    want = grid_surprise(log_density, grid, cell, ys)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-4)


def test_shared_parameter_on_two_features_integrates_their_joint():
    # the unknown force couples end.a and end.b: per cluster a 2-D Gaussian whose
    # cross-covariance is W_a S_c W_b; the surprise integrates that mixture over a grid
    params = random_params(SHARED, 2)
    # little noise beside a wide value: the features' cross-covariance dominates
    wide = {
        "param.force": replace(
            params["param.force"], scale_tril=params["param.force"].scale_tril * 3
        )
    }
    for s in ("end.a", "end.b"):
        wide[s] = replace(params[s], scale_tril=params[s].scale_tril * 0.2)
    table = params["cluster.force"]  # clusters of comparable weight: their overlap counts
    wide["cluster.force"] = replace(table, probs=torch.tensor([[0.4, 0.3, 0.3], [1.0, 0, 0]]))
    params = replace(params, cpds=params.cpds | wide)
    push = 0
    x0 = np.array([0.2, -0.3])
    weights = params["cluster.force"].probs[push].numpy()
    prior = params["param.force"]
    means, covs = [], []
    for c in range(3):
        loading, offset, noise = [], [], []
        for s in ("end.a", "end.b"):
            g = params[s]
            w = g.weight[push, c, 0].numpy()  # initial.a, initial.b, param.force
            loading.append(w[2])
            offset.append(w[:2] @ x0 + g.bias[push, c, 0].numpy() + w[2] * prior.bias[c, 0].numpy())
            noise.append(g.covariance[push, c, 0, 0].numpy())
        loading = np.array(loading)
        means.append(np.array(offset))
        covs.append(np.diag(noise) + np.outer(loading, loading) * prior.covariance[c, 0, 0].numpy())
    observations = np.array(
        [means[0] + [0.1, -0.2], (means[0] + means[2]) / 2, means[2] + [0.3, -0.3]]
    )
    evidence = {
        "initial.a": [[x0[0]]] * 3,
        "initial.b": [[x0[1]]] * 3,
        "action": ["push"] * 3,
        "end.a": observations[:, :1],
        "end.b": observations[:, 1:],
    }
    # the components' joint Gaussians, read off the model's chain of conditionals
    mean, tril = _joint_gaussians(SHARED, params, SHARED.encode(evidence), ["end.a", "end.b"], [])
    np.testing.assert_allclose(mean[:, 0].numpy(), np.broadcast_to(means, (3, 3, 2)), atol=1e-12)
    cov = (tril @ tril.mT)[:, 0].numpy()
    np.testing.assert_allclose(cov, np.broadcast_to(covs, (3, 3, 2, 2)), atol=1e-12)
    got = imitation_check(SHARED, params, evidence).surprise.numpy()
    low = np.min([m - 9 * np.sqrt(np.diag(c)) for m, c in zip(means, covs, strict=True)], 0)
    high = np.max([m + 9 * np.sqrt(np.diag(c)) for m, c in zip(means, covs, strict=True)], 0)
    ga, gb = np.linspace(low[0], high[0], 2001), np.linspace(low[1], high[1], 2001)
    points = np.stack(np.meshgrid(ga, gb, indexing="ij"), -1).reshape(-1, 2)

    def log_density(y):
        parts = [
            w * stats.multivariate_normal(m, c).pdf(y)
            for w, m, c in zip(weights, means, covs, strict=True)
        ]
        return np.log(np.sum(parts, 0))

    cell = (ga[1] - ga[0]) * (gb[1] - gb[0])
    want = grid_surprise(log_density, points, cell, observations)
    np.testing.assert_allclose(got, want, rtol=0, atol=3e-4)  # the grid's own error: 1e-4


def test_identical_rows_get_identical_surprises():
    params = random_params(TAP, 1)
    n = 40
    rng = np.random.default_rng(0)
    y = rng.normal(size=(n, 1))
    y[::5] = 0.37  # the same row at several places in the batch
    force = np.where(np.arange(n)[:, None] % 2 == 0, np.nan, 7.0)  # mixtures and one Gaussian
    force[::5] = np.nan
    evidence = {
        "initial.visible": [True] * n,
        "initial.position": np.zeros((n, 1)),
        "action": ["tap"] * n,
        "param.force": force,
        "end.position": y,
    }
    surprise = imitation_check(TAP, params, evidence).surprise
    assert torch.equal(surprise[::5], surprise[:1].expand(len(surprise[::5])))
    alone = imitation_check(TAP, params, {k: v[:1] for k, v in evidence.items()}).surprise
    assert torch.equal(alone, surprise[:1])
    again = imitation_check(TAP, params, evidence).surprise
    assert torch.equal(again, surprise)


def test_ten_thousand_one_gaussian_rows_take_well_under_a_second():
    # each row was a Monte Carlo sample of its own (tens of seconds); now a closed form
    net = EffectNetwork((Continuous("pos", 1),), ("a", "b"))
    params = random_params(net, 3)
    n = 10_000
    rng = np.random.default_rng(0)
    evidence = {
        "initial.pos": rng.normal(size=(n, 1)),
        "action": ["a"] * n,
        "end.pos": rng.normal(size=(n, 1)),
    }
    start = time.perf_counter()
    check = imitation_check(net, params, evidence)
    assert time.perf_counter() - start < 2.0  # about 0.1 s on one core; slack for load
    assert check.surprise.dtype == DTYPE and check.surprise.shape == (n,)


def test_partial_evidence_under_a_mixture_integrates_the_observed_dimensions():
    # a 2-D feature observed in x only, the force unknown: the predictive of x is the
    # mixture's marginal (predict's components, their x rows), integrated numerically
    net = EffectNetwork(
        (Continuous("xy", 2),),
        ("push",),
        (Parameter("force", low=0.0, high=4.0, bins=4, actions=("push",), affects="xy"),),
    )
    params = random_params(net, 5)
    start = {"initial.xy": [[0.1, -0.2]], "action": ["push"]}
    mix = predict(net, params, start).continuous["xy"]
    weights = mix.weights[0].numpy()
    mean, sd = mix.means[0, :, 0].numpy(), mix.covs[0, :, 0, 0].sqrt().numpy()
    xs = np.linspace(mean.min() - 2, mean.max() + 2, 9)
    evidence = {
        "initial.xy": [[0.1, -0.2]] * len(xs),
        "action": ["push"] * len(xs),
        "end.xy": Partial(np.stack([xs, np.zeros_like(xs)], -1), observed=[True, False]),
    }
    got = imitation_check(net, params, evidence).surprise.numpy()
    grid = np.linspace(mean.min() - 12 * sd.max(), mean.max() + 12 * sd.max(), 1_000_001)

    def log_density(y):
        return np.log((weights * stats.norm.pdf(y[:, None], mean, sd)).sum(1))

    want = grid_surprise(log_density, grid, grid[1] - grid[0], xs)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-4)


def test_many_separated_clusters_equal_numerical_integration():
    # 64 clusters, most far apart in each other's whitened coordinates: the quadrature
    # weighs only the components that can matter near each one
    net = EffectNetwork(
        (Continuous("pos", 1),),
        ("tap",),
        (Parameter("force", low=0.0, high=20.0, bins=64, actions=("tap",), affects="pos"),),
    )
    params = random_params(net, 1)
    start = {"initial.pos": [[0.0]], "action": ["tap"]}
    mix = predict(net, params, start).continuous["pos"]
    weights = mix.weights[0].numpy()
    mean, sd = mix.means[0, :, 0].numpy(), mix.covs[0, :, 0, 0].sqrt().numpy()
    ys = np.quantile(mean, [0.1, 0.3, 0.5, 0.7, 0.9]) + 0.3
    evidence = {"initial.pos": np.zeros((5, 1)), "action": ["tap"] * 5, "end.pos": ys[:, None]}
    got = imitation_check(net, params, evidence).surprise.numpy()
    grid = np.linspace(mean.min() - 10 * sd.max(), mean.max() + 10 * sd.max(), 400_001)

    def log_density(y):
        return np.log((weights * stats.norm.pdf(y[:, None], mean, sd)).sum(1))

    want = grid_surprise(log_density, grid, grid[1] - grid[0], ys)
    np.testing.assert_allclose(got, want, rtol=0, atol=5e-4)  # 4e-5 with n_samples=1024


def test_discrete_outcome_beside_a_mixture():
    # end.visible and end.position observed, the force unknown: p(v, y) = p(v) m(y) (the
    # position does not depend on the end state of visible), so the surprise is
    # sum_v p(v) P_m(p(v) m(Y) > p(v*) m(y*)), each term integrated over a grid
    params = random_params(TAP, 2)
    start = {"initial.visible": [True], "initial.position": [[0.2]], "action": ["tap"]}
    p_vis = predict(TAP, params, start).discrete["visible"][0].numpy()
    weights, mean, sd = tap_mixture(params, 1, 0.2)
    grid = np.linspace(mean.min() - 12 * sd.max(), mean.max() + 12 * sd.max(), 1_000_001)
    cell = grid[1] - grid[0]

    def log_m(y):
        return np.log((weights * stats.norm.pdf(y[:, None], mean, sd)).sum(1))

    ys = np.array([-1.0, 0.5, 2.0, 4.0])
    for vis in (False, True):
        evidence = {
            "initial.visible": [True] * len(ys),
            "initial.position": [[0.2]] * len(ys),
            "action": ["tap"] * len(ys),
            "end.visible": [vis] * len(ys),
            "end.position": ys[:, None],
        }
        got = imitation_check(TAP, params, evidence).surprise.numpy()
        star = np.log(p_vis[int(vis)]) + log_m(ys)
        want = sum(p * grid_surprise(log_m, grid, cell, ys, star - np.log(p)) for p in p_vis)
        np.testing.assert_allclose(got, want, rtol=0, atol=2e-4)


@pytest.mark.parametrize("start", [0.0, 1e4, 1e6, 1e8])
def test_the_surprise_is_exact_at_a_large_initial_state(start):
    """A continuous initial state far out shifts every log-weight by its density (about
    -start^2 / 2); the surprise keeps its digits. Two discrete outcomes, one Gaussian
    each (the softmax's slope set to 0, so p(visible) does not move with the start)."""
    net = EffectNetwork((Discrete("visible", (False, True)), Continuous("pos", 1)), ("a", "b"))
    params = random_params(net, 7)
    soft = replace(params["end.visible"], weight=torch.zeros_like(params["end.visible"].weight))
    params = replace(params, cpds=params.cpds | {"end.visible": soft})
    p_vis = soft.bias[1, 0].softmax(-1).numpy()
    g = params["end.pos"]
    mean = float(g.weight[1, 0, 0, 0]) * start + float(g.bias[1, 0, 0])
    sd = float(g.scale_tril[1, 0, 0, 0])
    pos1 = mean + 0.7 * sd
    log_star = np.log(p_vis[0]) + stats.norm.logpdf(0.7) - np.log(sd)
    want = 0.0
    for v in (0, 1):
        r2 = 2 * (np.log(p_vis[v]) - np.log(sd) - 0.5 * np.log(2 * np.pi) - log_star)
        want += p_vis[v] * stats.chi2.cdf(max(r2, 0.0), 1)
    evidence = {
        "initial.visible": [True],
        "initial.pos": [[start]],
        "action": ["a"],
        "end.visible": [False],
        "end.pos": [[pos1]],
    }
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OutsideTrainingData)
        got = imitation_check(net, params, evidence)
    assert abs(float(got.surprise[0]) - want) < 1e-6
