"""Missing values marked in the training rows themselves: EM with closed-form Gaussian
conditioning, against an EM written out here in numpy (its own E-step by the Gaussian
block formulas, its own closed-form M-step, its own start), the complete-data fit and the
refusals where no closed form exists."""

import itertools
import math
from dataclasses import fields, replace

import numpy as np
import pytest
import torch
from effect_networks.inference import ConvergenceWarning, fit, simulate
from effect_networks.inference.fitting.missing import missing_log_likelihood
from effect_networks.models import Continuous, Discrete, EffectNetwork, Partial, random_params
from effect_networks.models.params import NetworkParams
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.networks import mixed_networks

SHAPES, ACTIONS = ("box", "ball"), ("push", "lift")

# shape: discrete initial and end; x: continuous initial and end; y: a 2-D end feature
#
#   initial.shape ---------> end.shape <--- action
#         |                                   |
#         +------> end.y <--------------------+
#                    ^
#   initial.x -------+-----> end.x
MIXED = EffectNetwork(
    (Discrete("shape", SHAPES), Continuous("x", 1), Continuous("y", 2, initial=False)),
    ACTIONS,
    parents={
        "end.shape": ("initial.shape", "action"),
        "end.x": ("initial.x",),
        "end.y": ("initial.shape", "initial.x", "action"),
    },
)


def even_params(net, seed):
    """Random parameters whose root tables (the initial discrete states, the action) are
    uniform, so that every configuration has rows."""
    params = random_params(net, seed)
    cpds = dict(params.cpds)
    for spec in net.sites:
        if spec.discrete and not net.cpd(spec.name).parents:
            probs = torch.full_like(cpds[spec.name].probs, 1.0 / spec.size)
            cpds[spec.name] = replace(cpds[spec.name], probs=probs)
    return NetworkParams(cpds, params.pseudo_count, net)


def mixed_rows(n, seed, share):
    """Rows of MIXED drawn from random parameters, each value (each dimension of a
    continuous one) missing with probability ``share``, completely at random: None for a
    label, NaN for a number. Also the complete rows."""
    rows = simulate(MIXED, even_params(MIXED, seed), n, seed=seed)
    rng = np.random.default_rng(seed)
    data = {}
    for site, values in rows.items():
        if MIXED.site(site).discrete:
            a = np.asarray(values, dtype=object)
            a[rng.random(a.shape) < share] = None
        else:
            a = np.array(np.asarray(values), dtype=float)
            a[rng.random(a.shape) < share] = np.nan
        data[site] = a
    return data, rows


# ------------------------------------------------------------ the EM written in numpy
def _gaussian(p, s, a):
    """Mean (4,) and covariance (4, 4) of [x0, x1, y1, y2] given the initial shape s and
    the action a, by the linear-Gaussian rules written out."""
    m0, v0, c, d, v1, w, b, r = (p[k] for k in ("m0", "v0", "c", "d", "v1", "w", "b", "r"))
    mean = np.concatenate([[m0, c * m0 + d], w[s, a] * m0 + b[s, a]])
    cov = np.zeros((4, 4))
    cov[0, 0] = v0
    cov[1, 1] = c * c * v0 + v1
    cov[0, 1] = cov[1, 0] = c * v0
    cov[2:, 0] = cov[0, 2:] = w[s, a] * v0
    cov[2:, 1] = cov[1, 2:] = w[s, a] * c * v0
    cov[2:, 2:] = np.outer(w[s, a], w[s, a]) * v0 + r[s, a]
    return mean, cov


def _e_step(p, s0, act, s1, v):
    """Per row and configuration (s0, a, s1): the log joint of the observed values, and
    per (s0, a) the conditional mean and covariance of v's missing entries."""
    n = len(v)
    log_joint = np.full((n, 2, 2, 2), -np.inf)
    mean = np.zeros((n, 2, 2, 4))
    second = np.zeros((n, 2, 2, 4, 4))  # E[v v^T]
    miss = np.isnan(v)
    patterns = {tuple(row) for row in miss}
    for s, a in itertools.product(range(2), range(2)):
        mu, cov = _gaussian(p, s, a)
        log_dens = np.zeros(n)
        for pattern in patterns:
            rows = np.all(miss == np.array(pattern), axis=1)
            m, o = np.array(pattern), ~np.array(pattern)
            r = v[rows][:, o] - mu[o]
            s_oo = cov[np.ix_(o, o)]
            if o.any():
                sol = np.linalg.solve(s_oo, r.T).T
                log_dens[rows] = -0.5 * (
                    (r * sol).sum(1) + np.linalg.slogdet(s_oo)[1] + o.sum() * math.log(2 * math.pi)
                )
            filled = v[rows].copy()
            c_full = np.zeros((4, 4))
            if m.any():
                gain = (
                    cov[np.ix_(m, o)] @ np.linalg.inv(s_oo) if o.any() else np.zeros((m.sum(), 0))
                )
                filled[:, m] = mu[m] + r @ gain.T
                c_full[np.ix_(m, m)] = cov[np.ix_(m, m)] - gain @ cov[np.ix_(o, m)]
            mean[rows, s, a] = filled
            second[rows, s, a] = filled[:, :, None] * filled[:, None, :] + c_full
        for t in range(2):
            with np.errstate(divide="ignore"):  # a probability 0: -inf
                lp = np.log(p["ps"][s] * p["pa"][a] * p["t"][s, a, t]) + log_dens
            agree = ((s0 < 0) | (s0 == s)) & ((act < 0) | (act == a)) & ((s1 < 0) | (s1 == t))
            log_joint[:, s, a, t] = np.where(agree, lp, -np.inf)
    return log_joint, mean, second


def _m_step(resp, mean, second):
    """The closed-form maximum from the expected sums (responsibilities ``resp`` (n, 2,
    2, 2) over (s0, a, s1))."""
    n = len(resp)
    w_sa = resp.sum(3)  # (n, 2, 2)
    p = {"ps": resp.sum((0, 2, 3)) / n, "pa": resp.sum((0, 1, 3)) / n}
    p["t"] = resp.sum(0) / resp.sum((0, 3))[:, :, None]
    ev = (w_sa[..., None] * mean).sum((1, 2))  # (n, 4): E[v] over the configurations
    evv = (w_sa[..., None, None] * second).sum((1, 2))
    p["m0"] = ev[:, 0].mean()
    p["v0"] = evv[:, 0, 0].mean() - p["m0"] ** 2
    # x1 on z = [x0, 1]
    zz = np.array([[evv[:, 0, 0].sum(), ev[:, 0].sum()], [ev[:, 0].sum(), n]])
    zx = np.array([evv[:, 0, 1].sum(), ev[:, 1].sum()])
    beta = np.linalg.solve(zz, zx)
    p["c"], p["d"] = beta
    p["v1"] = (evv[:, 1, 1].sum() - beta @ zx) / n
    p["w"], p["b"], p["r"] = np.zeros((2, 2, 2)), np.zeros((2, 2, 2)), np.zeros((2, 2, 2, 2))
    for s, a in itertools.product(range(2), range(2)):
        w = w_sa[:, s, a]
        m, sec = mean[:, s, a], second[:, s, a]
        zz = np.array(
            [[(w * sec[:, 0, 0]).sum(), (w * m[:, 0]).sum()], [(w * m[:, 0]).sum(), w.sum()]]
        )
        zy = np.stack([(w[:, None] * sec[:, 0, 2:]).sum(0), (w[:, None] * m[:, 2:]).sum(0)])
        yy = (w[:, None, None] * sec[:, 2:, 2:]).sum(0)
        beta = np.linalg.solve(zz, zy)  # (2, 2): rows x0 and 1
        p["w"][s, a], p["b"][s, a] = beta
        p["r"][s, a] = (yy - zy.T @ beta) / w.sum()
    return p


def numpy_em(data, iterations):
    """EM on MIXED's rows, from the closed form on the rows that miss nothing; the
    parameters and the log-likelihood after each step."""
    code = {None: -1} | {label: i for i, label in enumerate(SHAPES)}
    s0 = np.array([code[v] for v in data["initial.shape"]])
    s1 = np.array([code[v] for v in data["end.shape"]])
    act = np.array([{None: -1, "push": 0, "lift": 1}[v] for v in data["action"]])
    v = np.column_stack([data["initial.x"], data["end.x"], data["end.y"]])
    complete = (s0 >= 0) & (s1 >= 0) & (act >= 0) & ~np.isnan(v).any(1)
    resp = np.zeros((complete.sum(), 2, 2, 2))
    resp[np.arange(complete.sum()), s0[complete], act[complete], s1[complete]] = 1
    vc = v[complete]
    mean = np.broadcast_to(vc[:, None, None], (len(vc), 2, 2, 4))
    p = _m_step(resp, mean, mean[..., :, None] * mean[..., None, :])
    curve = []
    for _ in range(iterations):
        log_joint, mean, second = _e_step(p, s0, act, s1, v)
        flat = log_joint.reshape(len(v), -1)
        top = flat.max(1, keepdims=True)
        norm = top[:, 0] + np.log(np.exp(flat - top).sum(1))
        curve.append(norm.sum())
        p = _m_step(np.exp(log_joint - norm[:, None, None, None]), mean, second)
    return p, curve


def as_numpy(params):
    """The project's fitted MIXED parameters in the numpy EM's names."""

    def arr(t):
        return t.detach().numpy()

    y = params["end.y"]
    return {
        "ps": arr(params["initial.shape"].probs),
        "pa": arr(params["action"].probs),
        "t": arr(params["end.shape"].probs),
        "m0": arr(params["initial.x"].bias)[0],
        "v0": arr(params["initial.x"].covariance)[0, 0],
        "c": arr(params["end.x"].weight)[0, 0],
        "d": arr(params["end.x"].bias)[0],
        "v1": arr(params["end.x"].covariance)[0, 0],
        "w": arr(y.weight)[..., 0],
        "b": arr(y.bias),
        "r": arr(y.covariance),
    }


# ---------------------------------------------------------------------------- tests
def test_em_reaches_the_fixed_point_of_an_independent_numpy_em():
    data, _ = mixed_rows(400, seed=3, share=0.25)
    result = fit(MIXED, data, pseudo_count=0.0, min_variance=0.0, tol=1e-15, steps=3000)
    assert result.converged
    theirs, curve = numpy_em(data, 80)  # settled to 1e-12 by then
    mine = as_numpy(result.params)
    for key, value in theirs.items():
        np.testing.assert_allclose(mine[key], value, atol=1e-6, rtol=0, err_msg=key)
    # the log-likelihood EM reports is the numpy EM's (which at its fixed point is flat)
    assert result.log_likelihoods[-1] == pytest.approx(curve[-1], rel=1e-9)
    assert missing_log_likelihood(MIXED, result.params, data) == pytest.approx(
        result.log_likelihoods[-1], rel=1e-12
    )


def test_em_log_likelihood_is_the_numpy_one_and_never_falls_step_by_step():
    data, _ = mixed_rows(300, seed=5, share=0.3)
    settings = dict(pseudo_count=0.0, min_variance=0.0, tol=1e-300)
    with pytest.warns(ConvergenceWarning, match="end.y"):  # tol=1e-300: never settles
        result = fit(MIXED, data, steps=8, **settings)
    curve = np.array(result.log_likelihoods)
    assert len(curve) == 9
    assert np.all(np.diff(curve) >= -1e-9 * abs(curve[-1]))
    assert curve[-1] > curve[0] + 1.0  # and it moved
    # each step's parameters scored by the numpy E-step, not EM's own
    for k in (1, 4):
        with pytest.warns(ConvergenceWarning):
            params = fit(MIXED, data, steps=k, **settings).params
        p = as_numpy(params)
        code = {None: -1} | {label: i for i, label in enumerate(SHAPES)}
        s0 = np.array([code[v] for v in data["initial.shape"]])
        s1 = np.array([code[v] for v in data["end.shape"]])
        act = np.array([{None: -1, "push": 0, "lift": 1}[v] for v in data["action"]])
        v = np.column_stack([data["initial.x"], data["end.x"], data["end.y"]])
        flat = _e_step(p, s0, act, s1, v)[0].reshape(len(v), -1)
        top = flat.max(1, keepdims=True)
        total = (top[:, 0] + np.log(np.exp(flat - top).sum(1))).sum()
        assert curve[k] == pytest.approx(total, rel=1e-10)


#: a mixed network of five features: two discrete, three continuous (one 2-D); every
#: end feature depends on its own initial state and the action, the continuous ones on
#: the initial shape too (no discrete site reads a continuous one, so every missing
#: value has a closed form)
FIVE = EffectNetwork(
    (
        Discrete("shape", SHAPES),
        Discrete("open", (False, True)),
        Continuous("pos", 2),
        Continuous("angle", 1),
        Continuous("speed", 1, initial=False),
    ),
    ACTIONS,
    parents={
        "end.shape": ("initial.shape", "action"),
        "end.open": ("initial.open", "action"),
        "end.pos": ("initial.shape", "action", "initial.pos"),
        "end.angle": ("action", "initial.angle"),
        "end.speed": ("initial.shape", "action", "initial.pos", "initial.angle"),
    },
)


def test_thirty_percent_missing_stays_within_sampling_error_of_the_complete_fit():
    # 2,000 rows, each value (each dimension) missing with probability 0.3, completely
    # at random. The EM estimate and the complete-data estimate differ by an error of
    # the size of the estimators' standard errors (the complete one is efficient, so
    # their difference has about the variance the lost information adds: less than the
    # complete one's own variance times 1/0.7^2 - 1 ~ 1). The bound: 5 standard errors
    # of the complete-data estimate, per number -- a table entry sqrt(p (1-p) / N), a
    # mean at the rows' inputs sigma sqrt(q / N) (q inputs with the offset), a noise
    # variance sigma^2 sqrt(2 / N), N the configuration's rows.
    n = 2000
    rows = simulate(FIVE, even_params(FIVE, 7), n, seed=7)
    rng = np.random.default_rng(7)
    data = {}
    for site, values in rows.items():
        if FIVE.site(site).discrete:
            a = np.asarray(values, dtype=object)
            a[rng.random(a.shape) < 0.3] = None
        else:
            a = np.array(np.asarray(values), dtype=float)
            a[rng.random(a.shape) < 0.3] = np.nan
        data[site] = a
    complete = fit(FIVE, rows, pseudo_count=0.0).params
    result = fit(FIVE, data, pseudo_count=0.0, tol=1e-9, steps=2000)
    assert result.converged
    em = result.params
    enc = FIVE.encode(rows)
    for spec in FIVE.sites:
        cpd, a, b = FIVE.cpd(spec.name), complete[spec.name], em[spec.name]
        count = a.n.reshape(-1).clamp_min(1.0)
        if spec.discrete:
            p = a.probs.reshape(count.shape[0], -1)
            se = (p * (1 - p) / count[:, None]).sqrt()
            diff = (b.probs.reshape(p.shape) - p).abs()
            assert bool((diff <= 5 * se + 1e-12).all()), (spec.name, diff, se)
            continue
        # the means at the complete rows' own inputs, in noise units
        index = tuple(enc[q] for q in cpd.parents)
        x = torch.cat([enc[q] for q in cpd.inputs], -1) if cpd.inputs else None
        means = []
        for params in (a, b):
            loc = params.bias[index] if index else params.bias.expand(n, -1)
            if x is not None:
                weight = params.weight[index] if index else params.weight.expand(n, -1, -1)
                loc = loc + (weight @ x[:, :, None]).squeeze(-1)
            means.append(loc)
        sigma = a.covariance.diagonal(dim1=-2, dim2=-1).sqrt()
        sigma = sigma[index] if index else sigma.expand(n, -1)
        n_rows = a.n[index] if index else a.n.expand(n)
        q = cpd.width + 1
        bound = 5 * sigma * (q / n_rows)[:, None].sqrt()
        assert bool(((means[1] - means[0]).abs() <= bound).all()), spec.name
        var_a = a.covariance.diagonal(dim1=-2, dim2=-1)
        var_b = b.covariance.diagonal(dim1=-2, dim2=-1)
        spread = 5 * var_a * (2 / a.n.clamp_min(1.0))[..., None].sqrt()
        assert bool(((var_b - var_a).abs() <= spread).all()), spec.name


def test_values_marked_in_the_rows_are_those_masks_mark():
    # None in the rows and a False in masks are the same missing value; NaN in an end
    # feature and Partial's unobserved dimensions too
    data, rows = mixed_rows(200, seed=1, share=0.2)
    given = {
        site: np.array([v is not None for v in values])
        for site, values in data.items()
        if MIXED.site(site).discrete
    }
    by_masks = dict(data)
    for site in given:
        by_masks[site] = np.asarray(rows[site], dtype=object)
    y = data["end.y"]
    by_masks["end.y"] = Partial(np.nan_to_num(y), observed=~np.isnan(y))
    a = fit(MIXED, data, tol=1e-10, steps=500)
    b = fit(MIXED, by_masks, masks=given, tol=1e-10, steps=500)
    assert a.log_likelihoods == b.log_likelihoods
    for site in a.params.cpds:
        for f in fields(a.params[site]):
            assert torch.equal(getattr(a.params[site], f.name), getattr(b.params[site], f.name))


def test_complete_rows_keep_the_one_pass_closed_form():
    # nothing missing: no EM, and the numbers of the chunked closed form bit for bit
    _, rows = mixed_rows(200, seed=2, share=0.0)
    result = fit(MIXED, rows)
    assert result.log_likelihoods == () and result.losses == ()
    chunked = fit(MIXED, iter([rows])).params
    for site in result.params.cpds:
        for f in fields(result.params[site]):
            assert torch.equal(getattr(result.params[site], f.name), getattr(chunked[site], f.name))


def test_a_discrete_child_of_a_missing_continuous_value_is_refused_by_name():
    # end.shape is a softmax of initial.x here: no closed-form integral over x
    net = EffectNetwork(
        (Discrete("shape", SHAPES), Continuous("x", 1)),
        ACTIONS,
        parents={"end.shape": ("initial.x", "action"), "end.x": ("initial.x",)},
    )
    rows = simulate(net, random_params(net, 0), 50, seed=0)
    x = np.array(rows["initial.x"], dtype=float)
    x[3] = np.nan
    with pytest.raises(ValueError, match=r"'initial.x'.*row 3.*'end.shape' \(softmax\)"):
        fit(net, rows | {"initial.x": x})


def test_a_missing_value_of_a_parameter_its_action_uses_is_refused():
    # NaN in param.p means "the action does not use p"; where it does, NaN is refused
    from tests.networks import tap_data, tap_net

    net = tap_net(layout="grid")
    rows = dict(tap_data(net, n=40).items())
    rows = {s: v for s, v in rows.items() if not s.startswith("cluster.")}
    force = rows["param.force"].clone()
    used = int((~torch.isnan(force[:, 0])).nonzero()[0])
    force[used] = torch.nan
    with pytest.raises(ValueError, match=rf"'param.force': row {used} .*uses the parameter"):
        fit(net, net.encode_indices(rows | {"param.force": force}))


def test_the_guide_example_runs():
    # docs/missing.md's example, as written there
    from pathlib import Path

    page = (Path(__file__).parents[3] / "docs" / "missing.md").read_text()
    blocks = [b.split("```")[0] for b in page.split("```python\n")[1:]]
    assert len(blocks) == 3
    namespace: dict = {}
    exec(compile("\n".join(blocks), "docs/missing.md", "exec"), namespace)
    assert namespace["scored"].per_row.shape == (500,)  # the gaps scored row by row


def test_no_complete_row_is_needed():
    # every row misses exactly one of MIXED's values (a dimension of end.y counts as
    # one): EM starts from each CPD's own available rows and lands near the complete fit
    data, rows = mixed_rows(1500, seed=4, share=0.0)
    rng = np.random.default_rng(4)
    slots = [("initial.shape", None), ("action", None), ("end.shape", None)]
    slots += [("initial.x", 0), ("end.x", 0), ("end.y", 0), ("end.y", 1)]
    for i, k in enumerate(rng.integers(len(slots), size=1500)):
        site, dim = slots[k]
        if dim is None:
            data[site][i] = None
        else:
            data[site][i, dim] = np.nan
    result = fit(MIXED, data, pseudo_count=0.0, tol=1e-10, steps=2000)
    assert result.converged
    curve = np.array(result.log_likelihoods)
    assert np.all(np.diff(curve) >= -1e-9 * abs(curve[-1]))
    complete = fit(MIXED, rows, pseudo_count=0.0).params
    for site in ("initial.shape", "action", "end.shape"):
        torch.testing.assert_close(
            result.params[site].probs, complete[site].probs, atol=0.03, rtol=0
        )
    for site in ("initial.x", "end.x", "end.y"):
        torch.testing.assert_close(result.params[site].bias, complete[site].bias, atol=0.1, rtol=0)


def test_missing_continuous_values_beside_missing_actions_with_a_parameter():
    # the force acts on end.pos; the action is missing in 30 % of the rows (one of those
    # using exactly the parameters the row gives), end.pos in 25 %. The oracle: Pyro's
    # enumeration of the model, which reads a NaN end value as unobserved (the leaf's
    # factor integrates to one), and its gradient over every CPD, zero at EM's optimum
    from effect_networks.models.evidence import Evidence

    from tests.networks import marginal_loss, tap3_rows

    net, rows, masks = tap3_rows(n=300, seed=1)
    pos = rows["end.pos"].clone()
    pos[torch.rand(300, generator=torch.Generator().manual_seed(1)) < 0.25] = torch.nan
    rows = Evidence(net, dict(rows.items()) | {"end.pos": pos}, rows.n_rows)
    settings = dict(masks=masks, pseudo_count=0.0, min_variance=0.0, tol=1e-13, steps=2000)
    result = fit(net, rows, **settings)
    assert result.converged
    curve = np.array(result.log_likelihoods)
    assert np.all(np.diff(curve) >= -1e-9 * abs(curve[-1]))
    loss, gradient = marginal_loss(net, result.params, rows, masks, presence=True)
    assert loss == pytest.approx(result.losses[-1], rel=1e-10)
    assert gradient < 1e-5


@settings(max_examples=25, deadline=None)
@given(net=mixed_networks(), seed=st.integers(0, 1000), share=st.floats(0.05, 0.6))
def test_the_closed_form_e_step_scores_rows_as_pyro_enumerates_them(net, seed, share):
    # random mixed networks (softmax, parameters, 2-D features): rows missing discrete
    # labels and end dimensions scored by the joint-Gaussian E-step equal the model's
    # own enumeration, which reads a NaN end dimension as unobserved
    from effect_networks.inference.exact.enumeration import enumerate_model
    from effect_networks.models.evidence import Evidence

    params = random_params(net, seed)
    rows = net.encode(simulate(net, params, 25, seed=seed))
    rng = np.random.default_rng(seed)
    data, masks = dict(rows.items()), {}
    for spec in net.sites:
        if spec.role == "end" and not spec.discrete:
            x = data[spec.name].clone()
            x[torch.from_numpy(rng.random(tuple(x.shape)) < share)] = torch.nan
            data[spec.name] = x
        elif (
            spec.discrete
            and spec.role in ("initial", "end")
            or (spec.name == "action" and not net.mixtures)
        ):
            masks[spec.name] = torch.from_numpy(rng.random(25) >= share)
    gapped = Evidence(net, data, 25)
    mine = missing_log_likelihood(net, params, gapped, masks)
    theirs = float(enumerate_model(net, params, gapped, masks=masks).log_evidence.sum())
    assert mine == pytest.approx(theirs, rel=1e-9, abs=1e-9)


def test_missing_labels_read_alike_in_every_container():
    # NaN in a float tensor or array, None or pandas' NA in an object array: the same
    # missing value; None is a label where the feature declares it as a state
    net = EffectNetwork(
        (Discrete("v", (0, 1)), Discrete("w", (None, "x")), Continuous("p", 1)),
        ACTIONS,
        parents={"end.v": ("initial.v", "action"), "end.w": ("initial.w", "action")},
    )
    rows = simulate(net, random_params(net, 0), 200, seed=0)
    v = np.asarray(rows["initial.v"], dtype=float)
    v[[3, 8]] = np.nan
    as_none = np.asarray(rows["initial.v"], dtype=object)
    as_none[[3, 8]] = None
    forms = [v, torch.from_numpy(v), as_none]
    pd = pytest.importorskip("pandas")
    forms.append(np.asarray(pd.array(list(as_none), dtype="Int64"), dtype=object))
    fits = [fit(net, rows | {"initial.v": form}, tol=1e-10) for form in forms]
    for other in fits[1:]:
        assert other.log_likelihoods == fits[0].log_likelihoods
    assert len(fits[0].log_likelihoods) > 1  # EM ran
    # None is one of w's states: rows giving it miss nothing
    assert None in list(rows["initial.w"])
    assert fit(net, rows).log_likelihoods == ()
