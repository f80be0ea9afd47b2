"""The physics-bounds example: the held-out choice on hand-made cases, a tiny run end to end."""

import json

import numpy as np

from tests.helpers import load_example

bounds = load_example("physics_bounds")


def test_held_out_best_scores_the_choice_on_the_other_half():
    # repeats (first half | second half); action 1 looks best on the first half
    success = np.array(
        [
            [[1, 0, 1, 1], [1, 1, 0, 0], [0, 0, 1, 1]],  # chooses 1 (first half 2/2): scores 0
            [[1, 1, 1, 0], [0, 0, 1, 1], [1, 1, 1, 1]],  # tie 0 and 2: the lowest, 0: scores 1/2
        ],
        dtype=bool,
    )
    np.testing.assert_array_equal(bounds.held_out_best(success), [0.0, 0.5])


def test_tiny_run_end_to_end(tmp_path):
    args = bounds.parse_args(
        ["--scale", "tiny", "--data-dir", str(tmp_path), "--out", str(tmp_path / "out")]
        + ["--repeats", "2", "--combined-repeats", "2", "--step", "0.1", "--quiet"]
    )
    result = bounds.main(args)
    saved = json.loads((tmp_path / "out" / "physics_bounds.json").read_text())
    assert saved["table_one"] == result["table_one"]
    t = result["table_one"]
    assert 0 <= t["exact_fraction_bound"] <= 1 and t["n_cases"] > 0
    assert set(saved["combined"]["0.75"]) == {"top_three", "near_flank", "far_flank"}
    for s in saved["combined"]["0.75"].values():
        for key in ("success_bound", "success_in_sample", "one_throw_bound"):
            assert 0 <= s[key] <= 1
        assert s["n_heights"] > 0 and s["n_states"] >= 1
