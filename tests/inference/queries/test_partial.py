"""Partial continuous evidence (``Partial``): some dimensions of an end feature observed.

Every query is compared with the Gaussian identities written out here on sub-matrices
(the observed dimensions' marginal: their rows and columns of the covariance; the
unobserved ones' conditional by the block formula), evaluated with
``torch.distributions`` and ``scipy``, and with full evidence when every dimension is
observed.
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
from effect_networks.inference.queries.implausibility import plausibility
from effect_networks.models import Continuous, Discrete, EffectNetwork, Parameter, Partial
from effect_networks.models.declaration import DTYPE
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats
from torch.distributions import MultivariateNormal

from effect_networks import inference
from tests.helpers import random_params

NET = EffectNetwork(
    (Discrete("visible", (False, True)), Continuous("pos", 3)),
    ("remove", "tap", "push"),
    (Parameter("force", (0.0,), (10.0,), (3,), ("tap", "push"), "pos"),),
)
USES = (False, True, True)
POS0 = torch.tensor([0.3, -0.2, 0.5], dtype=DTYPE)


def component(params, vis0, action, cluster, pos0=POS0):
    """Mean and covariance of end.pos given the initial state, the action and the
    force's cluster, the force integrated out (by hand: y = W [x, theta] + b + e)."""
    cpd = params["end.pos"]
    w, b, r = (t[vis0, action, cluster] for t in (cpd.weight, cpd.bias, cpd.covariance))
    mean = w[:, :3] @ pos0 + b
    if not USES[action]:
        return mean, r
    m, s = params["param.force"].bias[cluster], params["param.force"].covariance[cluster]
    wp = w[:, 3:]
    return mean + wp @ m, r + wp @ s @ wp.T


def observed_density(y, mask, mean, cov):
    """N(y_o; mean_o, cov_oo) by torch.distributions on the observed sub-vector."""
    o = torch.as_tensor(mask).nonzero().squeeze(-1)
    if o.numel() == 0:
        return torch.tensor(1.0, dtype=DTYPE)
    return MultivariateNormal(mean[o], cov[o][:, o]).log_prob(y[o]).exp()


def evidence(vis0, ys, masks, **extra):
    n = len(ys)
    ev = {"initial.visible": [bool(vis0)] * n, "initial.pos": POS0.expand(n, 3)}
    return ev | {"end.pos": Partial(torch.stack(ys), observed=torch.tensor(masks))} | extra


def brute_action_posterior(params, vis0, y, mask):
    post = []
    for a in range(3):
        probs = params["cluster.force"].probs[a]
        total = sum(
            float(probs[c]) * observed_density(y, mask, *component(params, vis0, a, c))
            for c in range(3)
        )
        post.append(float(params["action"].probs[a]) * total)
    post = torch.tensor(post, dtype=DTYPE)
    return post / post.sum()


@settings(max_examples=12, deadline=None)
@given(
    seed=st.integers(0, 50),
    masks=st.lists(st.lists(st.booleans(), min_size=3, max_size=3), min_size=1, max_size=4),
)
def test_action_posterior_marginalises_the_unobserved_dimensions(seed, masks):
    params = random_params(NET, seed)
    g = torch.Generator().manual_seed(seed)
    ys = [torch.randn(3, generator=g, dtype=DTYPE) * 2 for _ in masks]
    # unobserved entries are ignored, whatever they hold
    ys_given = [torch.where(torch.tensor(m), y, torch.nan) for y, m in zip(ys, masks, strict=True)]
    got = infer_action(NET, params, evidence(1, ys_given, masks))
    for i, (y, mask) in enumerate(zip(ys, masks, strict=True)):
        want = brute_action_posterior(params, 1, y, mask)
        torch.testing.assert_close(got.probs[i], want, atol=1e-9, rtol=1e-7)


def test_every_dimension_observed_is_full_evidence():
    params = random_params(NET, 3)
    y = torch.tensor([[1.0, -0.5, 2.0], [0.2, 0.1, -0.3]], dtype=DTYPE)
    full = evidence(0, list(y), [[True] * 3] * 2) | {"end.pos": y}
    part = evidence(0, list(y), [[True] * 3] * 2)
    torch.testing.assert_close(
        infer_action(NET, params, part).probs, infer_action(NET, params, full).probs
    )
    tap = {"action": ["tap", "push"]}
    for a, b in [
        (imitation_check(NET, params, part | tap), imitation_check(NET, params, full | tap)),
        (
            infer_parameter(NET, params, "force", part | tap),
            infer_parameter(NET, params, "force", full | tap),
        ),
    ]:
        for field in ("log_likelihood", "surprise", "mean", "cov", "cluster_probs"):
            if hasattr(a, field):
                torch.testing.assert_close(getattr(a, field), getattr(b, field))
    # all observed: predict has nothing to predict for pos, as with full evidence
    assert "pos" not in predict(NET, params, part | tap).continuous


def test_predict_conditions_the_unobserved_dimensions_on_the_observed():
    params = random_params(NET, 11)
    y = torch.tensor([0.8, 99.0, -0.4], dtype=DTYPE)  # the middle value is not observed
    mask = [True, False, True]
    pred = predict(NET, params, evidence(1, [y], [mask], action=["tap"]))
    mix = pred.continuous["pos"]
    o, u = torch.tensor([0, 2]), torch.tensor([1])
    weights = []
    for c in range(3):
        mean, cov = component(params, 1, 1, c)
        weights.append(
            float(params["cluster.force"].probs[1, c]) * observed_density(y, mask, mean, cov)
        )
        gain = cov[u][:, o] @ torch.linalg.inv(cov[o][:, o])
        want_mean = mean.clone()
        want_mean[o] = y[o]
        want_mean[u] = mean[u] + gain @ (y[o] - mean[o])
        want_cov = torch.zeros(3, 3, dtype=DTYPE)
        want_cov[1, 1] = (cov[u][:, u] - gain @ cov[o][:, u])[0, 0]
        torch.testing.assert_close(mix.means[0, c], want_mean)
        torch.testing.assert_close(mix.covs[0, c], want_cov)
    weights = torch.tensor(weights, dtype=DTYPE)
    torch.testing.assert_close(mix.weights[0], weights / weights.sum())
    # end.visible is independent of end.pos given the initial state and the action
    plain = predict(NET, params, evidence(1, [y], [[False] * 3], action=["tap"]))
    torch.testing.assert_close(pred.discrete["visible"], plain.discrete["visible"])


def test_a_row_with_no_dimension_observed_is_the_prior():
    params = random_params(NET, 4)
    y = torch.full((3,), torch.nan, dtype=DTYPE)
    got = predict(NET, params, evidence(0, [y], [[False] * 3], action=["push"]))
    want = predict(
        NET, params, {"initial.visible": [False], "initial.pos": POS0[None], "action": ["push"]}
    )
    torch.testing.assert_close(got.continuous["pos"].means, want.continuous["pos"].means)
    torch.testing.assert_close(got.continuous["pos"].weights, want.continuous["pos"].weights)
    assert not got.implausible.any()


def test_parameter_posterior_from_the_observed_dimensions():
    params = random_params(NET, 13)
    ys = [torch.tensor([2.0, 0.0, 1.0], dtype=DTYPE)] * 3
    masks = [[False, True, True], [True, True, True], [False, False, False]]
    ev = evidence(1, ys, masks, action=["push"] * 3)
    got = infer_parameter(NET, params, "force", ev, mixture=True)
    for i, mask in enumerate(masks):
        o = torch.tensor(mask).nonzero().squeeze(-1)
        lik = []
        for c in range(3):
            m, s = params["param.force"].bias[c], params["param.force"].covariance[c]
            mean, cov = component(params, 1, 2, c)
            wp = params["end.pos"].weight[1, 2, c][o, 3:]
            s_ty = s @ wp.T
            s_yy = cov[o][:, o]
            want_mean = m + s_ty @ torch.linalg.solve(s_yy, ys[i][o] - mean[o])
            want_cov = s - s_ty @ torch.linalg.solve(s_yy, s_ty.T)
            torch.testing.assert_close(got.mixture.means[i, c], want_mean)
            torch.testing.assert_close(got.mixture.covs[i, c], want_cov)
            lik.append(
                float(params["cluster.force"].probs[2, c])
                * observed_density(ys[i], mask, mean, cov)
            )
        lik = torch.tensor(lik, dtype=DTYPE)
        torch.testing.assert_close(got.cluster_probs[i], lik / lik.sum())
    compiled = (
        inference.compile(NET, params).parameter_query("force").infer_parameter(ev, mixture=True)
    )
    for field in (
        "cluster_probs",
        "best_cluster",
        "mean",
        "cov",
        "unseen",
        "outside",
        "implausible",
    ):
        torch.testing.assert_close(getattr(compiled, field), getattr(got, field))
    torch.testing.assert_close(compiled.mixture.means, got.mixture.means)
    torch.testing.assert_close(compiled.mixture.covs, got.mixture.covs)


def test_implausibility_counts_only_the_observed_dimensions():
    params = random_params(NET, 2)
    mean, cov = component(params, 0, 0, 0)  # remove: one component
    y = mean + torch.tensor([0.0, 50.0, 0.0], dtype=DTYPE) * cov.diagonal().sqrt()
    for mask, far in [([True, False, True], False), ([False, True, False], True)]:
        ev = evidence(0, [y], [mask], action=["remove"])
        got = plausibility(NET, params, NET.encode(ev))
        o = torch.tensor(mask).nonzero().squeeze(-1)
        diff = y[o] - mean[o]
        d2 = float(diff @ torch.linalg.solve(cov[o][:, o], diff))
        assert abs(float(got.tail[0]) - stats.chi2.sf(d2, len(o))) < 1e-9
        assert bool(imitation_check(NET, params, ev).implausible[0]) is far


def test_imitation_log_likelihood_is_the_observed_marginal():
    params = random_params(NET, 9)
    y = torch.tensor([0.5, 0.5, 0.5], dtype=DTYPE)
    mask = [True, True, False]
    got = imitation_check(NET, params, evidence(1, [y], [mask], action=["tap"]), n_samples=500)
    want = sum(
        float(params["cluster.force"].probs[1, c])
        * observed_density(y, mask, *component(params, 1, 1, c))
        for c in range(3)
    )
    assert abs(float(got.log_likelihood[0]) - math.log(want)) < 1e-9
    assert 0 <= float(got.surprise[0]) <= 1


def test_simulate_draws_the_unobserved_dimensions_from_their_conditional():
    params = random_params(NET, 5)
    y = torch.tensor([1.0, 0.0, -1.0], dtype=DTYPE)
    n = 4000
    rows = simulate(
        NET, params, n, evidence(0, [y], [[True, False, True]], action=["remove"]), seed=1
    )
    pos = rows["end.pos"]
    assert torch.equal(pos[:, [0, 2]], y[[0, 2]].expand(n, 2))
    mean, cov = component(params, 0, 0, 0)
    o, u = torch.tensor([0, 2]), torch.tensor([1])
    gain = cov[u][:, o] @ torch.linalg.inv(cov[o][:, o])
    want = float((mean[u] + gain @ (y[o] - mean[o]))[0])
    sd = float((cov[u][:, u] - gain @ cov[o][:, u])[0, 0].sqrt())
    assert abs(float(pos[:, 1].mean()) - want) < 4 * sd / math.sqrt(n)
    assert abs(float(pos[:, 1].std()) / sd - 1) < 0.05


def test_bad_partial_evidence_is_refused():
    params = random_params(NET, 0)
    y = torch.zeros(2, 3, dtype=DTYPE)
    base = {"initial.visible": [True, True], "initial.pos": torch.zeros(2, 3)}
    bad = [
        ({"end.pos": Partial(y, observed=[1, 0, 1])}, "must be bool"),
        ({"end.pos": Partial(y, observed=[True, False])}, "observed has shape"),
        (
            {"end.pos": Partial(y, observed=torch.ones(3, 3, dtype=torch.bool))},
            "observed has shape",
        ),
        (
            {"end.pos": Partial(y.fill_diagonal_(torch.nan), observed=[True] * 3)},
            "observed dimension",
        ),
        ({"end.pos": Partial(torch.zeros(2, 4), observed=[True] * 4)}, "expected shape"),
        ({"initial.pos": Partial(y, observed=[True] * 3)}, "end features only"),
        ({"end.pos": torch.tensor([[0.0, torch.nan, 0.0]] * 2)}, "NaN or inf"),
    ]
    for ev, match in bad:
        with pytest.raises(ValueError, match=match):
            infer_action(NET, params, base | ev)
    rows = simulate(NET, params, 20, seed=0)
    rows["end.pos"] = Partial(rows["end.pos"], observed=[True, False, True])
    # training rows may miss dimensions (EM fills them), but EM starts from each CPD's
    # rows that give its site and parents: none gives end.pos whole
    with pytest.raises(ValueError, match="site 'end.pos': no training row gives it"):
        fit(NET, rows)


def test_a_shared_parameter_conditions_on_the_observed_dimensions():
    # one aim acting on end.land (2-D) and end.roll (1-D); land observed in its second
    # dimension only: the joint Gaussian of (land, roll) per cluster, rows and columns
    # [1, 2] kept
    from tests.networks import joint_by_hand, throwing

    net, params = throwing()
    x_land, x_roll = np.array([0.1, -0.2]), np.array([0.3])
    y = np.array([np.nan, 1.0, 0.7])
    ev = {"initial.land": [x_land], "initial.roll": [x_roll], "action": ["throw"]}
    ev |= {"end.land": Partial([y[:2]], observed=[False, True]), "end.roll": [y[2:]]}
    answer = infer_parameter(net, params, "aim", ev, mixture=True)
    pred = predict(net, params, ev).continuous["land"]
    o = [1, 2]
    clusters = params["cluster.aim"].probs[0].numpy()
    joint = []
    for c in range(2):
        mu, cov, w, m, s = joint_by_hand(params, x_land, x_roll, c)
        joint.append(clusters[c] * stats.multivariate_normal(mu[o], cov[np.ix_(o, o)]).pdf(y[o]))
        want = m + s @ w[o].T @ np.linalg.solve(cov[np.ix_(o, o)], y[o] - mu[o])
        np.testing.assert_allclose(answer.mixture.means[0, c].numpy(), want, rtol=1e-9)
        gain = cov[0, o] @ np.linalg.inv(cov[np.ix_(o, o)])
        np.testing.assert_allclose(pred.means[0, c, 0], mu[0] + gain @ (y[o] - mu[o]), rtol=1e-9)
        np.testing.assert_allclose(pred.covs[0, c, 0, 0], cov[0, 0] - gain @ cov[o, 0], rtol=1e-9)
    joint = np.array(joint)
    np.testing.assert_allclose(answer.cluster_probs[0].numpy(), joint / joint.sum(), rtol=1e-9)
    np.testing.assert_allclose(pred.weights[0].numpy(), joint / joint.sum(), rtol=1e-9)
    check = imitation_check(net, params, ev, n_samples=10)
    np.testing.assert_allclose(float(check.log_likelihood[0]), np.log(joint.sum()), rtol=1e-9)
    both = ev | {"end.roll": Partial([[0.7]], observed=[True])}
    assert set(predict(net, params, both).continuous) == {"land"}  # roll: all observed
    both = ev | {"end.roll": Partial([[0.7]], observed=[[False]])}
    with pytest.raises(ValueError, match="share the parameter 'aim'"):
        predict(net, params, both)
