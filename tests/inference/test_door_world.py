"""README's documented behaviour on a world of its own: a door, a drawer and a switch.

Features ``door`` (locked/shut/open), ``drawer`` (shut/open), ``switch`` (off/on) and a
continuous ``handle_angle``; actions press, pull, turn and wait. The end state of the
door depends on the handle's angle through a softmax. Rows are drawn here with numpy;
every answer is checked against something the library did not compute: the softmax
optimum's gradient written out in numpy, a brute-force joint over every discrete
assignment, a direct maximisation of the observed-data likelihood by scipy, pgmpy's
variable elimination.
"""

from __future__ import annotations

import itertools
import math
import time

import numpy as np
import pytest
import torch
from effect_networks.models import Continuous, Discrete, EffectNetwork

from tests.networks import DOOR_ACTIONS, DOOR_PARENTS, DOOR_STATES, door_rows, door_world


def states_of(site: str) -> tuple:
    return DOOR_ACTIONS if site == "action" else DOOR_STATES[site.split(".", 1)[1]]


def index_of(site: str, labels) -> np.ndarray:
    states = states_of(site)
    return np.array([states.index(v) for v in np.asarray(labels).reshape(-1)])


# ---------------------------------------------------------------- oracle: the joint by hand
def log_factor(net, params, site: str, values: dict) -> np.ndarray:
    """``log p(site | parents)`` per row, from the fitted numbers alone (numpy): a table
    row, a softmax of the inputs, or a Gaussian density. ``values``: state indices for
    discrete sites, ``(n, d)`` arrays for continuous ones."""
    cpd, cpd_params = net.cpd(site), params[site]
    n = len(next(iter(values.values())))
    # every row's parent configuration (a root: one configuration, read for every row)
    at = tuple(np.broadcast_to(values[p], (n,)) for p in cpd.parents) or (np.zeros(n, int),)

    def numbers(name):
        value = getattr(cpd_params, name).numpy()
        return value[at] if cpd.parents else value[None][at]

    x = np.concatenate([values[s] for s in cpd.inputs], -1) if cpd.inputs else np.zeros((n, 0))
    if cpd.name == "table":
        return np.log(numbers("probs")[np.arange(n), values[site]])
    if cpd.name == "softmax":
        weight, bias = numbers("weight"), numbers("bias")
        logits = np.einsum("nkp,np->nk", weight, x) + bias
        logits -= logits.max(1, keepdims=True)
        logp = logits - np.log(np.exp(logits).sum(1, keepdims=True))
        return logp[np.arange(n), values[site]]
    assert cpd.name == "linear_gaussian"
    weight, bias, cov = numbers("weight"), numbers("bias"), numbers("covariance")
    residual = values[site] - np.einsum("ndp,np->nd", weight, x) - bias
    d = residual.shape[1]
    solved = np.linalg.solve(cov, residual[..., None])[..., 0]
    return -0.5 * (
        (residual * solved).sum(1) + np.linalg.slogdet(cov)[1] + d * math.log(2 * math.pi)
    )


def brute_force(net, params, evidence: dict) -> tuple[np.ndarray, dict]:
    """``log p(evidence)`` per row and every latent discrete site's posterior, by summing
    the joint over every assignment of the latent discrete sites (continuous sites left
    out of ``evidence`` are end sites: they integrate to one)."""
    n = len(next(iter(evidence.values())))
    given = {}
    for site, value in evidence.items():
        discrete = net.site(site).discrete
        given[site] = index_of(site, value) if discrete else np.asarray(value, float)
    latent = [s.name for s in net.sites if s.discrete and s.name not in given]
    logs, assignments = [], list(itertools.product(*(range(net.site(s).size) for s in latent)))
    for assignment in assignments:
        values = given | {s: np.full(n, k) for s, k in zip(latent, assignment, strict=True)}
        logs.append(sum(log_factor(net, params, s, values) for s in values))
    logs = np.stack(logs)  # (assignments, n)
    top = logs.max(0)
    log_evidence = top + np.log(np.exp(logs - top).sum(0))
    weights = np.exp(logs - log_evidence)
    posterior = {}
    for j, site in enumerate(latent):
        marginal = np.zeros((n, net.site(site).size))
        for a, assignment in enumerate(assignments):
            marginal[:, assignment[j]] += weights[a]
        posterior[site] = marginal
    return log_evidence, posterior


# ---------------------------------------------------------------- fitting: softmax
def numpy_kkt(net, params, rows, l2):
    """The largest component of the gradient of the penalised objective
    ``sum_i -log softmax(W[g_i] x_i + b[g_i])[y_i] + l2 / 2 |W|^2`` of ``end.door``."""
    cpd = net.cpd("end.door")
    weight = params["end.door"].weight.numpy().reshape(-1, 3, 1)
    bias = params["end.door"].bias.numpy().reshape(-1, 3)
    group = np.ravel_multi_index([index_of(s, rows[s]) for s in cpd.parents], cpd.card)
    x = np.asarray(rows["initial.handle_angle"], float)
    y = index_of("end.door", rows["end.door"])
    logits = np.einsum("nkp,np->nk", weight[group], x) + bias[group]
    prob = np.exp(logits - logits.max(1, keepdims=True))
    prob /= prob.sum(1, keepdims=True)
    residual = prob - np.eye(3)[y]
    grad_w, grad_b = l2 * weight, np.zeros_like(bias)
    np.add.at(grad_w, group, residual[:, :, None] * x[:, None, :])
    np.add.at(grad_b, group, residual)
    return max(np.abs(grad_w).max(), np.abs(grad_b).max())


@pytest.mark.parametrize("parents", [DOOR_PARENTS, None], ids=["own", "default"])
@pytest.mark.parametrize("l2", [0.01, 1.0])
def test_softmax_fit_meets_the_kkt_conditions_quickly(parents, l2):
    from effect_networks.inference import fit

    net = door_world(parents)
    assert net.cpd("end.door").name == "softmax"
    rows = door_rows(3000, seed=1)
    fit(net, door_rows(50), l2=l2)  # warm (first calls build caches)
    start = time.perf_counter()
    result = fit(net, rows, l2=l2)
    elapsed = time.perf_counter() - start
    print(f"door world, 3,000 rows, parents {'own' if parents else 'default'}: {elapsed:.3f} s")
    assert result.converged
    assert numpy_kkt(net, result.params, rows, l2) < 1e-6
    assert elapsed < 1.0  # goal 0.2 s; the bound leaves room for a loaded machine
    if parents is not DOOR_PARENTS:
        return
    # the table sites beside it are the counts
    drawer = result.params["end.drawer"].probs.numpy()
    pulled = (rows["action"] == "pull") & (rows["initial.drawer"] == "shut")
    share = np.mean(rows["end.drawer"][pulled] == "open")
    assert drawer[0, DOOR_ACTIONS.index("pull"), 1] == pytest.approx(share, abs=1e-4)


def test_softmax_fit_at_large_angles():
    # angles in milli-radians far from 1: the same optimality conditions
    from effect_networks.inference import fit

    net = door_world()
    rows = door_rows(1000, seed=2)
    rows["initial.handle_angle"] = rows["initial.handle_angle"] * 1e5
    result = fit(net, rows)
    assert result.converged
    x_scale = np.abs(rows["initial.handle_angle"]).max()
    assert numpy_kkt(net, result.params, rows, 0.01) < 1e-6 * x_scale


# ---------------------------------------------------------------- fitting: missing values
def masked(rows, seed, sites=("end.door", "initial.drawer", "action", "end.switch"), share=0.2):
    rng = np.random.default_rng(seed)
    n = len(rows["action"])
    return {s: rng.random(n) > share for s in sites}


def test_missing_values_em_never_lowers_the_likelihood_and_is_fast():
    from effect_networks.inference import fit
    from effect_networks.inference.fitting.missing import missing_log_likelihood

    net = door_world()
    rows = door_rows(1000, seed=3)
    masks = masked(rows, 4)
    fit(net, door_rows(60), masks=masked(door_rows(60), 0))  # warm
    start = time.perf_counter()
    result = fit(net, rows, masks=masks, pseudo_count=0.0, min_variance=0.0)
    elapsed = time.perf_counter() - start
    print(f"door world, EM over missing values, 1,000 rows: {elapsed:.3f} s")
    assert result.converged
    assert elapsed < 4.0  # goal 2 s; the bound leaves room for a loaded machine
    losses = np.array(result.losses)
    assert (np.diff(losses) <= 0).all() and losses[-1] < losses[0]
    # the curve is the model's own likelihood, missing values summed out (softmax prior
    # added), against the brute-force joint
    own = missing_log_likelihood(net, result.params, rows, masks)
    prior = 0.5 * 0.01 * float(result.params["end.door"].weight.square().sum())
    assert (prior - own) / 1000 == pytest.approx(losses[-1], rel=1e-10)
    ours = 0.0
    for pattern in {tuple(bool(masks[s][i]) for s in masks) for i in range(1000)}:
        which = np.all([masks[s] == kept for s, kept in zip(masks, pattern, strict=True)], 0)
        evidence = {
            s: np.asarray(v)[which]
            for s, v in rows.items()
            if s not in masks or pattern[list(masks).index(s)]
        }
        ours += brute_force(net, result.params, evidence)[0].sum()
    assert ours == pytest.approx(own, rel=1e-12)


def test_a_missing_value_is_ignored_whatever_stands_in_its_place():
    # None, NaN or a label the site does not have where masks say missing: the same fit
    from effect_networks.inference import fit
    from effect_networks.inference.fitting.missing import missing_log_likelihood

    net = door_world()
    rows = door_rows(300, seed=15)
    masks = masked(rows, 16)
    holes = dict(rows)
    for site, junk in (("end.door", None), ("initial.drawer", "ajar"), ("action", np.nan)):
        values = rows[site].astype(object)
        values[~masks[site]] = junk
        holes[site] = values
    expected = fit(net, rows, masks=masks)
    found = fit(net, holes, masks=masks)
    assert found.losses == expected.losses
    for site in expected.params.cpds:
        for name in expected.params[site].__dataclass_fields__:
            value = getattr(expected.params[site], name)
            assert torch.equal(getattr(found.params[site], name), value), (site, name)
    assert missing_log_likelihood(net, found.params, holes, masks) == missing_log_likelihood(
        net, found.params, rows, masks
    )


@pytest.mark.parametrize(
    ("masks", "words"),
    [
        ({"end.doors": np.ones(50, bool)}, r"masks\['end\.doors'\]: no such site"),
        ({"end.door": np.full(50, 0.5)}, r"masks\['end\.door'\] must hold bools"),
        ({"end.door": np.full(50, "no")}, r"masks\['end\.door'\] must hold bools"),
    ],
)
def test_bad_masks_are_value_errors_naming_the_site(masks, words):
    from effect_networks.inference import fit

    with pytest.raises(ValueError, match=words):
        fit(door_world(), door_rows(50), masks=masks)


def tiny_world() -> EffectNetwork:
    return EffectNetwork(
        features=(Discrete("door", DOOR_STATES["door"]), Continuous("handle_angle", 1)),
        actions=("turn", "wait"),
        parents={
            "end.door": ("action", "initial.handle_angle"),
            "end.handle_angle": ("initial.handle_angle", "action"),
        },
    )


def tiny_rows(n, seed):
    rng = np.random.default_rng(seed)
    rows = door_rows(n, seed)
    turn = rng.random(n) < 0.5
    rows["action"] = np.where(turn, "turn", "wait")
    angle = rows["initial.handle_angle"][:, 0]
    logits = np.stack([np.zeros(n), np.where(turn, 1.0, 0.5), np.where(turn, 3 * angle, -1.0)], 1)
    prob = np.exp(logits) / np.exp(logits).sum(1, keepdims=True)
    rows["end.door"] = np.array(DOOR_STATES["door"])[
        (rng.random(n)[:, None] > prob.cumsum(1)).sum(1)
    ]
    end = np.where(turn, 0.5 * angle + 0.3, angle) + rng.normal(0.0, 0.1, n)
    rows["end.handle_angle"] = end[:, None]
    keep = ("initial.door", "initial.handle_angle", "action", "end.door", "end.handle_angle")
    return {s: rows[s] for s in keep}


def test_missing_values_em_reaches_scipy_s_maximum_of_the_observed_likelihood():
    # the observed-data likelihood written by hand in torch (missing action and end
    # state summed out), maximised by scipy over unconstrained parameters
    from effect_networks.inference import fit
    from scipy.optimize import minimize

    net = tiny_world()
    n, l2 = 80, 0.01
    rows = tiny_rows(n, seed=5)
    masks = masked(rows, 6, sites=("action", "end.door"), share=0.3)
    result = fit(net, rows, masks=masks, pseudo_count=0.0, min_variance=0.0, tol=1e-14, steps=5000)
    assert result.converged

    door0 = torch.as_tensor(index_of("initial.door", rows["initial.door"]))
    action = torch.as_tensor((rows["action"] == "wait").astype(int))  # turn 0, wait 1
    end = torch.as_tensor(index_of("end.door", rows["end.door"]))
    x = torch.as_tensor(rows["initial.handle_angle"][:, 0])
    y = torch.as_tensor(rows["end.handle_angle"][:, 0])
    seen_a, seen_e = (torch.as_tensor(masks[s]) for s in ("action", "end.door"))

    def split(theta):
        return torch.split(theta, [3, 2, 6, 6, 2, 2, 2], 0)

    def negative(theta):
        door_logits, action_logits, w, b, slope, offset, log_sd = split(theta)
        ll = torch.log_softmax(door_logits, 0)[door0].sum()  # observed always
        mean_x, var_x = x.mean(), x.var(unbiased=False)  # initial angle: closed form
        ll = ll + torch.distributions.Normal(mean_x, var_x.sqrt()).log_prob(x).sum()
        joint = torch.log_softmax(action_logits, 0)[None, :].expand(n, 2)  # (n, a)
        logits = w.reshape(2, 3)[None] * x[:, None, None] + b.reshape(2, 3)[None]
        logp_end = torch.log_softmax(logits, -1)  # (n, a, K)
        end_term = torch.where(
            seen_e[:, None], logp_end.gather(-1, end[:, None, None].expand(n, 2, 1))[..., 0], 0.0
        )
        angle = torch.distributions.Normal(slope * x[:, None] + offset, log_sd.exp())
        joint = joint + end_term + angle.log_prob(y[:, None])
        joint = torch.where(seen_a[:, None], joint.gather(1, action[:, None]).expand(n, 2), joint)
        per_row = torch.where(seen_a, joint[:, 0], torch.logsumexp(joint, 1))
        return -(ll + per_row.sum()) + 0.5 * l2 * w.square().sum()

    def value_and_grad(theta):
        t = torch.as_tensor(theta).requires_grad_()
        f = negative(t)
        (g,) = torch.autograd.grad(f, t)
        return float(f), g.numpy()

    found = minimize(value_and_grad, np.zeros(23), jac=True, method="BFGS", options={"gtol": 1e-10})
    best = found.fun / n
    # EM's loss counts the same factors (plus the constant ones scipy left to closed form)
    p = result.params
    theta = torch.cat(
        [
            p["initial.door"].probs.log(),
            p["action"].probs.log(),
            p["end.door"].weight.reshape(-1),
            p["end.door"].bias.reshape(-1),
            p["end.handle_angle"].weight.reshape(-1),
            p["end.handle_angle"].bias.reshape(-1),
            p["end.handle_angle"].scale_tril.reshape(-1).log(),
        ]
    )
    ours = float(negative(theta)) / n
    assert ours == pytest.approx(result.losses[-1], rel=1e-9)  # EM's own curve, by hand
    assert ours <= best + 1e-9  # EM is at the maximum scipy finds
    assert best <= ours + 1e-9
    # and at the same point: the tables and the regression
    door_logits, action_logits, w, b, slope, offset, log_sd = split(torch.as_tensor(found.x))
    torch.testing.assert_close(
        p["action"].probs, torch.softmax(action_logits, 0), atol=1e-5, rtol=0
    )
    torch.testing.assert_close(p["end.handle_angle"].bias.reshape(-1), offset, atol=1e-5, rtol=0)
    weight = p["end.door"].weight.reshape(2, 3)
    torch.testing.assert_close(
        weight - weight.mean(1, keepdim=True),
        w.reshape(2, 3) - w.reshape(2, 3).mean(1, keepdim=True),
        atol=1e-4,
        rtol=0,
    )


# ---------------------------------------------------------------- queries against pgmpy
def pgmpy_network(net, params):
    """The discrete network written into pgmpy by hand: each site's table, its parents
    in the declared order (pgmpy's columns run over them with the last fastest)."""
    from pgmpy.factors.discrete import TabularCPD
    from pgmpy.models import DiscreteBayesianNetwork

    model = DiscreteBayesianNetwork()
    model.add_nodes_from([s.name for s in net.sites])
    cpds = []
    for spec in net.sites:
        cpd = net.cpd(spec.name)
        probs = params[spec.name].probs.numpy()
        k = probs.shape[-1]
        for parent in cpd.parents:
            model.add_edge(parent, spec.name)
        cpds.append(
            TabularCPD(
                spec.name,
                k,
                probs.reshape(-1, k).T,
                evidence=list(cpd.parents) or None,
                evidence_card=list(cpd.card) or None,
                state_names={s: list(range(net.site(s).size)) for s in (spec.name, *cpd.parents)},
            )
        )
    model.add_cpds(*cpds)
    model.check_model()
    return model


EVIDENCE_PATTERNS = [
    ("initial.door", "initial.drawer", "initial.switch", "end.door", "end.drawer", "end.switch"),
    ("initial.door", "end.door", "end.switch"),
    ("end.door", "end.drawer"),
    ("initial.switch", "end.switch"),
]


@pytest.mark.parametrize("pattern", EVIDENCE_PATTERNS, ids=lambda p: "+".join(p))
def test_discrete_queries_equal_pgmpy_variable_elimination(pattern):
    from effect_networks.inference import fit, infer_action, predict
    from pgmpy.inference import VariableElimination

    from effect_networks import inference

    net = door_world(None, handle=False)
    params = fit(net, door_rows(400, seed=7, handle=False)).params
    ve = VariableElimination(pgmpy_network(net, params))
    rows = door_rows(6, seed=8, handle=False)
    posterior = infer_action(net, params, {s: rows[s] for s in pattern})
    compiled = inference.compile(net, params).action_tables
    tables = compiled.infer_action({s: rows[s] for s in pattern})
    for i in range(6):
        evidence = {s: int(index_of(s, rows[s][i : i + 1])[0]) for s in pattern}
        expected = ve.query(["action"], evidence=evidence, show_progress=False).values
        np.testing.assert_allclose(posterior.probs[i].numpy(), expected, rtol=0, atol=1e-12)
        np.testing.assert_allclose(tables.probs[i].numpy(), expected, rtol=0, atol=1e-12)
        one = compiled.infer_action({s: rows[s][i : i + 1] for s in pattern})  # one row
        np.testing.assert_allclose(one.probs[0].numpy(), expected, rtol=0, atol=1e-12)
        assert one.best_names == (DOOR_ACTIONS[int(np.argmax(expected))],) or one.unseen.any()
    # predict: the initial sites of the pattern and an action; every end feature
    initial = [s for s in pattern if s.startswith("initial.")]
    prediction = predict(net, params, {s: rows[s] for s in initial} | {"action": rows["action"]})
    for i in range(6):
        evidence = {s: int(index_of(s, rows[s][i : i + 1])[0]) for s in (*initial, "action")}
        for feature, states in DOOR_STATES.items():
            expected = ve.query([f"end.{feature}"], evidence=evidence, show_progress=False).values
            ours = np.array([float(prediction.prob(feature, state)[i]) for state in states])
            np.testing.assert_allclose(ours, expected, rtol=0, atol=1e-12)


def test_mixed_queries_equal_the_brute_force_joint():
    # the continuous world: infer_action's posterior and evidence, predict's door
    from effect_networks.inference import fit, infer_action, predict

    net = door_world()
    params = fit(net, door_rows(1500, seed=9)).params
    rows = door_rows(8, seed=10)
    for observed in (
        ("initial.door", "initial.drawer", "initial.switch", "end.door", "end.handle_angle"),
        ("initial.door", "end.door", "end.drawer"),
        ("initial.switch", "end.switch", "end.handle_angle"),
    ):
        evidence = {s: rows[s] for s in ("initial.handle_angle", *observed)}
        posterior = infer_action(net, params, evidence)
        log_evidence, marginals = brute_force(net, params, evidence)
        np.testing.assert_allclose(posterior.probs.numpy(), marginals["action"], atol=1e-12)
        np.testing.assert_allclose(posterior.log_evidence.numpy(), log_evidence, rtol=1e-12)
    evidence = {s: rows[s] for s in ("initial.handle_angle", "initial.door", "action")}
    prediction = predict(net, params, evidence)
    _, marginals = brute_force(net, params, evidence)
    ours = np.stack([prediction.prob("door", s).numpy() for s in DOOR_STATES["door"]], 1)
    np.testing.assert_allclose(ours, marginals["end.door"], rtol=0, atol=1e-12)


# ---------------------------------------------------------------- README's Pyro idioms
@pytest.fixture(scope="module")
def fitted():
    from effect_networks.inference import fit

    net = door_world()
    return net, fit(net, door_rows(2000, seed=11)).params


def test_predictive_in_parallel_draws_from_the_tables(fitted):
    import pyro
    from effect_networks.models import effect_model
    from pyro.infer import Predictive

    net, params = fitted
    sites = [site.name for site in net.sites]
    pyro.set_rng_seed(0)
    start = time.perf_counter()
    draws = Predictive(effect_model, num_samples=100, parallel=True, return_sites=sites)(
        net, params, n_rows=5
    )
    print(f"Predictive(parallel=True), 100 x 5 draws: {time.perf_counter() - start:.3f} s")
    assert set(draws) == set(sites)
    for site in sites:
        size = net.site(site).size
        assert draws[site].shape == ((100, 5) if net.site(site).discrete else (100, 5, size))
    # more draws for the statistics: every site given the drawn parents, against the
    # fitted numbers read by hand
    draws = Predictive(effect_model, num_samples=800, parallel=True, return_sites=sites)(
        net, params, n_rows=5
    )
    values = {
        s: (v.reshape(-1).numpy() if net.site(s).discrete else v.reshape(-1, 1).double().numpy())
        for s, v in draws.items()
    }
    n = len(values["action"])
    for site in sites:
        if net.site(site).discrete:
            k = net.site(site).size
            probs = np.stack(
                [
                    np.exp(log_factor(net, params, site, values | {site: np.full(n, j)}))
                    for j in range(k)
                ],
                1,
            )
            np.testing.assert_allclose(probs.sum(1), 1.0, atol=1e-12)
            excess = (np.eye(k)[values[site]] - probs).sum(0)
            spread = np.sqrt((probs * (1 - probs)).sum(0)).clip(1e-9)
            assert (np.abs(excess) <= 5 * spread + 1e-9).all(), (site, excess, spread)
        else:
            # the standardised residual of each draw: mean 0, variance 1
            cpd = net.cpd(site)
            weight = params[site].weight.numpy()
            at = tuple(values[p] for p in cpd.parents)
            x = (
                np.concatenate([values[s] for s in cpd.inputs], -1)
                if cpd.inputs
                else np.zeros((n, 0))
            )
            w = weight[at] if cpd.parents else np.broadcast_to(weight, (n, *weight.shape))
            b = params[site].bias.numpy()[at] if cpd.parents else params[site].bias.numpy()
            sd = params[site].scale_tril.numpy()[..., 0, 0]
            sd = sd[at] if cpd.parents else sd
            z = (values[site][:, 0] - np.einsum("ndp,np->nd", w, x)[:, 0] - b[..., 0]) / sd
            assert abs(z.mean()) < 5 / math.sqrt(n) and abs(z.var() - 1) < 5 * math.sqrt(2 / n)


EVIDENCE_FOR_ELBO = [
    # the action and the drawer latent; the handle's end observed or not
    ("initial.door", "initial.switch", "end.door", "end.switch", "end.handle_angle"),
    ("initial.door", "initial.switch", "end.door", "end.switch"),
    ("initial.drawer", "end.drawer"),
]


@pytest.mark.parametrize("observed", EVIDENCE_FOR_ELBO, ids=lambda p: "+".join(p))
def test_trace_enum_elbo_is_minus_log_evidence_exactly(fitted, observed):
    from effect_networks.models import effect_model
    from pyro.infer import TraceEnum_ELBO

    net, params = fitted
    rows = door_rows(7, seed=12)
    evidence = {s: rows[s] for s in ("initial.handle_angle", *observed)}
    expected = -brute_force(net, params, evidence)[0].sum()
    enc = net.encode(evidence)
    elbo = TraceEnum_ELBO(max_plate_nesting=1)
    collapsed = [
        elbo.loss(lambda: effect_model(net, params, enc, collapse=True), lambda: None)
        for _ in range(3)
    ]
    assert collapsed == pytest.approx([expected] * 3, rel=1e-12)
    ends = {s for s in observed if s.startswith("end.")}
    kept = [
        elbo.loss(lambda: effect_model(net, params, enc, end_sites=ends), lambda: None)
        for _ in range(3)
    ]
    assert kept == pytest.approx([expected] * 3, rel=1e-12)
    if "end.handle_angle" in observed:  # every continuous end site observed: the default form too
        plain = elbo.loss(lambda: effect_model(net, params, enc), lambda: None)
        assert plain == pytest.approx(expected, rel=1e-12)


def test_infer_discrete_draws_the_exact_posterior(fitted):
    import pyro
    from effect_networks.models import effect_model
    from pyro.infer import infer_discrete

    net, params = fitted
    rows = door_rows(1, seed=13)
    evidence = {
        s: np.repeat(rows[s], 2000, 0) for s in ("initial.handle_angle", "initial.door", "end.door")
    }
    _, posterior = brute_force(net, params, {s: v[:1] for s, v in evidence.items()})
    enc = net.encode(evidence)
    pyro.set_rng_seed(1)
    drawn = infer_discrete(
        lambda: effect_model(net, params, enc, collapse=True), first_available_dim=-2, temperature=1
    )()["action"].numpy()
    p = posterior["action"][0]
    freq = np.bincount(drawn, minlength=4) / 2000
    assert (np.abs(freq - p) <= 5 * np.sqrt(p * (1 - p) / 2000) + 1e-9).all()


@pytest.mark.parametrize(
    "observed",
    [
        ("end.door", "end.drawer", "end.switch", "end.handle_angle"),
        ("end.door", "end.handle_angle"),
        ("end.door", "end.switch"),
    ],
    ids=lambda p: "+".join(p),
)
def test_imitation_surprise_equals_the_closed_form(fitted, observed):
    # surprise = P(p(O | E) > p(o* | E)): per discrete outcome d, the Gaussian's share
    # of angles whose density exceeds p(o*) / p(d), erf(r / sqrt 2) at radius r
    from effect_networks.inference import imitation_check
    from scipy.special import erf

    net, params = fitted
    rows = door_rows(6, seed=14)
    initial = ("initial.door", "initial.drawer", "initial.switch", "initial.handle_angle")
    given = {s: rows[s] for s in (*initial, "action")}
    check = imitation_check(net, params, given | {s: rows[s] for s in observed})
    discrete = [s for s in observed if net.site(s).discrete]
    for i in range(6):
        row = {s: (rows[s][i : i + 1] if s == "initial.handle_angle" else index_of(s, rows[s][i]))
               for s in given}  # fmt: skip

        def p_discrete(assignment, row=row):
            values = row | {s: np.array([k]) for s, k in zip(discrete, assignment, strict=True)}
            return math.exp(sum(log_factor(net, params, s, values)[0] for s in discrete))

        level = p_discrete([int(index_of(s, rows[s][i])[0]) for s in discrete])
        sd = None
        if "end.handle_angle" in observed:
            density = math.exp(log_factor(net, params, "end.handle_angle", row | {
                "end.handle_angle": rows["end.handle_angle"][i : i + 1]})[0])  # fmt: skip
            a = int(row["action"][0])
            sd = float(params["end.handle_angle"].scale_tril[a, 0, 0])
            level *= density
        surprise = 0.0
        for assignment in itertools.product(*(range(net.site(s).size) for s in discrete)):
            p = p_discrete(assignment)
            if sd is None:
                surprise += p if p > level else 0.0
                continue
            peak = level / p * sd * math.sqrt(2 * math.pi)  # the level against the peak
            surprise += p * float(erf(math.sqrt(-math.log(peak)))) if peak < 1 else 0.0
        assert float(check.surprise[i]) == pytest.approx(surprise, abs=1e-12)


def test_an_unknown_torque_integrated_out_equals_numerical_integration():
    # "turn" takes a torque (4 cells on [0, 2]) that moves the handle; the torque is
    # unknown: the collapsed model's ELBO and infer_action against the joint summed over
    # actions and clusters, the torque integrated on a fine grid
    from effect_networks.inference import fit, infer_action
    from effect_networks.models import Parameter, effect_model
    from pyro.infer import TraceEnum_ELBO
    from scipy.stats import norm

    net = EffectNetwork(
        features=(Discrete("door", DOOR_STATES["door"]), Continuous("handle_angle", 1)),
        actions=DOOR_ACTIONS,
        parameters=(Parameter("torque", 0.0, 2.0, 4, actions=("turn",), affects="handle_angle"),),
        parents={
            "end.door": ("initial.door", "action", "initial.handle_angle"),
            "end.handle_angle": ("initial.handle_angle", "action"),
        },
    )
    rows = door_rows(2000, seed=3)
    torque = np.where(
        rows["action"] == "turn", np.random.default_rng(0).uniform(0, 2, 2000), np.nan
    )
    rows["end.handle_angle"] = rows["end.handle_angle"] + 0.3 * np.nan_to_num(torque)[:, None]
    kept = ("initial.door", "initial.handle_angle", "action", "end.door", "end.handle_angle")
    params = fit(net, {s: rows[s] for s in kept} | {"param.torque": torque[:, None]}).params
    x, y = 0.4, 0.9
    evidence = {"initial.door": ["locked"], "initial.handle_angle": [[x]], "end.door": ["open"]}
    evidence |= {"end.handle_angle": [[y]]}
    enc = net.encode(evidence)
    loss = TraceEnum_ELBO(max_plate_nesting=1).loss(
        lambda: effect_model(net, params, enc, collapse=True), lambda: None
    )
    posterior = infer_action(net, params, evidence)

    p = {s.name: params[s.name] for s in net.sites}
    start = math.log(p["initial.door"].probs[0]) + norm.logpdf(
        x,
        float(p["initial.handle_angle"].bias[0]),
        float(p["initial.handle_angle"].scale_tril[0, 0]),
    )
    t = np.linspace(-20.0, 22.0, 400_001)
    joint = np.zeros(4)
    for a, name in enumerate(DOOR_ACTIONS):
        logits = p["end.door"].weight[0, a, :, 0].numpy() * x + p["end.door"].bias[0, a].numpy()
        opened = np.exp(logits - logits.max())[2] / np.exp(logits - logits.max()).sum()
        moved = 0.0
        for c in range(4):
            share = float(p["cluster.torque"].probs[a, c])
            if share == 0.0:  # an action that does not use the torque: cluster 0 only
                continue
            (w_x, w_t), b = (
                p["end.handle_angle"].weight[a, c, 0].tolist(),
                float(p["end.handle_angle"].bias[a, c, 0]),
            )
            sd = float(p["end.handle_angle"].scale_tril[a, c, 0, 0])
            if name != "turn":
                moved += share * norm.pdf(y, w_x * x + b, sd)
                continue
            m, s = float(p["param.torque"].bias[c, 0]), float(p["param.torque"].scale_tril[c, 0, 0])
            density = norm.pdf(t, m, s) * norm.pdf(y, w_x * x + w_t * t + b, sd)
            moved += share * density.sum() * (t[1] - t[0])
        joint[a] = float(p["action"].probs[a]) * opened * moved
    expected = -(start + math.log(joint.sum()))
    assert loss == pytest.approx(expected, rel=1e-9)
    assert -float(posterior.log_evidence[0]) == pytest.approx(expected, rel=1e-9)
    np.testing.assert_allclose(
        posterior.probs[0].numpy(), joint / joint.sum(), rtol=1e-8, atol=1e-12
    )
