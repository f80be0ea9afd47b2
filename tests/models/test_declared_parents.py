"""Declared parent sets: Fig. 1 by default, checked, drawn, and answered right.

Answers are compared with a joint enumerated by hand from the tables
(``itertools.product`` over every discrete site), with pgmpy's VariableElimination on
the network's discrete part, and with closed-form Gaussian identities.
"""

import itertools
import math

import numpy as np
import pytest
import torch
from effect_networks.inference import fit, infer_action, predict, simulate
from effect_networks.inference.queries.implausibility import OutsideTrainingData
from effect_networks.models import (
    Continuous,
    Discrete,
    EffectNetwork,
    Parameter,
    effect_model,
    load,
    random_params,
    save,
    to_pgmpy,
)
from effect_networks.models.declaration import DTYPE
from hypothesis import given, settings
from hypothesis import strategies as st
from pyro.infer.inspect import get_dependencies

from effect_networks import inference

FEATURES = (Discrete("a", (0, 1)), Discrete("b", ("x", "y", "z")), Continuous("pos", 1))


def test_default_is_fig1_and_declaring_it_changes_nothing():
    default = EffectNetwork(FEATURES, ("push", "pull"))
    initial = ("initial.a", "initial.b", "initial.pos")
    fig1 = {f"end.{f.name}": (*initial, "action") for f in FEATURES}
    declared = EffectNetwork(FEATURES, ("push", "pull"), parents=fig1)
    assert declared == default and declared.parents == ()
    for spec in default.sites:
        assert declared.cpd(spec.name) == default.cpd(spec.name)
    assert default.discrete_parents("pos") == ("initial.a", "initial.b", "action")
    rows = simulate(default, random_params(default, 0), 300, seed=0)
    fitted = fit(default, rows).params
    again = fit(declared, rows).params
    for site, cpd in fitted.cpds.items():
        for name, value in vars(cpd).items():
            assert torch.equal(value, getattr(again.cpds[site], name)), (site, name)


@pytest.mark.parametrize(
    ("parents", "message"),
    [
        ({"end.nope": ("initial.a",)}, r"'end.nope', which is not a site"),
        ({"action": ("initial.a",)}, r"'action', which has fixed parents"),
        ({"end.a": ("initial.zz",)}, r"parent 'initial.zz' of 'end.a' is not a site"),
        ({"end.a": ("a",)}, r"a feature's sites are 'initial.a' and 'end.a'"),
        ({"initial.a": ("end.b",)}, r"'end.b' cannot be a parent of the initial site"),
        ({"initial.a": ("action",)}, r"'action' cannot be a parent of the initial site"),
        ({"end.a": ("end.pos",)}, r"continuous end site 'end.pos' cannot be a parent"),
        ({"end.a": ("action", "action")}, r"repeat a site"),
        ({"end.a": "initial.a"}, r"must be a sequence of site names"),
        ({"end.a": ("end.b",), "end.b": ("end.a",)}, r"cycle: end.a -> end.b -> end.a"),
        ({"end.a": ("end.a",)}, r"cycle: end.a -> end.a"),
        ({"initial.a": ("initial.b",), "initial.b": ("initial.a",)}, r"cycle"),
        ({"end.pos": ("cluster.f", "action")}, r"do not name them"),
        ({"end.pos": ("initial.pos",)}, r"the action must be a parent of 'end.pos'"),
    ],
)
def test_bad_structures_are_named(parents, message):
    force = Parameter("f", 0.0, 1.0, 2, ("push",), "pos")
    with pytest.raises(ValueError, match=message):
        EffectNetwork(FEATURES, ("push", "pull"), (force,), parents=parents)


def test_kinds_are_checked_against_their_sites():
    with pytest.raises(ValueError, match=r"'end.a' .* cannot have kind 'table': a table has no"):
        EffectNetwork(FEATURES, ("push",), kinds={"end.a": "table"})
    with pytest.raises(ValueError, match=r"unknown kind 'tabel'"):
        EffectNetwork(FEATURES, ("push",), kinds={"end.a": "tabel"})
    with pytest.raises(ValueError, match=r"'end.pos' .* cannot have kind 'softmax'"):
        EffectNetwork(FEATURES, ("push",), kinds={"end.pos": "softmax"})
    # with its continuous parent dropped, a discrete end feature is a table again
    net = EffectNetwork(FEATURES, ("push",), parents={"end.a": ("initial.a", "action")})
    assert net.cpd("end.a").name == "table"
    assert net.cpd("end.b").name == "softmax"


def test_the_model_draws_the_declared_edges():
    force = Parameter("f", 0.0, 1.0, 2, ("push",), "pos")
    parents = {
        "initial.b": ("initial.a",),
        "end.a": ("initial.a", "action"),
        "end.b": ("end.a", "initial.pos"),
        "end.pos": ("initial.pos", "action"),
    }
    net = EffectNetwork(FEATURES, ("push", "pull"), (force,), parents=parents)
    deps = get_dependencies(effect_model, (net, random_params(net, 0)), {"n_rows": 2})
    drawn = {s: set(d) - {s} for s, d in deps["prior_dependencies"].items()}
    for site, ps in parents.items():
        extra = {"cluster.f", "param.f"} if site == "end.pos" else set()
        assert drawn[site] == set(ps) | extra, site
    assert drawn["initial.a"] == set()


def test_structure_survives_save_and_load(tmp_path):
    net = EffectNetwork(
        FEATURES, ("push",), parents={"end.b": ("end.a", "action"), "initial.b": ("initial.a",)}
    )
    params = random_params(net, 1)
    save(tmp_path / "net.pt", net, params)
    back, back_params = load(tmp_path / "net.pt")
    assert back == net
    assert back.cpd("end.b").parents == ("action", "end.a")
    assert torch.equal(back_params["end.b"].probs, params["end.b"].probs)


# ---------------------------------------------------------------- discrete: brute force
@st.composite
def structures(draw):
    """Small discrete networks with random parent sets: initial -> initial edges, end ->
    end edges, dropped edges, an end-only feature."""
    features = [
        Discrete(f"f{i}", tuple(range(draw(st.integers(2, 3)))), initial=i < 2)
        for i in range(draw(st.integers(2, 3)))
    ]
    initial = [f"initial.{f.name}" for f in features if f.initial]
    parents = {}
    for i, site in enumerate(initial):
        parents[site] = tuple(q for q in initial[:i] if draw(st.booleans()))
    ends = []
    for f in features:
        site = f"end.{f.name}"
        pool = [*initial, "action", *ends]
        parents[site] = tuple(q for q in pool if draw(st.booleans()))
        ends.append(site)
    return EffectNetwork(tuple(features), ("p", "q"), parents=parents)


def brute_force(net, params, evidence):
    """Every discrete site's assignment with its joint probability, from the tables."""
    sites = [s for s in net.sites]
    out = []
    for values in itertools.product(*[range(s.size) for s in sites]):
        x = dict(zip([s.name for s in sites], values, strict=True))
        if any(x[k] != v for k, v in evidence.items()):
            continue
        p = 1.0
        for s in sites:
            cpd = net.cpd(s.name)
            p *= float(params[s.name].probs[tuple(x[q] for q in cpd.parents) + (x[s.name],)])
        out.append((x, p))
    return out


def conditional(net, params, evidence, target):
    joint = brute_force(net, params, evidence)
    probs = torch.zeros(net.site(target).size, dtype=DTYPE)
    for x, p in joint:
        probs[x[target]] += p
    return probs / probs.sum()


@settings(max_examples=20, deadline=None)
@given(structures(), st.integers(0, 2**16), st.data())
def test_queries_equal_the_enumerated_joint(net, seed, data):
    params = random_params(net, seed)
    ends = [s.name for s in net.sites if s.role == "end"]
    initial = [s.name for s in net.sites if s.role == "initial"]
    observed = data.draw(st.lists(st.sampled_from(initial + ends), min_size=1, unique=True))
    evidence = {s: data.draw(st.integers(0, net.site(s).size - 1)) for s in observed}
    enc = net.encode_indices({s: [v] for s, v in evidence.items()})
    truth = conditional(net, params, evidence, "action")
    posterior = infer_action(net, params, enc)
    torch.testing.assert_close(posterior.probs[0], truth)
    compiled = inference.compile(net, params).infer_action(enc)
    torch.testing.assert_close(compiled.probs[0], truth)
    given_action = evidence | {"action": 1}
    enc = net.encode_indices({s: [v] for s, v in given_action.items()})
    prediction = predict(net, params, enc)
    for site in ends:
        if site not in evidence:
            feature = site.removeprefix("end.")
            expected = conditional(net, params, given_action, site)
            torch.testing.assert_close(prediction.discrete[feature][0], expected)


def test_custom_structure_equals_pgmpy():
    pytest.importorskip("pgmpy")
    from pgmpy.inference import VariableElimination

    net = EffectNetwork(
        (
            Discrete("a", (0, 1)),
            Discrete("b", ("x", "y", "z")),
            Discrete("c", (0, 1), initial=False),
        ),
        ("push", "pull", "wait"),
        parents={
            "initial.b": ("initial.a",),
            "end.a": ("initial.a", "action"),
            "end.b": ("initial.b", "action", "end.a"),
            "end.c": ("end.b",),
        },
    )
    params = random_params(net, 3)
    model, left_out = to_pgmpy(net, params)
    assert left_out == ()
    assert set(model.get_parents("end.b")) == {"initial.b", "action", "end.a"}
    ve = VariableElimination(model)
    for evidence in ({"end.c": 1}, {"initial.a": 0, "end.c": 0}, {"end.b": "z", "end.a": 1}):
        ours = infer_action(net, params, {k: [v] for k, v in evidence.items()})
        theirs = ve.query(["action"], evidence=evidence, show_progress=False)
        order = [theirs.state_names["action"].index(a) for a in net.actions]
        np.testing.assert_allclose(ours.probs[0].numpy(), theirs.values[order], atol=1e-12)
    ours = predict(net, params, {"initial.a": [1], "action": ["wait"]})
    theirs = ve.query(["end.c"], evidence={"initial.a": 1, "action": "wait"}, show_progress=False)
    np.testing.assert_allclose(ours.discrete["c"][0].numpy(), theirs.values, atol=1e-12)


# ---------------------------------------------------------------- Gaussians: closed form
def test_a_dropped_parent_is_left_out_of_the_least_squares():
    net = EffectNetwork(
        (Continuous("x", 1), Continuous("z", 1), Continuous("y", 1)),
        ("act",),
        parents={"end.y": ("initial.x", "action")},
    )
    g = np.random.default_rng(0)
    n = 400
    x, z = g.normal(size=(n, 1)), g.normal(size=(n, 1))
    y = 2.0 * x - 0.5 + 0.1 * g.normal(size=(n, 1))
    rows = {
        "initial.x": x,
        "initial.z": z,
        "initial.y": g.normal(size=(n, 1)),
        "action": ["act"] * n,
        "end.x": x,
        "end.z": z,
        "end.y": y,
    }
    cpd = fit(net, rows, pseudo_count=0.0, min_variance=0.0).params["end.y"]
    assert cpd.weight.shape == (1, 1, 1)  # (action, d, one continuous parent)
    design = np.hstack([x, np.ones((n, 1))])
    beta, *_ = np.linalg.lstsq(design, y, rcond=None)
    resid = y - design @ beta
    np.testing.assert_allclose(cpd.weight[0, 0].numpy(), beta[:1, 0], rtol=1e-10)
    np.testing.assert_allclose(cpd.bias[0].numpy(), beta[1], rtol=1e-10)
    np.testing.assert_allclose(cpd.covariance[0].numpy(), resid.T @ resid / n, rtol=1e-8)


def test_a_discrete_parent_of_an_initial_gaussian_is_inferred_by_bayes():
    net = EffectNetwork(
        (Discrete("heavy", (False, True)), Continuous("mass", 1)),
        ("lift",),
        parents={"initial.mass": ("initial.heavy",), "end.heavy": ("initial.heavy", "action")},
    )
    params = random_params(net, 2)
    mass = 0.7
    posterior = predict(net, params, {"initial.mass": [[mass]], "action": ["lift"]})
    prior = params["initial.heavy"].probs
    lg = params["initial.mass"]
    mean, sd = lg.bias[:, 0], lg.scale_tril[:, 0, 0]
    density = torch.exp(-0.5 * ((mass - mean) / sd) ** 2) / (sd * math.sqrt(2 * math.pi))
    heavy = prior * density / (prior * density).sum()  # Bayes on the initial feature
    expected = heavy @ params["end.heavy"].probs[:, 0]  # then the table, action "lift"
    torch.testing.assert_close(posterior.discrete["heavy"][0], expected)


def test_a_latent_discrete_end_parent_of_a_gaussian_is_summed_out():
    net = EffectNetwork(
        (Discrete("a", (0, 1)), Continuous("pos", 1)),
        ("push", "pull"),
        parents={"end.a": ("initial.a", "action"), "end.pos": ("initial.pos", "action", "end.a")},
    )
    assert net.cpd("end.pos").parents == ("action", "end.a")
    params = random_params(net, 6)
    x, y = 0.4, 1.3
    table, lg, prior = params["end.a"].probs, params["end.pos"], params["action"].probs

    def density(action, a):
        mean = lg.bias[action, a, 0] + lg.weight[action, a, 0, 0] * x
        sd = lg.scale_tril[action, a, 0, 0]
        return torch.exp(-0.5 * ((y - mean) / sd) ** 2) / (sd * math.sqrt(2 * math.pi))

    likelihood = torch.stack(
        [sum(table[1, act, a] * density(act, a) for a in range(2)) for act in range(2)]
    )
    posterior = infer_action(
        net, params, {"initial.a": [1], "initial.pos": [[x]], "end.pos": [[y]]}
    )
    torch.testing.assert_close(posterior.probs[0], prior * likelihood / (prior @ likelihood))
    pred = predict(net, params, {"initial.a": [1], "initial.pos": [[x]], "action": ["pull"]})
    means = lg.bias[1, :, 0] + lg.weight[1, :, 0, 0] * x
    torch.testing.assert_close(pred.continuous["pos"].mean[0, 0], table[1, 1] @ means)


def push_world(n=3000, seed=0):
    """The issue's push world: a position and two discrete features. Push moves the
    object 0.3 m and makes contact, grasp makes contact and holds it, wait does nothing;
    positions seen in training lie in [-1, 1]."""
    rng = np.random.default_rng(seed)
    action = rng.choice(["wait", "push", "grasp"], n)
    pos = rng.uniform(-1, 1, (n, 1))
    contact, held = rng.random(n) < 0.3, rng.random(n) < 0.2
    moved = pos + np.where(action[:, None] == "push", 0.3, 0.0) + rng.normal(0, 0.01, (n, 1))
    return {
        "initial.contact": contact,
        "initial.held": held,
        "initial.pos": pos,
        "action": action,
        "end.contact": contact | (action != "wait"),
        "end.held": held | (action == "grasp"),
        "end.pos": moved,
    }


def test_the_issues_push_world_answers_right_with_the_spurious_edges_dropped():
    features = (
        Discrete("contact", (False, True)),
        Discrete("held", (False, True)),
        Continuous("pos", 1),
    )
    actions = ("wait", "push", "grasp")
    declared = EffectNetwork(
        features,
        actions,
        parents={
            "end.contact": ("initial.contact", "action"),
            "end.held": ("initial.held", "action"),
        },
    )
    assert declared.cpd("end.contact").name == "table"  # no softmax over the position
    params = fit(declared, push_world()).params
    far = {"initial.contact": [False], "initial.held": [False], "initial.pos": [[5.0]]}
    # 5 m lies far outside the positions trained on: answered, flagged, and named
    with pytest.warns(OutsideTrainingData, match="initial.pos"):
        waiting = predict(declared, params, far | {"action": ["wait"]})
    assert float(waiting.prob("contact", True)[0]) < 0.01  # was 0.995 with Fig. 1's softmax
    unchanged = far | {"end.contact": [False], "end.held": [False], "end.pos": [[5.0]]}
    with pytest.warns(OutsideTrainingData, match="initial.pos"):
        post = infer_action(declared, params, unchanged)
    assert post.best_names == ("wait",) and float(post.prob("wait")[0]) > 0.99  # not "grasp"
    assert float(post.unseen[0, 0]) == 0.0 and bool(post.implausible[0])
    # evidence the model gives no probability: no action releases contact
    released = {"initial.contact": [True], "initial.held": [False], "initial.pos": [[0.0]]}
    released |= {"end.contact": [False], "end.held": [False], "end.pos": [[0.0]]}
    assert bool(infer_action(declared, params, released).implausible[0])
