"""The inverse model: parameter_for_effect against closed forms and a brute-force sum."""

import math

import pytest
import torch
from effect_networks.inference import fit, fit_em, infer_parameter, parameter_for_effect, predict
from effect_networks.models import Continuous, Discrete, EffectNetwork, Parameter, Partial
from effect_networks.models.declaration import DTYPE
from hypothesis import given, settings
from hypothesis import strategies as st


def one_d_net(bins=1, layout="grid"):
    return EffectNetwork(
        (Continuous("y", 1, initial=False),),
        ("go",),
        (Parameter("p", (0.0,), (1.0,), (bins,), ("go",), "y", layout=layout),),
    )


def one_d_params(net, n=400, seed=0, noise=0.05, curve=lambda t: torch.sin(6 * t)):
    g = torch.Generator().manual_seed(seed)
    theta = torch.rand(n, 1, generator=g, dtype=DTYPE)
    y = curve(theta) + noise * torch.randn(n, 1, generator=g, dtype=DTYPE)
    rows = {"action": ["go"] * n, "param.p": theta, "end.y": y}
    if any(p.adaptive for p in net.parameters):
        return fit_em(net, rows, steps=5).params
    return fit(net, rows).params


def tap_net():
    """A force acting on a continuous position and on a discrete visibility."""
    return EffectNetwork(
        (Discrete("visible", (0, 1)), Continuous("pos", 1, initial=False)),
        ("remove", "tap"),
        (Parameter("force", (0.0,), (10.0,), (3,), ("tap",), ("pos", "visible")),),
    )


def normal(x, mean, var):
    return -0.5 * (math.log(2 * math.pi * var) + (x - mean) ** 2 / var)


def test_one_cluster_inverts_the_regression_where_the_posterior_shrinks():
    """One Gaussian: the answer is (y - b) / w exactly, its score the closed-form joint
    density; the posterior mean lies between it and the cluster's mean."""
    net = one_d_net(bins=1)
    params = one_d_params(net, noise=0.3, curve=lambda t: 2 * t + 1)
    lg, prior = params["end.y"], params["param.p"]
    w, b = float(lg.weight[0, 0, 0, 0]), float(lg.bias[0, 0, 0])
    r = float(lg.covariance[0, 0, 0, 0])
    mu, s2 = float(prior.bias[0, 0]), float(prior.covariance[0, 0, 0])
    y = torch.tensor([[1.2], [2.0], [2.9]], dtype=DTYPE)
    answer = parameter_for_effect(net, params, "p", {"end.y": y})
    expected = (y - b) / w
    torch.testing.assert_close(answer.value, expected)
    for i in range(3):
        theta = float(expected[i, 0])
        score = normal(theta, mu, s2) + normal(float(y[i, 0]), w * theta + b, r)
        assert float(answer.log_density[i]) == pytest.approx(score, abs=1e-9)
    torch.testing.assert_close(answer.miss, torch.zeros(3, dtype=DTYPE), atol=1e-12, rtol=0)
    posterior = infer_parameter(net, params, "p", {"end.y": y}).mean
    # shrunk towards mu by the share of y's spread that is noise: strictly between
    lo, hi = (
        torch.minimum(expected, torch.full_like(expected, mu)),
        torch.maximum(expected, torch.full_like(expected, mu)),
    )
    assert bool(((posterior > lo) & (posterior < hi)).all())


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 10_000), bins=st.integers(2, 5), y=st.floats(-0.9, 0.9))
def test_adaptive_candidates_and_scores_match_a_brute_force_sum(seed, bins, y):
    """Every cluster's candidate solves its own line; each score is the sum over all
    clusters of p(c) N(theta; m_c, s_c) N(y; w_c theta + b_c, r_c); the answer is the best."""
    net = one_d_net(bins, layout="adaptive")
    params = one_d_params(net, seed=seed)
    lg, prior = params["end.y"], params["param.p"]
    table = params["cluster.p"].probs[0]
    answer = parameter_for_effect(net, params, "p", {"end.y": [[y]]})
    for c in range(bins):
        w, b = float(lg.weight[0, c, 0, 0]), float(lg.bias[0, c, 0])
        theta = float(answer.candidates[0, c, 0])
        assert theta == pytest.approx((y - b) / w, rel=1e-7, abs=1e-9)
        terms = [
            math.log(float(table[k]))
            + normal(theta, float(prior.bias[k, 0]), float(prior.covariance[k, 0, 0]))
            + normal(
                y,
                float(lg.weight[0, k, 0, 0]) * theta + float(lg.bias[0, k, 0]),
                float(lg.covariance[0, k, 0, 0]),
            )
            for k in range(bins)
        ]
        brute = max(terms) + math.log(sum(math.exp(t - max(terms)) for t in terms))
        assert float(answer.candidate_log_density[0, c]) == pytest.approx(brute, abs=1e-8)
    best = int(answer.candidate_log_density[0].argmax())
    assert int(answer.cluster[0]) == best
    assert float(answer.value[0, 0]) == float(answer.candidates[0, best, 0])


def test_grid_scores_a_candidate_under_the_cell_it_falls_in():
    """Under the grid layout the cluster is the value's cell: a candidate's score is its
    cell's table entry, Gaussian and regression alone."""
    bins = 4
    net = one_d_net(bins)
    params = one_d_params(net)
    lg, prior = params["end.y"], params["param.p"]
    table = params["cluster.p"].probs[0]
    answer = parameter_for_effect(net, params, "p", {"end.y": [[0.5], [-0.3]]})
    for i, y in enumerate((0.5, -0.3)):
        for c in range(bins):
            theta = float(answer.candidates[i, c, 0])
            cell = min(bins - 1, max(0, math.floor(theta * bins)))
            score = (
                math.log(float(table[cell]))
                + normal(theta, float(prior.bias[cell, 0]), float(prior.covariance[cell, 0, 0]))
                + normal(
                    y,
                    float(lg.weight[0, cell, 0, 0]) * theta + float(lg.bias[0, cell, 0]),
                    float(lg.covariance[0, cell, 0, 0]),
                )
            )
            assert float(answer.candidate_log_density[i, c]) == pytest.approx(score, abs=1e-8)
    # sin(6 t) = 0.5 has a root in the first cell: the answer reproduces y there
    assert float(answer.miss[0]) == pytest.approx(0.0, abs=1e-12)
    assert 0 <= float(answer.value[0, 0]) <= 1


def test_a_value_with_more_dims_than_the_effect_is_nearest_the_cluster_mean():
    """A 2-D parameter acting on a 1-D feature: the answer lies on the line w . theta + b
    = y, at the point nearest the cluster's mean in its own metric (closed form)."""
    net = EffectNetwork(
        (Continuous("y", 1, initial=False),),
        ("go",),
        (Parameter("p", (0.0, 0.0), (1.0, 1.0), (1, 1), ("go",), "y"),),
    )
    g = torch.Generator().manual_seed(3)
    theta = torch.rand(300, 2, generator=g, dtype=DTYPE) * torch.tensor([1.0, 0.3], dtype=DTYPE)
    y = theta @ torch.tensor([[1.0], [2.0]], dtype=DTYPE) + 0.1
    y = y + 0.01 * torch.randn(300, 1, generator=g, dtype=DTYPE)
    params = fit(net, {"action": ["go"] * 300, "param.p": theta, "end.y": y}).params
    lg, prior = params["end.y"], params["param.p"]
    w, b = lg.weight[0, 0], lg.bias[0, 0]  # (1, 2), (1,)
    mu, cov = prior.bias[0], prior.covariance[0]
    target = torch.tensor([0.9], dtype=DTYPE)
    answer = parameter_for_effect(net, params, "p", {"end.y": target[None]})
    expected = mu + cov @ w.T @ torch.linalg.solve(w @ cov @ w.T, target - b - w @ mu)
    torch.testing.assert_close(answer.value[0], expected, rtol=1e-6, atol=1e-8)
    torch.testing.assert_close(w @ answer.value[0] + b, target)


def test_several_effects_are_weighed_by_their_noise():
    """A value acting on two features: the answer solves the normal equations
    sum_j W_j^T R_j^-1 (y_j - b_j - W_j theta) = 0 of the chosen cluster."""
    aim = Parameter("aim", 0.0, 2.0, 2, ("throw",), ("land", "roll"))
    net = EffectNetwork((Continuous("land", 2), Continuous("roll", 1)), ("throw",), (aim,))
    g = torch.Generator().manual_seed(5)
    n = 400
    a = torch.rand(n, 1, generator=g, dtype=DTYPE) * 2
    land = torch.cat([a, a**2], -1) + 0.05 * torch.randn(n, 2, generator=g, dtype=DTYPE)
    roll = 3 * a + 0.4 * torch.randn(n, 1, generator=g, dtype=DTYPE)
    params = fit(
        net,
        {
            "action": ["throw"] * n,
            "initial.land": torch.zeros(n, 2, dtype=DTYPE),
            "initial.roll": torch.zeros(n, 1, dtype=DTYPE),
            "param.aim": a,
            "end.land": land,
            "end.roll": roll,
        },
    ).params
    evidence = {
        "initial.land": torch.zeros(1, 2, dtype=DTYPE),
        "initial.roll": torch.zeros(1, 1, dtype=DTYPE),
        "end.land": torch.tensor([[1.5, 2.1]], dtype=DTYPE),
        "end.roll": torch.tensor([[4.0]], dtype=DTYPE),
    }
    answer = parameter_for_effect(net, params, "aim", evidence)
    c = int(answer.cluster[0])
    theta = answer.value[0]
    gradient = torch.zeros(1, dtype=DTYPE)
    for site in ("end.land", "end.roll"):
        lg = params[site]
        weight = lg.weight[0, c]  # (d, inputs): the other inputs, then the aim
        x = torch.cat([evidence[s][0] for s in net.cpd(site).inputs[:-1]])
        y = evidence[site][0] - lg.bias[0, c] - weight[:, :-1] @ x
        w = weight[:, -1:]
        gradient = gradient + w.T @ torch.linalg.solve(lg.covariance[0, c], y - w @ theta)
    assert float(gradient.abs().max()) < 1e-8
    assert float(answer.miss[0]) > 0  # three equations, one unknown: not exact


def test_refusals_and_empty_evidence():
    net = tap_net()
    g = torch.Generator().manual_seed(0)
    n = 200
    a = torch.randint(0, 2, (n,), generator=g)
    force = torch.rand(n, 1, generator=g, dtype=DTYPE) * 10
    force[a == 0] = float("nan")
    rows = {
        "initial.visible": torch.ones(n, dtype=torch.long),
        "action": a,
        "param.force": force,
        "end.visible": (a == 0).long(),
        "end.pos": force.nan_to_num() * 0.5,
    }
    params = fit(net, net.encode_indices(rows)).params
    base = {"initial.visible": [1], "action": ["tap"]}
    with pytest.raises(ValueError, match="continuous"):
        parameter_for_effect(net, params, "force", base | {"end.visible": [0]})
    with pytest.raises(ValueError, match="infers"):
        parameter_for_effect(
            net, params, "force", base | {"end.pos": [[1.0]], "param.force": [[2.0]]}
        )
    with pytest.raises(ValueError, match="does not use"):
        parameter_for_effect(
            net, params, "force", {"initial.visible": [1], "action": ["remove"], "end.pos": [[1.0]]}
        )
    with pytest.raises(ValueError, match="unknown parameter"):
        parameter_for_effect(net, params, "nothing", base | {"end.pos": [[1.0]]})
    empty = parameter_for_effect(
        net, params, "force", {"initial.visible": [], "action": [], "end.pos": torch.zeros(0, 1)}
    )
    assert empty.value.shape == (0, 1) and empty.candidates.shape == (0, 3, 1)
    answer = parameter_for_effect(net, params, "force", base | {"end.pos": [[2.0]]})
    assert float(answer.value[0, 0]) == pytest.approx(4.0, abs=1e-6)


def test_another_parameter_on_the_same_feature_is_taken_as_given():
    """force and angle both move pos: with the angle given, the force's answer solves its
    cell's line pos = b + w_x x + w_f force + w_a angle, and is scored under its cell."""
    force = Parameter("force", 0.0, 4.0, 2, ("push",), "pos")
    angle = Parameter("angle", -1.0, 1.0, 2, ("push",), "pos")
    net = EffectNetwork((Continuous("pos", 1),), ("stay", "push"), (force, angle))
    g = torch.Generator().manual_seed(11)
    n = 500
    f = torch.rand(n, 1, generator=g, dtype=DTYPE) * 4
    a = torch.rand(n, 1, generator=g, dtype=DTYPE) * 2 - 1
    x = torch.rand(n, 1, generator=g, dtype=DTYPE)
    pos = x + 0.3 * f + 0.1 * f**2 * a + 0.01 * torch.randn(n, 1, generator=g, dtype=DTYPE)
    rows = {
        "initial.pos": x,
        "action": ["push"] * n,
        "param.force": f,
        "param.angle": a,
        "end.pos": pos,
    }
    params = fit(net, rows).params
    evidence = {
        "initial.pos": [[0.2], [0.5]],
        "action": ["push", "push"],
        "param.angle": [[0.5], [-0.7]],
        "end.pos": [[1.1], [0.9]],
    }
    answer = parameter_for_effect(net, params, "force", evidence)
    with pytest.raises(ValueError, match="param.angle"):
        parameter_for_effect(
            net, params, "force", {k: v for k, v in evidence.items() if k != "param.angle"}
        )
    lg = params["end.pos"]
    for i in range(2):
        x0, ang, y = (
            evidence["initial.pos"][i][0],
            evidence["param.angle"][i][0],
            evidence["end.pos"][i][0],
        )
        ca = int(ang >= 0)  # the angle's cell of two over [-1, 1]
        for c in range(2):
            w = lg.weight[1, c, ca, 0]  # push, force cell, angle cell: [x, force, angle]
            b = float(lg.bias[1, c, ca, 0])
            theta = (y - b - float(w[0]) * x0 - float(w[2]) * ang) / float(w[1])
            assert float(answer.candidates[i, c, 0]) == pytest.approx(theta, rel=1e-9, abs=1e-12)


def test_rows_sharing_their_parents_answer_as_rows_apart():
    """Parameters gathered once for rows that share every parent (broadcast over the
    rows) give the answers the rows give one at a time, or mixed with another action."""
    force = Parameter("force", 0.0, 4.0, 3, ("push",), "pos")
    net = EffectNetwork((Continuous("pos", 1),), ("stay", "push"), (force,))
    g = torch.Generator().manual_seed(2)
    n = 300
    act = torch.randint(0, 2, (n,), generator=g)
    f = torch.rand(n, 1, generator=g, dtype=DTYPE) * 4
    f[act == 0] = float("nan")
    x = torch.rand(n, 1, generator=g, dtype=DTYPE)
    pos = x + torch.sin(f.nan_to_num()) + 0.05 * torch.randn(n, 1, generator=g, dtype=DTYPE)
    params = fit(
        net, net.encode_indices({"initial.pos": x, "action": act, "param.force": f, "end.pos": pos})
    ).params
    hits = torch.tensor([[0.4], [1.3], [0.9]], dtype=DTYPE)
    start = torch.tensor([[0.1], [0.2], [0.3]], dtype=DTYPE)
    together = parameter_for_effect(
        net, params, "force", {"initial.pos": start, "action": ["push"] * 3, "end.pos": hits}
    )
    for i in range(3):
        alone = parameter_for_effect(
            net,
            params,
            "force",
            {"initial.pos": start[i : i + 1], "action": ["push"], "end.pos": hits[i : i + 1]},
        )
        torch.testing.assert_close(
            alone.candidate_log_density[0], together.candidate_log_density[i]
        )
    both = predict(
        net,
        params,
        {"initial.pos": torch.cat([start, start]), "action": ["push"] * 3 + ["stay"] * 3},
    )
    pushed = predict(net, params, {"initial.pos": start, "action": ["push"] * 3})
    torch.testing.assert_close(both.continuous["pos"].mean[:3], pushed.continuous["pos"].mean)
    torch.testing.assert_close(both.continuous["pos"].cov[:3], pushed.continuous["pos"].cov)
    for i in range(3):
        alone = predict(net, params, {"initial.pos": start[i : i + 1], "action": ["push"]})
        torch.testing.assert_close(
            alone.continuous["pos"].mean[0], pushed.continuous["pos"].mean[i]
        )


def test_partial_evidence_counts_its_observed_dimensions():
    """A 2-D effect observed in one dimension: the answer solves that dimension's line
    alone (one equation, one unknown), and equals the answer from a 1-D network fitted on
    that dimension."""
    net = EffectNetwork(
        (Continuous("xy", 2, initial=False),),
        ("go",),
        (Parameter("p", (0.0,), (1.0,), (1,), ("go",), "xy"),),
    )
    g = torch.Generator().manual_seed(4)
    n = 300
    theta = torch.rand(n, 1, generator=g, dtype=DTYPE)
    xy = torch.cat([2 * theta + 0.5, -theta], -1) + 0.05 * torch.randn(
        n, 2, generator=g, dtype=DTYPE
    )
    params = fit(net, {"action": ["go"] * n, "param.p": theta, "end.xy": xy}).params
    value = torch.tensor([[1.3, float("nan")]], dtype=DTYPE)
    answer = parameter_for_effect(
        net, params, "p", {"end.xy": Partial(value, observed=[True, False])}
    )
    lg = params["end.xy"]
    expected = (1.3 - float(lg.bias[0, 0, 0])) / float(lg.weight[0, 0, 0, 0])
    assert float(answer.value[0, 0]) == pytest.approx(expected, rel=1e-9)
    assert torch.isfinite(answer.log_density).all()
    assert float(answer.miss[0]) == pytest.approx(0.0, abs=1e-12)


def _throw_case(layout):
    """The throw network (a 2-D target acting on a 2-D hit) on a curved map."""
    from effect_networks.models.humanoid_throw import throw_data, throw_network

    net = throw_network((3, 3))
    if layout == "adaptive":
        p = net.parameters[0]
        net = EffectNetwork(
            net.features, net.actions, (Parameter(**_fields(p, layout="adaptive")),)
        )
    g = torch.Generator().manual_seed(7)
    targets = torch.rand(600, 2, generator=g, dtype=DTYPE) * 2 + torch.tensor([-1.0, 0.4])
    hits = torch.stack([targets[:, 0], targets[:, 1] - 0.1 * targets[:, 1] ** 2], -1)
    hits = hits + 0.002 * torch.randn(600, 2, generator=g, dtype=DTYPE)
    data = throw_data(net, targets.numpy(), hits.numpy())
    params = fit_em(net, data, steps=3).params if layout == "adaptive" else fit(net, data).params
    desired = torch.tensor([[0.1, 1.0], [-0.8, 0.5], [0.9, 2.0], [5.0, 5.0]], dtype=DTYPE)
    return net, params, "target", {"end.hit": desired}


def _fields(p, **changes):
    import dataclasses

    return {f.name: getattr(p, f.name) for f in dataclasses.fields(p)} | changes


def _two_effects_case():
    aim = Parameter("aim", 0.0, 2.0, 2, ("throw",), ("land", "roll"), layout="adaptive")
    net = EffectNetwork((Continuous("land", 2), Continuous("roll", 1)), ("throw",), (aim,))
    g = torch.Generator().manual_seed(5)
    n = 400
    a = torch.rand(n, 1, generator=g, dtype=DTYPE) * 2
    x = torch.rand(n, 2, generator=g, dtype=DTYPE)
    land = x + torch.cat([a, a**2], -1) + 0.05 * torch.randn(n, 2, generator=g, dtype=DTYPE)
    roll = 3 * a + 0.4 * torch.randn(n, 1, generator=g, dtype=DTYPE)
    rows = {
        "action": ["throw"] * n,
        "initial.land": x,
        "initial.roll": torch.zeros(n, 1, dtype=DTYPE),
        "param.aim": a,
        "end.land": land,
        "end.roll": roll,
    }
    params = fit_em(net, rows, steps=3).params
    evidence = {
        "initial.land": [[0.1, 0.2], [0.5, 0.5]],
        "initial.roll": [[0.0], [0.0]],
        "end.land": Partial(
            torch.tensor([[1.5, 2.1], [0.9, float("nan")]], dtype=DTYPE),
            observed=[[True, True], [True, False]],
        ),
        "end.roll": [[4.0], [2.5]],
    }
    return net, params, "aim", evidence


def _two_parameters_case():
    force = Parameter("force", 0.0, 4.0, 2, ("push",), "pos")
    angle = Parameter("angle", -1.0, 1.0, 2, ("push",), "pos")
    net = EffectNetwork((Continuous("pos", 1),), ("stay", "push"), (force, angle))
    g = torch.Generator().manual_seed(11)
    n = 500
    act = torch.randint(0, 2, (n,), generator=g)
    f = torch.rand(n, 1, generator=g, dtype=DTYPE) * 4
    a = torch.rand(n, 1, generator=g, dtype=DTYPE) * 2 - 1
    f[act == 0], a[act == 0] = float("nan"), float("nan")
    x = torch.rand(n, 1, generator=g, dtype=DTYPE)
    pos = x + 0.3 * f.nan_to_num() + 0.1 * f.nan_to_num() ** 2 * a.nan_to_num()
    pos = pos + 0.01 * torch.randn(n, 1, generator=g, dtype=DTYPE)
    rows = {"initial.pos": x, "action": act, "param.force": f, "param.angle": a, "end.pos": pos}
    params = fit(net, net.encode_indices(rows)).params
    evidence = {
        "initial.pos": [[0.2], [0.5]],
        "action": ["push", "push"],
        "param.angle": [[0.5], [-0.7]],
        "end.pos": [[1.1], [0.9]],
    }
    return net, params, "force", evidence


def _discrete_effect_case():
    """The force also acts on a discrete feature: its table depends on the cluster, so
    the closed-form scores do not apply and the model scores every candidate."""
    net = tap_net()
    g = torch.Generator().manual_seed(0)
    n = 200
    force = torch.rand(n, 1, generator=g, dtype=DTYPE) * 10
    rows = {
        "initial.visible": torch.ones(n, dtype=torch.long),
        "action": torch.ones(n, dtype=torch.long),
        "param.force": force,
        "end.visible": (force[:, 0] > 5).long(),
        "end.pos": force * 0.5 + 0.1 * torch.randn(n, 1, generator=g, dtype=DTYPE),
    }
    params = fit(net, net.encode_indices(rows)).params
    evidence = {"initial.visible": [1, 1], "action": ["tap"] * 2, "end.pos": [[2.0], [4.0]]}
    return net, params, "force", evidence


CASES = {
    "throw, grid": lambda: _throw_case("grid"),
    "throw, adaptive": lambda: _throw_case("adaptive"),
    "two effects, partial": _two_effects_case,
    "two parameters": _two_parameters_case,
    "one d, adaptive": lambda: (
        one_d_net(4, "adaptive"),
        one_d_params(one_d_net(4, "adaptive")),
        "p",
        {"end.y": [[0.5], [-0.3], [0.95]]},
    ),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_closed_form_scores_equal_the_models_own(case, monkeypatch):
    """The candidates' scores in closed form (the mixture's terms, shifted by one model
    evaluation per row) equal the model's log p(value, evidence) at every candidate."""
    import effect_networks.inference.queries.inverse as queries

    net, params, p, evidence = CASES[case]()
    m = net.mixture(p)
    scored_rows, chunked = [], queries.over_row_chunks
    with monkeypatch.context() as patch:
        patch.setattr(
            queries,
            "over_row_chunks",
            lambda n, q, e, *a: scored_rows.append(e.n_rows) or chunked(n, q, e, *a),
        )
        fast = parameter_for_effect(net, params, p, evidence)
    n = fast.value.shape[0]
    assert scored_rows == [n]  # the model evaluated at each row's best only
    monkeypatch.setattr(queries, "_candidate_scores", lambda *args: None)
    slow = parameter_for_effect(net, params, p, evidence)
    finite = torch.isfinite(slow.candidate_log_density)
    assert bool(finite.any(-1).all()) and m.parameter.n_clusters > 1
    torch.testing.assert_close(fast.candidates, slow.candidates)
    assert torch.equal(finite, torch.isfinite(fast.candidate_log_density))
    torch.testing.assert_close(
        fast.candidate_log_density[finite], slow.candidate_log_density[finite], rtol=1e-9, atol=1e-8
    )
    assert torch.equal(fast.cluster, slow.cluster)


def test_a_discrete_effect_of_the_cluster_is_scored_by_the_model():
    import effect_networks.inference.queries.inverse as queries
    from effect_networks.inference.queries.batching import prepare

    net, params, p, evidence = _discrete_effect_case()
    answer = parameter_for_effect(net, params, p, evidence)
    m = net.mixture(p)
    enc = prepare(net, params, evidence)
    children = [net.cpd("end.pos")]
    every = torch.arange(m.parameter.n_clusters).expand(enc.n_rows, -1)
    whitened = m.whitened(params, children, enc, every)
    scores = queries._candidate_scores(
        net, params, m, enc, children, (m,), answer.candidates, whitened
    )
    assert scores is None  # end.visible's table depends on the cluster
    assert torch.isfinite(answer.log_density).all()
