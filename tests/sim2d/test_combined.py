"""The combined scene: settle rule, first contact, the robot's ball entering the can world."""

import errno
import os
from pathlib import Path

import numpy as np
import pytest
from effect_networks.sim2d import geometry, materials
from effect_networks.sim2d.analytic_throw import exact_target_for_hit, throw
from effect_networks.sim2d.combined import (
    CAN_BAND,
    TABLE_TOP_Z,
    entry_state,
    exact_throws,
    first_contact,
    play_throw,
    settle,
)
from effect_networks.sim2d.configurations import stable_configurations

from tests.helpers import InlineExecutor


def test_settle_keeps_stable_sets_and_drops_unsupported_cans():
    stable = frozenset(stable_configurations())
    assert settle(geometry.FULL_PYRAMID, stable) == geometry.FULL_PYRAMID
    lone_top = geometry.cans_to_mask([0, 1, 2, 3, 9])  # the top can with nothing under it
    settled = settle(lone_top)
    assert settled in stable and settled & ~lone_top == 0
    assert settled == geometry.cans_to_mask([0, 1, 2, 3])


def test_first_contact_meets_the_first_can_on_the_path():
    # a flat throw through row 1 of the near column meets can 0 at its near face
    x, z = first_contact(geometry.FULL_PYRAMID, 1 * geometry.N_COLUMNS + 0, 0)
    cx, cz = geometry.can_positions()[0]
    assert x == pytest.approx(cx - geometry.CAN_WIDTH / 2 - materials.BALL_RADIUS, abs=2e-3)
    # with no cans the path is matched at the field centre
    assert first_contact(0, 100, 0) == pytest.approx(tuple(geometry.field_centres()[100]))


def test_entry_state_runs_the_ball_back_along_its_parabola():
    hit, v = np.array([0.0, TABLE_TOP_Z + 0.4]), np.array([7.0, 0.5, -2.0])
    (x, z), (vx, vz) = entry_state(hit, v)
    dt = (geometry.PYRAMID_X - x) / vx
    # flying forward from the entry state lands exactly on the hit, with the hit's velocity
    assert x == geometry.ENTRY_X and vx == 7.0
    assert z + vz * dt - 0.5 * materials.GRAVITY * dt**2 == pytest.approx(0.4, abs=1e-12)
    assert vz - materials.GRAVITY * dt == pytest.approx(-2.0, abs=1e-12)
    assert entry_state([CAN_BAND + 1e-3, hit[1]], v) is None  # beside the pyramid
    assert entry_state([0.0, TABLE_TOP_Z + 0.01], v) is None  # into the table in front


def test_a_throw_beside_the_pyramid_changes_nothing_and_a_throw_at_the_top_removes_it():
    aims = exact_target_for_hit(np.array([[0.5, TABLE_TOP_Z + 0.3], [0.0, TABLE_TOP_Z + 0.58]]))
    r = throw(aims)
    assert (
        play_throw(geometry.FULL_PYRAMID, r.hit[0], r.velocity_at_plane[0]) == geometry.FULL_PYRAMID
    )
    top = play_throw(geometry.FULL_PYRAMID, r.hit[1], r.velocity_at_plane[1])
    assert top & ~geometry.cans_to_mask([9]) == top and not top >> 9 & 1  # can 9 gone
    # the jitter is seeded: the same seed, the same outcome
    again = [
        play_throw(geometry.FULL_PYRAMID, r.hit[1], r.velocity_at_plane[1], jitter=0.003, seed=7)
    ]
    again.append(
        play_throw(geometry.FULL_PYRAMID, r.hit[1], r.velocity_at_plane[1], jitter=0.003, seed=7)
    )
    assert again[0] == again[1]


def test_exact_throws_hit_the_heights_they_aim_at():
    heights, result = exact_throws(0.05)
    np.testing.assert_allclose(result.hit[:, 1], heights + TABLE_TOP_Z, atol=1e-6)
    np.testing.assert_allclose(result.hit[:, 0], 0.0, atol=1e-6)
    assert heights.min() >= 0 and heights.max() < geometry.PYRAMID_HEIGHT + materials.BALL_RADIUS
    with pytest.raises(ValueError, match="step"):
        exact_throws(0.0)


def test_explore_covers_every_state_its_throws_reach_and_resumes(tmp_path):
    from effect_networks.sim2d.combined import reachable_throws, throws_from

    kw = dict(depth=2, step=0.05, repeats=2, jitter=0.003, seed=5)
    serial = InlineExecutor()
    out = reachable_throws(
        tmp_path / "x", geometry.FULL_PYRAMID, executor=serial, progress=False, **kw
    )
    full = out[geometry.FULL_PYRAMID]
    assert np.array_equal(
        full, throws_from(geometry.FULL_PYRAMID, TABLE_TOP_Z, 0.05, 2, 0.003, 5)["next_states"]
    )
    # layer 1: exactly the non-empty states the full pyramid's throws produced
    assert set(out) - {geometry.FULL_PYRAMID} == {int(s) for s in np.unique(full) if s} - {
        geometry.FULL_PYRAMID
    }
    assert serial.submitted == len(out)
    again = InlineExecutor()
    same = reachable_throws(
        tmp_path / "x", geometry.FULL_PYRAMID, executor=again, progress=False, **kw
    )
    assert again.submitted == 0 and set(same) == set(out)
    assert all(np.array_equal(same[s], out[s]) for s in out)
    # finished, it is usable in a read-only folder (no lock can be created there)
    real_open = os.open

    def read_only(file, flags, *args, **kwargs):
        if tmp_path in Path(file).parents and flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(file))
        return real_open(file, flags, *args, **kwargs)

    before = sorted(tmp_path.rglob("*"))
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(os, "open", read_only)
        read = reachable_throws(
            tmp_path / "x", geometry.FULL_PYRAMID, executor=again, progress=False, **kw
        )
    assert again.submitted == 0 and all(np.array_equal(read[s], out[s]) for s in out)
    assert sorted(tmp_path.rglob("*")) == before


def test_explore_refuses_bad_arguments(tmp_path):
    from effect_networks.sim2d.combined import reachable_throws

    with pytest.raises(ValueError, match="depth"):
        reachable_throws(tmp_path, geometry.FULL_PYRAMID, depth=0)
    with pytest.raises(ValueError, match="not a physically possible"):
        reachable_throws(tmp_path, geometry.cans_to_mask([9]), depth=1)


def test_play_policy_stops_at_the_goal_and_replays_with_its_seed():
    from effect_networks.sim2d.combined import play_policy

    states = sorted(stable_configurations())
    full = geometry.FULL_PYRAMID
    top = full & ~geometry.cans_to_mask([9])
    # aim at the top can's middle, every state, every step
    aim = exact_target_for_hit(np.array([[0.0, TABLE_TOP_Z + geometry.PYRAMID_HEIGHT - 0.05]]))
    policy = np.zeros((4, len(states)), dtype=np.int64)
    kw = dict(episodes=5, jitter=0.003, seed=11)
    a = play_policy(full, top, policy, states, aim, **kw)
    b = play_policy(full, top, policy, states, aim, **kw)
    assert np.array_equal(a["end"], b["end"]) and np.array_equal(a["throws"], b["throws"])
    assert ((a["throws"] >= 1) & (a["throws"] <= 3)).all()
    # an episode that ends early ended at the goal or lost a goal can
    early = a["throws"] < 3
    assert all(e == top or e & top != top for e in a["end"][early])
    stop = play_policy(full, top, np.full((4, len(states)), -1), states, aim, **kw)
    assert (stop["end"] == full).all() and (stop["throws"] == 0).all()
    with pytest.raises(ValueError, match="policy"):
        play_policy(full, top, policy[:, :3], states, aim, **kw)
