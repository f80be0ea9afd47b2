"""Maximum likelihood: closed form equals sample statistics; the gradient route agrees."""

import pytest
import torch
from effect_networks.inference import fit, fit_gradient
from effect_networks.models import Continuous, Discrete, EffectNetwork, Parameter
from effect_networks.models.declaration import DTYPE

from tests.networks import HANDLE_ACTIONS, HANDLE_KINDS, HANDLE_STATES, handle_world


def tap_data(net, n=400, seed=0):
    """Rows of a tap world, by state index (``remove`` = 0, ``tap`` = 1)."""
    g = torch.Generator().manual_seed(seed)
    a = torch.randint(0, 2, (n,), generator=g)
    vis0 = torch.randint(0, 2, (n,), generator=g)
    pos0 = torch.randn(n, 1, generator=g, dtype=DTYPE)
    force = torch.rand(n, 1, generator=g, dtype=DTYPE) * 10
    force[a == 0] = float("nan")
    vis1 = torch.where((a == 0) | (torch.rand(n, generator=g) < 0.2), 0, vis0)
    pos1 = (
        pos0
        + torch.where(a[:, None] == 1, 0.3 * force.nan_to_num(), 0.0)
        + 0.1 * torch.randn(n, 1, generator=g, dtype=DTYPE)
    )
    return net.encode_indices(
        {
            "initial.visible": vis0,
            "initial.pos": pos0,
            "action": a,
            "param.force": force,
            "end.visible": vis1,
            "end.pos": pos1,
        }
    )


DISCRETE = EffectNetwork(
    (Discrete("visible", (0, 1)), Discrete("colour", ("r", "g", "b"))), ("remove", "paint")
)


def discrete_data(n=3000, seed=1):
    g = torch.Generator().manual_seed(seed)
    a = torch.randint(0, 2, (n,), generator=g)
    v0 = torch.randint(0, 2, (n,), generator=g)
    c0 = torch.randint(0, 3, (n,), generator=g)
    v1 = torch.where((a == 0) & (torch.rand(n, generator=g) < 0.9), 0, v0)
    c1 = torch.where(a == 1, torch.randint(0, 3, (n,), generator=g), c0)
    return DISCRETE.encode_indices(
        {
            "initial.visible": v0,
            "initial.colour": c0,
            "action": a,
            "end.visible": v1,
            "end.colour": c1,
        }
    )


def test_tables_are_normalised_counts():
    data = discrete_data()
    params = fit(DISCRETE, data, pseudo_count=0.0).params
    t = params["end.visible"].probs
    for v0, c0, a in [(0, 0, 0), (1, 2, 1), (1, 1, 0)]:
        rows = (
            (data["initial.visible"] == v0) & (data["initial.colour"] == c0) & (data["action"] == a)
        )
        freq = torch.bincount(data["end.visible"][rows], minlength=2).to(DTYPE) / rows.sum()
        torch.testing.assert_close(t[v0, c0, a], freq)
        assert params["end.visible"].n[v0, c0, a] == rows.sum()


def test_pseudo_count_policy():
    data = discrete_data().rows(slice(0, 5))
    params = fit(DISCRETE, data, pseudo_count=1.0).params
    t, n = params["end.colour"].probs, params["end.colour"].n
    assert (n == 0).any()
    torch.testing.assert_close(t[n == 0], torch.full_like(t[n == 0], 1 / 3))
    seen = (n > 0).nonzero()[0].tolist()
    assert (t[tuple(seen)] > 0).all()


def test_linear_gaussian_is_least_squares_and_residual_covariance():
    net = EffectNetwork(
        (Discrete("visible", (0, 1)), Continuous("pos", 1)),
        ("remove", "tap"),
        (Parameter("force", 0.0, 10.0, 2, ("tap",), "pos"),),
    )
    data = tap_data(net)
    params = fit(net, data, pseudo_count=0.0, min_variance=0.0, steps=50).params
    cpd = params["end.pos"]
    c = net.parameters[0].cluster_of(data["param.force"].nan_to_num())
    rows = (data["initial.visible"] == 1) & (data["action"] == 1) & (c == 1)
    x = torch.cat(
        [
            data["initial.pos"][rows],
            data["param.force"][rows],
            torch.ones(int(rows.sum()), 1, dtype=DTYPE),
        ],
        -1,
    )
    y = data["end.pos"][rows]
    beta = torch.linalg.lstsq(x, y).solution
    torch.testing.assert_close(cpd.weight[1, 1, 1], beta[:2].T, atol=1e-8, rtol=1e-6)
    torch.testing.assert_close(cpd.bias[1, 1, 1], beta[2], atol=1e-8, rtol=1e-6)
    resid = y - x @ beta
    torch.testing.assert_close(
        cpd.covariance[1, 1, 1], resid.T @ resid / rows.sum(), atol=1e-10, rtol=1e-6
    )
    # cluster Gaussian = sample mean and (biased) covariance of the parameter in its cell
    f = data["param.force"][(data["action"] == 1) & (c == 0)]
    torch.testing.assert_close(params["param.force"].bias[0], f.mean(0))
    torch.testing.assert_close(
        params["param.force"].covariance[0], f.var(0, unbiased=False)[None], rtol=1e-6, atol=1e-12
    )


def test_gradient_route_reaches_the_closed_form_optimum():
    data = discrete_data()
    closed = fit(DISCRETE, data).params
    grad = fit_gradient(DISCRETE, data, steps=600, lr=0.1).params
    for site in ("action", "end.visible", "end.colour"):
        seen = closed[site].n > 20
        torch.testing.assert_close(
            grad[site].probs[seen], closed[site].probs[seen], atol=2e-3, rtol=0
        )


def test_gradient_route_for_gaussians():
    net = EffectNetwork((Continuous("pos", 1),), ("stay", "move"))
    g = torch.Generator().manual_seed(3)
    n = 500
    a = torch.randint(0, 2, (n,), generator=g)
    x0 = torch.randn(n, 1, generator=g, dtype=DTYPE)
    x1 = 0.5 * x0 + a[:, None] * 2.0 + 0.2 * torch.randn(n, 1, generator=g, dtype=DTYPE)
    data = net.encode_indices({"initial.pos": x0, "action": a, "end.pos": x1})
    closed = fit(net, data, pseudo_count=0.0, min_variance=0.0).params["end.pos"]
    grad = fit_gradient(net, data, steps=300, lr=0.1).params["end.pos"]
    torch.testing.assert_close(grad.weight, closed.weight, atol=1e-2, rtol=0)
    torch.testing.assert_close(grad.bias, closed.bias, atol=1e-2, rtol=0)
    torch.testing.assert_close(grad.covariance, closed.covariance, atol=1e-2, rtol=0)


def test_too_few_samples_stay_positive_definite():
    net = EffectNetwork((Continuous("pos", 3),), ("a", "b"))
    data = {
        "initial.pos": torch.randn(3, 3, dtype=DTYPE),
        "action": ["a", "a", "b"],
        "end.pos": torch.randn(3, 3, dtype=DTYPE),
    }
    params = fit(net, data).params
    assert (torch.linalg.eigvalsh(params["end.pos"].covariance) > 0).all()


def test_fit_rejects_bad_data():
    data = discrete_data(n=20)
    with pytest.raises(ValueError, match="missing.*end.colour"):
        fit(DISCRETE, data.without("end.colour"))
    with pytest.raises(ValueError, match="pseudo_count"):
        fit(DISCRETE, data, pseudo_count=-1)
    net = EffectNetwork(
        (Discrete("visible", (0, 1)), Continuous("pos", 1)),
        ("remove", "tap"),
        (Parameter("force", 0.0, 10.0, 2, ("tap",), "pos"),),
    )
    tap = tap_data(net, n=20)
    tap["param.force"][tap["action"] == 1] = float("nan")
    with pytest.raises(ValueError, match="uses the parameter, but the row gives no value"):
        fit(net, tap)


@pytest.mark.filterwarnings(
    "ignore::effect_networks.inference.fitting.maximum_likelihood.ConvergenceWarning"
)  # 5 steps only
def test_fitting_leaves_pyros_param_store_alone():
    import pyro

    pyro.clear_param_store()
    mine = pyro.param("my_weight", torch.ones(2))
    data = discrete_data(n=200)
    fit(DISCRETE, data, masks={"end.colour": torch.arange(200) % 3 > 0}, steps=5)
    fit_gradient(DISCRETE, data, steps=5)
    store = pyro.get_param_store()
    assert list(store.keys()) == ["my_weight"]
    assert torch.equal(store["my_weight"], mine)
    pyro.clear_param_store()


@pytest.mark.timeout(60)
@pytest.mark.parametrize("huge", [1e160, 1e200, 1e300, -1e308])
def test_huge_values_are_refused_not_spun_on(huge):
    net = EffectNetwork((Continuous("pos", 1),), ("stay", "move"))
    data = {
        "initial.pos": [[0.0], [1.0], [huge]],
        "action": ["stay", "move", "move"],
        "end.pos": [[0.0], [2.0], [1.0]],
    }
    with pytest.raises(ValueError, match=r"site .initial.pos.: row 2 .*Rescale"):
        fit(net, data)


def test_large_but_safe_values_fit():
    net = EffectNetwork((Continuous("pos", 1),), ("stay",))
    data = {"initial.pos": [[1e100], [2e100], [4e100]], "action": ["stay"] * 3}
    data["end.pos"] = data["initial.pos"]
    params = fit(net, data, pseudo_count=0.0, min_variance=0.0).params
    assert torch.isfinite(params["initial.pos"].bias).all()


@pytest.mark.timeout(60)
@pytest.mark.parametrize(
    ("setting", "value"),
    [
        ("pseudo_count", float("nan")),
        ("pseudo_count", float("inf")),
        ("pseudo_count", -1.0),
        ("min_variance", float("nan")),
        ("steps", 0),
        ("steps", 2.5),
        ("lr", 0.0),
        ("lr", float("nan")),
    ],
)
def test_bad_settings_are_named(setting, value):
    with pytest.raises(ValueError, match=setting):
        fit(DISCRETE, discrete_data(n=20), **{setting: value})


def test_zero_rows_are_named():
    empty = {
        "initial.visible": [],
        "initial.colour": [],
        "action": [],
        "end.visible": [],
        "end.colour": [],
    }
    with pytest.raises(ValueError, match="no training rows"):
        fit(DISCRETE, empty)
    with pytest.raises(ValueError, match="no training rows"):
        fit(DISCRETE, {})


def threshold_world(n=2000, seed=0):
    """Pushing moves the object 0.3 m; beyond 0.8 m it falls off the table."""
    import numpy as np

    net = EffectNetwork(
        (Discrete("on_table", ("no", "yes")), Continuous("pos", 1)), ("wait", "push")
    )
    rng = np.random.default_rng(seed)
    pos = rng.uniform(-1, 1, (n, 1))
    action = rng.choice(net.actions, n)
    moved = pos + np.where(action[:, None] == "push", 0.3, 0.0)
    data = {
        "initial.on_table": ["yes"] * n,
        "initial.pos": pos,
        "action": action,
        "end.on_table": np.where(moved[:, 0] < 0.8, "yes", "no"),
        "end.pos": moved,
    }
    return net, data


def test_softmax_fit_settles_on_a_real_dependence():
    from effect_networks.inference import predict

    net, data = threshold_world()
    result = fit(net, data)
    assert result.converged and len(result.losses) > 1
    ev = {"initial.on_table": ["yes"] * 3, "initial.pos": [[0.0], [0.3], [0.7]]}
    pred = predict(net, result.params, ev | {"action": ["push"] * 3})
    on = pred.prob("on_table", "yes")
    assert float(on[0]) > 0.999 and float(on[1]) > 0.9 and float(on[2]) < 0.01


def test_softmax_fit_is_the_penalised_optimum():
    # at the optimum the gradient of NLL + l2/2 |W|^2, written out with numpy, vanishes
    import numpy as np

    net, data = threshold_world(n=600, seed=1)
    l2 = 0.5
    cpd = fit(net, data, l2=l2).params["end.on_table"]
    x = np.asarray(data["initial.pos"])[:, 0]
    y = (np.asarray(data["end.on_table"]) == "yes").astype(int)
    for a, name in enumerate(net.actions):
        rows = np.asarray(data["action"]) == name
        w = cpd.weight[1, a, :, 0].numpy()  # initial.on_table = yes
        b = cpd.bias[1, a].numpy()
        logits = x[rows, None] * w[None] + b[None]
        p = np.exp(logits - logits.max(1, keepdims=True))
        p /= p.sum(1, keepdims=True)
        err = p - np.eye(2)[y[rows]]
        grad_w = (err * x[rows, None]).sum(0) + l2 * w
        grad_b = err.sum(0)
        assert np.abs(grad_w).max() < 1e-3 and np.abs(grad_b).max() < 1e-3


def test_an_unsettled_softmax_fit_warns_and_names_the_cpd():
    from effect_networks.inference import ConvergenceWarning

    net, data = threshold_world(n=300)
    with pytest.warns(ConvergenceWarning, match=r"\['end.on_table'\] did not settle in 2 steps"):
        result = fit(net, data, steps=2)
    assert not result.converged
    with pytest.raises(ValueError, match="l2 must be a finite number >= 0"):
        fit(net, data, l2=-1.0)
    with pytest.raises(ValueError, match="tol must be a finite number > 0"):
        fit(net, data, tol=0.0)


def test_chunks_ending_with_an_empty_chunk_fit_as_their_rows():
    rows = discrete_data(n=300)
    chunks = [
        rows.rows(torch.arange(300) < 200),
        rows.rows(torch.arange(300) >= 200),
        rows.rows(torch.zeros(300, dtype=torch.bool)),  # the last of a split: 0 rows
    ]
    assert [c.n_rows for c in chunks] == [200, 100, 0]
    whole = fit(DISCRETE, rows).params
    chunked = fit(DISCRETE, iter(chunks)).params
    for site in whole.cpds:
        assert torch.allclose(chunked[site].probs, whole[site].probs, rtol=0, atol=1e-12), site
    with pytest.raises(ValueError, match="no training rows: each of the 2 chunks has 0 rows"):
        fit(DISCRETE, iter([chunks[2], chunks[2]]))
    with pytest.raises(ValueError, match="no training rows: the iterable was empty"):
        fit(DISCRETE, iter([]))


def door_arrays(data):
    """The door rows as numpy: configuration ``(kind, state, action)``, inputs, class."""
    import numpy as np

    config = tuple(
        np.array([states.index(v) for v in data[site]])
        for site, states in (
            ("initial.kind", HANDLE_KINDS),
            ("initial.state", HANDLE_STATES),
            ("action", HANDLE_ACTIONS),
        )
    )
    x = np.concatenate([data["initial.handle"], data["initial.effort"]], 1)
    y = np.array([HANDLE_STATES.index(s) for s in data["end.state"]])
    return config, x, y


def softmax_objective(theta, x, y, l2, k):
    """Penalised negative log-likelihood of one configuration and its gradient, numpy."""
    import numpy as np

    q = x.shape[1] + 1
    m = theta.reshape(k, q)
    z = np.concatenate([x, np.ones((len(x), 1))], 1)
    logits = z @ m.T
    top = logits.max(1, keepdims=True)
    log_norm = top[:, 0] + np.log(np.exp(logits - top).sum(1))
    prob = np.exp(logits - log_norm[:, None])
    penalty = np.ones(q)
    penalty[-1] = 0.0
    f = (log_norm - logits[np.arange(len(y)), y]).sum() + 0.5 * l2 * (penalty * m**2).sum()
    grad = (prob - np.eye(k)[y]).T @ z + l2 * penalty * m
    return f, grad.reshape(-1)


def test_softmax_fit_is_the_optimum_an_independent_optimiser_finds():
    # scipy's BFGS on the penalised likelihood written out with numpy, per configuration
    import numpy as np
    from scipy.optimize import minimize

    net, data = handle_world(n=1500, seed=3)
    l2 = 0.05
    cpd = fit(net, data, l2=l2).params["end.state"]
    config, x, y = door_arrays(data)
    worst_gradient = 0.0
    for g in np.ndindex(3, 3, 3):
        rows = (config[0] == g[0]) & (config[1] == g[1]) & (config[2] == g[2])
        assert rows.sum() > 20
        mine = torch.cat([cpd.weight[g], cpd.bias[g][:, None]], -1).numpy()
        f, grad = softmax_objective(mine.reshape(-1), x[rows], y[rows], l2, 3)
        worst_gradient = max(worst_gradient, float(np.abs(grad).max()))
        theirs = minimize(
            softmax_objective,
            np.zeros(9),
            args=(x[rows], y[rows], l2, 3),
            jac=True,
            method="BFGS",
            options={"gtol": 1e-10, "maxiter": 10_000},
        )
        assert f <= theirs.fun + 1e-9
        theirs = theirs.x.reshape(3, 3)
        # the slopes are identified (the prior centres them); the offsets are not (a
        # class a configuration never shows has its offset's optimum at -inf): compare
        # the fitted probabilities
        np.testing.assert_allclose(mine[:, :2], theirs[:, :2], atol=1e-5)
        z = np.concatenate([x[rows], np.ones((rows.sum(), 1))], 1)
        probs = [torch.as_tensor(z @ m.T).softmax(-1).numpy() for m in (mine, theirs)]
        np.testing.assert_allclose(probs[0], probs[1], atol=1e-6)
    assert worst_gradient < 1e-6  # KKT: the gradient of the summed objective


def noisy_threshold_world(n=300, seed=0):
    """Pushing may knock the object off the table, the more likely the nearer the edge."""
    import numpy as np

    net = EffectNetwork(
        (Discrete("on_table", ("no", "yes")), Continuous("pos", 1)), ("wait", "push")
    )
    rng = np.random.default_rng(seed)
    pos = rng.uniform(-1, 1, (n, 1))
    action = rng.choice(net.actions, n)
    falls = rng.random(n) < 1 / (1 + np.exp(-4 * (pos[:, 0] - 0.3)))
    falls &= action == "push"
    data = {
        "initial.on_table": ["yes"] * n,
        "initial.pos": pos,
        "action": action,
        "end.on_table": np.where(falls, "no", "yes"),
        "end.pos": pos + np.where(action[:, None] == "push", 0.3, 0.0),
    }
    return net, data


def test_softmax_fit_reaches_the_gradient_routes_optimum():
    # the traced Pyro model minimised by L-BFGS (the route that differentiates the
    # model itself) finds the same optimum
    from effect_networks.inference import params_from_statistics
    from effect_networks.inference.fitting.sufficient_statistics import statistics
    from effect_networks.models.params import NetworkParams

    net, data = noisy_threshold_world()
    newton = fit(net, data, pseudo_count=0.0).params["end.on_table"]
    enc = net.encode(data)
    start = NetworkParams(params_from_statistics(net, statistics(net, enc), 0.0, 1e-6), 0.0)
    gradient = fit_gradient(
        net, data, init=start, sites=["end.on_table"], steps=500, tol=1e-12
    ).params["end.on_table"]
    # (initial.on_table = yes, push): the configuration whose rows show both classes
    # (under wait the object never falls: that class's offset has its optimum at -inf)
    mine, theirs = (
        torch.cat([c.weight[1, 1], c.bias[1, 1, :, None]], -1) for c in (newton, gradient)
    )
    torch.testing.assert_close(mine - mine.mean(0), theirs - theirs.mean(0), atol=1e-5, rtol=0)


def test_softmax_fit_of_3000_rows_is_fast():
    # Newton per configuration: about 0.1 s for the door world on one thread (the traced
    # model under L-BFGS took 7-23 s); the bound leaves room for a loaded machine
    import time

    net, data = handle_world(n=3000)
    fit(net, data)  # warm-up
    start = time.perf_counter()
    result = fit(net, data)
    assert time.perf_counter() - start < 1.0
    assert result.converged


def test_weighted_rows_count_as_repeated_rows():
    # the weights an EM step gives: a row of weight 2 is the row twice
    import numpy as np

    net, data = handle_world(n=300, seed=5)
    cpd = net.cpd("end.state")
    config, x, y = door_arrays(data)
    index = torch.as_tensor((config[0] * 3 + config[1]) * 3 + config[2])
    x, y = torch.as_tensor(x), torch.as_tensor(y)
    start = cpd.initialize()
    weights = torch.as_tensor(np.random.default_rng(0).integers(0, 3, len(y))).to(DTYPE)
    weighted = cpd.maximise(index, x, y, start, weights=weights, l2=0.1).params
    repeat = weights.long()
    repeated = cpd.maximise(
        index.repeat_interleave(repeat),
        x.repeat_interleave(repeat, 0),
        y.repeat_interleave(repeat),
        start,
        l2=0.1,
    ).params
    torch.testing.assert_close(weighted.weight, repeated.weight, atol=1e-7, rtol=0)
    # offsets compared through the probabilities (a class a configuration never shows
    # has its offset's optimum at -inf, where the two stop at different places)
    probs = [
        cpd.distribution(c, [index // 9, index // 3 % 3, index % 3], x, {}).probs
        for c in (weighted, repeated)
    ]
    torch.testing.assert_close(probs[0], probs[1], atol=1e-7, rtol=0)


def test_a_row_giving_its_cluster_is_filed_under_it():
    # The cluster is data: a force of 4.5 N drawn from cluster 0 (cells 0-5 and 5-10 N)
    # lies in cell 0 anyway; one of 6 N drawn from cluster 0 lies in cell 1 but counts
    # for cluster 0. Rows that give no cluster are filed under their cells.
    net = EffectNetwork(
        (Continuous("pos", 1),),
        ("push", "wait"),
        (Parameter("force", 0.0, 10.0, 2, "push", "pos"),),
    )
    nan = float("nan")
    rows = {
        "initial.pos": [[0.0], [0.1], [0.2], [0.3], [0.4]],
        "action": ["push", "push", "push", "push", "wait"],
        "param.force": [[4.5], [6.0], [7.0], [9.0], [nan]],
        "end.pos": [[0.5], [0.7], [0.9], [1.2], [0.4]],
    }
    given = fit(net, rows | {"cluster.force": [0, 0, 1, 1, 0]}, pseudo_count=0.0).params
    cells = fit(net, rows, pseudo_count=0.0).params
    torch.testing.assert_close(
        given["param.force"].bias[:, 0], torch.tensor([5.25, 8.0], dtype=DTYPE)
    )
    torch.testing.assert_close(
        given["cluster.force"].probs[0], torch.tensor([0.5, 0.5], dtype=DTYPE)
    )
    torch.testing.assert_close(
        cells["param.force"].bias[:, 0], torch.tensor([4.5, (6.0 + 7.0 + 9.0) / 3], dtype=DTYPE)
    )
    torch.testing.assert_close(
        cells["cluster.force"].probs[0], torch.tensor([0.25, 0.75], dtype=DTYPE)
    )
    with pytest.raises(ValueError, match=r"'cluster.force': row 4 has cluster 1 for action 'wait'"):
        fit(net, rows | {"cluster.force": [0, 0, 1, 1, 1]})
