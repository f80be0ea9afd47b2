"""The throw network (paper Fig. 4) on simulated throws, against hand-computed numerics."""

import numpy as np
import pytest
import torch
from effect_networks.inference import fit, infer_parameter, predict
from effect_networks.models.humanoid_throw import (
    HIT,
    PAPER_AREA_HIGH,
    PAPER_AREA_LOW,
    TARGET,
    THROW,
    hit_evidence,
    throw_data,
    throw_network,
)
from effect_networks.sim2d.analytic_throw import TARGET_AREA, sample_targets, throw
from scipy.stats import multivariate_normal

BINS = (4, 5)


@pytest.fixture(scope="module")
def throws():
    targets = sample_targets(3000, np.random.default_rng(7))
    return targets, throw(targets).hit


@pytest.fixture(scope="module")
def fitted(throws):
    """Plain maximum likelihood: no pseudo-counts, no variance floor."""
    net = throw_network(BINS)
    params = fit(net, throw_data(net, *throws), pseudo_count=0.0, min_variance=0.0).params
    return net, params


def cells(targets, bins):
    """Row-major (y major) equidistant cell of each target, by hand."""
    low, high = np.array(PAPER_AREA_LOW), np.array(PAPER_AREA_HIGH)
    cell = np.floor((targets - low) / (high - low) * bins).astype(int)
    cell = np.clip(cell, 0, np.array(bins) - 1)
    return cell[:, 0] * bins[1] + cell[:, 1]


def joint_per_cluster(params):
    """Mean (C, 4) and covariance (C, 4, 4) of (target, hit) implied by the fitted CPDs."""
    prior, end = params[f"param.{TARGET}"], params[f"end.{HIT}"]
    m, s = prior.bias.numpy(), prior.covariance.numpy()
    w, b, r = end.weight[0].numpy(), end.bias[0].numpy(), end.covariance[0].numpy()
    mean_hit = np.einsum("cij,cj->ci", w, m) + b
    s_th = s @ w.transpose(0, 2, 1)
    s_hh = w @ s_th + r
    mean = np.concatenate([m, mean_hit], -1)
    cov = np.block([[s, s_th], [s_th.transpose(0, 2, 1), s_hh]])
    return mean, cov


def test_area_matches_the_simulator():
    assert PAPER_AREA_LOW == tuple(TARGET_AREA.low)
    assert PAPER_AREA_HIGH == tuple(TARGET_AREA.high)


def test_structure_is_fig4():
    net = throw_network((3, 7))
    assert [s.name for s in net.sites] == ["action", "cluster.target", "param.target", "end.hit"]
    assert net.actions == (THROW,)
    assert net.site("cluster.target").size == 21 and net.site("cluster.target").discrete
    assert net.site("param.target").size == 2 and net.site("end.hit").size == 2
    assert net.discrete_parents(HIT) == ("action", "cluster.target")
    assert net.continuous_parents(HIT) == ("param.target",)
    assert throw_network((1, 1)).parameters[0].n_clusters == 1


def test_fit_gives_the_sample_statistics_per_cluster(throws, fitted):
    targets, hits = throws
    net, params = fitted
    mean, cov = joint_per_cluster(params)
    cluster = cells(targets, BINS)
    joint = np.concatenate([targets, hits], -1)
    counts = np.bincount(cluster, minlength=np.prod(BINS))
    np.testing.assert_allclose(params["cluster.target"].probs[0].numpy(), counts / len(targets))
    for c in range(np.prod(BINS)):
        rows = joint[cluster == c]
        assert len(rows) > 50
        np.testing.assert_allclose(mean[c], rows.mean(0), atol=1e-10)
        np.testing.assert_allclose(cov[c], np.cov(rows.T, bias=True), atol=1e-9)


def test_cluster_posterior_is_direct_enumeration(throws, fitted):
    net, params = fitted
    hits = throw(sample_targets(40, np.random.default_rng(8))).hit
    got = infer_parameter(net, params, TARGET, {"end.hit": hits})
    mean, cov = joint_per_cluster(params)
    prior = params["cluster.target"].probs[0].numpy()
    density = np.stack(
        [
            prior[c] * multivariate_normal(mean[c, 2:], cov[c, 2:, 2:]).pdf(hits)
            for c in range(len(prior))
        ],
        -1,
    )
    want = density / density.sum(-1, keepdims=True)
    np.testing.assert_allclose(got.cluster_probs.numpy(), want, atol=1e-6)
    np.testing.assert_array_equal(got.best_cluster.numpy(), want.argmax(-1))


def test_target_is_gaussian_conditioning_in_the_best_cluster(fitted):
    net, params = fitted
    hits = throw(sample_targets(20, np.random.default_rng(9))).hit
    got = infer_parameter(net, params, TARGET, {"end.hit": hits})
    mean, cov = joint_per_cluster(params)
    for i, c in enumerate(got.best_cluster.numpy()):
        gain = np.linalg.solve(cov[c, 2:, 2:], cov[c, 2:, :2]).T  # S_th S_hh^-1
        want_mean = mean[c, :2] + gain @ (hits[i] - mean[c, 2:])
        want_cov = cov[c, :2, :2] - gain @ cov[c, 2:, :2]
        np.testing.assert_allclose(got.mean[i].numpy(), want_mean, atol=1e-9)
        np.testing.assert_allclose(got.cov[i].numpy(), want_cov, atol=1e-9)


def test_forward_query_is_the_clusters_linear_gaussian(fitted):
    net, params = fitted
    targets = sample_targets(10, np.random.default_rng(10))
    mixture = predict(net, params, {"action": [THROW] * 10, "param.target": targets}).continuous[
        HIT
    ]
    end = params["end.hit"]
    c = torch.as_tensor(cells(targets, BINS))
    want = (end.weight[0, c] @ torch.as_tensor(targets)[..., None]).squeeze(-1) + end.bias[0, c]
    torch.testing.assert_close(mixture.mean, want)


def test_clusters_beat_a_single_gaussian_on_rethrows():
    targets = sample_targets(5000, np.random.default_rng(11))
    hits = throw(targets).hit
    train, test = slice(0, 4500), slice(4500, None)
    rms = {}
    for bins in ((8, 8), (1, 1)):
        net = throw_network(bins)
        params = fit(net, throw_data(net, targets[train], hits[train])).params
        aim = infer_parameter(net, params, TARGET, {"end.hit": hits[test]}).mean.numpy()
        aim = np.clip(aim, TARGET_AREA.low, TARGET_AREA.high)
        rms[bins] = np.sqrt(np.mean((throw(aim).hit - hits[test]) ** 2, axis=0))
    assert np.all(rms[(8, 8)] < 0.25 * rms[(1, 1)]), rms
    assert np.all(rms[(8, 8)] < 0.010), rms


WINDOW = {"low": (-1.0, 0.0), "high": (1.0, 2.4)}


@pytest.mark.parametrize(
    ("hits", "match"),
    [
        ([[0.0, 1.0], [1.5, 1.0]], r"hits\[1\] = \[1.5, 1.0\]: expected inside y in \[-1, 1\]"),
        ([[0.0, np.nan]], r"hits\[0\].*finite"),
        ([[0.0, 1.0, 2.0]], r"shape \(1, 3\): expected \(n, 2\)"),
        ([0.0, 1.0], r"shape \(2,\): expected \(n, 2\)"),
        ([["a", "b"]], r"expected an \(n, 2\) float array"),
    ],
)
def test_bad_hits_say_what_is_wrong(hits, match):
    with pytest.raises(ValueError, match=match):
        hit_evidence(hits, **WINDOW)


def test_hit_evidence_encodes_good_hits():
    evidence = hit_evidence([[0.1, 0.3]], **WINDOW)
    assert evidence["end.hit"].dtype == torch.float64 and evidence["end.hit"].shape == (1, 2)


def test_bad_training_rows_say_what_is_wrong():
    net = throw_network((2, 2))
    good = np.zeros((3, 2)) + [0.0, 1.0]
    with pytest.raises(ValueError, match="one hit per target"):
        throw_data(net, good, good[:2])
    with pytest.raises(ValueError, match=r"targets\[0\] = \[0.0, 3.0\]: expected inside"):
        throw_data(net, [[0.0, 3.0]], [[0.0, 1.0]])
    with pytest.raises(ValueError, match="throw_network"):
        throw_data(_other_network(), good, good)
    with pytest.raises(ValueError, match="bins"):
        throw_network((4,))


def _other_network():
    from effect_networks.models import Continuous, EffectNetwork

    return EffectNetwork((Continuous("x", 2),), ("push",))
