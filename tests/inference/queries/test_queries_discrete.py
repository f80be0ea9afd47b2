"""Exact queries on discrete networks against brute-force enumeration and pgmpy."""

import itertools

import pytest
import torch
from effect_networks.inference import imitation_check, infer_action, predict
from effect_networks.models import Discrete, EffectNetwork
from effect_networks.models.declaration import DTYPE
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.helpers import brute_joint, discrete_network, random_params


def brute_posterior(joint, keep, target):
    """p(target | keep) where keep(init, a, end) filters assignments."""
    total = sum(p for k, p in joint.items() if keep(*k))
    out = {}
    for k, p in joint.items():
        if keep(*k):
            out[target(*k)] = out.get(target(*k), 0.0) + p / total
    return out


@settings(max_examples=25, deadline=None)
@given(
    cards=st.lists(st.integers(2, 3), min_size=1, max_size=3),
    n_actions=st.integers(2, 4),
    seed=st.integers(0, 10_000),
    data=st.data(),
)
def test_action_posterior_equals_brute_force(cards, n_actions, seed, data):
    net = discrete_network(cards, n_actions)
    params = random_params(net, seed)
    joint = brute_joint(net, params)
    init = tuple(data.draw(st.integers(0, k - 1)) for k in cards)
    observed = data.draw(st.lists(st.integers(0, len(cards) - 1), unique=True, max_size=len(cards)))
    end_obs = {i: data.draw(st.integers(0, cards[i] - 1)) for i in observed}
    evidence = {f"initial.f{i}": torch.tensor([v]) for i, v in enumerate(init)}
    evidence |= {f"end.f{i}": torch.tensor([v]) for i, v in end_obs.items()}
    post = infer_action(net, params, evidence)
    expect = brute_posterior(
        joint,
        lambda i, a, e: i == init and all(e[k] == v for k, v in end_obs.items()),
        lambda i, a, e: a,
    )
    want = torch.tensor([expect[a] for a in range(n_actions)], dtype=DTYPE)
    torch.testing.assert_close(post.probs[0], want, atol=1e-6, rtol=0)
    assert post.best[0] == int(want.argmax())


@settings(max_examples=25, deadline=None)
@given(
    cards=st.lists(st.integers(2, 3), min_size=1, max_size=3),
    seed=st.integers(0, 10_000),
    data=st.data(),
)
def test_predict_and_imitation_equal_brute_force(cards, seed, data):
    net = discrete_network(cards, 3)
    params = random_params(net, seed)
    joint = brute_joint(net, params)
    init = tuple(data.draw(st.integers(0, k - 1)) for k in cards)
    action = data.draw(st.integers(0, 2))
    evidence = {f"initial.f{i}": torch.tensor([v]) for i, v in enumerate(init)} | {
        "action": [net.actions[action]]
    }
    pred = predict(net, params, evidence)
    for i, k in enumerate(cards):
        expect = brute_posterior(
            joint, lambda ii, a, e: ii == init and a == action, lambda ii, a, e, i=i: e[i]
        )
        want = torch.tensor([expect.get(s, 0.0) for s in range(k)], dtype=DTYPE)
        torch.testing.assert_close(pred.discrete[f"f{i}"][0], want, atol=1e-6, rtol=0)
    # imitation: log-likelihood of a full end state and its tail probability
    end = tuple(data.draw(st.integers(0, k - 1)) for k in cards)
    check = imitation_check(
        net, params, evidence | {f"end.f{i}": torch.tensor([v]) for i, v in enumerate(end)}
    )
    outcomes = brute_posterior(
        joint, lambda ii, a, e: ii == init and a == action, lambda ii, a, e: e
    )
    p_obs = outcomes[end]
    assert abs(float(check.log_likelihood[0].exp()) - p_obs) < 1e-6
    tail = sum(p for p in outcomes.values() if p > p_obs + 1e-12)
    assert abs(float(check.surprise[0]) - tail) < 1e-6


def test_batched_rows_equal_one_at_a_time():
    net = discrete_network([3, 2], 4)
    params = random_params(net, 7)
    g = torch.Generator().manual_seed(0)
    ev = {
        "initial.f0": torch.randint(0, 3, (50,), generator=g),
        "initial.f1": torch.randint(0, 2, (50,), generator=g),
    }
    ev["end.f0"] = torch.randint(0, 3, (50,), generator=g)
    batched = infer_action(net, params, ev).probs
    single = torch.cat(
        [
            infer_action(net, params, {k: v[i : i + 1] for k, v in ev.items()}).probs
            for i in range(50)
        ]
    )
    torch.testing.assert_close(batched, single)


def test_matches_pgmpy_variable_elimination():
    pgmpy = pytest.importorskip("pgmpy")
    from pgmpy.factors.discrete import TabularCPD
    from pgmpy.inference import VariableElimination

    try:
        from pgmpy.models import DiscreteBayesianNetwork as BN
    except ImportError:  # older pgmpy
        from pgmpy.models import BayesianNetwork as BN
    assert pgmpy
    net = discrete_network([3, 2], 5)
    params = random_params(net, 11)
    names = {"initial.f0": "i0", "initial.f1": "i1", "action": "a", "end.f0": "e0", "end.f1": "e1"}
    parents = ["i0", "i1", "a"]
    bn = BN([(p, e) for p in parents for e in ("e0", "e1")])
    for site, var in names.items():
        probs = params[site].probs.numpy()
        if site.startswith("end."):
            cards = list(probs.shape[:-1])
            values = probs.reshape(-1, probs.shape[-1]).T
            bn.add_cpds(
                TabularCPD(var, probs.shape[-1], values, evidence=parents, evidence_card=cards)
            )
        else:
            bn.add_cpds(TabularCPD(var, probs.shape[-1], probs.reshape(-1, 1)))
    ve = VariableElimination(bn)
    for i0, i1, e1 in itertools.product(range(3), range(2), range(2)):
        ours = infer_action(
            net,
            params,
            {
                "initial.f0": torch.tensor([i0]),
                "initial.f1": torch.tensor([i1]),
                "end.f1": torch.tensor([e1]),
            },
        )
        theirs = ve.query(["a"], evidence={"i0": i0, "i1": i1, "e1": e1}, show_progress=False)
        torch.testing.assert_close(
            ours.probs[0], torch.as_tensor(theirs.values, dtype=DTYPE), atol=1e-6, rtol=0
        )
        best = ve.map_query(["a"], evidence={"i0": i0, "i1": i1, "e1": e1}, show_progress=False)
        assert int(ours.best[0]) == int(best["a"])


def test_unseen_configuration_is_reported():
    net = discrete_network([2], 3)
    params = random_params(net, 3)
    n = params["end.f0"].n.clone()
    n[1, 2] = 0  # initial f0 = 1, action a2: never seen
    params.cpds["end.f0"] = type(params["end.f0"])(params["end.f0"].probs, n)
    post = infer_action(net, params, {"initial.f0": torch.tensor([1]), "end.f0": torch.tensor([0])})
    assert post.unseen[0].tolist() == [0.0, 0.0, 1.0]
    assert post.best[0] != 2
    pred = predict(net, params, {"initial.f0": torch.tensor([1, 0]), "action": ["a2", "a2"]})
    assert pred.unseen.tolist() == [1.0, 0.0]


def test_ties_go_to_the_lowest_index_whatever_the_rounding():
    from effect_networks.inference.queries.batching import first_best

    score = torch.tensor(
        [[0.2, 0.4, 0.4 * (1 + 1e-12), 0.1], [0.5, 0.5 * (1 - 1e-12), 0.0, 0.0]], dtype=DTYPE
    )
    assert first_best(score).tolist() == [1, 0]
    assert first_best(torch.tensor([[0.1, 0.3, 0.2]], dtype=DTYPE)).tolist() == [1]


def test_allowed_actions_by_name_and_mask():
    from effect_networks import inference

    net = discrete_network([2], 3)
    params = random_params(net, 4)
    ev = {"initial.f0": [1, 0]}
    compiled = inference.compile(net, params).action_tables
    for run in (
        lambda **k: infer_action(net, params, ev, **k),
        lambda **k: compiled.infer_action(ev, **k),
    ):
        assert run(allowed=["a2"]).best_names == ("a2", "a2")
        assert run(allowed="a1").best_names == ("a1", "a1")
        per_row = torch.tensor([[True, False, False], [False, False, True]])
        assert run(allowed=per_row).best_names == ("a0", "a2")
        with pytest.raises(ValueError, match="permits no action"):
            run(allowed=torch.zeros(3, dtype=torch.bool))
        with pytest.raises(ValueError, match="permits no action in row 1"):
            run(allowed=torch.tensor([[True, False, False], [False, False, False]]))
        with pytest.raises(ValueError, match=r"allowed has shape \(2,\); expected \(3,\)"):
            run(allowed=torch.tensor([True, False]))
        with pytest.raises(ValueError, match="unknown action 'fly'"):
            run(allowed=["fly"])


def test_empty_batches_give_empty_results():
    from effect_networks.inference import infer_parameter

    from effect_networks import inference
    from tests.networks import NET

    net = discrete_network([2, 3], 4)
    params = random_params(net, 0)
    none = {"initial.f0": [], "initial.f1": []}
    post = infer_action(net, params, none | {"end.f1": []})
    assert post.probs.shape == (0, 4) and post.best.shape == (0,) and post.best_names == ()
    assert inference.compile(net, params).action_tables.infer_action(none).probs.shape == (0, 4)
    pred = predict(net, params, none | {"action": []})
    assert pred.discrete["f0"].shape == (0, 2) and pred.discrete["f1"].shape == (0, 3)
    assert pred.unseen.shape == (0,)
    check = imitation_check(net, params, none | {"action": [], "end.f0": []})
    assert check.surprise.shape == (0,) and check.log_likelihood.shape == (0,)

    mixed = random_params(NET, 0)
    ev = {"initial.visible": [], "initial.pos": torch.zeros(0, 2), "end.pos": torch.zeros(0, 2)}
    ev |= {"action": []}
    par = infer_parameter(NET, mixed, "force", ev)
    assert par.mean.shape == (0, 1) and par.cov.shape == (0, 1, 1)
    assert par.cluster_probs.shape == (0, 3)
    par = inference.compile(NET, mixed).parameter_query("force").infer_parameter(ev)
    assert par.mean.shape == (0, 1)
    pred = predict(NET, mixed, ev | {"param.force": torch.zeros(0, 1)})
    assert pred.discrete["visible"].shape == (0, 2)
    assert pred.continuous == {}
    mix = predict(NET, mixed, {"initial.visible": [], "initial.pos": torch.zeros(0, 2)})
    assert mix.continuous["pos"].mean.shape == (0, 2)


def test_discrete_predictions_by_state_name():
    net = EffectNetwork((Discrete("door", ("shut", "open")),), ("wait", "pull"))
    params = random_params(net, 1)
    pred = predict(net, params, {"initial.door": ["shut", "open"], "action": ["pull", "pull"]})
    torch.testing.assert_close(pred.prob("door", "open"), pred.discrete["door"][:, 1])
    assert pred.most_likely("door") == tuple(
        ("shut", "open")[i] for i in pred.discrete["door"].argmax(-1).tolist()
    )
    with pytest.raises(ValueError, match="no state 'ajar'"):
        pred.prob("door", "ajar")
    post = infer_action(net, params, {"initial.door": ["shut"], "end.door": ["open"]})
    torch.testing.assert_close(post.prob("pull"), post.probs[:, 1])


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 10_000), zero_n=st.sampled_from([0.0, 0.3]), data=st.data())
def test_answers_do_not_depend_on_the_row_chunks(seed, zero_n, data):
    """Rows are enumerated in chunks of ``CHUNK_ELEMENTS``: chunks of one row give the
    same answers (posterior, evidence, unseen mass, best, flags) as one chunk of all."""
    from unittest import mock

    import effect_networks.inference.exact.enumeration as enumeration

    net = discrete_network([3, 2], 4)
    params = random_params(net, seed, unseen=zero_n)
    g = torch.Generator().manual_seed(seed)
    given_sites = data.draw(
        st.sampled_from(
            [("end.f0", "end.f1"), ("initial.f0", "end.f1"), ("initial.f0", "initial.f1")]
        )
    )
    sizes = {"initial.f0": 3, "initial.f1": 2, "end.f0": 3, "end.f1": 2}
    ev = {s: torch.randint(0, sizes[s], (9,), generator=g) for s in given_sites}
    whole = infer_action(net, params, ev)
    with mock.patch.object(enumeration, "CHUNK_ELEMENTS", 1):  # one row per chunk
        assert len(enumeration.row_chunks(9, 24)) == 9
        rows = infer_action(net, params, ev)
    for name in ("probs", "log_evidence", "unseen"):
        torch.testing.assert_close(getattr(rows, name), getattr(whole, name), atol=1e-14, rtol=0)
    assert torch.equal(rows.best, whole.best)
    assert torch.equal(rows.implausible, whole.implausible)
