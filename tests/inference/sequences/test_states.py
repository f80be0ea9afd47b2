"""The state space of a network: states as label tuples, indices, selections."""

from __future__ import annotations

import itertools

import pytest
import torch
from effect_networks.inference.sequences.states import StateSpace, state_features
from effect_networks.models import Continuous, Discrete, EffectNetwork


def door_net() -> EffectNetwork:
    return EffectNetwork(
        features=(
            Discrete("door", ("shut", "open")),
            Continuous("angle", 1),
            Discrete("lock", ("off", "on", "jammed")),
            Discrete("noise", (False, True), initial=False),
        ),
        actions=("push", "unlock", "wait"),
    )


def test_states_are_the_product_of_the_state_features_in_feature_order():
    net = door_net()
    space = StateSpace.of(net)
    assert [f.name for f in state_features(net)] == ["door", "lock"]
    assert space.names == ("door", "lock")
    expected = list(itertools.product(("shut", "open"), ("off", "on", "jammed")))
    assert list(space) == expected
    for i, s in enumerate(expected):
        assert space.index_of(s) == i
        assert space.index_of(dict(zip(space.names, s, strict=True))) == i
        assert space.labels(i) == dict(zip(space.names, s, strict=True))
        assert [
            f.states[k] for f, k in zip(space.features, space.index[i].tolist(), strict=True)
        ] == list(s)


def test_a_subset_keeps_its_order_and_refuses_states_outside_it():
    net = door_net()
    space = StateSpace.of(net, [{"door": "open", "lock": "on"}, ("shut", "off")])
    assert space.states == (("open", "on"), ("shut", "off"))
    assert space.index_of(("shut", "off")) == 1
    assert ("open", "off") not in space
    with pytest.raises(ValueError, match="not in this state space"):
        space.index_of(("open", "off"))
    with pytest.raises(ValueError, match="repeats"):
        StateSpace.of(net, [("shut", "off"), ("shut", "off")])
    with pytest.raises(ValueError, match="no state 'ajar'"):
        StateSpace.of(net, [("ajar", "off")])
    with pytest.raises(ValueError, match="missing"):
        StateSpace.of(net, [{"door": "open"}])


def test_masks_and_distributions_from_partial_labels_and_predicates():
    space = StateSpace.of(door_net())
    shut = space.mask({"door": "shut"})
    assert shut.tolist() == [s[0] == "shut" for s in space]
    both = space.mask({"door": "open", "lock": "on"})
    assert both.nonzero().flatten().tolist() == [space.index_of(("open", "on"))]
    pred = space.mask(lambda s: s["lock"] != "off")
    assert pred.tolist() == [s[1] != "off" for s in space]
    d = space.distribution({"door": "shut"})
    assert torch.allclose(d, shut.double() / 3)
    prior = torch.arange(1.0, 7.0, dtype=torch.float64)
    d = space.distribution({"door": "open"}, prior)
    assert torch.allclose(d, torch.where(~shut, prior, 0.0) / prior[~shut].sum())
    full = space.distribution(("open", "jammed"))
    assert full[space.index_of(("open", "jammed"))] == 1 and full.sum() == 1
    with pytest.raises(ValueError, match="not a state feature"):
        space.mask({"angle": 0.0})
    with pytest.raises(ValueError, match="picks no state"):
        space.distribution(lambda s: False)


def test_a_network_without_a_state_is_refused_by_name():
    net = EffectNetwork(features=(Continuous("x", 1),), actions=("a", "b"))
    with pytest.raises(ValueError, match="no state"):
        StateSpace.of(net)
