"""experiments.arrival_transfer: one field's next state, the models against the physics."""

from dataclasses import dataclass, replace

import numpy as np
import pytest
import torch
from effect_networks.experiments.arrival_transfer import (
    OTHER,
    TRANSFER_SEED_BASE,
    WAYS,
    measure_transfer,
)
from effect_networks.experiments.cans import can_dataset
from effect_networks.experiments.combined import CombinedConfig, build_world, transition_model
from effect_networks.inference.sequences.dynamic_programming import exact_plan
from effect_networks.sim2d import geometry
from effect_networks.sim2d.combined import settle
from effect_networks.sim2d.field_throws import throw_at_field

HORIZON = 2


@pytest.fixture(scope="module")
def planned(tiny_data_dir):
    """The tiny world, the top-three scenario's states, chained model and exact plan."""
    data = can_dataset(tiny_data_dir, "tiny", progress=False)
    config = CombinedConfig(scale="tiny", data_dir=tiny_data_dir, n_throws=300, bins=2)
    world, _ = build_world(config, data)
    start = geometry.FULL_PYRAMID
    goal = start & ~geometry.cans_to_mask(geometry.TOP_THREE)
    states = sorted(s for s in world.stable if s & goal == goal)
    t = transition_model(world, states)
    plan = exact_plan(t, states.index(goal), HORIZON, allowed=t.sum(-1) > 0)
    first = int(plan.policy[HORIZON, states.index(start)])
    return world, data, start, states, t, plan, first


def measure(planned, field=None, **kwargs):
    world, _, start, states, t, plan, first = planned
    kwargs = {"repeats": 3, "seed": 0} | kwargs
    field = first if field is None else field
    return measure_transfer(world, start, field, states, t, plan.value[HORIZON - 1], **kwargs)


def test_every_way_is_a_distribution_and_the_distances_lie_in_0_1(planned):
    got = measure(planned)
    assert set(got.frequencies) == set(WAYS) == set(got.values) == set(got.kept)
    for way, freq in got.frequencies.items():
        assert sum(freq.values()) == pytest.approx(1.0, abs=1e-12)
        assert all(p >= 0 for p in freq.values())
        assert 0.0 <= got.kept[way] <= 1.0 + 1e-12
        assert -1e-12 <= got.values[way] <= 1.0 + 1e-12
    for model, distances in got.tv.items():
        assert distances[model] == 0.0
        assert all(0.0 <= d <= 1.0 + 1e-12 for d in distances.values())


def test_the_planner_row_is_the_chained_model_and_its_value_the_planned_success(planned):
    world, _, start, states, t, plan, first = planned
    got = measure(planned)
    row = t[states.index(start), first]
    for j, s in enumerate(states):
        assert got.frequencies["planner"].get(s, 0.0) == pytest.approx(float(row[j]), abs=1e-12)
    predicted = float(plan.value[HORIZON, states.index(start)])
    assert got.values["planner"] == pytest.approx(predicted, abs=1e-12)


@dataclass
class ExactRobot:
    """A robot that hits exactly where it is asked to (its aim is the hit itself)."""

    rng: np.random.Generator
    noise: None = None

    def aim(self, hits):
        return np.asarray(hits, float)

    def hit_distribution(self, aims):
        return np.asarray(aims, float), np.tile(np.eye(2) * 1e-16, (len(aims), 1, 1))


def test_the_can_network_row_is_the_chained_model_of_a_robot_that_hits_exactly(planned):
    """With a hit 1e-8 m sure and sharp boundaries the chain reads the aim as its own field:
    the transition model's row is then the can network's row for that field alone."""
    world, _, start, states, *_ = planned
    exact = replace(world, robot=ExactRobot(world.robot.rng), boundary_sd=0.0, _heights={})
    heights = exact.heights(start)
    fields = np.flatnonzero(world.can.throwable.numpy())
    gaps = np.abs(heights[fields][:, None] - heights[fields][None, :]) + np.eye(len(fields))
    field = int(fields[gaps.min(-1).argmax()])  # the field farthest from its neighbours' heights
    assert gaps.min(-1).max() > 1e-4
    t = transition_model(exact, states)
    got = measure_transfer(
        exact, start, field, states, t, torch.zeros(len(states)), repeats=1, seed=0
    )
    row = t[states.index(start), field]
    for j, s in enumerate(states):
        assert got.frequencies["can_network"].get(s, 0.0) == pytest.approx(float(row[j]), abs=1e-12)


def test_without_jitter_the_data_sets_replays_are_its_deterministic_throw(planned):
    world, _, start, states, t, plan, first = planned
    still = replace(world, jitter=0.0)
    got = measure_transfer(still, start, first, states, t, plan.value[HORIZON - 1], repeats=3)
    end = settle(throw_at_field(start, first, world.can.angle).end_config, world.stable)
    assert got.frequencies["dataset_throw"] == {end if end in states else OTHER: 1.0}
    assert len(got.frequencies["robot_throw"]) == 1  # noise-free robot, no jitter


def test_reproducible_fresh_seeds_and_the_experiments_rng_untouched(planned):
    world, data = planned[:2]
    before = world.robot.rng.bit_generator.state
    a, b = measure(planned, seed=5), measure(planned, seed=5)
    assert a.as_dict() == b.as_dict()
    assert world.robot.rng.bit_generator.state == before
    # the replays' aim seeds are none of the data set's
    words = np.random.SeedSequence(
        [TRANSFER_SEED_BASE, 5, planned[2], planned[6], world.can.angle]
    ).generate_state(3, dtype=np.uint32)
    assert not set(words.tolist()) & set(data.seed.tolist())


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"field": 3}, "cannot be thrown"),  # the bottom row: never throwable
        ({"field": 195}, "field = 195"),
        ({"repeats": 0}, "repeats = 0"),
        ({"seed": -1}, "seed = -1"),
    ],
)
def test_bad_input_names_the_argument(planned, change, match):
    with pytest.raises(ValueError, match=match):
        measure(planned, **change)


def test_a_state_outside_the_plan_is_refused(planned):
    world, _, start, states, t, plan, first = planned
    with pytest.raises(ValueError, match="plan's states"):
        measure_transfer(world, 0, first, states, t, plan.value[HORIZON - 1], repeats=1)
