"""The combined example: its rules on hand-made cases, and an end-to-end run at tiny scale."""

import json
from pathlib import Path

from sim2d import geometry
from tests.helpers import load_example

ROOT = Path(__file__).resolve().parents[2]
combined = load_example("combined")


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
    assert saved["angle_choice"]["chosen_angle"] in geometry.ANGLE_NAMES
    assert (tmp_path / "combined.md").read_text().count("success rate") == 3
