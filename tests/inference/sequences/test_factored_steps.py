"""The factored step model against the dense transitions it factors.

The dense tensor of :func:`~inference.sequences.transition_tables.transitions` is itself
checked against a brute force over the traced model's joint (test_transition_tables);
here every entry the factors give, their unseen shares and their relevant features are
checked against it, on networks with end -> end parents, end-only features, clusters,
a continuous context and configurations no row reached.
"""

from __future__ import annotations

import itertools

import pytest
import torch
from effect_networks.experiments.switch_worlds import switch_world
from effect_networks.inference import fit
from effect_networks.inference.sequences.factored_planning import _Backup
from effect_networks.inference.sequences.factored_steps import step_model
from effect_networks.inference.sequences.states import ProjectedSpace
from effect_networks.inference.sequences.transition_tables import transitions
from effect_networks.models import random_params
from hypothesis import HealthCheck, given, settings

from tests.networks import declared_networks, rich_net, rich_rows


def _check_against_dense(net, params, **kw):
    t = transitions(net, params, **kw)
    model = step_model(net, params, **kw)
    assert model.actions == t.actions
    torch.testing.assert_close(model.dense(), t.probs, rtol=0, atol=1e-12)
    space = ProjectedSpace(model.features, model.features)
    unseen = _Backup(model, space, {}).unseen()
    torch.testing.assert_close(unseen, t.unseen, rtol=0, atol=1e-12)
    s = t.space.states
    for i, a, j in itertools.islice(
        itertools.product(range(len(s)), range(len(t.actions)), range(len(s))), 0, None, 7
    ):
        assert model.prob(s[i], a, s[j]) == pytest.approx(float(t.probs[i, a, j]), abs=1e-12)


@pytest.mark.parametrize("mode", ["integrate", "clusters"])
def test_the_factors_give_the_dense_transitions_with_clusters_and_a_context(mode):
    net = rich_net()
    params = fit(net, rich_rows(net, 400, 0)).params
    _check_against_dense(net, params, given={"x": [0.3]}, parameter_values=mode)
    model = step_model(net, params, given={"x": [0.3]}, parameter_values=mode)
    assert "end.noise" in model.latent
    assert ("cluster.force" in model.latent) == (mode == "integrate")


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(declared_networks())
def test_the_factors_give_the_dense_transitions_on_declared_networks(net):
    params = random_params(net, 3, unseen=0.3)
    _check_against_dense(net, params)


def test_relevant_features_follow_the_declared_parents():
    world = switch_world(12, "sparse")
    model = step_model(world.net, world.params)
    assert model.relevant(["f0"]) == ("f0", "f1")
    assert model.relevant(["f0", "f2"]) == ("f0", "f1", "f2", "f3")
    chain = step_model(*(lambda w: (w.net, w.params))(switch_world(9, "coupled")))
    assert chain.relevant(["f6"]) == ("f6", "f7", "f8")
    with pytest.raises(ValueError, match="not state features"):
        model.relevant(["nope"])


def test_the_step_model_is_linear_in_the_tables_at_64_features():
    world = switch_world(64, "sparse")
    model = step_model(world.net, world.params)
    assert len(model.factors) == 64
    assert max(f.log_table.numel() for f in model.factors) == 2 * 65 * 2 * 2
    start, after = world.start, ("on",) + world.start[1:]
    assert model.prob(start, "flip_0", after) == pytest.approx(0.9)


def test_the_dense_refusal_states_its_size_and_the_factored_way():
    world = switch_world(14, "sparse")
    with pytest.raises(ValueError, match=r"GiB of float64.*step_model"):
        transitions(world.net, world.params)
    bigger = switch_world(17, "sparse")
    with pytest.raises(ValueError, match="step_model"):
        transitions(bigger.net, bigger.params)


def test_a_step_model_of_some_features_keeps_what_they_read_and_refuses_the_rest():
    world = switch_world(12, "sparse")
    part = step_model(world.net, world.params, features=["f4"])
    assert part.kept == ("f4", "f5") and len(part.factors) == 2
    with pytest.raises(ValueError, match="keeps the steps of"):
        part.dense()
    with pytest.raises(ValueError, match="keeps the steps of"):
        part.relevant(["f0"])
