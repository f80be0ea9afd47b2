"""Tests of sim2d.analytic_throw: the analytic throw against physics and geometry it does not use."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from effect_networks.sim2d.analytic_throw import (
    FOREARM_LENGTH,
    HAND_SPEED,
    PITCH_LIMITS_DEG,
    RELEASE_X,
    SHOULDER,
    TARGET_AREA,
    TARGET_PLANE_X,
    UPPER_ARM_LENGTH,
    YAW_LIMITS_DEG,
    ReleaseNoise,
    exact_target_for_hit,
    is_reachable_hit,
    reachable_hit_boundary,
    sample_targets,
    throw,
)
from effect_networks.sim2d.materials import GRAVITY
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

ROOT = Path(__file__).resolve().parents[2]

targets_in_area = arrays(
    np.float64,
    st.integers(1, 20).map(lambda n: (n, 2)),
    elements=st.floats(0.0, 1.0),
).map(lambda u: TARGET_AREA.low + u * (TARGET_AREA.high - TARGET_AREA.low))


def rk4_flight_to_plane(position, velocity, dt=1e-4):
    """Integrate x'' = (0, 0, -g) by RK4 until x crosses the plane; interpolate there."""
    state = np.concatenate([position, velocity], axis=1)

    def derivative(s):
        acceleration = np.zeros_like(s[:, 3:])
        acceleration[:, 2] = -GRAVITY
        return np.concatenate([s[:, 3:], acceleration], axis=1)

    crossed = np.full_like(state, np.nan)
    flying = np.ones(len(state), dtype=bool)
    while np.any(flying):
        k1 = derivative(state)
        k2 = derivative(state + 0.5 * dt * k1)
        k3 = derivative(state + 0.5 * dt * k2)
        k4 = derivative(state + dt * k3)
        new = state + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        # Between two steps the state is linear in time to O(dt**2 g) ~ 1e-8 m.
        now = flying & (new[:, 0] >= TARGET_PLANE_X)
        w = (TARGET_PLANE_X - state[now, 0]) / (new[now, 0] - state[now, 0])
        crossed[now] = state[now] + w[:, None] * (new[now] - state[now])
        flying &= ~now
        state = new
    return crossed[:, 1:3], crossed[:, 3:]


def yaw_pitch_deg(vectors):
    """Yaw about +z and elevation of (n, 3) vectors, degrees."""
    vectors = np.asarray(vectors)
    yaw = np.degrees(np.arctan2(vectors[:, 1], vectors[:, 0]))
    pitch = np.degrees(np.arctan2(vectors[:, 2], np.hypot(vectors[:, 0], vectors[:, 1])))
    return yaw, pitch


# --- the ball crosses the plane at the returned point ---------------------------------


def test_hit_and_velocity_match_numerically_integrated_flight():
    targets = np.vstack([sample_targets(40, 1), [[-0.2, 1.4]], TARGET_AREA.low, TARGET_AREA.high])
    result = throw(targets)
    hit, velocity = rk4_flight_to_plane(result.release_position, result.release_velocity)
    np.testing.assert_allclose(result.hit, hit, atol=1e-6)
    np.testing.assert_allclose(result.velocity_at_plane, velocity, atol=1e-5)


def test_energy_is_conserved_between_release_and_plane():
    result = throw(sample_targets(1000, 2))
    z_release = result.release_position[:, 2]
    speed_release = np.linalg.norm(result.release_velocity, axis=1)
    speed_plane = np.linalg.norm(result.velocity_at_plane, axis=1)
    np.testing.assert_allclose(
        0.5 * speed_plane**2 + GRAVITY * result.hit[:, 1],
        0.5 * speed_release**2 + GRAVITY * z_release,
        rtol=1e-12,
    )


# --- a reachable target straight ahead, and unclamped targets in general ---------------


def test_target_straight_ahead_of_shoulder_is_hit_directly_below_by_the_drop():
    result = throw(np.array([[SHOULDER[1], SHOULDER[2]]]))
    flight_time = (TARGET_PLANE_X - RELEASE_X) / HAND_SPEED
    assert not result.clamped[0]
    np.testing.assert_allclose(result.release_position[0], [RELEASE_X, SHOULDER[1], SHOULDER[2]])
    np.testing.assert_allclose(result.release_velocity[0], [HAND_SPEED, 0.0, 0.0])
    np.testing.assert_allclose(
        result.hit[0], [SHOULDER[1], SHOULDER[2] - 0.5 * GRAVITY * flight_time**2]
    )
    np.testing.assert_allclose(
        result.velocity_at_plane[0], [HAND_SPEED, 0.0, -GRAVITY * flight_time]
    )
    assert result.hit[0, 1] == pytest.approx(1.4 - 0.2893, abs=1e-4)  # 28.9 cm below


@given(targets_in_area)
@settings(max_examples=50, deadline=None)
def test_unclamped_targets_are_hit_directly_below_by_the_gravity_drop(targets):
    # Geometry alone: the ball leaves along the line shoulder -> target at HAND_SPEED;
    # its speed towards the plane is HAND_SPEED * (2 m) / |target - shoulder|.
    result = throw(targets)
    offset = np.column_stack([np.full(len(targets), TARGET_PLANE_X), targets]) - SHOULDER
    vx = HAND_SPEED * offset[:, 0] / np.linalg.norm(offset, axis=1)
    drop = 0.5 * GRAVITY * ((TARGET_PLANE_X - RELEASE_X) / vx) ** 2
    free = ~result.clamped
    np.testing.assert_allclose(result.hit[free, 0], targets[free, 0], atol=1e-12)
    np.testing.assert_allclose(result.hit[free, 1], targets[free, 1] - drop[free], atol=1e-12)


# --- joint limits -------------------------------------------------------------------


@given(targets_in_area)
@settings(max_examples=100, deadline=None)
def test_joint_limits_hold_for_every_throw(targets):
    result = throw(targets)
    yaw, pitch = yaw_pitch_deg(result.release_velocity)
    eps = 1e-9
    assert np.all((yaw >= YAW_LIMITS_DEG[0] - eps) & (yaw <= YAW_LIMITS_DEG[1] + eps))
    assert np.all((pitch >= PITCH_LIMITS_DEG[0] - eps) & (pitch <= PITCH_LIMITS_DEG[1] + eps))
    # The hand moves on a straight line from the shoulder, at constant speed, and lets
    # go at x = 0.3 m, within the arm's reach.
    hand = result.release_position - SHOULDER
    np.testing.assert_allclose(result.release_position[:, 0], RELEASE_X)
    np.testing.assert_allclose(
        hand / np.linalg.norm(hand, axis=1, keepdims=True),
        result.release_velocity / HAND_SPEED,
        atol=1e-12,
    )
    assert np.all(np.linalg.norm(hand, axis=1) <= UPPER_ARM_LENGTH + FOREARM_LENGTH)
    # Clamped exactly when the direction shoulder -> target leaves the limits.
    aim_yaw, aim_pitch = yaw_pitch_deg(
        np.column_stack([np.full(len(targets), TARGET_PLANE_X), targets]) - SHOULDER
    )
    outside = (
        (aim_yaw < YAW_LIMITS_DEG[0])
        | (aim_yaw > YAW_LIMITS_DEG[1])
        | (aim_pitch < PITCH_LIMITS_DEG[0])
        | (aim_pitch > PITCH_LIMITS_DEG[1])
    )
    np.testing.assert_array_equal(result.clamped, outside)
    np.testing.assert_allclose(np.degrees(result.arm_yaw_pitch), np.column_stack([yaw, pitch]))


def test_limits_bind_on_every_side_and_clamp_a_sizeable_share():
    result = throw(sample_targets(30_000, 3))
    share = result.clamped.mean()
    print(f"clamped share of uniform targets: {share:.3f}")
    assert 0.35 < share < 0.6
    yaw, pitch = np.degrees(result.arm_yaw_pitch).T
    for value, limit in (
        (yaw, YAW_LIMITS_DEG[0]),
        (yaw, YAW_LIMITS_DEG[1]),
        (pitch, PITCH_LIMITS_DEG[0]),
        (pitch, PITCH_LIMITS_DEG[1]),
    ):
        assert np.mean(np.isclose(value, limit)) > 0.02  # least: yaw -20 deg, 4 %


def test_mapping_is_non_linear_over_the_area_but_affine_in_a_small_unclamped_patch():
    def affine_residual_rms(hit, target):
        design = np.column_stack([hit, np.ones(len(hit))])
        coefficients, *_ = np.linalg.lstsq(design, target, rcond=None)
        return np.sqrt(np.mean((design @ coefficients - target) ** 2, axis=0))

    targets = sample_targets(30_000, 4)
    whole = affine_residual_rms(throw(targets).hit, targets)
    rng = np.random.default_rng(5)
    patch = np.column_stack([rng.uniform(-0.4, 0.0, 3000), rng.uniform(1.2, 1.6, 3000)])
    patch_result = throw(patch)
    assert not patch_result.clamped.any()
    local = affine_residual_rms(patch_result.hit, patch)
    print(f"affine hit->target residual RMS: whole area {whole} m, patch {local} m")
    assert np.all(whole > 0.04)
    assert np.all(local < 0.002)


# --- reachable hits and the exact inverse -------------------------------------------


def test_exact_inverse_round_trips_and_recovers_unclamped_targets():
    targets = sample_targets(5000, 6)
    result = throw(targets)
    assert np.all(is_reachable_hit(result.hit))
    aimed = exact_target_for_hit(result.hit)
    np.testing.assert_allclose(throw(aimed).hit, result.hit, atol=1e-12)
    free = ~result.clamped
    np.testing.assert_allclose(aimed[free], targets[free], atol=1e-12)


def test_unreachable_points_have_no_target_and_the_boundary_agrees():
    far = np.array([[1.0, 2.4], [-1.0, 0.4], [0.0, 2.3], [0.0, 0.05], [0.0, 10.0]])
    assert not is_reachable_hit(far).any()
    assert np.all(np.isnan(exact_target_for_hit(far)))
    # Every direction inside the limits aims into the target area: its corners.
    corners = np.radians(np.array(np.meshgrid(YAW_LIMITS_DEG, PITCH_LIMITS_DEG)).reshape(2, -1).T)
    distance = TARGET_PLANE_X / np.cos(corners[:, 0])
    aim = np.column_stack(
        [
            SHOULDER[1] + distance * np.sin(corners[:, 0]),
            SHOULDER[2] + distance * np.tan(corners[:, 1]),
        ]
    )
    assert TARGET_AREA.contains(aim).all()
    # The polygon boundary (image of the limit box's edges) encloses the reachable points.
    boundary = reachable_hit_boundary(400)
    grid = np.stack(np.meshgrid(np.linspace(-1, 1, 81), np.linspace(0, 2.4, 97)), -1).reshape(-1, 2)
    from matplotlib.path import Path as PolygonPath

    inside_polygon = PolygonPath(boundary).contains_points(grid)
    reachable = is_reachable_hit(grid)
    share = is_reachable_hit(
        np.stack(np.meshgrid(np.linspace(-1, 1, 201), np.linspace(0.4, 2.4, 201)), -1).reshape(
            -1, 2
        )
    ).mean()
    print(f"share of the target area any throw can hit: {share:.3f}")
    assert 0.3 < share < 0.8
    assert np.mean(inside_polygon == reachable) > 0.995
    # All hits stay above the floor z = 0 (the model has no floor).
    assert boundary[:, 1].min() > 0.0


# --- noise ----------------------------------------------------------------------------


def test_noise_is_seeded_reproducible_and_leaves_the_arm_within_limits():
    targets = sample_targets(2000, 7)
    noise = ReleaseNoise()
    a = throw(targets, noise=noise, rng=11)
    b = throw(targets, noise=noise, rng=np.random.default_rng(11))
    c = throw(targets, noise=noise, rng=12)
    exact = throw(targets)
    np.testing.assert_array_equal(a.hit, b.hit)
    assert not np.allclose(a.hit, c.hit)
    np.testing.assert_array_equal(a.arm_yaw_pitch, exact.arm_yaw_pitch)
    np.testing.assert_array_equal(a.release_position, exact.release_position)
    np.testing.assert_array_equal(
        throw(targets, noise=ReleaseNoise(0.0, 0.0), rng=1).hit, exact.hit
    )
    scatter = (a.hit - exact.hit).std(axis=0)
    print(f"noise scatter at the plane: y {scatter[0]:.4f} m, z {scatter[1]:.4f} m")
    # First order: 0.5 deg over ~1.7-1.9 m of flight is ~1.5-1.7 cm; speed adds to z.
    assert 0.010 < scatter[0] < 0.025
    assert 0.012 < scatter[1] < 0.030
    speed = np.linalg.norm(a.release_velocity, axis=1) / HAND_SPEED - 1
    assert speed.std() == pytest.approx(0.02, rel=0.1)


def test_noise_without_rng_is_refused():
    with pytest.raises(ValueError, match="rng"):
        throw(np.array([[0.0, 1.4]]), noise=ReleaseNoise())


# --- bad input ------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("targets", "match"),
    [
        (np.array([0.0, 1.4]), r"targets with shape \(2,\): expected \(n, 2\)"),
        (np.zeros((3, 3)) + 1.0, r"targets with shape \(3, 3\)"),
        (np.array([[0.0, np.nan]]), r"targets\[0\] = \[0.0, nan\]: expected finite"),
        (np.array([[0.0, 1.0], [np.inf, 1.0]]), r"targets\[1\] = \[inf, 1.0\]"),
        (np.array([[0.0, 1.0], [1.5, 1.0]]), r"targets\[1\] = \[1.5, 1.0\]: expected inside"),
        (np.array([[0.0, 0.1]]), r"z in \[0.4, 2.4\]"),
        ("a string", r"targets = 'a string'"),
    ],
)
def test_bad_targets_are_refused_with_the_value_and_what_was_expected(targets, match):
    with pytest.raises(ValueError, match=match):
        throw(targets)


def test_other_bad_arguments():
    with pytest.raises(ValueError, match="direction_std_deg"):
        ReleaseNoise(direction_std_deg=-1.0)
    with pytest.raises(ValueError, match="speed_rel_std"):
        ReleaseNoise(speed_rel_std=float("nan"))
    with pytest.raises(ValueError, match="n = -1"):
        sample_targets(-1, 0)
    with pytest.raises(ValueError, match="rng = 'seed'"):
        sample_targets(3, "seed")
    with pytest.raises(ValueError, match="hits with shape"):
        exact_target_for_hit(np.array([[np.nan, 1.0]]))


def test_sample_targets_is_uniform_on_the_area_and_seeded():
    targets = sample_targets(20_000, 8)
    assert targets.shape == (20_000, 2)
    assert TARGET_AREA.contains(targets).all()
    np.testing.assert_allclose(targets.mean(axis=0), [0.0, 1.4], atol=0.02)
    np.testing.assert_array_equal(targets, sample_targets(20_000, 8))


# --- layering and speed ---------------------------------------------------------------


def test_sim2d_throw_imports_neither_torch_nor_pyro_nor_matplotlib():
    code = (
        "import sys, sim2d.analytic_throw, sim2d.throw_plot; "
        "bad = [m for m in ('torch', 'pyro', 'matplotlib') if m in sys.modules]; "
        "assert not bad, bad"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)
