"""The model generates data from itself: fit(simulate(...)) recovers the parameters, and
draws given evidence follow the exact posteriors of the queries."""

import math

import numpy as np
import pytest
import torch
from effect_networks.inference import fit, infer_action, infer_parameter, simulate
from effect_networks.models import Continuous, Discrete, EffectNetwork, Parameter, random_params
from effect_networks.models.cpds import LinearGaussianParams, TableParams
from effect_networks.models.declaration import DTYPE
from effect_networks.models.params import NetworkParams, check_params

from tests.helpers import spilling_network

NET = EffectNetwork(
    (Discrete("door", ("shut", "open")), Continuous("pos", 1)),
    ("wait", "push"),
    (Parameter("force", 0.0, 10.0, 2, ("push",), "pos"),),
)


def balanced_params(seed):
    """Random parameters with every configuration well visited (for recovery tests)."""
    p = random_params(NET, seed)
    cpds = dict(p.cpds)
    cpds["action"] = TableParams(torch.tensor([0.5, 0.5], dtype=DTYPE), p["action"].n)
    cpds["initial.door"] = TableParams(torch.tensor([0.5, 0.5], dtype=DTYPE), p["initial.door"].n)
    c = p["cluster.force"]
    cpds["cluster.force"] = TableParams(torch.tensor([[1.0, 0.0], [0.5, 0.5]], dtype=DTYPE), c.n)
    soft = p["end.door"]
    cpds["end.door"] = type(soft)(0.5 * soft.weight, 0.3 * soft.bias, soft.n)
    return NetworkParams(cpds, p.pseudo_count)


def test_random_params_are_valid():
    params = random_params(NET, 0)
    check_params(NET, params)
    prior = params["param.force"]
    cells = NET.parameters[0].cluster_of(prior.bias)
    assert cells.tolist() == [0, 1]  # each cluster's Gaussian sits in its own cell
    assert params["cluster.force"].probs[0].tolist() == [1.0, 0.0]  # wait: cell 0
    with pytest.raises(ValueError, match="unseen"):
        random_params(NET, 0, unseen=2.0)


def test_fit_of_simulated_rows_recovers_the_parameters():
    params = balanced_params(1)
    n = 20_000
    rows = simulate(NET, params, n, seed=3)
    assert set(rows) == {s.name for s in NET.sites}
    assert all(
        math.isnan(f[0])
        for f, a in zip(rows["param.force"].tolist(), rows["action"], strict=True)
        if a == "wait"
    )
    fitted = fit(NET, rows, steps=10).params  # steps: the softmax of end.door only
    for site in ("action", "initial.door"):
        p = params[site].probs
        assert (fitted[site].probs - p).abs().max() < 4 * math.sqrt(0.25 / n)
    # the pushed position, per door state and cluster: weight on [pos, force] and bias
    # (about 2,500 rows per pushed configuration: standard errors near 0.03 for the mean
    # at the cell's centre and 0.05 for the slope on a force spread over a quarter cell)
    truth, got = params["end.pos"], fitted["end.pos"]
    centres = NET.parameters[0].cluster_centres()
    for door in (0, 1):
        for c in (0, 1):
            at = torch.cat([torch.zeros(1, dtype=DTYPE), centres[c]])
            mean_got = got.weight[door, 1, c] @ at + got.bias[door, 1, c]
            mean_true = truth.weight[door, 1, c] @ at + truth.bias[door, 1, c]
            assert (mean_got - mean_true).abs().max() < 0.15
            assert (got.weight[door, 1, c] - truth.weight[door, 1, c]).abs().max() < 0.25
            ratio = got.covariance[door, 1, c] / truth.covariance[door, 1, c]
            assert abs(float(ratio) - 1) < 0.15
        # waiting: the force is ignored, its weight is zero
        assert float(got.weight[door, 0, 0, 0, 1]) == 0.0
        assert (got.weight[door, 0, 0, 0, :1] - truth.weight[door, 0, 0, 0, :1]).abs().max() < 0.1
    assert (got.covariance > 0).all()
    lg = fitted["param.force"]
    assert isinstance(lg, LinearGaussianParams)
    assert (lg.bias - params["param.force"].bias).abs().max() < 0.05


def test_draws_given_an_end_state_follow_the_action_posterior():
    params = random_params(NET, 2)
    ev = {"initial.door": ["shut"], "initial.pos": [[0.2]], "end.door": ["open"]}
    exact = infer_action(NET, params, ev).probs[0]
    n = 4000
    rows = simulate(NET, params, n, ev, seed=0)
    assert rows["end.door"] == ["open"] * n and rows["initial.door"] == ["shut"] * n
    freq = torch.tensor([rows["action"].count(a) / n for a in NET.actions], dtype=DTYPE)
    assert (freq - exact).abs().max() < 4 * math.sqrt(0.25 / n)


def test_draws_given_the_affected_feature_follow_the_cluster_posterior():
    params = random_params(NET, 4)
    ev = {"initial.door": ["open"], "initial.pos": [[0.0]], "action": ["push"], "end.pos": [[1.0]]}
    exact = infer_parameter(NET, params, "force", ev).cluster_probs[0]
    n = 4000
    drawn = torch.tensor(simulate(NET, params, n, ev, seed=1)["cluster.force"])
    freq = torch.bincount(drawn, minlength=2).to(DTYPE) / n
    assert (freq - exact).abs().max() < 4 * math.sqrt(0.25 / n)


def test_seeded_and_local():
    params = random_params(NET, 0)
    torch.manual_seed(123)
    before = torch.rand(3)
    torch.manual_seed(123)
    a = simulate(NET, params, 50, seed=9)
    after = torch.rand(3)
    b = simulate(NET, params, 50, seed=9)
    assert torch.equal(before, after)  # the global random state is untouched
    assert a["action"] == b["action"] and torch.equal(a["end.pos"], b["end.pos"])
    c = simulate(NET, params, 50, seed=10)
    assert not torch.equal(a["end.pos"], c["end.pos"])


def test_bad_requests_are_named():
    params = random_params(NET, 0)
    with pytest.raises(ValueError, match="n must be a positive int"):
        simulate(NET, params, 0)
    with pytest.raises(ValueError, match="give one row or n = 5 rows"):
        simulate(NET, params, 5, {"action": ["push", "wait"]})
    with pytest.raises(ValueError, match="continuous features"):
        simulate(NET, params, 5, {"end.door": ["open"]})  # initial position unknown
    net = EffectNetwork((Discrete("door", ("shut", "open")),), ("wait",))
    rows = simulate(net, random_params(net, 0), 3, {"initial.door": ["open"]})
    assert rows["initial.door"] == ["open"] * 3 and len(rows["end.door"]) == 3


@pytest.mark.parametrize("seed", ["a", 1.5, True, None, -(2**63) - 1, 2**64])
def test_a_bad_seed_is_named(seed):
    with pytest.raises(ValueError, match=r"seed=.* is invalid; expected an int"):
        simulate(NET, balanced_params(0), 3, seed=seed)


def test_every_int_seed_torch_accepts_draws():
    for seed in (-(2**63), -1, 0, 2**64 - 1):
        assert len(simulate(NET, balanced_params(0), 2, seed=seed)["action"]) == 2


def sampling_errors(net, params, rows):
    """Every fitted number of the spilling network paired with its truth and its sampling
    error at these rows: ``[(name, fitted-site, index, truth, error)]``. Tables: the
    binomial error of each probability; Gaussians: ``sd / sqrt(n)`` for a mean, ``var *
    sqrt(2 / n)`` for a variance; linear Gaussians: ``sqrt(var * (Z^T Z)^-1)`` per
    coefficient of the rows' design ``Z`` (inputs and a one) in their configuration."""
    n = len(rows["action"])
    action = np.array(rows["action"])
    cluster = np.array(rows["cluster.force"])
    x = rows["initial.pos"][:, 0].numpy()
    force = np.nan_to_num(rows["param.force"][:, 0].numpy())
    out = []
    for a in range(len(net.actions)):
        p = float(params["action"].probs[a])
        out.append(("action", (a,), p, math.sqrt(p * (1 - p) / n)))
    pushed = action == "push"
    for c in range(4):
        p = float(params["cluster.force"].probs[0, c])
        out.append(("cluster.force", (0, c), p, math.sqrt(p * (1 - p) / pushed.sum())))
        here = pushed & (cluster == c)
        var = float(params["param.force"].covariance[c, 0, 0])
        out.append(
            (
                "param.force:mean",
                (c,),
                float(params["param.force"].bias[c, 0]),
                math.sqrt(var / here.sum()),
            )
        )
        out.append(("param.force:var", (c,), var, var * math.sqrt(2 / here.sum())))
    var = float(params["initial.pos"].covariance[0, 0])
    out.append(("initial.pos:mean", (), float(params["initial.pos"].bias[0]), math.sqrt(var / n)))
    out.append(("initial.pos:var", (), var, var * math.sqrt(2 / n)))
    cpd = params["end.pos"]
    for a, c in [(0, 0), (0, 1), (0, 2), (0, 3), (1, 0)]:
        here = (action == net.actions[a]) & (cluster == c)
        columns = (
            [x[here], force[here], np.ones(here.sum())]
            if a == 0
            else [x[here], np.ones(here.sum())]
        )
        design = np.stack(columns, -1)
        var = float(cpd.covariance[a, c, 0, 0])
        errors = np.sqrt(var * np.diag(np.linalg.inv(design.T @ design)))
        truth = cpd.weight[a, c, 0, : len(columns) - 1].tolist() + [float(cpd.bias[a, c, 0])]
        for k, (value, error) in enumerate(zip(truth, errors, strict=True)):
            out.append(("end.pos:coef", (a, c, k), value, float(error)))
        out.append(("end.pos:var", (a, c), var, var * math.sqrt(2 / here.sum())))
    return out


def fitted_value(fitted, name, index):
    site, _, part = name.partition(":")
    cpd = fitted[site]
    if not part:
        return float(cpd.probs[index])
    if part == "mean":
        return float(cpd.bias[(*index, 0)])
    if part == "var":
        return float(cpd.covariance[(*index, 0, 0)])
    a, c, k = index  # coefficients: the weights on the inputs, then the bias
    q = 2 if a == 0 else 1
    return float(cpd.weight[a, c, 0, k]) if k < q else float(cpd.bias[a, c, 0])


def misses(n, seed):
    """The fitted numbers of fit(simulate(n rows)) more than their sampling error away,
    each as (name, index, (fitted - truth) / error)."""
    net, params = spilling_network()
    rows = simulate(net, params, n, seed=seed)
    fitted = fit(net, rows).params
    out = []
    for name, index, truth, error in sampling_errors(net, params, rows):
        out.append((name, index, (fitted_value(fitted, name, index) - truth) / error))
    return out


def test_fit_of_simulated_rows_is_unbiased_where_clusters_spill_out_of_their_cells():
    # The force drawn from its cluster's Gaussian often lies in another cell; the rows
    # carry the cluster they were drawn from, and fit files them under it. (Filed under
    # their cells instead, the cluster sds come back 20-50 % small.)
    z = misses(20_000, seed=0)
    worst = max(z, key=lambda t: abs(t[2]))
    assert abs(worst[2]) < 4, worst


def test_fit_of_200000_simulated_rows_recovers_every_parameter_within_3_sampling_errors():
    z = misses(200_000, seed=1)
    worst = max(z, key=lambda t: abs(t[2]))
    assert abs(worst[2]) < 3, worst
