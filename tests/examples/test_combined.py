"""The combined example: its rules on hand-made cases, and an end-to-end run at tiny scale."""

import json
from pathlib import Path

import pytest

from sim2d import cans
from sim2d.configurations import stable_configurations
from tests.helpers import load_example

ROOT = Path(__file__).resolve().parents[2]
combined = load_example("combined")


def test_settle_keeps_stable_sets_and_drops_unsupported_cans():
    stable = frozenset(stable_configurations())
    assert combined.settle(cans.FULL_PYRAMID, stable) == cans.FULL_PYRAMID
    lone_top = cans.cans_to_mask([0, 1, 2, 3, 9])  # the top can with nothing under it
    settled = combined.settle(lone_top, stable)
    assert settled in stable and settled & ~lone_top == 0
    assert settled == cans.cans_to_mask([0, 1, 2, 3])


def test_first_contact_meets_the_first_can_on_the_path():
    # a flat throw through row 1 of the near column meets can 0 at its near face
    x, z = combined.first_contact(cans.FULL_PYRAMID, 1 * cans.N_COLUMNS + 0, 0)
    cx, cz = cans.can_positions()[0]
    assert x == pytest.approx(cx - cans.CAN_WIDTH / 2 - cans.BALL_RADIUS, abs=2e-3)
    # with no cans the path is matched at the field centre
    assert combined.first_contact(0, 100, 0) == pytest.approx(tuple(cans.field_centres()[100]))


def test_tiny_run_end_to_end(tmp_path):
    args = combined.parse_args(
        [
            "--scale",
            "tiny",
            "--data-dir",
            str(tmp_path),
            "--out",
            str(tmp_path),
            "--n-throws",
            "3000",
        ]
        + ["--bins", "6", "--episodes", "2", "--horizon", "2", "--quiet"]
    )
    result = combined.main(args)
    saved = json.loads((tmp_path / "combined.json").read_text())
    assert set(saved["scenarios"]) == {"top_three", "near_flank", "far_flank"}
    for s in result["scenarios"].values():
        assert 0.0 <= s["success_rate"] <= 1.0 and 0.0 <= s["success_rate_exact_planner"] <= 1.0
        assert 0.0 <= s["exact_planner_predicted"] <= 1.0 + 1e-9
        first = s["rounds"][0]
        assert first["actions"] == first["success"] + first["fail_too_many"] + first[
            "fail_no_hit"
        ] + sum(first["intermediate"].values())
    assert saved["angle_choice"]["chosen_angle"] in cans.ANGLE_NAMES
    assert (tmp_path / "combined.md").read_text().count("success rate") == 3
