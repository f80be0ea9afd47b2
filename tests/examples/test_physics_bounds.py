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


class Counting:
    """Runs each task at submission, in this process, and counts them."""

    def __init__(self):
        self.submitted = 0

    def submit(self, fn, *args):
        from concurrent.futures import Future

        self.submitted += 1
        future = Future()
        future.set_result(fn(*args))
        return future


def test_the_combined_bound_resumes_from_its_saved_states(tmp_path):
    args = bounds.parse_args(
        ["--scale", "tiny", "--data-dir", str(tmp_path), "--step", "0.2", "--combined-repeats", "2"]
    )
    states = [1023, 15]
    first = Counting()
    outcomes = bounds.combined_outcomes(args, 0.75, 0.003, states, first)
    assert first.submitted == 2 and set(outcomes) == {15, 1023}
    again = Counting()
    assert bounds.combined_outcomes(args, 0.75, 0.003, states, again).keys() == outcomes.keys()
    assert again.submitted == 0
    folder = next(tmp_path.glob("combined_bound_*.parts"))
    (folder / "chunk-000001.npz").unlink()  # chunks are in sorted state order: 1023
    resumed = Counting()
    redone = bounds.combined_outcomes(args, 0.75, 0.003, states, resumed)
    assert resumed.submitted == 1
    assert all(np.array_equal(redone[s], outcomes[s]) for s in states)
