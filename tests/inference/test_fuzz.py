"""Fuzzing the public API: every call gives the brute-force answer or a ValueError.

Random discrete networks with labels of several types, random evidence in random
containers, sometimes corrupted (an unknown label, a wrong row count, an unknown site,
indices where labels belong, an empty ``allowed``). A correct call is compared with a
brute-force sum over the joint written here from the tables; a corrupted one must raise
``ValueError``. Hypothesis also drives fits of random rows and continuous networks with
bad numbers. pytest-timeout bounds every test, so a hang fails instead of stalling.
"""

import itertools
import math

import numpy as np
import pytest
import torch
from effect_networks.inference import fit, imitation_check, infer_action, predict
from effect_networks.models import Continuous, Discrete, EffectNetwork, Parameter, random_params
from hypothesis import given, settings
from hypothesis import strategies as st

from effect_networks import inference
from tests.networks import mixed_networks

STATE_KINDS = {
    "int": lambda k: tuple(range(10, 10 + k)),
    "str": lambda k: tuple(f"s{i}" for i in range(k)),
    "bool": lambda k: (False, True),
    "float": lambda k: tuple(0.5 * i for i in range(k)),
}


@st.composite
def discrete_networks(draw):
    features = []
    for i in range(draw(st.integers(1, 2))):
        kind = draw(st.sampled_from(sorted(STATE_KINDS)))
        k = 2 if kind == "bool" else draw(st.integers(2, 3))
        features.append(Discrete(f"f{i}", STATE_KINDS[kind](k)))
    actions = tuple(f"a{j}" for j in range(draw(st.integers(1, 3))))
    return EffectNetwork(tuple(features), actions)


def container(draw, values: list):
    """The same labels in a list, a tuple, a numpy array or a torch tensor."""
    kind = draw.draw(st.sampled_from(["list", "tuple", "numpy", "torch"]))
    if kind == "list":
        return list(values)
    if kind == "tuple":
        return tuple(values)
    if kind == "numpy" or isinstance(values[0], str):
        return np.array(values)
    return torch.tensor(values)


def brute(net, params, fixed):
    """p(assignment | fixed) over full assignments (index tuples), from the tables."""
    feats = net.features
    weights = {}
    for init in itertools.product(*[range(f.cardinality) for f in feats]):
        for a in range(len(net.actions)):
            for end in itertools.product(*[range(f.cardinality) for f in feats]):
                full = {"action": a}
                full |= {f"initial.{f.name}": v for f, v in zip(feats, init, strict=True)}
                full |= {f"end.{f.name}": v for f, v in zip(feats, end, strict=True)}
                if any(full[s] != v for s, v in fixed.items()):
                    continue
                p = float(params["action"].probs[a])
                for f, v in zip(feats, init, strict=True):
                    p *= float(params[f"initial.{f.name}"].probs[v])
                for f, v in zip(feats, end, strict=True):
                    p *= float(params[f"end.{f.name}"].probs[(*init, a, v)])
                weights[tuple(sorted(full.items()))] = p
    total = sum(weights.values())
    return {k: w / total for k, w in weights.items()}, total


def marginal(post, site, size):
    out = [0.0] * size
    for key, p in post.items():
        out[dict(key)[site]] += p
    return torch.tensor(out, dtype=torch.float64)


@pytest.mark.timeout(600)
@settings(max_examples=60, deadline=None)
@given(net=discrete_networks(), seed=st.integers(0, 1000), data=st.data())
def test_discrete_queries_are_right_or_refused(net, seed, data):
    params = random_params(net, seed)
    query = data.draw(st.sampled_from(["predict", "infer_action", "compiled", "imitation"]))
    sites = [f"initial.{f.name}" for f in net.features]
    ends = [f"end.{f.name}" for f in net.features]
    given_ends = data.draw(st.lists(st.sampled_from(ends), unique=True, max_size=len(ends)))
    if query == "imitation" and not given_ends:
        given_ends = ends[:1]
    chosen = sites + given_ends + (["action"] if query in ("predict", "imitation") else [])
    fixed, evidence = {}, {}
    for site in chosen:
        labels = net.actions if site == "action" else net.feature(site.split(".")[1]).states
        i = data.draw(st.integers(0, len(labels) - 1))
        fixed[site] = i
        evidence[site] = container(data, [labels[i]])
    allowed = None
    if query in ("infer_action", "compiled") and data.draw(st.booleans()):
        allowed = data.draw(
            st.lists(st.sampled_from(net.actions), min_size=1, max_size=len(net.actions))
        )
    corruption = data.draw(
        st.sampled_from(["none"] * 4 + ["label", "rows", "site", "indices", "allowed"])
    )
    if corruption == "label":
        evidence[sites[0]] = ["no such state"]
    elif corruption == "rows":  # two rows beside one; a lone site's two rows are valid
        if len(chosen) < 2:
            corruption = "none"
        else:
            evidence[sites[0]] = list(evidence[sites[0]]) * 2
    elif corruption == "site":
        evidence["initial.nothing"] = [1]
    elif corruption == "indices":  # an index that is no label of an int/str/float feature
        feature = net.features[0]
        if isinstance(feature.states[0], bool) or 5 in feature.states:
            corruption = "none"
        else:
            evidence[sites[0]] = torch.tensor([5])
    elif corruption == "allowed":
        if query in ("infer_action", "compiled"):
            allowed = []
        else:
            corruption = "none"

    def call():
        if query == "predict":
            return predict(net, params, evidence)
        if query == "infer_action":
            return infer_action(net, params, evidence, allowed=allowed, avoid_unseen=False)
        if query == "compiled":
            compiled = inference.compile(net, params).action_tables
            return compiled.infer_action(evidence, allowed=allowed, avoid_unseen=False)
        return imitation_check(net, params, evidence)

    if corruption != "none":
        with pytest.raises(ValueError):
            call()
        return
    result = call()
    post, total = brute(net, params, fixed)
    if query == "predict":
        for f in net.features:
            if f"end.{f.name}" in fixed:
                continue
            want = marginal(post, f"end.{f.name}", f.cardinality)
            torch.testing.assert_close(result.discrete[f.name][0], want, atol=1e-9, rtol=0)
    elif query in ("infer_action", "compiled"):
        want = marginal(post, "action", len(net.actions))
        torch.testing.assert_close(result.probs[0], want, atol=1e-9, rtol=0)
        ok = [net.action_index(a) for a in allowed] if allowed else range(len(net.actions))
        top = max(float(want[i]) for i in ok)
        assert int(result.best[0]) in ok
        assert float(want[int(result.best[0])]) >= top - 1e-9
    else:
        prior, prior_total = brute(net, params, {k: v for k, v in fixed.items() if k not in ends})
        assert abs(float(result.log_likelihood[0]) - math.log(total / prior_total)) < 1e-9


@st.composite
def bad_numbers(draw):
    return draw(st.sampled_from([float("nan"), float("inf"), -float("inf"), 1e200]))


@pytest.mark.timeout(600)
@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 1000), bad=bad_numbers(), where=st.integers(0, 4), data=st.data())
def test_continuous_calls_are_right_or_refused(seed, bad, where, data):
    net = EffectNetwork(
        (Discrete("door", ("shut", "open")), Continuous("pos", 2)),
        ("wait", "push"),
        (Parameter("force", 0.0, 1.0, 2, ("push",), "pos"),),
    )
    params = random_params(net, seed)
    rng = np.random.default_rng(seed)
    n = 40
    action = rng.choice(net.actions, n)
    rows = {
        "initial.door": rng.choice(["shut", "open"], n),
        "initial.pos": rng.normal(size=(n, 2)),
        "action": action,
        "param.force": np.where(action[:, None] == "push", rng.uniform(size=(n, 1)), np.nan),
        "end.door": rng.choice(["shut", "open"], n),
        "end.pos": rng.normal(size=(n, 2)),
    }
    site = ["initial.pos", "end.pos", "param.force", "end.pos", "initial.pos"][where]
    corrupt = data.draw(st.booleans())
    if corrupt:
        row = int(np.flatnonzero(action == "push")[0])
        rows[site] = rows[site].copy()
        rows[site][row, 0] = bad
    huge_only = bad == 1e200
    if corrupt and np.isnan(bad) and site == "end.pos":  # a missing value: EM fills it
        fitted = fit(net, rows).params
        assert torch.isfinite(fitted["end.pos"].bias).all()
    elif corrupt and not (huge_only and site != "param.force"):
        with pytest.raises(ValueError, match=site.replace(".", r"\.")):
            fit(net, rows)
    else:
        if corrupt:  # 1e200 is a number, but squared it overflows: refused by name
            with pytest.raises(ValueError, match=site):
                fit(net, rows)
            return
        fitted = fit(net, rows).params
        query = {k: v[:3] for k, v in rows.items() if k.startswith("initial")}
        out = predict(net, fitted, query)
        assert torch.isfinite(out.continuous["pos"].mean).all()
        assert torch.isfinite(out.discrete["door"]).all()
    query = {"initial.door": ["open"], "initial.pos": [[0.0, bad]]}
    with pytest.raises(ValueError, match="initial.pos"):
        predict(net, params, query) if not huge_only else predict(
            net, params, {"initial.door": ["open"], "initial.pos": [[0.0]]}
        )


def _assert_distribution(probs: torch.Tensor, what: str):
    assert not probs.isnan().any(), what
    assert (probs >= 0).all(), what
    assert float((probs.sum(-1) - 1).abs().max()) < 1e-12, what


@pytest.mark.timeout(600)
@settings(max_examples=40, deadline=None)
@given(
    net=mixed_networks(),
    seed=st.integers(0, 1000),
    exponent=st.floats(0.0, 150.0),
    sign=st.sampled_from([1.0, -1.0]),
    where=st.sampled_from(["initial", "end", "param"]),
)
def test_every_distribution_sums_to_one_at_every_accepted_magnitude(
    net, seed, exponent, sign, where
):
    """From ordinary values to the magnitude limit, on an initial state, an observed end
    state or a parameter: every query's distributions sum to 1 within 1e-12 and hold no
    NaN, or the query refuses the row by name (a density below float64's range)."""
    import warnings

    from effect_networks.inference import infer_parameter
    from effect_networks.inference.queries.implausibility import OutsideTrainingData

    params = random_params(net, seed)
    big = sign * 10.0**exponent
    g = np.random.default_rng(seed)
    ev = {}
    for f in net.features:
        if isinstance(f, Discrete):
            ev[f"initial.{f.name}"] = [f.states[int(g.integers(len(f.states)))]]
        else:
            value = g.normal(size=(1, f.dim))
            if where == "initial" and f.name == "c0":
                value[0, -1] = big
            ev[f"initial.{f.name}"] = value
    end = {"end.c0": g.normal(size=(1, net.feature("c0").dim))}
    if where == "end":
        end["end.c0"][0, 0] = big
    uses = net.actions[0]
    force = [[big if where == "param" else 0.5]]
    calls = {
        "predict": lambda: predict(net, params, ev | {"action": [uses]}),
        "infer_action": lambda: infer_action(net, params, ev | end),
        "predict_end": lambda: predict(net, params, ev | end),
    }
    if net.parameters:
        calls["predict_param"] = lambda: predict(
            net, params, ev | {"action": [uses], "param.p": force}
        )
        calls["infer_parameter"] = lambda: infer_parameter(
            net, params, "p", ev | end | {"action": [uses]}, mixture=True
        )
    for name, call in calls.items():
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", OutsideTrainingData)
                answer = call()
        except ValueError as error:
            assert "has probability 0 under every configuration" in str(error), name
            continue
        if name.startswith("predict"):
            for feature, probs in answer.discrete.items():
                _assert_distribution(probs, f"{name}: {feature}")
            for feature, mixture in answer.continuous.items():
                _assert_distribution(mixture.weights, f"{name}: {feature}")
                assert torch.isfinite(mixture.means).all() and torch.isfinite(mixture.covs).all()
        elif name == "infer_action":
            _assert_distribution(answer.probs, name)
            assert float(answer.probs[0, int(answer.best[0])]) > 0 or bool(
                (answer.unseen[0] >= 0.5).any()
            )
        else:
            _assert_distribution(answer.cluster_probs, name)
            _assert_distribution(answer.mixture.weights, name)
            assert torch.isfinite(answer.mean).all()
