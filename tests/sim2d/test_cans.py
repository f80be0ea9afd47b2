"""Tests of the can world (sim2d/cans.py): geometry, physics invariants, outcomes, errors."""

import math
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sim2d import cans
from sim2d.configurations import stable_configurations
from tests.helpers import load_example

FULL = cans.FULL_PYRAMID
BOTTOM_ROW = cans.cans_to_mask([0, 1, 2, 3])


def field(row: int, column: int) -> int:
    return row * cans.N_COLUMNS + column


# --- geometry -----------------------------------------------------------------------------


def test_constants():
    assert cans.N_CANS == 10 and cans.N_FIELDS == 195 == cans.N_COLUMNS * cans.N_ROWS
    assert (cans.N_COLUMNS, cans.N_ROWS) == (15, 13)
    assert cans.ANGLES == ((7.0, 0.0), (7.0, -4.0), (7.0, 4.0))
    assert cans.ANGLE_NAMES == ("0deg", "30deg", "-30deg")
    assert cans.BALL_MASS == 2.0
    assert math.isclose(cans.PYRAMID_WIDTH, 0.54) and math.isclose(cans.PYRAMID_HEIGHT, 0.64)


def test_can_positions_rows_gaps_and_support():
    p = cans.can_positions()
    assert p.shape == (10, 2)
    rows = [[0, 1, 2, 3], [4, 5, 6], [7, 8], [9]]
    for r, members in enumerate(rows):
        np.testing.assert_allclose(p[members, 1], cans.CAN_HEIGHT * (r + 0.5))
        # neighbours in a row: 2 cm between their faces
        np.testing.assert_allclose(np.diff(p[members, 0]), cans.CAN_WIDTH + cans.GAP)
    assert math.isclose(p[0, 0] - cans.CAN_WIDTH / 2, cans.PYRAMID_X)
    assert math.isclose(p[3, 0] + cans.CAN_WIDTH / 2, cans.PYRAMID_X + 0.54)
    for i, below in enumerate(cans.SUPPORTERS):
        if below is None:
            assert i < 4
            continue
        # centred over the gap between its two supporters, resting on them
        assert math.isclose(p[i, 0], p[list(below), 0].mean())
        assert math.isclose(p[i, 1] - p[below[0], 1], cans.CAN_HEIGHT)
    # the named groups are the pyramid's edges
    assert cans.NEAR_FLANK == (0, 4, 7, 9) and cans.FAR_FLANK == (3, 6, 8, 9)
    assert cans.TOP_THREE == (7, 8, 9)
    assert np.all(np.diff(p[list(cans.NEAR_FLANK), 0]) > 0)
    assert np.all(np.diff(p[list(cans.FAR_FLANK), 0]) < 0)


def test_field_centres_grid():
    c = cans.field_centres()
    assert c.shape == (195, 2)
    assert np.all(c[:, 0] > cans.PYRAMID_X) and np.all(c[:, 0] < cans.PYRAMID_X + 0.54)
    assert np.all(c[:, 1] > 0) and np.all(c[:, 1] < 0.64)
    np.testing.assert_allclose(c[field(0, 0)], [cans.PYRAMID_X + 0.018, 0.32 / 13])
    np.testing.assert_allclose(c[field(12, 14)], [cans.PYRAMID_X + 0.54 - 0.018, 0.64 - 0.32 / 13])
    # field = row * 15 + column: columns vary x, rows vary z
    np.testing.assert_allclose(c[field(5, 3)], [c[field(0, 3), 0], c[field(5, 0), 1]])


@given(st.sets(st.integers(0, 9)))
def test_mask_round_trip(members):
    mask = cans.cans_to_mask(members)
    assert cans.mask_to_cans(mask) == tuple(sorted(members))
    assert cans.count(mask) == len(members)


# --- throws: kinematics -------------------------------------------------------------------


@pytest.mark.parametrize("angle", [0, 1, 2])
def test_launch_state_parabola_passes_the_field_centre(angle):
    for f in [field(3, 0), field(7, 8), field(12, 14)]:
        (x0, z0), (vx0, vz0) = cans.launch_state(f, angle)
        assert x0 == cans.ENTRY_X
        t = (cans.field_centres()[f, 0] - x0) / vx0
        z = z0 + vz0 * t - 0.5 * cans.GRAVITY * t * t
        assert math.isclose(z, cans.field_centres()[f, 1], abs_tol=1e-12)
        assert np.allclose((vx0, vz0 - cans.GRAVITY * t), cans.ANGLES[angle])


def test_throwable_fields():
    table = np.array([[cans.is_throwable(f, a) for a in range(3)] for f in range(195)])
    assert not table[: cans.N_COLUMNS].any(), "the bottom row lies below the ball's radius"
    assert table[cans.N_COLUMNS :, 1].all(), "descending throws come from above"
    assert table[field(1, 0), 0] and table[field(12, 14), 2]
    assert not table[field(1, 14), 2], "low ascending throws far away pass below the table"


def test_free_flight_matches_ballistic_formula():
    # Only the far bottom can stands; a high flat throw passes over it untouched.
    f, a = field(12, 7), 0
    trace = cans.trace_throw(cans.cans_to_mask([3]), f, a, frame_interval=cans.TIME_STEP)
    assert not trace.outcome.hit_any_can
    (x0, z0), (vx, vz) = cans.launch_state(f, a)
    t = trace.times
    expected = np.stack([x0 + vx * t, z0 + vz * t - 0.5 * cans.GRAVITY * t * t], axis=1)
    np.testing.assert_allclose(trace.ball, expected, atol=1e-9)
    assert len(t) > 50


@settings(max_examples=25, deadline=None)
@given(
    height=st.floats(cans.BALL_RADIUS + 0.002, cans.CAN_HEIGHT + cans.BALL_RADIUS - 0.01),
    speed=st.floats(3.0, 20.0),
)
def test_no_tunnelling_through_a_single_can(height, speed):
    """A ball flying at a lone can's height always hits it, up to 20 m/s at a 1 ms step."""
    outcome = cans.play_ball(cans.cans_to_mask([0]), (cans.ENTRY_X, height), (speed, 0.0))
    assert outcome.hit_any_can and outcome.touched == 1
    assert outcome.thrown_off == 1, "a 2 kg ball moves a 0.1 kg can"


# --- throws: outcomes ---------------------------------------------------------------------


def test_same_throw_same_seed_same_outcome():
    a = cans.throw(FULL, field(6, 4), 1, jitter=0.003, seed=123)
    b = cans.throw(FULL, field(6, 4), 1, jitter=0.003, seed=123)
    assert a == b
    assert a.hit_any_can and not a.timed_out


def test_jitter_changes_aim_by_millimetres():
    nominal = cans.launch_state(field(6, 4), 0)[0]
    offset = cans._aim_offset(0.003, 7)
    assert np.all(np.abs(offset) <= 0.009) and np.any(offset != 0)
    assert np.array_equal(cans._aim_offset(0.003, 7), offset)
    raised = cans.launch_state(field(6, 4), 0, offset=(0.0, offset[1]))[0]
    np.testing.assert_allclose(raised - nominal, [0.0, offset[1]], atol=1e-15)


def test_a_miss_changes_nothing():
    # The bottom row stands; a flat throw at row 8 flies over it.
    o = cans.throw(BOTTOM_ROW, field(8, 7), 0, jitter=0.003, seed=1)
    assert not o.hit_any_can and o.thrown_off == 0
    assert o.end_config == o.start_config == BOTTOM_ROW and o.count_after == o.count_before == 4
    # A ball well above the full pyramid.
    o = cans.play_ball(FULL, (cans.ENTRY_X, 0.85), (7.0, 0.0))
    assert not o.hit_any_can and o.end_config == FULL and not o.timed_out
    assert o.sim_time < 0.2, "a miss stops as soon as the ball has passed every can"


def test_low_throw_at_near_bottom_can_brings_down_what_it_supports():
    o = cans.throw(FULL, field(1, 0), 0)
    assert o.touched & 1, "the ball hits can 0 first"
    supported_by_0 = cans.cans_to_mask([0, 4, 7, 9])  # 4 rests on 0, 7 on 4, 9 on 7
    assert o.thrown_off & supported_by_0 == supported_by_0
    # With only can 0 and the cans resting on it (and their other supporters) standing:
    config = cans.cans_to_mask([0, 1, 4])
    o = cans.throw(config, field(1, 0), 0)
    assert o.thrown_off & cans.cans_to_mask([0, 4]) == cans.cans_to_mask([0, 4])


def test_top_throw_takes_the_top_can():
    o = cans.throw(FULL, field(12, 7), 1)
    assert o.thrown_off >> 9 & 1
    assert o.thrown_off & BOTTOM_ROW == 0, "a descending throw at the top leaves the bottom row"


@settings(max_examples=15, deadline=None)
@given(
    config=st.sampled_from(stable_configurations()),
    fld=st.integers(cans.N_COLUMNS, cans.N_FIELDS - 1),
    seed=st.integers(0, 2**31),
)
def test_outcome_invariants(config, fld, seed):
    o = cans.throw(config, fld, 1, jitter=0.003, seed=seed)
    assert o.start_config == config
    assert o.end_config | o.thrown_off == config and o.end_config & o.thrown_off == 0
    assert o.count_before == cans.count(config) and o.count_after == cans.count(o.end_config)
    assert o.touched & ~config == 0 and o.hit_any_can == bool(o.touched)
    assert 0 < o.sim_time <= cans.MAX_SIM_TIME + 1e-9
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
        cans.throw(**args, jitter=jitter)


@pytest.mark.parametrize(
    ("position", "velocity", "pattern"),
    [
        (cans.can_positions()[0], (7.0, 0.0), r"position=.* inside can 0"),
        ((cans.PYRAMID_X - 0.05, 0.1), (7.0, 0.0), r"inside can 0"),
        ((cans.ENTRY_X, 0.03), (7.0, 0.0), r"into the table top"),
        ((cans.ENTRY_X, float("nan")), (7.0, 0.0), r"position=.* is not finite"),
        ((cans.ENTRY_X, 0.3), (float("nan"), 0.0), r"velocity=.* is not finite"),
        ((cans.ENTRY_X, 0.3, 0.0), (7.0, 0.0), r"position=.* shape \(2,\)"),
        ((-5.0, 0.3), (7.0, 0.0), r"off the table"),
    ],
)
def test_play_ball_rejects_bad_state(position, velocity, pattern):
    with pytest.raises(ValueError, match=pattern):
        cans.play_ball(FULL, position, velocity)


def test_play_ball_accepts_a_ball_where_a_missing_can_would_be():
    position = cans.can_positions()[9]  # can 9 is absent from the bottom row configuration
    o = cans.play_ball(BOTTOM_ROW, position, (7.0, 0.0))
    assert not o.hit_any_can and o.end_config == BOTTOM_ROW


# --- layering and pictures ----------------------------------------------------------------


def test_sim2d_can_world_imports_neither_torch_nor_pyro_nor_matplotlib():
    code = (
        "import sys, sim2d.cans, sim2d.configurations, sim2d.can_dataset, sim2d.render; "
        "print(sorted(m for m in ('torch', 'pyro', 'matplotlib') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_example_runs_with_tiny_arguments(tmp_path):
    files = load_example("can_world").main(["--out", str(tmp_path), "--frame-interval", "0.25"])
    assert set(files) == {"pyramid", "throw", "gif"}
    for path in files.values():
        assert path.exists() and path.stat().st_size > 1000
