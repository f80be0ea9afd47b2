"""``explain`` over each time's hidden configurations against the dense route.

The dense route (:func:`inference.sequences.dense_explanation.explain_dense`) sums over
every state at every time; the structured one over the configurations of the features
each time hides. On small networks with partly observed demonstrations (end -> end
parents, an end-only outcome, a parameterised action whose clusters are summed out,
continuous features, a listed state space) every answer agrees to 1e-10. Past the dense
route's reach, a fully observed demonstration is each step's own question.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from effect_networks.inference import infer_action
from effect_networks.inference.sequences import explanation, hidden_steps
from effect_networks.inference.sequences.dense_explanation import explain_dense
from effect_networks.inference.sequences.explanation import Explanation, explain
from effect_networks.inference.sequences.hidden_steps import ProductStates, unique_rows
from effect_networks.inference.sequences.states import StateSpace
from effect_networks.models import Discrete, EffectNetwork, random_params
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.inference.sequences.demonstration_worlds import (
    OUTCOME_NET,
    PLAIN_NET,
    flip_world,
    uniform_prior,
)
from tests.networks import rich_net

RICH_NET = rich_net()


def assert_same(ours: Explanation, dense: Explanation) -> None:
    """Every field equal: numbers to 1e-10, indices and labels exactly."""
    for name in ("probs", "state_probs", "log_likelihood"):
        a, b = getattr(ours, name), getattr(dense, name)
        assert a.shape == b.shape, name
        assert torch.allclose(a, b, atol=1e-10, rtol=0), (name, (a - b).abs().max())
    for name in ("best", "path", "implausible"):
        assert torch.equal(getattr(ours, name), getattr(dense, name)), name
    for name in ("best_names", "actions", "features", "states"):
        assert getattr(ours, name) == getattr(dense, name), name


def draw_batch(data, net, n: int, steps: int, hide: float) -> dict:
    """``n`` demonstrations of ``steps`` steps, each discrete value hidden with ``hide``;
    continuous features with an initial node observed at every time."""
    batch = {}
    for f in net.features:
        if isinstance(f, Discrete):
            values = np.empty((n, steps + 1), dtype=object)
            for i in range(n):
                for t in range(steps + 1):
                    seen = (f.initial or t > 0) and data.draw(st.floats(0, 1)) >= hide
                    values[i, t] = data.draw(st.sampled_from(f.states)) if seen else None
            batch[f.name] = values
        else:
            seed = data.draw(st.integers(0, 2**16))
            batch[f.name] = np.random.default_rng(seed).normal(0, 1, (n, steps + 1, f.dim))
    return batch


@settings(max_examples=30, deadline=None)
@given(
    net=st.sampled_from([OUTCOME_NET, PLAIN_NET, RICH_NET]),
    seed=st.integers(0, 50),
    steps=st.integers(1, 3),
    hide=st.sampled_from([0.0, 0.3, 0.7]),
    data=st.data(),
)
@pytest.mark.filterwarnings("ignore::effect_networks.inference.OutsideTrainingData")
def test_equals_the_dense_route_on_partly_observed_batches(net, seed, steps, hide, data):
    params = random_params(net, seed)
    batch = draw_batch(data, net, 3, steps, hide)
    assert_same(explain(net, params, batch), explain_dense(net, params, batch))


@pytest.mark.filterwarnings("ignore::effect_networks.inference.OutsideTrainingData")
def test_equals_the_dense_route_with_a_prior_and_a_listed_state_space():
    """The hidden configurations are the listed states that agree with what a time shows;
    an action the prior rules out is ruled out exactly."""
    net = OUTCOME_NET
    params = random_params(net, 3)
    space = [("shut", "off"), ("open", "on"), ("locked", "off"), ("open", "off")]
    demo = [{"door": "shut"}, {"creak": True}, {"light": "off"}, {}]
    for prior in (None, [0.5, 0.5, 0.0]):
        ours = explain(net, params, demo, prior=prior, state_space=space)
        assert_same(ours, explain_dense(net, params, demo, prior=prior, state_space=space))


@pytest.mark.filterwarnings("ignore::effect_networks.inference.OutsideTrainingData")
def test_a_parameterised_action_with_everything_hidden_equals_the_dense_route():
    """Every discrete value hidden after the start: the clusters, the outcome and the
    latent states summed together, over every path."""
    net = RICH_NET
    params = random_params(net, 9)
    x = np.random.default_rng(1).normal(0, 1, (2, 4, 1))
    batch = {
        "door": np.array([["shut", None, None, "open"], [None, None, "open", None]], dtype=object),
        "lock": np.array([["off", None, "on", None], [None] * 4], dtype=object),
        "noise": np.array([[None, 2, None, 0], [None] * 4], dtype=object),
        "x": x,
    }
    assert_same(explain(net, params, batch), explain_dense(net, params, batch))


def test_fully_observed_twelve_features_is_each_steps_own_question(monkeypatch):
    """k = 12 binary features (4096 states, 13 actions): the dense route refuses; the
    structured one reads each step as infer_action does, and its state posterior is the
    observed states, held sparse."""
    net = flip_world(12)
    params = random_params(net, 0)
    rng = np.random.default_rng(0)
    states = {f.name: rng.random((2, 4)) < 0.5 for f in net.features}
    with pytest.raises(ValueError, match="exceeds"):
        explain_dense(net, params, states)
    result = explain(net, params, states)
    assert isinstance(result.states, ProductStates) and len(result.states) == 4096
    assert result.states == ProductStates(net.features) != ProductStates(net.features[1:])
    assert result.state_probs.is_sparse and result.state_probs.shape == (2, 4, 4096)
    dense_probs = result.state_probs.to_dense()
    assert torch.allclose(
        dense_probs.sum(-1), torch.ones(2, 4, dtype=dense_probs.dtype), atol=1e-12
    )
    uniform = uniform_prior(net, params)
    log_likelihood = 0.0
    for t in range(3):
        ev = {f"initial.{f}": [bool(v[0, t])] for f, v in states.items()}
        ev |= {f"end.{f}": [bool(v[0, t + 1])] for f, v in states.items()}
        step = infer_action(net, uniform, ev)
        assert torch.allclose(result.probs[0, t], step.probs[0], atol=1e-10)
        assert int(result.best[0, t]) == int(step.probs[0].argmax())
        start = infer_action(net, uniform, {k: v for k, v in ev.items() if "initial" in k})
        log_likelihood += float(step.log_evidence[0] - start.log_evidence[0])
    assert float(result.log_likelihood[0]) == pytest.approx(log_likelihood, abs=1e-10)
    monkeypatch.setattr(explanation, "TABLE_ELEMENTS", 1)  # one demonstration a part
    parts = explain(net, params, states)
    assert torch.equal(parts.state_probs.to_dense(), dense_probs)
    assert torch.equal(parts.probs, result.probs) and torch.equal(parts.path, result.path)
    assert result.path_labels(0) == [
        {f: bool(v[0, t]) for f, v in states.items()} for t in range(4)
    ]


def test_a_step_past_the_budget_is_refused_naming_it(monkeypatch):
    net = flip_world(6)
    params = random_params(net, 0)
    rng = np.random.default_rng(0)
    states = {f.name: (rng.random((1, 3)) < 0.5).astype(object) for f in net.features}
    for f in ("f0", "f1", "f2"):
        states[f][0, 1] = None  # 8 configurations in the middle
    monkeypatch.setattr(hidden_steps, "MAX_STEP_TABLE", 8 * 7 * 1 - 1)
    with pytest.raises(ValueError, match="demonstration 0 step 0: 1 x 7 x 8 = 56 .* 55"):
        explain(net, params, states)
    monkeypatch.setattr(hidden_steps, "MAX_STEP_TABLE", 7)
    with pytest.raises(ValueError, match="time 1 hides 3 state features, 8 configurations"):
        explain(net, params, states)


def test_a_state_past_what_an_index_numbers_is_refused():
    net = flip_world(62)
    states = {f.name: np.zeros((1, 2), dtype=bool) for f in net.features}
    with pytest.raises(ValueError, match="past the 2\\*\\*62 a state's index can number"):
        explain(net, random_params(net, 0), states)


def test_no_demonstrations_past_the_dense_route_give_sparse_empty_answers():
    net = flip_world(12)
    states = {f.name: np.zeros((0, 3), dtype=object) for f in net.features}
    result = explain(net, random_params(net, 0), states)
    assert result.state_probs.shape == (0, 3, 4096) and result.state_probs.is_sparse
    assert result.probs.shape == (0, 2, 13)


def test_product_states_are_the_state_space_in_order():
    net = EffectNetwork(
        features=(Discrete("a", ("x", "y", "z")), Discrete("b", (0, 1)), Discrete("c", ("p", "q"))),
        actions=("go",),
    )
    states = ProductStates([f for f in net.features])
    assert tuple(states) == StateSpace.of(net).states
    assert states[-1] == ("z", 1, "q") and states[1:3] == StateSpace.of(net).states[1:3]
    with pytest.raises(IndexError):
        states[len(states)]


@given(
    rows=st.lists(st.tuples(st.integers(0, 3), st.integers(0, 6), st.integers(0, 6)), max_size=30)
)
def test_unique_rows_by_numbers_equal_torch_unique(rows):
    rows = torch.tensor(rows, dtype=torch.long).reshape(-1, 3)
    fast = unique_rows(rows, (4, 7, 7))
    slow = unique_rows(rows, (4, 1 << 31, 1 << 31))  # past an int64: torch.unique
    assert torch.equal(fast[0], slow[0]) and torch.equal(fast[1], slow[1])
    assert torch.equal(fast[0][fast[1]], rows)
