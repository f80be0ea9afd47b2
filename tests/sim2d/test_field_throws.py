"""Tests of throws at fields (sim2d/field_throws.py): kinematics, outcomes, bad input."""

import math

import numpy as np
import pytest
from effect_networks.sim2d import field_throws, geometry, materials
from effect_networks.sim2d.configurations import stable_configurations
from hypothesis import given, settings
from hypothesis import strategies as st

FULL = geometry.FULL_PYRAMID
BOTTOM_ROW = geometry.cans_to_mask([0, 1, 2, 3])


def field(row: int, column: int) -> int:
    return row * geometry.N_COLUMNS + column


# --- kinematics ----------------------------------------------------------------------------


@pytest.mark.parametrize("angle", [0, 1, 2])
def test_launch_state_parabola_passes_the_field_centre(angle):
    for f in [field(3, 0), field(7, 8), field(12, 14)]:
        (x0, z0), (vx0, vz0) = field_throws.launch_state(f, angle)
        assert x0 == geometry.ENTRY_X
        t = (geometry.field_centres()[f, 0] - x0) / vx0
        z = z0 + vz0 * t - 0.5 * materials.GRAVITY * t * t
        assert math.isclose(z, geometry.field_centres()[f, 1], abs_tol=1e-12)
        assert np.allclose((vx0, vz0 - materials.GRAVITY * t), geometry.ANGLES[angle])


def test_throwable_fields():
    table = np.array([[field_throws.is_throwable(f, a) for a in range(3)] for f in range(195)])
    assert not table[: geometry.N_COLUMNS].any(), "the bottom row lies below the ball's radius"
    assert table[geometry.N_COLUMNS :, 1].all(), "descending throws come from above"
    assert table[field(1, 0), 0] and table[field(12, 14), 2]
    assert not table[field(1, 14), 2], "low ascending throws far away pass below the table"


# --- throws: outcomes ---------------------------------------------------------------------


def test_same_throw_same_seed_same_outcome():
    a = field_throws.throw_at_field(FULL, field(6, 4), 1, jitter=0.003, seed=123)
    b = field_throws.throw_at_field(FULL, field(6, 4), 1, jitter=0.003, seed=123)
    assert a == b
    assert a.hit_any_can and not a.timed_out


def test_jitter_changes_aim_by_millimetres():
    nominal = field_throws.launch_state(field(6, 4), 0)[0]
    offset = field_throws.aim_offset(0.003, 7)
    assert np.all(np.abs(offset) <= 0.009) and np.any(offset != 0)
    assert np.array_equal(field_throws.aim_offset(0.003, 7), offset)
    raised = field_throws.launch_state(field(6, 4), 0, offset=(0.0, offset[1]))[0]
    np.testing.assert_allclose(raised - nominal, [0.0, offset[1]], atol=1e-15)


def test_a_miss_changes_nothing():
    # The bottom row stands; a flat throw at row 8 flies over it.
    o = field_throws.throw_at_field(BOTTOM_ROW, field(8, 7), 0, jitter=0.003, seed=1)
    assert not o.hit_any_can and o.thrown_off == 0
    assert o.end_config == o.start_config == BOTTOM_ROW and o.count_after == o.count_before == 4
    # A ball well above the full pyramid.
    o = field_throws.play_ball(FULL, (geometry.ENTRY_X, 0.85), (7.0, 0.0))
    assert not o.hit_any_can and o.end_config == FULL and not o.timed_out
    assert o.sim_time < 0.2, "a miss stops as soon as the ball has passed every can"


def test_low_throw_at_near_bottom_can_brings_down_what_it_supports():
    o = field_throws.throw_at_field(FULL, field(1, 0), 0)
    assert o.touched & 1, "the ball hits can 0 first"
    supported_by_0 = geometry.cans_to_mask([0, 4, 7, 9])  # 4 rests on 0, 7 on 4, 9 on 7
    assert o.thrown_off & supported_by_0 == supported_by_0
    # With only can 0 and the cans resting on it (and their other supporters) standing:
    config = geometry.cans_to_mask([0, 1, 4])
    o = field_throws.throw_at_field(config, field(1, 0), 0)
    assert o.thrown_off & geometry.cans_to_mask([0, 4]) == geometry.cans_to_mask([0, 4])


def test_top_throw_takes_the_top_can():
    o = field_throws.throw_at_field(FULL, field(12, 7), 1)
    assert o.thrown_off >> 9 & 1
    assert o.thrown_off & BOTTOM_ROW == 0, "a descending throw at the top leaves the bottom row"


@settings(max_examples=15, deadline=None)
@given(
    config=st.sampled_from(stable_configurations()),
    fld=st.integers(geometry.N_COLUMNS, geometry.N_FIELDS - 1),
    seed=st.integers(0, 2**31),
)
def test_outcome_invariants(config, fld, seed):
    o = field_throws.throw_at_field(config, fld, 1, jitter=0.003, seed=seed)
    assert o.start_config == config
    assert o.end_config | o.thrown_off == config and o.end_config & o.thrown_off == 0
    assert o.count_before == geometry.n_cans(config) and o.count_after == geometry.n_cans(
        o.end_config
    )
    assert o.touched & ~config == 0 and o.hit_any_can == bool(o.touched)
    assert 0 < o.sim_time <= materials.MAX_SIM_TIME + 1e-9
    if not o.hit_any_can:
        assert o.thrown_off == 0


# --- bad input ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "pattern"),
    [
        ({"field": 195}, r"field=195 .*expected a field index in 0\.\.194"),
        ({"field": -1}, r"field=-1"),
        ({"field": 2.5}, r"field=2\.5 is a float; expected an int"),
        ({"angle": 3}, r"angle=3 .*expected an angle index in 0\.\.2"),
        ({"config": 512}, r"config=512 \(cans \(9,\)\) is not a physically possible"),
        ({"config": 1024}, r"config=1024 .*10-bit configuration mask"),
        ({"jitter": -0.001}, r"jitter=-0\.001"),
        ({"jitter": float("nan")}, r"jitter=nan"),
        ({"field": 0}, r"\(field=0, angle=0\) cannot be thrown"),
    ],
)
def test_throw_rejects_bad_input(kwargs, pattern):
    args = {"config": FULL, "field": field(5, 5), "angle": 0} | kwargs
    jitter = args.pop("jitter", 0.0)
    with pytest.raises(ValueError, match=pattern):
        field_throws.throw_at_field(**args, jitter=jitter)


@pytest.mark.parametrize(
    ("position", "velocity", "pattern"),
    [
        (geometry.can_positions()[0], (7.0, 0.0), r"position=.* inside can 0"),
        ((geometry.PYRAMID_X - 0.05, 0.1), (7.0, 0.0), r"inside can 0"),
        ((geometry.ENTRY_X, 0.03), (7.0, 0.0), r"into the table top"),
        ((geometry.ENTRY_X, float("nan")), (7.0, 0.0), r"position=.* is not finite"),
        ((geometry.ENTRY_X, 0.3), (float("nan"), 0.0), r"velocity=.* is not finite"),
        ((geometry.ENTRY_X, 0.3, 0.0), (7.0, 0.0), r"position=.* shape \(2,\)"),
        ((-5.0, 0.3), (7.0, 0.0), r"off the table"),
    ],
)
def test_play_ball_rejects_bad_state(position, velocity, pattern):
    with pytest.raises(ValueError, match=pattern):
        field_throws.play_ball(FULL, position, velocity)


def test_play_ball_accepts_a_ball_where_a_missing_can_would_be():
    position = geometry.can_positions()[9]  # can 9 is absent from the bottom row configuration
    o = field_throws.play_ball(BOTTOM_ROW, position, (7.0, 0.0))
    assert not o.hit_any_can and o.end_config == BOTTOM_ROW
