"""The compiled tables answer exactly what the traced model answers."""

import dataclasses
from unittest import mock

import mpmath
import numpy as np
import pytest
import torch
from effect_networks.experiments.switch_worlds import switch_world
from effect_networks.inference import infer_action
from effect_networks.inference.queries.action_tables import compile_discrete
from effect_networks.models import Continuous, EffectNetwork
from hypothesis import example, given, settings
from hypothesis import strategies as st

from effect_networks import inference
from tests.helpers import discrete_network, random_params


@settings(max_examples=20, deadline=None)
@given(
    cards=st.lists(st.integers(2, 4), min_size=1, max_size=3),
    n_actions=st.integers(2, 5),
    seed=st.integers(0, 1000),
    zero_n=st.sampled_from([0.0, 0.3]),
    data=st.data(),
)
def test_compiled_equals_traced(cards, n_actions, seed, zero_n, data):
    net = discrete_network(cards, n_actions)
    params = random_params(net, seed, unseen=zero_n)
    compiled = inference.compile(net, params).action_tables
    g = torch.Generator().manual_seed(seed)
    ev = {}
    for i, k in enumerate(cards):
        if data.draw(st.booleans()):
            ev[f"initial.f{i}"] = torch.randint(0, k, (7,), generator=g)
        if data.draw(st.booleans()):
            ev[f"end.f{i}"] = torch.randint(0, k, (7,), generator=g)
    if not ev:
        ev["initial.f0"] = torch.randint(0, cards[0], (7,), generator=g)
    ev = net.encode_indices(ev)
    a = compiled.infer_action(ev)
    b = infer_action(net, params, ev)
    torch.testing.assert_close(a.probs, b.probs, atol=1e-9, rtol=0)
    torch.testing.assert_close(a.log_evidence, b.log_evidence, atol=1e-9, rtol=0)
    torch.testing.assert_close(a.unseen, b.unseen, atol=1e-9, rtol=0)
    assert torch.equal(a.best, b.best)


def test_compile_refuses_continuous_networks():
    net = EffectNetwork((Continuous("x"),), ("a", "b"))
    with pytest.raises(ValueError, match="all-discrete"):
        compile_discrete(net, random_params(net, 0))


def test_compiled_parameter_query_equals_traced():
    from effect_networks.inference import infer_parameter

    from tests.networks import NET

    params = random_params(NET, 21, unseen=0.2)
    query = inference.compile(NET, params).parameter_query("force")
    g = torch.Generator().manual_seed(1)
    n = 40
    ev = {
        "initial.visible": torch.randint(0, 2, (n,), generator=g),
        "initial.pos": torch.randn(n, 2, generator=g, dtype=torch.float64),
        "action": torch.randint(1, 3, (n,), generator=g),  # tap or push: both use the force
        "end.pos": 3 * torch.randn(n, 2, generator=g, dtype=torch.float64),
    }
    ev = NET.encode_indices(ev)
    a = query.infer_parameter(ev)
    b = infer_parameter(NET, params, "force", ev)
    torch.testing.assert_close(a.cluster_probs, b.cluster_probs, atol=1e-9, rtol=0)
    assert torch.equal(a.best_cluster, b.best_cluster)
    torch.testing.assert_close(a.mean, b.mean)
    torch.testing.assert_close(a.cov, b.cov)
    torch.testing.assert_close(a.unseen, b.unseen)


def test_compiled_parameter_query_with_one_shared_configuration():
    from effect_networks.inference import infer_parameter

    from tests.networks import NET

    params = random_params(NET, 4)
    g = torch.Generator().manual_seed(2)
    n = 30
    ev = {
        "initial.visible": torch.ones(n, dtype=torch.long),
        "initial.pos": torch.randn(n, 2, generator=g, dtype=torch.float64),
        "action": torch.full((n,), 2),
        "end.pos": 3 * torch.randn(n, 2, generator=g, dtype=torch.float64),
    }
    ev = NET.encode_indices(ev)
    a = inference.compile(NET, params).parameter_query("force").infer_parameter(ev)
    b = infer_parameter(NET, params, "force", ev)
    torch.testing.assert_close(a.cluster_probs, b.cluster_probs, atol=1e-9, rtol=0)
    torch.testing.assert_close(a.mean, b.mean)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 1000), zero_n=st.sampled_from([0.0, 0.3]), data=st.data())
def test_answers_per_configuration_equal_the_answers_per_row(seed, zero_n, data):
    """The answers gathered from the per-configuration tables (the action the only latent
    site) are those computed row by row from the log table."""
    net = discrete_network([3, 2], 4)
    params = random_params(net, seed, unseen=zero_n)
    g = torch.Generator().manual_seed(seed)
    ev = net.encode_indices(
        {
            "initial.f0": torch.randint(0, 3, (9,), generator=g),
            "initial.f1": torch.randint(0, 2, (9,), generator=g),
            "end.f1": torch.randint(0, 2, (9,), generator=g),
        }
    )
    allowed = data.draw(st.sampled_from([None, torch.tensor([False, True, True, False])]))
    fast = inference.compile(net, params).action_tables
    a = fast.infer_action(ev, allowed=allowed)
    [(pattern, plan)] = fast.plans.items()
    assert plan.answers is not None
    slow = inference.compile(net, params).action_tables
    slow.plans[pattern] = dataclasses.replace(plan, answers=None)
    b = slow.infer_action(ev, allowed=allowed)
    for name in ("probs", "log_evidence", "unseen"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), atol=1e-12, rtol=0)
    assert torch.equal(a.best, b.best) and a.best_names == b.best_names


@settings(max_examples=15, deadline=None)
@given(
    seed=st.integers(0, 1000),
    zero_n=st.sampled_from([0.0, 0.3]),
    given_sites=st.sampled_from(
        [("end.f0", "end.f1"), ("end.f1",), ("initial.f0", "end.f0", "end.f1")]
    ),
    chunk=st.sampled_from([None, 40]),
    data=st.data(),
)
def test_answers_with_latent_initial_sites_equal_the_answers_per_row(
    seed, zero_n, given_sites, chunk, data
):
    """With latent sites besides the action (an initial state unknown), the answers per
    observed configuration (the others summed out, in chunks of any size) are those
    computed row by row, and the traced model's: posterior, evidence, unseen mass, best
    action (with and without allowed actions and the unseen rule) and the flag."""
    import effect_networks.inference.queries.action_tables as action_module

    chunk = action_module.ANSWERS_CHUNK if chunk is None else chunk  # 40: small chunks
    with mock.patch.object(action_module, "ANSWERS_CHUNK", chunk):
        _latent_answers_case(seed, zero_n, given_sites, data)


def _latent_answers_case(seed, zero_n, given_sites, data):
    net = discrete_network([3, 2], 4)
    params = random_params(net, seed, unseen=zero_n)
    g = torch.Generator().manual_seed(seed)
    sizes = {"initial.f0": 3, "initial.f1": 2, "end.f0": 3, "end.f1": 2}
    ev = net.encode_indices(
        {s: torch.randint(0, sizes[s], (11,), generator=g) for s in given_sites}
    )
    allowed = data.draw(st.sampled_from([None, torch.tensor([False, True, True, False])]))
    avoid = data.draw(st.booleans())
    fast = inference.compile(net, params).action_tables
    a = fast.infer_action(ev, allowed=allowed, avoid_unseen=avoid)
    [(pattern, plan)] = [(p, q) for p, q in fast.plans.items() if p == frozenset(given_sites)]
    assert plan.answers is not None and len(plan.latent) > 1
    assert (plan.answers.unseen_mass is None) == (plan.unseen is None)
    slow = inference.compile(net, params).action_tables
    slow.plans[pattern] = dataclasses.replace(fast.plan(pattern), answers=None)
    b = slow.infer_action(ev, allowed=allowed, avoid_unseen=avoid)
    traced = infer_action(net, params, ev, allowed=allowed, avoid_unseen=avoid)
    for name in ("probs", "log_evidence", "unseen"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), atol=1e-12, rtol=0)
        torch.testing.assert_close(getattr(a, name), getattr(traced, name), atol=1e-9, rtol=0)
    assert torch.equal(a.best, b.best) and a.best_names == b.best_names
    assert torch.equal(a.implausible, b.implausible)
    for i in range(3):  # one row at a time: its row of the batched answer
        one = fast.infer_action(ev.rows(slice(i, i + 1)), allowed=allowed, avoid_unseen=avoid)
        torch.testing.assert_close(one.probs, a.probs[i : i + 1], atol=1e-15, rtol=0)
        assert torch.equal(one.best, a.best[i : i + 1])


@settings(max_examples=15, deadline=None)
@given(
    seed=st.integers(0, 1000),
    zero_n=st.sampled_from([0.0, 0.3]),
    below=st.sampled_from([0.01, 0.3, 0.9]),
)
def test_one_row_action_queries_are_the_batched_rows(seed, zero_n, below):
    """A single row (read by its position in the per-configuration answers when the plan
    has them) answers bit for bit as its row of the batched query, the implausible flag
    included, and as the traced model; its tensors are its own."""
    net = discrete_network([3, 2], 4)
    params = random_params(net, seed, unseen=zero_n)
    g = torch.Generator().manual_seed(seed)
    ev = net.encode_indices(
        {
            "initial.f0": torch.randint(0, 3, (12,), generator=g),
            "initial.f1": torch.randint(0, 2, (12,), generator=g),
            "end.f1": torch.randint(0, 2, (12,), generator=g),
        }
    )
    compiled = inference.compile(net, params).action_tables
    batched = compiled.infer_action(ev, implausible_below=below)
    traced = infer_action(net, params, ev, implausible_below=below)
    [plan] = compiled.plans.values()
    assert plan.answers is not None and (plan.unseen is None) == (zero_n == 0.0)
    for i in range(12):
        one = compiled.infer_action(ev.rows(slice(i, i + 1)), implausible_below=below)
        for name in ("probs", "best", "log_evidence", "unseen", "implausible"):
            mine, theirs = getattr(one, name), getattr(batched, name)[i : i + 1]
            assert mine.dtype == theirs.dtype and torch.equal(mine, theirs), name
        assert one.best_names == batched.best_names[i : i + 1]
        torch.testing.assert_close(one.probs, traced.probs[i : i + 1])
        assert torch.equal(one.implausible, traced.implausible[i : i + 1])
        one.probs.zero_()  # the caller's to change: the plan's answers stay
    again = compiled.infer_action(ev.rows(slice(0, 1)), implausible_below=below)
    assert torch.equal(again.probs, batched.probs[:1])


# ---------------------------------------------------------------- a parameter on several features
def assert_same_answer(a, b):
    for name in ("cluster_probs", "mean", "cov", "unseen", "outside", "implausible"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), atol=1e-9, rtol=1e-9)
    assert torch.equal(a.best_cluster, b.best_cluster)
    if b.mixture is not None:
        for name in ("weights", "means", "covs"):
            torch.testing.assert_close(getattr(a.mixture, name), getattr(b.mixture, name))


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 1000), which=st.sampled_from(["both", "land", "roll", "partial"]))
def test_compiled_query_of_a_parameter_on_two_continuous_features(seed, which):
    """One aim acting on end.land (2-D) and end.roll: their joint Gaussian per cluster."""
    from effect_networks.inference import infer_parameter
    from effect_networks.inference.queries.parameter import CompiledJointParameterQuery
    from effect_networks.models import Partial

    from tests.networks import throwing

    net, _ = throwing()
    params = random_params(net, seed, unseen=0.3)
    query = inference.compile(net, params).parameter_query("aim")
    assert isinstance(query, CompiledJointParameterQuery)
    g = torch.Generator().manual_seed(seed)
    n = 12
    ev = {
        "initial.land": torch.randn(n, 2, generator=g, dtype=torch.float64),
        "initial.roll": torch.randn(n, 1, generator=g, dtype=torch.float64),
        "action": ["throw"] * n,
    }
    land = 2 * torch.randn(n, 2, generator=g, dtype=torch.float64)
    roll = 2 * torch.randn(n, 1, generator=g, dtype=torch.float64)
    if which in ("both", "land"):
        ev["end.land"] = land
    if which in ("both", "roll", "partial"):
        ev["end.roll"] = roll
    if which == "partial":
        ev["end.land"] = Partial(land, observed=torch.rand(n, 2, generator=g) < 0.5)
    for mixture in (False, True):
        assert_same_answer(
            query.infer_parameter(ev, mixture=mixture),
            infer_parameter(net, params, "aim", ev, mixture=mixture),
        )


def test_compiled_query_of_a_parameter_on_a_continuous_and_a_discrete_feature():
    from effect_networks.inference import infer_parameter
    from effect_networks.models import Continuous, Discrete, Parameter

    force = Parameter("force", 0.0, 6.0, 3, ("push",), ("pos", "upright"))
    net = EffectNetwork(
        (Discrete("upright", (True, False)), Continuous("pos", 1)),
        ("push", "wait"),
        (force,),
        parents={
            "end.upright": ("initial.upright", "action"),
            "end.pos": ("initial.pos", "action"),
        },
    )
    params = random_params(net, 2, unseen=0.3)
    query = inference.compile(net, params).parameter_query("force")
    g = torch.Generator().manual_seed(0)
    n = 10
    ev = {
        "initial.upright": torch.rand(n, generator=g) < 0.5,
        "initial.pos": torch.randn(n, 1, generator=g, dtype=torch.float64),
        "action": ["push"] * n,
    }
    pos = {"end.pos": 3 * torch.randn(n, 1, generator=g, dtype=torch.float64)}
    upright = {"end.upright": torch.rand(n, generator=g) < 0.5}
    for extra in (pos | upright, pos, upright):
        assert_same_answer(
            query.infer_parameter(ev | extra, mixture=True),
            infer_parameter(net, params, "force", ev | extra, mixture=True),
        )
    empty = query.infer_parameter({k: v[:0] for k, v in (ev | pos).items()})
    assert empty.mean.shape == (0, 1) and empty.cluster_probs.shape == (0, 3)
    with pytest.raises(ValueError, match=r"discrete parents \['initial.upright'\]"):
        query.infer_parameter({k: v for k, v in (ev | upright).items() if k != "initial.upright"})


def test_compiled_query_refuses_a_feature_shared_by_two_parameters():
    from effect_networks.inference.queries.parameter import compile_parameter_query

    from tests.networks import sliding

    net, params = sliding()
    with pytest.raises(ValueError, match=r"'force' shares \['end.pos'\] with another parameter"):
        compile_parameter_query(net, params, "force")


def test_compiled_query_without_other_inputs_answers_as_the_traced_model():
    """A feature whose only continuous input is the parameter (the throw's hit): every
    cluster's mean is fixed; the same answers as the traced model."""
    from effect_networks.inference import infer_parameter
    from effect_networks.models import Continuous, Parameter

    target = Parameter("target", (0.0, 0.0), (1.0, 2.0), (3, 4), ("throw", "lob"), "hit")
    net = EffectNetwork((Continuous("hit", 2, initial=False),), ("throw", "lob"), (target,))
    params = random_params(net, 3, unseen=0.2)
    query = inference.compile(net, params).parameter_query("target")
    assert query.offset.shape == (2, 12, 2) and query.w_x.shape[-1] == 0
    g = torch.Generator().manual_seed(0)
    hits = 3 * torch.randn(20, 2, generator=g, dtype=torch.float64)
    for actions in (["throw"] * 20, ["throw", "lob"] * 10):
        ev = {"end.hit": hits, "action": actions}
        assert_same_answer(
            query.infer_parameter(ev, mixture=True),
            infer_parameter(net, params, "target", ev, mixture=True),
        )


def _one_row_network(dim: int = 2):
    from effect_networks.models import Parameter

    low, high = (0.0,) * dim, (1.0, 2.0, 1.5)[:dim]
    target = Parameter("target", low, high, (3, 4, 2)[:dim], ("throw", "lob"), "hit")
    return EffectNetwork((Continuous("hit", dim, initial=False),), ("throw", "lob"), (target,))


@settings(max_examples=15, deadline=None)
@given(
    seed=st.integers(0, 1000),
    dim=st.sampled_from([1, 2, 3]),
    scale=st.sampled_from([0.5, 3.0, 30.0]),
    mixture=st.booleans(),
)
def test_one_row_queries_answer_as_the_batched_query_and_the_traced_model(
    seed, dim, scale, mixture
):
    """One hit at a time (read with numpy from per-action tables) gives, row by row, the
    batched query's answers and the traced model's, flags and mixture included, for
    every way of giving one row."""
    from effect_networks.inference import infer_parameter

    net = _one_row_network(dim)
    params = random_params(net, seed, unseen=0.3)
    query = inference.compile(net, params).parameter_query("target")
    g = torch.Generator().manual_seed(seed)
    hits = scale * torch.randn(8, dim, generator=g, dtype=torch.float64)
    actions = ["throw", "lob"] * 4
    assert query._one_row({"end.hit": hits[0], "action": "lob"}, mixture, 0.01) is not None
    batched = query.infer_parameter({"end.hit": hits, "action": actions}, mixture=mixture)
    traced = infer_parameter(net, params, "target", {"end.hit": hits, "action": actions})
    assert traced.implausible.any() or scale < 30  # far hits are flagged
    for i in range(len(hits)):
        forms = [
            {"end.hit": hits[i : i + 1], "action": [actions[i]]},
            {"end.hit": hits[i], "action": actions[i]},
            {"end.hit": hits[i].numpy(), "action": (actions[i],)},
            {"end.hit": hits[i].tolist(), "action": actions[i]},
        ]
        for ev in forms:
            one = query.infer_parameter(ev, mixture=mixture)
            assert one.cluster_probs.shape == (1, batched.cluster_probs.shape[1])
            assert one.best_cluster.dtype == torch.long and one.implausible.dtype == torch.bool
            assert one.outside.dtype == torch.bool and one.unseen.dtype == torch.float64
            row = dataclasses.replace(
                batched,
                **{
                    f.name: getattr(batched, f.name)[i : i + 1]
                    for f in dataclasses.fields(batched)
                    if f.name != "mixture"
                },
                mixture=None
                if batched.mixture is None
                else dataclasses.replace(
                    batched.mixture,
                    **{
                        f.name: getattr(batched.mixture, f.name)[i : i + 1]
                        for f in dataclasses.fields(batched.mixture)
                    },
                ),
            )
            assert_same_answer(one, row)
            assert (one.mixture is None) == (not mixture)
            assert torch.equal(one.implausible, traced.implausible[i : i + 1])
            torch.testing.assert_close(one.mean, traced.mean[i : i + 1])


def test_one_row_query_with_an_impossible_cluster_and_the_default_action():
    """A cluster the action never takes is left out of the closest-cluster distance; with
    one action using the parameter, the action may be left out of the evidence."""
    from effect_networks.models import Parameter

    target = Parameter("target", (0.0, 0.0), (1.0, 2.0), (3, 4), ("throw",), "hit")
    net = EffectNetwork((Continuous("hit", 2, initial=False),), ("throw", "lob"), (target,))
    params = random_params(net, 5, unseen=0.2)
    query = inference.compile(net, params).parameter_query("target")
    log_cluster = query.log_cluster.clone()
    log_cluster[0, :6] = -torch.inf  # "throw" never takes the first six clusters
    query = dataclasses.replace(query, log_cluster=log_cluster)
    hits = torch.tensor([[0.1, 0.2], [0.9, 1.9], [40.0, -3.0]], dtype=torch.float64)
    batched = query.infer_parameter({"end.hit": hits})
    assert (batched.cluster_probs[:, :6] == 0).all()
    for i in range(len(hits)):
        one = query.infer_parameter({"end.hit": hits[i]})
        torch.testing.assert_close(one.cluster_probs, batched.cluster_probs[i : i + 1])
        assert torch.equal(one.best_cluster, batched.best_cluster[i : i + 1])
        assert torch.equal(one.implausible, batched.implausible[i : i + 1])
    assert batched.implausible.tolist() == [False, False, True]


def test_one_row_query_reports_bad_evidence_as_before():
    from effect_networks.models import Partial

    net = _one_row_network()
    params = random_params(net, 1)
    query = inference.compile(net, params).parameter_query("target")
    hit = torch.tensor([[0.3, 0.4]], dtype=torch.float64)
    with pytest.raises(ValueError, match="action"):
        query.infer_parameter({"end.hit": hit})  # two actions use it: which one?
    with pytest.raises(ValueError, match="not one of its states"):
        query.infer_parameter({"end.hit": hit, "action": "jump"})
    with pytest.raises(ValueError, match="NaN or inf"):
        query.infer_parameter({"end.hit": [[0.3, float("nan")]], "action": "throw"})
    with pytest.raises(ValueError, match="shape"):
        query.infer_parameter({"end.hit": [0.3, 0.4, 0.5], "action": "throw"})
    with pytest.raises(ValueError, match="does not exist"):
        query.infer_parameter({"end.hit": hit, "action": "throw", "end.miss": [1]})
    partial = query.infer_parameter(
        {"end.hit": Partial([[0.3, 0.0]], [[True, False]]), "action": "lob"}
    )
    assert partial.cluster_probs.shape == (1, 12)


@settings(max_examples=200, deadline=None)
@given(dof=st.integers(1, 400), x=st.floats(0, 1e5))
@example(dof=41, x=29.0)  # torch's gammaincc is off by 1.6e-10 here; ours by 1.5e-15
def test_chi_square_tail_is_the_regularised_upper_gamma(dof, x):
    """Against mpmath's regularised upper incomplete gamma at 40 digits (torch's
    gammaincc, which the traced queries use, is within about 1e-10 of it)."""
    import mpmath
    from effect_networks.models.gaussian import chi_square_tail

    with mpmath.workdps(40):
        expected = float(mpmath.gammainc(dof / 2, x / 2, mpmath.inf, regularized=True))
    assert chi_square_tail(dof, x) == pytest.approx(expected, rel=1e-11, abs=1e-300)


def _throw_like(n: int, seed: int, noise: float):
    """Targets over the paper's area and hits through a clamped (saturating) map, as the
    arm's joint limits make it: where the map saturates, a cluster's hit spread is the
    noise alone, and its precision ~1 / noise^2."""
    g = np.random.default_rng(seed)
    t = np.column_stack([g.uniform(-1.0, 1.0, n), g.uniform(0.4, 2.4, n)])
    h = np.column_stack(
        [np.clip(1.1 * t[:, 0], -0.6, 0.5), np.clip(t[:, 1] + 0.3 * t[:, 0], 0.8, 2.0)]
    )
    return t, h + g.normal(0.0, noise, h.shape)


def _cluster_posterior_oracle(params, hit) -> list:
    """``p(cluster | hit)`` of the throw network in 50-digit arithmetic, from the fitted
    numbers alone: per cluster ``c`` the hit is ``N(b_c + W_c mu_c, S_c + W_c Sigma_c
    W_c^T)`` (the target integrated out), weighted by the cluster table."""
    cpd, prior = params["end.hit"], params["param.target"]
    pi = params["cluster.target"].probs[0]
    with mpmath.workdps(50):
        y = mpmath.matrix(hit.tolist())
        logs = []
        for c in range(len(pi)):
            w = mpmath.matrix(cpd.weight[0, c].tolist())
            noise = mpmath.matrix(cpd.scale_tril[0, c].tolist())
            spread = mpmath.matrix(prior.scale_tril[c].tolist())
            mean = mpmath.matrix(cpd.bias[0, c].tolist()) + w * mpmath.matrix(
                prior.bias[c].tolist()
            )
            ws = w * spread
            cov = noise * noise.T + ws * ws.T
            r = y - mean
            d2 = (r.T * mpmath.inverse(cov) * r)[0]
            logs.append(
                mpmath.log(mpmath.mpf(float(pi[c]))) - d2 / 2 - mpmath.log(mpmath.det(cov)) / 2
            )
        top = max(logs)
        e = [mpmath.exp(v - top) for v in logs]
        return [float(v / sum(e)) for v in e]


@pytest.mark.parametrize("layout", ["grid", "adaptive"])
@pytest.mark.parametrize("noise", [1e-4, 1e-5])
def test_compiled_parameter_query_keeps_every_digit_with_a_small_fitted_noise(layout, noise):
    """Throw-like data with noise 1e-4 or 1e-5 (large cluster precisions): the compiled
    query's cluster posterior agrees with the traced model's to 1e-12, batched and one
    row at a time, picks the same best cluster, and matches a 50-digit oracle."""
    from effect_networks.inference import fit, fit_em, infer_parameter
    from effect_networks.models.humanoid_throw import throw_data, throw_network

    net = throw_network((8, 8))
    if layout == "adaptive":
        target = dataclasses.replace(net.parameters[0], layout="adaptive")
        net = EffectNetwork(net.features, net.actions, (target,))
    targets, hits = _throw_like(4000, 0, noise)
    rows = throw_data(net, targets, hits)
    if layout == "grid":
        params = fit(net, rows).params
    else:
        params = fit_em(net, rows, steps=30).params
    query = inference.compile(net, params).parameter_query("target")
    assert float(query.whiten.abs().amax()) > 100  # precisions 1e4-1e5
    _, asked = _throw_like(400, 1, noise)
    asked = torch.from_numpy(asked)
    compiled = query.infer_parameter({"end.hit": asked})
    traced = infer_parameter(net, params, "target", {"end.hit": asked})
    torch.testing.assert_close(compiled.cluster_probs, traced.cluster_probs, atol=1e-12, rtol=0)
    assert torch.equal(compiled.best_cluster, traced.best_cluster)
    for i in range(0, 400, 20):
        one = query.infer_parameter({"end.hit": asked[i]})
        torch.testing.assert_close(
            one.cluster_probs[0], traced.cluster_probs[i], atol=1e-12, rtol=0
        )
        want = torch.tensor(_cluster_posterior_oracle(params, asked[i]), dtype=torch.float64)
        torch.testing.assert_close(one.cluster_probs[0], want, atol=1e-12, rtol=0)
        torch.testing.assert_close(compiled.cluster_probs[i], want, atol=1e-12, rtol=0)


def test_compiled_parameter_query_refuses_a_hit_with_no_probability_in_float64():
    """A hit ~1e156 standard deviations from every cluster (within the magnitude limit):
    its density underflows under every cluster; the compiled query, batched and one row,
    refuses the row by name as the traced one does, instead of answering NaN."""
    from effect_networks.inference import infer_parameter
    from effect_networks.models.params import NetworkParams

    net = _one_row_network()
    params = random_params(net, 0)
    narrow = {
        site: dataclasses.replace(params[site], scale_tril=1e-6 * params[site].scale_tril)
        for site in ("end.hit", "param.target")
    }
    params = NetworkParams(params.cpds | narrow, params.pseudo_count)
    query = inference.compile(net, params).parameter_query("target")
    hits = torch.tensor([[0.5, 1.0], [1e150, 0.0]], dtype=torch.float64)
    ev = {"end.hit": hits, "action": ["throw", "throw"]}
    for call in (
        lambda: query.infer_parameter(ev),
        lambda: query.infer_parameter({"end.hit": hits[1], "action": "throw"}),
        lambda: infer_parameter(net, params, "target", ev),
    ):
        with pytest.raises(ValueError, match=r"row \d has probability 0 under every"):
            call()
    ordinary = query.infer_parameter({"end.hit": hits[:1], "action": ["throw"]})
    assert abs(float(ordinary.cluster_probs.sum()) - 1) < 1e-12


@pytest.mark.parametrize(
    ("hit", "match"),
    [
        (np.array([0.3, 5j]), r"site 'end\.hit': complex numbers"),
        (torch.tensor([0.3 + 0j, 0.4]), r"site 'end\.hit': complex numbers"),
        ([0.3, 1e200], r"site 'end\.hit': row 0 .* beyond \+-1e\+150"),
        (np.array([[-1e151, 0.0]]), r"site 'end\.hit': row 0 .* beyond \+-1e\+150"),
    ],
)
def test_one_row_query_refuses_complex_and_huge_hits_as_encode_does(hit, match):
    """The one-row path reads numbers itself; what evidence refuses, it refuses too (the
    general path names the site), never reading 5j as 0 or answering beyond the limit."""
    import warnings

    net = _one_row_network()
    query = inference.compile(net, random_params(net, 1)).parameter_query("target")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ValueError, match=match):
            query.infer_parameter({"end.hit": hit, "action": "throw"})


def test_a_compiled_plan_of_a_large_world_takes_the_factored_route():
    world = switch_world(12, "sparse")
    compiled = inference.compile(world.net, world.params)
    got = compiled.plan(world.start, world.goal, 5)
    want = inference.plan(world.net, world.params, world.start, world.goal, 5)
    assert got.route == want.route == "projected" and got.success == want.success
    with pytest.raises(ValueError, match="route must be"):
        compiled.plan(world.start, world.goal, 5, route="quick")
