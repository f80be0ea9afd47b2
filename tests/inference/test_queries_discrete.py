"""Exact queries on discrete networks against brute-force enumeration and pgmpy."""

import itertools

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from inference import imitation_check, infer_action, predict
from models.declaration import DTYPE
from tests.helpers import discrete_network, random_params


def brute_joint(net, params):
    """p(initial..., action, end...) as a dict over full assignments, from the tables."""
    names = [f.name for f in net.features]
    cards = [f.cardinality for f in net.features]
    joint = {}
    for init in itertools.product(*[range(k) for k in cards]):
        for a in range(len(net.actions)):
            for end in itertools.product(*[range(k) for k in cards]):
                p = float(params["action"].probs[a])
                for name, v in zip(names, init, strict=True):
                    p *= float(params[f"initial.{name}"].probs[v])
                for name, v in zip(names, end, strict=True):
                    p *= float(params[f"end.{name}"].probs[(*init, a, v)])
                joint[(init, a, end)] = p
    return joint


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
    pred = predict(
        net, params, {"initial.f0": torch.tensor([1, 0]), "action": ["a2", "a2"]}
    )
    assert pred.unseen.tolist() == [1.0, 0.0]


def test_ties_go_to_the_lowest_index_whatever_the_rounding():
    from inference.queries import first_best

    score = torch.tensor(
        [[0.2, 0.4, 0.4 * (1 + 1e-12), 0.1], [0.5, 0.5 * (1 - 1e-12), 0.0, 0.0]], dtype=DTYPE
    )
    assert first_best(score).tolist() == [1, 0]
    assert first_best(torch.tensor([[0.1, 0.3, 0.2]], dtype=DTYPE)).tolist() == [1]
