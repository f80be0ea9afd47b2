"""Networks of other shapes against independent oracles: user-chosen parents, a
parameter acting on a discrete and a continuous feature, two parameters on one feature
(one of them used by one action only), a parameter on two continuous features (one
observed in part); every answer per row whatever its batch, compiled against traced,
the adaptive layout with an action not using its parameter, and every magnitude.

The oracle is numpy: the joint written factor by factor from the fitted numbers, the
discrete sites enumerated with itertools.product, unknown parameters integrated
numerically on a grid."""

from __future__ import annotations

import functools
import itertools
import math

import numpy as np
import pytest
import torch
from effect_networks.inference import (
    fit,
    fit_em,
    imitation_check,
    infer_action,
    infer_parameter,
    parameter_for_effect,
    predict,
    simulate,
)
from effect_networks.inference.queries.action_tables import compile_discrete
from effect_networks.inference.queries.parameter import compile_parameter_query
from effect_networks.models import (
    Continuous,
    Discrete,
    EffectNetwork,
    Parameter,
    Partial,
    random_params,
)
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from effect_networks import inference

ACTIONS = ("push", "lift", "wait")


def shelf_network() -> EffectNetwork:
    """A force (push, lift) acting on whether the object stays on the shelf and on its
    position; a height (lift only) acting on the position too; the tilt's own parents."""
    return EffectNetwork(
        features=(Discrete("on", (False, True)), Continuous("pos", 1), Continuous("tilt", 1)),
        actions=ACTIONS,
        parameters=(
            Parameter("force", 0.0, 10.0, 3, ("push", "lift"), ("pos", "on")),
            Parameter("height", 0.0, 1.0, 2, ("lift",), "pos"),
        ),
        parents={
            "end.on": ("initial.on", "action"),
            "end.tilt": ("initial.tilt", "action", "end.on"),
        },
    )


@functools.cache
def shelf_world():
    net = shelf_network()
    rows = simulate(net, random_params(net, seed=0), 3000, seed=0)
    return net, fit(net, rows).params, rows


# ---------------------------------------------------------------- numpy oracle
def gaussian_log(params, site, at, x, y):
    """log N(y; W x + b, S) with the CPD's numbers at the parent configuration ``at``;
    ``x`` (..., q), ``y`` (..., d): broadcast over leading dims."""
    cpd = params[site]
    weight, bias = cpd.weight.numpy()[at], cpd.bias.numpy()[at]
    cov = cpd.covariance.numpy()[at]
    residual = y - (x @ weight.T if weight.shape[-1] else 0.0) - bias
    solved = np.linalg.solve(cov, residual[..., None])[..., 0]
    d = y.shape[-1]
    return -0.5 * (
        (residual * solved).sum(-1) + np.linalg.slogdet(cov)[1] + d * math.log(2 * math.pi)
    )


def table(params, site, at):
    return params[site].probs.numpy()[at]


def shelf_oracle(net, params, row, grid=801):
    """log p(evidence, action) per action and the posterior of cluster.force, for one
    row giving the initial state and end.on, end.pos (force and height unknown,
    integrated on a grid over the clusters' Gaussians, +-12 sd)."""
    on, pos, tilt = row["initial.on"], row["initial.pos"], row["initial.tilt"]
    end_on = row.get("end.on")
    end_pos = row.get("end.pos")
    base = (
        math.log(table(params, "initial.on", (int(on),)))
        + gaussian_log(params, "initial.pos", (), np.zeros(0), np.array([pos]))
        + gaussian_log(params, "initial.tilt", (), np.zeros(0), np.array([tilt]))
    )
    per_action, per_cluster = [], np.full((3, 3), -np.inf)
    for a, name in enumerate(ACTIONS):
        uses_f, uses_h = name in ("push", "lift"), name == "lift"
        terms = []
        for cf, ch in itertools.product(range(3) if uses_f else (0,), range(2) if uses_h else (0,)):
            log_w = math.log(table(params, "action", (a,)))
            log_w += math.log(table(params, "cluster.force", (a, cf)))
            log_w += math.log(table(params, "cluster.height", (a, ch)))
            if end_on is not None:
                log_w += math.log(table(params, "end.on", (int(on), a, cf, int(end_on))))
            if end_pos is None:
                terms.append((cf, log_w))
                continue

            def axis(site, c, used):
                if not used:
                    return np.zeros(1), np.zeros(1)
                mean = float(params[site].bias[c, 0])
                sd = float(params[site].covariance[c, 0, 0]) ** 0.5
                values = np.linspace(mean - 12 * sd, mean + 12 * sd, grid)
                log_p = gaussian_log(params, site, (c,), np.zeros((grid, 0)), values[:, None])
                return values, log_p + math.log(values[1] - values[0])

            f, lf = axis("param.force", cf, uses_f)
            h, lh = axis("param.height", ch, uses_h)
            ff, hh = np.meshgrid(f, h, indexing="ij")
            x = np.stack([np.full(ff.shape, pos), np.full(ff.shape, tilt), ff, hh], -1)
            at = (int(on), a, cf, ch)
            lik = gaussian_log(params, "end.pos", at, x, np.array([end_pos])) + lf[:, None] + lh
            top = lik.max()
            # trapezoid weights at the ends are immaterial: +-12 sd carries no mass there
            terms.append((cf, log_w + top + math.log(np.exp(lik - top).sum())))
        logs = np.array([t for _, t in terms])
        per_action.append(base + np.logaddexp.reduce(logs))
        for cf, t in terms:
            per_cluster[a, cf] = np.logaddexp(per_cluster[a, cf], t)
    return np.array(per_action), per_cluster


def ordinary_rows(rows, n, with_on=True):
    out = []
    for i in range(n):
        row = {
            "initial.on": bool(rows["initial.on"][i]),
            "initial.pos": float(rows["initial.pos"][i, 0]),
            "initial.tilt": float(rows["initial.tilt"][i, 0]),
            "end.pos": float(rows["end.pos"][i, 0]),
        }
        if with_on:
            row["end.on"] = bool(rows["end.on"][i])
        out.append(row)
    return out


def evidence(rows):
    ev = {
        "initial.on": [r["initial.on"] for r in rows],
        "initial.pos": [[r["initial.pos"]] for r in rows],
        "initial.tilt": [[r["initial.tilt"]] for r in rows],
        "end.pos": [[r["end.pos"]] for r in rows],
    }
    if "end.on" in rows[0]:
        ev["end.on"] = [r["end.on"] for r in rows]
    return ev


# ---------------------------------------------------------------- tests
def test_infer_action_with_two_parameters_and_a_discrete_effect_against_integration():
    net, params, rows = shelf_world()
    sample = ordinary_rows(rows, 6) + ordinary_rows(rows, 3, with_on=False)
    for group in (sample[:6], sample[6:]):
        got = infer_action(net, params, evidence(group)).probs.numpy()
        for row, probs in zip(group, got, strict=True):
            logs, _ = shelf_oracle(net, params, row)
            want = np.exp(logs - np.logaddexp.reduce(logs))
            np.testing.assert_allclose(probs, want, atol=1e-9)
            assert abs(probs.sum() - 1.0) < 1e-12


def test_infer_parameter_ignores_a_parameter_the_action_does_not_use():
    """The height acts on the position with the force but only under "lift": a "push"
    row leaves it NaN (or out), as training rows must; the force's posterior is the
    numerically integrated one (it used to ask for param.height in every row)."""
    net, params, rows = shelf_world()
    sample = ordinary_rows(rows, 4)
    ev = evidence(sample) | {"action": ["push"] * 4}
    left_out = infer_parameter(net, params, "force", ev, mixture=True)
    nan = infer_parameter(net, params, "force", ev | {"param.height": [[np.nan]] * 4})
    torch.testing.assert_close(left_out.mean, nan.mean, rtol=0, atol=0)
    for i, row in enumerate(sample):
        _, per_cluster = shelf_oracle(net, params, row)
        logs = per_cluster[0]
        want = np.exp(logs - np.logaddexp.reduce(logs))
        np.testing.assert_allclose(left_out.cluster_probs[i].numpy(), want, atol=1e-9)
        # the posterior mean of the force, integrated on a grid
        mean, weight = 0.0, 0.0
        for c in range(3):
            m = float(params["param.force"].bias[c, 0])
            sd = float(params["param.force"].covariance[c, 0, 0]) ** 0.5
            f = np.linspace(m - 12 * sd, m + 12 * sd, 4001)
            log_p = (
                math.log(table(params, "cluster.force", (0, c)))
                + math.log(
                    table(params, "end.on", (int(row["initial.on"]), 0, c, int(row["end.on"])))
                )
                + gaussian_log(params, "param.force", (c,), np.zeros((f.size, 0)), f[:, None])
                + gaussian_log(
                    params,
                    "end.pos",
                    (int(row["initial.on"]), 0, c, 0),
                    np.stack(
                        [
                            np.full(f.size, row["initial.pos"]),
                            np.full(f.size, row["initial.tilt"]),
                            f,
                            np.zeros(f.size),
                        ],
                        -1,
                    ),
                    np.array([row["end.pos"]]),
                )
            )
            w = np.exp(log_p) * (f[1] - f[0])
            mean += (w * f).sum()
            weight += w.sum()
        assert abs(float(left_out.mixture.mean[i, 0]) - mean / weight) < 1e-8
    with pytest.raises(ValueError, match="param.height"):
        infer_parameter(net, params, "force", evidence(sample) | {"action": ["lift"] * 4})


def batch_evidence(rows, n):
    return {
        k: (np.asarray(rows[k])[:n])
        for k in ("initial.on", "initial.pos", "initial.tilt", "end.on", "end.pos")
    }


def take(ev, index):
    return {k: v[index] for k, v in ev.items()}


def fields_of(result, name="") -> dict:
    """Every tensor a query result holds (nested results and dicts of them), by a name."""
    if isinstance(result, torch.Tensor):
        return {name: result}
    if isinstance(result, dict):
        items = result.items()
    elif hasattr(result, "__dict__"):
        items = vars(result).items()
    else:
        return {}
    out = {}
    for key, value in items:
        out |= fields_of(value, f"{name}.{key}")
    return out


@pytest.mark.filterwarnings(
    "ignore::effect_networks.inference.queries.implausibility.OutsideTrainingData"
)
def test_every_row_answers_alike_in_batches_of_0_1_and_10000():
    net, params, _ = shelf_world()
    rows = simulate(net, params, 10_000, seed=5)
    ev = batch_evidence(rows, 10_000)
    push = {"action": np.array(["push"] * 10_000)}
    queries = {
        "infer_action": lambda e: infer_action(net, params, e),
        "predict": lambda e: predict(
            net, params, {k: e[k] for k in ("initial.on", "initial.pos", "initial.tilt", "action")}
        ),
        "imitation_check": lambda e: imitation_check(net, params, e),
        "infer_parameter": lambda e: infer_parameter(
            net, params, "force", {k: v for k, v in e.items()}, mixture=True
        ),
    }
    for name, query in queries.items():
        full_ev = ev | push if name != "infer_action" else ev
        whole = fields_of(query(full_ev))
        empty = fields_of(query(take(full_ev, slice(0, 0))))
        for index in (0, 4_321, 9_999):
            one = fields_of(query(take(full_ev, slice(index, index + 1))))
            assert one and one.keys() == whole.keys(), name
            for key, value in one.items():
                torch.testing.assert_close(
                    value,
                    whole[key][index : index + 1],
                    rtol=1e-12,
                    atol=1e-12,
                    msg=f"{name}.{key}",
                )
                assert empty[key].shape == (0, *value.shape[1:]), f"{name}.{key}"


# ---------------------------------------------------------------- a parameter on two features
def slide_network() -> EffectNetwork:
    """A speed (hit, nudge) acting on a 2-D position and a spin; the spin's own parents."""
    return EffectNetwork(
        features=(Discrete("lit", (False, True)), Continuous("xy", 2), Continuous("spin", 1)),
        actions=("hit", "nudge", "wait"),
        parameters=(Parameter("speed", 0.0, 4.0, 4, ("hit", "nudge"), ("xy", "spin")),),
        parents={"end.spin": ("initial.spin", "action", "initial.lit")},
    )


@functools.cache
def slide_world():
    net = slide_network()
    return net, fit(net, simulate(net, random_params(net, seed=1), 4000, seed=1)).params


def slide_oracle(params, row, action, observed):
    """Cluster posterior and per-cluster posterior mean and variance of the speed, by
    Gaussian conditioning by hand: the observed entries of (end.xy, end.spin) are jointly
    Gaussian given the cluster, linear in the speed."""
    lit = int(row["initial.lit"])
    x = np.concatenate([row["initial.xy"], row["initial.spin"]])
    y = np.concatenate([row["end.xy"], row["end.spin"]])
    logs, means, variances = [], [], []
    for c in range(4):
        m = float(params["param.speed"].bias[c, 0])
        s = float(params["param.speed"].covariance[c, 0, 0])
        w_xy = params["end.xy"].weight[lit, action, c].numpy()  # (2, 3 + 1)
        w_sp = params["end.spin"].weight[lit, action, c].numpy()  # (1, 1 + 1)
        slope = np.concatenate([w_xy[:, -1], w_sp[:, -1]])
        offset = np.concatenate(
            [
                w_xy[:, :3] @ x + params["end.xy"].bias[lit, action, c].numpy(),
                w_sp[:, :1] @ x[2:] + params["end.spin"].bias[lit, action, c].numpy(),
            ]
        )
        noise = np.zeros((3, 3))
        noise[:2, :2] = params["end.xy"].covariance[lit, action, c].numpy()
        noise[2:, 2:] = params["end.spin"].covariance[lit, action, c].numpy()
        o = np.asarray(observed)
        a, r = slope[o], (y - offset - slope * m)[o]
        cov = s * np.outer(a, a) + noise[np.ix_(o, o)]
        logs.append(
            math.log(float(params["cluster.speed"].probs[action, c]))
            - 0.5
            * (
                r @ np.linalg.solve(cov, r)
                + np.linalg.slogdet(cov)[1]
                + o.sum() * math.log(2 * math.pi)
            )
        )
        gain = s * np.linalg.solve(cov, a)
        means.append(m + gain @ r)
        variances.append(s - s * gain @ a)
    logs = np.array(logs)
    return np.exp(logs - np.logaddexp.reduce(logs)), np.array(means), np.array(variances)


@pytest.mark.filterwarnings(
    "ignore::effect_networks.inference.queries.implausibility.OutsideTrainingData"
)
def test_a_parameter_on_two_features_one_in_part_traced_compiled_and_by_hand():
    net, params = slide_world()
    rows = simulate(net, params, 12, seed=3)
    n = 12
    mask = np.ones((n, 3), bool)
    mask[:, 1] = np.arange(n) % 3 == 0  # y seen in every third row
    mask[1::4, 0] = False  # x unseen in some rows (then y or the spin decide)
    mask[2::4, :2] = False  # the position unseen
    xy = np.asarray(rows["end.xy"])
    ev = {k: rows[k] for k in ("initial.lit", "initial.xy", "initial.spin", "end.spin")} | {
        "action": ["hit", "nudge"] * 6,
        "end.xy": Partial(np.where(mask[:, :2], xy, np.nan), observed=mask[:, :2]),
    }
    traced = infer_parameter(net, params, "speed", ev, mixture=True)
    compiled = (
        inference.compile(net, params).parameter_query("speed").infer_parameter(ev, mixture=True)
    )
    for key, value in fields_of(traced).items():
        if key.endswith("implausible"):
            continue
        other = fields_of(compiled)[key]
        torch.testing.assert_close(other, value, rtol=0, atol=1e-12, msg=key)
    for i in range(n):
        row = {
            k: np.asarray(rows[k][i], float).reshape(-1)
            for k in ("initial.xy", "initial.spin", "end.xy", "end.spin")
        }
        row["initial.lit"] = bool(rows["initial.lit"][i])
        probs, means, variances = slide_oracle(params, row, i % 2, mask[i])
        np.testing.assert_allclose(traced.cluster_probs[i].numpy(), probs, atol=1e-10)
        np.testing.assert_allclose(traced.mixture.means[i, :, 0].numpy(), means, atol=1e-10)
        np.testing.assert_allclose(traced.mixture.covs[i, :, 0, 0].numpy(), variances, atol=1e-10)
        best = int(np.argmax(probs))
        assert int(traced.best_cluster[i]) == best
        assert abs(float(traced.mean[i, 0]) - means[best]) < 1e-10


def test_compiled_forms_refuse_what_they_do_not_serve_clearly():
    net, params, _ = shelf_world()
    with pytest.raises(ValueError, match="infer_parameter"):
        compile_parameter_query(net, params, "force")
    with pytest.raises(ValueError):
        compile_discrete(net, params)


# ---------------------------------------------------------------- the adaptive layout
@functools.cache
def adaptive_push_world():
    net = EffectNetwork(
        (Continuous("pos", 1),),
        ("push", "wait"),
        (Parameter("force", 0.0, 10.0, 4, ("push",), "pos", layout="adaptive"),),
    )
    rng = np.random.default_rng(0)
    n = 1500
    action = rng.choice(["push", "wait"], n)
    pos = rng.uniform(-1, 1, (n, 1))
    force = np.where(action[:, None] == "push", rng.uniform(0, 10, (n, 1)), np.nan)
    noise = np.where(action[:, None] == "push", 0.02, 0.005)
    end = pos + 0.05 * np.nan_to_num(force) + rng.normal(0.0, noise, (n, 1))
    rows = {"initial.pos": pos, "action": action, "param.force": force, "end.pos": end}
    return net, fit_em(net, rows).params


def test_adaptive_layout_an_action_not_using_the_parameter_sits_on_cluster_0():
    """ "wait" does not use the force: its cluster table is [1, 0, 0, 0] and every query
    scores it with its one configuration's Gaussian (the others are the pooled, wide fit
    of configurations no row reached); "push" is the mixture over the fitted clusters,
    the force integrated out by hand."""
    net, params = adaptive_push_world()
    np.testing.assert_array_equal(params["cluster.force"].probs[1].numpy(), [1.0, 0.0, 0.0, 0.0])
    start, end = np.array([0.0, 0.1, -0.4, 0.5]), np.array([0.2, -0.3, -0.4, 0.9])
    gauss = params["end.pos"]

    def log_normal(y, mean, var):
        return -0.5 * ((y - mean) ** 2 / var + np.log(2 * np.pi * var))

    wait = log_normal(
        end,
        float(gauss.weight[1, 0, 0, 0]) * start + float(gauss.bias[1, 0, 0]),
        float(gauss.covariance[1, 0, 0, 0]),
    )
    push_terms = []
    for c in range(4):
        slope, w_f = (float(v) for v in gauss.weight[0, c, 0])
        m, s = (
            float(params["param.force"].bias[c, 0]),
            float(params["param.force"].covariance[c, 0, 0]),
        )
        mean = slope * start + w_f * m + float(gauss.bias[0, c, 0])
        var = w_f**2 * s + float(gauss.covariance[0, c, 0, 0])
        push_terms.append(
            math.log(float(params["cluster.force"].probs[0, c])) + log_normal(end, mean, var)
        )
    push = np.logaddexp.reduce(np.stack(push_terms), 0)
    ev = {"initial.pos": start[:, None], "end.pos": end[:, None]}
    for name, want in (("wait", wait), ("push", push)):
        got = imitation_check(net, params, ev | {"action": [name] * 4}).log_likelihood.numpy()
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-9)
    prior = params["action"].probs.numpy()
    joint = np.stack([push, wait], 1) + np.log(prior)
    want = np.exp(joint - np.logaddexp.reduce(joint, 1, keepdims=True))
    posterior = infer_action(net, params, ev)
    np.testing.assert_allclose(posterior.probs.numpy(), want, atol=1e-12)
    assert not posterior.unseen.any()
    spread = predict(net, params, {"initial.pos": start[:, None], "action": ["wait"] * 4})
    np.testing.assert_allclose(
        spread.continuous["pos"].cov[:, 0, 0].numpy(),
        float(gauss.covariance[1, 0, 0, 0]),
        rtol=1e-12,
    )


# ---------------------------------------------------------------- every magnitude
def assert_distribution(probs, what):
    probs = probs.numpy()
    assert not np.isnan(probs).any(), what
    np.testing.assert_allclose(probs.sum(-1), 1.0, rtol=0, atol=1e-12, err_msg=what)
    assert (probs >= 0).all(), what


magnitudes = st.floats(-150.0, 150.0).map(lambda e: 10.0**e)


@pytest.mark.filterwarnings(
    "ignore::effect_networks.inference.queries.implausibility.OutsideTrainingData"
)
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.lists(st.tuples(st.sampled_from([-1.0, 1.0]), magnitudes), min_size=5, max_size=5),
    st.booleans(),
    st.booleans(),
)
def test_shelf_and_slide_at_every_magnitude(values, on, end_on):
    net, params, _ = shelf_world()
    v = [s * m for s, m in values]
    ev = {
        "initial.on": [on],
        "initial.pos": [[v[0]]],
        "initial.tilt": [[v[1]]],
        "end.on": [end_on],
        "end.pos": [[v[2]]],
    }
    queries = {
        "infer_action": lambda: infer_action(net, params, ev).probs,
        "infer_action with the force": lambda: (
            infer_action(net, params, ev | {"param.force": [[v[3]]]}).probs
        ),
        "predict": lambda: predict(
            net,
            params,
            {k: ev[k] for k in ev if k != "end.on"} | {"action": ["lift"], "param.force": [[v[3]]]},
        ).discrete["on"],
        "infer_parameter": lambda: (
            infer_parameter(net, params, "force", ev | {"action": ["push"]}).cluster_probs
        ),
    }
    slide, slide_params = slide_world()
    slide_ev = {
        "initial.lit": [on],
        "initial.xy": [[v[0], v[1]]],
        "initial.spin": [[v[2]]],
        "end.xy": Partial([[v[3], np.nan]], observed=[True, False]),
        "end.spin": [[v[4]]],
    }
    compiled = inference.compile(slide, slide_params).parameter_query("speed")
    queries["slide infer_action"] = lambda: infer_action(slide, slide_params, slide_ev).probs
    queries["slide compiled"] = lambda: (
        compiled.infer_parameter(slide_ev | {"action": ["hit"]}).cluster_probs
    )
    queries["slide traced"] = lambda: (
        infer_parameter(slide, slide_params, "speed", slide_ev | {"action": ["hit"]}).cluster_probs
    )
    for what, query in queries.items():
        try:
            probs = query()
        except ValueError as error:  # evidence of probability 0 in float64: refused by row
            assert "row" in str(error), (what, str(error))
            continue
        assert_distribution(probs, what)


@pytest.mark.parametrize("site", ["initial.pos", "initial.tilt", "end.pos", "param.force"])
def test_beyond_the_limit_is_refused_by_name(site):
    net, params, _ = shelf_world()
    ev = {
        "initial.on": [True],
        "initial.pos": [[0.0]],
        "initial.tilt": [[0.0]],
        "end.pos": [[0.1]],
        "param.force": [[2.0]],
    }
    with pytest.raises(ValueError, match=site):
        infer_action(net, params, ev | {site: [[-1.1e150]]})


def test_parameter_for_effect_with_a_second_parameter_the_action_does_not_use():
    """Per cluster the force that makes the observed position most likely, scored by
    log p(force, evidence) under the cell it falls in; the lift's height, unused by
    "push", left out (it used to be required)."""
    net, params, rows = shelf_world()
    sample = ordinary_rows(rows, 4)
    got = parameter_for_effect(net, params, "force", evidence(sample) | {"action": ["push"] * 4})
    for i, row in enumerate(sample):
        on = int(row["initial.on"])
        base = (
            math.log(table(params, "initial.on", (on,)))
            + gaussian_log(params, "initial.pos", (), np.zeros(0), np.array([row["initial.pos"]]))
            + gaussian_log(params, "initial.tilt", (), np.zeros(0), np.array([row["initial.tilt"]]))
            + math.log(table(params, "action", (0,)))
        )
        candidates = []
        for c in range(3):
            w = params["end.pos"].weight[on, 0, c, 0].numpy().reshape(-1)
            b = float(params["end.pos"].bias[on, 0, c, 0])
            force = (
                row["end.pos"] - w[0] * row["initial.pos"] - w[1] * row["initial.tilt"] - b
            ) / w[2]
            k = int(np.clip(np.floor(force / 10 * 3), 0, 2))  # the cell it falls in
            x = np.array([[row["initial.pos"], row["initial.tilt"], force, 0.0]])
            score = (
                math.log(table(params, "cluster.force", (0, k)))
                + math.log(table(params, "end.on", (on, 0, k, int(row["end.on"]))))
                + gaussian_log(params, "param.force", (k,), np.zeros((1, 0)), np.array([[force]]))[
                    0
                ]
                + gaussian_log(params, "end.pos", (on, 0, k, 0), x, np.array([row["end.pos"]]))[0]
            )
            candidates.append((score, force, c))
        score, force, c = max(candidates)
        assert int(got.cluster[i]) == c
        assert abs(float(got.value[i, 0]) - force) < 1e-9
        assert abs(float(got.log_density[i]) - (base + score)) < 1e-9


def test_imitation_log_likelihood_against_integration():
    net, params, rows = shelf_world()
    sample = ordinary_rows(rows, 4)
    for a, name in enumerate(ACTIONS):
        got = imitation_check(net, params, evidence(sample) | {"action": [name] * 4})
        for i, row in enumerate(sample):
            logs, _ = shelf_oracle(net, params, row)
            on = int(row["initial.on"])
            base = (
                math.log(table(params, "initial.on", (on,)))
                + gaussian_log(
                    params, "initial.pos", (), np.zeros(0), np.array([row["initial.pos"]])
                )
                + gaussian_log(
                    params, "initial.tilt", (), np.zeros(0), np.array([row["initial.tilt"]])
                )
                + math.log(table(params, "action", (a,)))
            )
            assert abs(float(got.log_likelihood[i]) - (logs[a] - base)) < 1e-9, (name, i)


# ---------------------------------------------------------------- a parameter on a discrete feature only
@functools.cache
def switch_world():
    """A force (push only) acting on a discrete feature alone; the light's own parents
    (an end parent)."""
    net = EffectNetwork(
        (Discrete("on", (False, True)), Discrete("lit", ("off", "dim", "bright"))),
        ("push", "wait"),
        (Parameter("force", 0.0, 10.0, 4, ("push",), "on"),),
        parents={"end.lit": ("initial.lit", "end.on")},
    )
    return net, fit(net, simulate(net, random_params(net, seed=4), 2000, seed=4)).params


def test_a_parameter_on_a_discrete_feature_only_against_the_tables():
    net, params = switch_world()
    assert net.cpd("end.on").parents == ("initial.on", "initial.lit", "action", "cluster.force")
    ev = {
        "initial.on": [True, True, False],
        "initial.lit": ["off", "dim", "bright"],
        "end.on": [False, True, False],
        "end.lit": ["dim", "dim", "off"],
    }
    keys = [(1, 0, 0, 1), (1, 1, 1, 1), (0, 2, 0, 0)]  # on, lit, end.on, end.lit indices
    cluster, end_on = params["cluster.force"].probs.numpy(), params["end.on"].probs.numpy()
    prior, light = params["action"].probs.numpy(), params["end.lit"].probs.numpy()
    mean = params["param.force"].bias.numpy()[:, 0]
    var = params["param.force"].covariance.numpy()[:, 0, 0]
    got = infer_parameter(net, params, "force", ev | {"action": ["push"] * 3}, mixture=True)
    given = infer_action(net, params, ev | {"param.force": [[1.0], [5.0], [np.nan]]})
    for i, (on, lit, e_on, e_lit) in enumerate(keys):
        w = cluster[0] * end_on[on, lit, 0, :, e_on]
        np.testing.assert_allclose(got.cluster_probs[i].numpy(), w / w.sum(), atol=1e-12)
        assert abs(float(got.mixture.mean[i, 0]) - (w / w.sum()) @ mean) < 1e-12
        force = [1.0, 5.0, None][i]
        if force is None:  # unknown: summed over the clusters
            push = prior[0] * w.sum()
        else:  # given: its cell is the cluster, and its density counts under "push" only
            c = int(force // 2.5)
            density = math.exp(-0.5 * (force - mean[c]) ** 2 / var[c]) / math.sqrt(
                2 * math.pi * var[c]
            )
            push = prior[0] * cluster[0, c] * density * end_on[on, lit, 0, c, e_on]
        wait = prior[1] * end_on[on, lit, 1, 0, e_on]  # "wait" sits on cluster 0
        # end.lit depends on end.on (given) alone: the same factor under both actions
        assert light[lit, e_on, e_lit] > 0
        np.testing.assert_allclose(given.probs[i].numpy(), [push, wait] / (push + wait), atol=1e-12)
    strong = predict(
        net,
        params,
        {"initial.on": [True], "initial.lit": ["off"], "action": ["push"], "param.force": [[9.0]]},
    )
    np.testing.assert_allclose(strong.discrete["on"][0].numpy(), end_on[1, 0, 0, 3], atol=1e-12)
    np.testing.assert_allclose(
        strong.discrete["lit"][0].numpy(), end_on[1, 0, 0, 3] @ light[0], atol=1e-12
    )


# ---------------------------------------------------------------- compiled: one row and many
@pytest.mark.filterwarnings(
    "ignore::effect_networks.inference.queries.implausibility.OutsideTrainingData"
)
def test_compiled_parameter_query_one_row_in_every_form_equals_its_row_in_10000():
    """A 2-D force whose feature's only parents are the action and the cluster (user
    parents): the single-row path in every documented form, the batched path and the
    traced query agree."""
    net = EffectNetwork(
        (Discrete("on", (False, True)), Continuous("pos", 2)),
        ("push", "throw", "wait"),
        (Parameter("force", (0.0, 0.0), (10.0, 5.0), (3, 2), ("push", "throw"), "pos"),),
        parents={"end.pos": ("action",), "end.on": ("initial.on", "action")},
    )
    params = fit(net, simulate(net, random_params(net, seed=6), 3000, seed=6)).params
    rows = simulate(net, params, 10_000, seed=7)
    y = np.asarray(rows["end.pos"])
    query = inference.compile(net, params).parameter_query("force")
    batch = query.infer_parameter({"end.pos": y, "action": ["throw"] * 10_000}, mixture=True)
    traced = infer_parameter(
        net,
        params,
        "force",
        {
            "end.pos": y[:50],
            "action": ["throw"] * 50,
            "initial.pos": y[:50] * 0,
            "initial.on": [True] * 50,
        },
        mixture=True,
    )
    for key, value in fields_of(traced).items():
        torch.testing.assert_close(fields_of(batch)[key][:50], value, rtol=0, atol=1e-12, msg=key)
    for i in (0, 17, 9_999):
        for form in (y[i], y[i : i + 1], list(y[i]), torch.tensor(y[i])):
            one = fields_of(
                query.infer_parameter({"end.pos": form, "action": "throw"}, mixture=True)
            )
            for key, value in fields_of(batch).items():
                torch.testing.assert_close(one[key], value[i : i + 1], rtol=0, atol=1e-12, msg=key)
    empty = fields_of(query.infer_parameter({"end.pos": y[:0], "action": []}, mixture=True))
    for key, value in fields_of(batch).items():
        assert empty[key].shape == (0, *value.shape[1:]), key


@pytest.mark.filterwarnings(
    "ignore::effect_networks.inference.queries.implausibility.OutsideTrainingData"
)
def test_adaptive_compiled_equals_traced_from_ordinary_values_to_the_limit():
    net, params = adaptive_push_world()
    values = np.concatenate([np.linspace(-1.0, 2.0, 301), [1e3, -1e3, 1e10, 1e50, 1e150, -1e150]])
    ev = {
        "initial.pos": np.full((values.size, 1), 0.1),
        "end.pos": values[:, None],
        "action": ["push"] * values.size,
    }
    traced = fields_of(infer_parameter(net, params, "force", ev, mixture=True))
    compiled = fields_of(
        inference.compile(net, params).parameter_query("force").infer_parameter(ev, mixture=True)
    )
    assert traced.keys() == compiled.keys()
    for key, value in traced.items():
        torch.testing.assert_close(compiled[key], value, rtol=0, atol=1e-12, msg=key)
    assert_distribution(compiled[".cluster_probs"], "compiled")


# ---------------------------------------------------------------- fitting with user parents
def test_fit_is_per_configuration_least_squares_with_two_parameters():
    """Each configuration of end.pos (on, action, force cluster, height cluster) is the
    least-squares fit on its rows' inputs, the parameters an action does not use dropped
    (numpy's lstsq). A fixed ridge used to move well-posed configurations by up to 3e-6."""
    net = shelf_network()
    rows = simulate(net, random_params(net, seed=0), 3000, seed=0)
    params = fit(net, rows, pseudo_count=0).params["end.pos"]
    on = np.asarray(rows["initial.on"]).astype(int)
    action = np.array([ACTIONS.index(a) for a in np.asarray(rows["action"])])
    force, height = np.asarray(rows["cluster.force"]), np.asarray(rows["cluster.height"])
    inputs = np.concatenate(
        [
            rows["initial.pos"],
            rows["initial.tilt"],
            np.nan_to_num(np.asarray(rows["param.force"])),
            np.nan_to_num(np.asarray(rows["param.height"])),
        ],
        1,
    )
    y = np.asarray(rows["end.pos"])[:, 0]
    checked = 0
    for o, a, c, h in itertools.product(range(2), range(3), range(3), range(2)):
        rows_here = (on == o) & (action == a) & (force == c) & (height == h)
        if rows_here.sum() < 10:
            continue
        used = [0, 1] + ([2] if a in (0, 1) else []) + ([3] if a == 1 else [])
        design = np.concatenate([inputs[rows_here][:, used], np.ones((rows_here.sum(), 1))], 1)
        coef, *_ = np.linalg.lstsq(design, y[rows_here], rcond=None)
        weight = np.zeros(4)
        weight[used] = coef[:-1]
        residual = y[rows_here] - design @ coef
        np.testing.assert_allclose(
            params.weight[o, a, c, h, 0].numpy(), weight, rtol=1e-9, atol=1e-10
        )
        assert abs(float(params.bias[o, a, c, h, 0]) - coef[-1]) < 1e-9
        variance = residual @ residual / rows_here.sum()
        assert abs(float(params.covariance[o, a, c, h, 0, 0]) / variance - 1) < 1e-9
        checked += 1
    assert checked >= 10


def test_predict_integrates_the_unknown_height_by_hand():
    """Lift with the force given (cell 1) and the height unknown: the position is the
    mixture over the height's clusters of the linear-Gaussian marginal; the tilt (its
    parents: the initial tilt, the action and the given end.on) one Gaussian."""
    net, params, _ = shelf_world()
    ev = {
        "initial.on": [True],
        "initial.pos": [[0.2]],
        "initial.tilt": [[-0.1]],
        "action": ["lift"],
        "param.force": [[4.0]],
        "end.on": [False],
    }
    got = predict(net, params, ev)
    pos, gauss = got.continuous["pos"], params["end.pos"]
    for h in range(2):
        w = gauss.weight[1, 1, 1, h, 0].numpy()
        m = float(params["param.height"].bias[h, 0])
        s = float(params["param.height"].covariance[h, 0, 0])
        mean = w @ [0.2, -0.1, 4.0, m] + float(gauss.bias[1, 1, 1, h, 0])
        var = w[3] ** 2 * s + float(gauss.covariance[1, 1, 1, h, 0, 0])
        assert abs(float(pos.weights[0, h]) - float(params["cluster.height"].probs[1, h])) < 1e-12
        assert abs(float(pos.means[0, h, 0]) - mean) < 1e-12
        assert abs(float(pos.covs[0, h, 0, 0]) - var) < 1e-12
    tilt = params["end.tilt"]
    want = float(tilt.weight[1, 0, 0, 0]) * -0.1 + float(tilt.bias[1, 0, 0])
    assert abs(float(got.continuous["tilt"].mean[0, 0]) - want) < 1e-12


@pytest.mark.filterwarnings(
    "ignore::effect_networks.inference.queries.implausibility.OutsideTrainingData"
)
def test_slide_with_per_row_masks_answers_alike_in_batches_and_forms():
    """10,000 rows with their own masks of the 2-D position: the compiled and traced
    parameter posteriors agree to 1e-12, and a row alone gets its row's answer from both and
    from infer_action."""
    net, params = slide_world()
    n = 10_000
    rows = simulate(net, params, n, seed=11)
    mask = np.random.default_rng(0).random((n, 2)) < 0.6
    xy = np.where(mask, np.asarray(rows["end.xy"]), np.nan)
    action = np.asarray(rows["action"])
    given = {
        k: np.asarray(rows[k]) for k in ("initial.lit", "initial.xy", "initial.spin", "end.spin")
    }
    ev = given | {"action": np.where(action == "wait", "hit", action)}
    query = inference.compile(net, params).parameter_query("speed")
    queries = {
        "compiled": lambda e, m: query.infer_parameter(
            e | {"end.xy": Partial(xy[m], observed=mask[m])}, mixture=True
        ),
        "traced": lambda e, m: infer_parameter(
            net, params, "speed", e | {"end.xy": Partial(xy[m], observed=mask[m])}, mixture=True
        ),
        "infer_action": lambda e, m: infer_action(
            net,
            params,
            {k: v for k, v in e.items() if k != "action"}
            | {"end.xy": Partial(xy[m], observed=mask[m])},
        ),
    }
    whole = {name: fields_of(q(ev, slice(None))) for name, q in queries.items()}
    for key, value in whole["traced"].items():
        torch.testing.assert_close(whole["compiled"][key], value, rtol=0, atol=1e-12, msg=key)
    for i in (0, 77, 9_999):
        part = slice(i, i + 1)
        for name, q in queries.items():
            for key, value in fields_of(q(take(ev, part), part)).items():
                torch.testing.assert_close(
                    value, whole[name][key][part], rtol=0, atol=1e-12, msg=f"{name}{key}"
                )
