"""The compiled tables answer exactly what the traced model answers."""

import dataclasses

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from inference import infer_action
from inference.compiled import compile_discrete
from models import Continuous, EffectNetwork
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
    compiled = compile_discrete(net, params)
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
    from inference import infer_parameter
    from inference.compiled import compile_parameter_query
    from tests.inference.test_queries_mixed import NET

    params = random_params(NET, 21, unseen=0.2)
    query = compile_parameter_query(NET, params, "force")
    g = torch.Generator().manual_seed(1)
    n = 40
    ev = {
        "initial.visible": torch.randint(0, 2, (n,), generator=g),
        "initial.pos": torch.randn(n, 2, generator=g, dtype=torch.float64),
        "action": torch.randint(1, 3, (n,), generator=g),  # tap or push: both use the force
        "end.pos": 3 * torch.randn(n, 2, generator=g, dtype=torch.float64),
    }
    ev = NET.encode_indices(ev)
    a = query.infer(ev)
    b = infer_parameter(NET, params, "force", ev)
    torch.testing.assert_close(a.cluster_probs, b.cluster_probs, atol=1e-9, rtol=0)
    assert torch.equal(a.best_cluster, b.best_cluster)
    torch.testing.assert_close(a.mean, b.mean)
    torch.testing.assert_close(a.cov, b.cov)
    torch.testing.assert_close(a.unseen, b.unseen)


def test_compiled_parameter_query_with_one_shared_configuration():
    from inference import infer_parameter
    from inference.compiled import compile_parameter_query
    from tests.inference.test_queries_mixed import NET

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
    a = compile_parameter_query(NET, params, "force").infer(ev)
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
    fast = compile_discrete(net, params)
    a = fast.infer_action(ev, allowed=allowed)
    [(pattern, plan)] = fast.plans.items()
    assert plan.answers is not None
    slow = compile_discrete(net, params)
    slow.plans[pattern] = dataclasses.replace(plan, answers=None)
    b = slow.infer_action(ev, allowed=allowed)
    for name in ("probs", "log_evidence", "unseen"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), atol=1e-12, rtol=0)
    assert torch.equal(a.best, b.best) and a.best_names == b.best_names
