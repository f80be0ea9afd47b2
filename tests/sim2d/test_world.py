"""Tests of the pymunk world and its stepping (sim2d/world.py): physics invariants, layering."""

import subprocess
import sys

import numpy as np
import pytest
from effect_networks.sim2d import field_throws, geometry, materials, recording
from effect_networks.sim2d.configurations import stable_configurations
from effect_networks.sim2d.world import clear_miss, run_ball
from hypothesis import given, settings
from hypothesis import strategies as st

#: The current step and solver iterations with the cans asleep until touched.
ASLEEP = materials.Stepping(materials.TIME_STEP, materials.SOLVER_ITERATIONS, start_asleep=True)
#: A faster stepping (measured and rejected in benchmarks/sim.py).
FAST = materials.Stepping(time_step=0.002, solver_iterations=5, start_asleep=True)


def field(row: int, column: int) -> int:
    return row * geometry.N_COLUMNS + column


def test_free_flight_matches_ballistic_formula():
    # Only the far bottom can stands; a high flat throw passes over it untouched.
    f, a = field(12, 7), 0
    trace = recording.record_throw(
        geometry.cans_to_mask([3]), f, a, frame_interval=materials.TIME_STEP
    )
    assert not trace.outcome.hit_any_can
    (x0, z0), (vx, vz) = field_throws.launch_state(f, a)
    t = trace.times
    expected = np.stack([x0 + vx * t, z0 + vz * t - 0.5 * materials.GRAVITY * t * t], axis=1)
    np.testing.assert_allclose(trace.ball, expected, atol=1e-9)
    assert len(t) > 50


@settings(max_examples=25, deadline=None)
@given(
    height=st.floats(
        materials.BALL_RADIUS + 0.002, geometry.CAN_HEIGHT + materials.BALL_RADIUS - 0.01
    ),
    speed=st.floats(3.0, 20.0),
)
def test_no_tunnelling_through_a_single_can(height, speed):
    """A ball flying at a lone can's height always hits it, up to 20 m/s (4 cm a step)."""
    outcome = field_throws.play_ball(
        geometry.cans_to_mask([0]), (geometry.ENTRY_X, height), (speed, 0.0)
    )
    assert outcome.hit_any_can and outcome.touched == 1
    assert outcome.thrown_off == 1, "a 2 kg ball moves a 0.1 kg can"


def test_sim2d_can_world_imports_neither_torch_nor_pyro_nor_matplotlib():
    code = (
        "import sys, sim2d.geometry, sim2d.materials, sim2d.world, sim2d.field_throws, "
        "sim2d.configurations, sim2d.recording, sim2d.can_dataset, sim2d.render; "
        "print(sorted(m for m in ('torch', 'pyro', 'matplotlib') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


@settings(max_examples=12, deadline=None)
@given(
    config=st.sampled_from(stable_configurations()),
    fld=st.integers(geometry.N_COLUMNS, geometry.N_FIELDS - 1),
    angle=st.sampled_from([0, 1, 2]),
    seed=st.integers(0, 2**31),
    stopping=st.sampled_from([materials.STOPPING, materials.STOPPING_FORMAT_1]),
    stepping=st.sampled_from([materials.STEPPING, ASLEEP, FAST]),
)
def test_stepping_through_the_binding_equals_the_public_api(
    config, fld, angle, seed, stopping, stepping
):
    """The fast loop and the reference loop are the same simulation, bit for bit."""
    if not field_throws.is_throwable(fld, angle):
        return
    offset = field_throws.aim_offset(0.003, seed)
    position, velocity = field_throws.launch_state(fld, angle, offset=offset)
    rules = {"stopping": stopping, "stepping": stepping}
    fast = run_ball(config, position, velocity, **rules)
    reference = run_ball(config, position, velocity, **rules, reference=True)
    assert np.array_equal(fast.end_positions, reference.end_positions, equal_nan=True)
    assert (fast.removed, fast.touched, fast.steps, fast.timed_out) == (
        reference.removed, reference.touched, reference.steps, reference.timed_out
    )  # fmt: skip


def test_a_can_on_the_table_falls_asleep_and_a_settled_pyramid_stops():
    """A ball that rolls away beyond every can ends the run long before the cap."""
    run = run_ball(geometry.FULL_PYRAMID, (geometry.ENTRY_X, 0.3), (7.0, 0.0))
    assert run.touched and not run.timed_out
    assert run.steps * materials.TIME_STEP < materials.MAX_SIM_TIME


def test_a_body_removed_at_the_scene_margin_has_moved_enough_to_be_thrown_off():
    """Every can's standard centre is more than the thrown-off distance from both margins."""
    x = geometry.can_positions()[:, 0]
    for stopping in (materials.STOPPING, materials.STOPPING_FORMAT_1):
        near = geometry.PYRAMID_X - stopping.scene_margin
        far = geometry.PYRAMID_X + geometry.PYRAMID_WIDTH + stopping.scene_margin
        assert np.all(x - near > materials.THROWN_OFF_HORIZONTAL)
        assert np.all(far - x > materials.THROWN_OFF_HORIZONTAL)


@settings(max_examples=15, deadline=None)
@given(
    config=st.sampled_from(stable_configurations()),
    height=st.floats(0.9, 1.5),  # the ball drops 6 cm while it passes the pyramid
)
def test_cans_that_start_asleep_stand_exactly_still_until_touched(config, height):
    """A ball flying over the pyramid leaves every can exactly where it stood."""
    run = run_ball(config, (geometry.ENTRY_X, height), (7.0, 0.0), stepping=ASLEEP)
    assert not run.touched and not run.removed and not run.timed_out
    cans = list(geometry.mask_to_cans(config))
    assert np.array_equal(run.end_positions[cans], geometry.can_positions()[cans])
    # awake from the start, the same cans sink into their contacts instead
    if config:
        awake = run_ball(
            config, (geometry.ENTRY_X, height), (7.0, 0.0), stepping=materials.STEPPING
        )
        assert not np.array_equal(awake.end_positions[cans], geometry.can_positions()[cans])


def test_a_touch_wakes_the_whole_pyramid():
    """The ball nudges only the near bottom can (0.1 m/s), yet the top can moves too, and
    every other can ends at rest within a millimetre of its place."""
    run = run_ball(geometry.FULL_PYRAMID, (geometry.ENTRY_X, 0.07), (0.1, 0.0), stepping=ASLEEP)
    assert run.touched == 1 and not run.removed and not run.timed_out
    moved = np.abs(run.end_positions - geometry.can_positions())
    assert np.all(moved[9] > 0) and np.all(moved[1:] < 1e-3)


@settings(max_examples=60, deadline=None)
@given(
    config=st.sampled_from([0, *stable_configurations()]),
    height=st.floats(0.08, 1.5),
    vx=st.floats(-2.0, 9.0),
    vz=st.floats(-4.0, 4.0),
)
def test_a_clear_miss_without_pymunk_is_the_simulated_run_bit_for_bit(config, height, vx, vz):
    """Where clear_miss answers, pymunk's public API steps to the very same run."""
    position, velocity = (geometry.ENTRY_X, height), (vx, vz)
    try:
        field_throws.check_ball_position(config, np.array(position))
    except ValueError:
        return  # the ball starts inside a can
    run = clear_miss(config, position, velocity, stepping=ASLEEP)
    reference = run_ball(config, position, velocity, stepping=ASLEEP, reference=True)
    if run is None:
        return
    assert np.array_equal(run.end_positions, reference.end_positions, equal_nan=True)
    assert (run.removed, run.touched, run.steps, run.timed_out) == (
        reference.removed, reference.touched, reference.steps, reference.timed_out
    )  # fmt: skip


def test_clear_miss_answers_only_when_nothing_is_near():
    full, rules = geometry.FULL_PYRAMID, {"stepping": ASLEEP}
    assert clear_miss(full, (geometry.ENTRY_X, 1.0), (7.0, 0.0), **rules) is not None  # over
    assert clear_miss(full, (geometry.ENTRY_X, 0.3), (7.0, 0.0), **rules) is None  # into cans
    assert clear_miss(0, (geometry.ENTRY_X, 0.3), (7.0, 0.0), **rules).steps == 10
    # a ball that lands on the table behind the pyramid is left to pymunk
    assert (
        clear_miss(geometry.cans_to_mask([3]), (geometry.ENTRY_X, 0.5), (1.0, 0.0), **rules) is None
    )
    with pytest.raises(ValueError, match="start_asleep"):
        clear_miss(full, (geometry.ENTRY_X, 1.0), (7.0, 0.0), stepping=materials.STEPPING)
