"""experiments.physics_bounds: the held-out choice on hand-made cases, both Table I
protocols on the same throws, a tiny run end to end, and resuming the combined bound."""

import numpy as np
import pytest
import torch
from effect_networks.experiments import physics_bounds as pb
from effect_networks.experiments.can_tossing.run import table_one_cases
from effect_networks.experiments.can_tossing.settings import PROTOCOLS
from effect_networks.experiments.cans import can_dataset
from effect_networks.experiments.harness.config import ConfigError

from tests.helpers import InlineExecutor


def test_held_out_best_scores_the_choice_on_the_other_half():
    # repeats (first half | second half); action 1 looks best on the first half
    success = np.array(
        [
            [[1, 0, 1, 1], [1, 1, 0, 0], [0, 0, 1, 1]],  # chooses 1 (first half 2/2): scores 0
            [[1, 1, 1, 0], [0, 0, 1, 1], [1, 1, 1, 1]],  # tie 0 and 2: the lowest, 0: scores 1/2
        ],
        dtype=bool,
    )
    np.testing.assert_array_equal(pb.held_out_best(success), [0.0, 0.5])


def test_tiny_run_end_to_end(tiny_data_dir, tmp_path):
    config = pb.PhysicsBoundsConfig(
        scale="tiny",
        data_dir=tiny_data_dir,
        repeats=2,
        combined_repeats=2,
        step=0.1,
        progress=False,
    )
    result = pb.run_physics_bounds(config)
    assert set(result.table_one) == set(PROTOCOLS)
    data = can_dataset(tiny_data_dir, "tiny", progress=False)
    for protocol, t in result.table_one.items():
        assert t["n_cases"] == len(table_one_cases(data, protocol)[0]) > 0
        assert 0 <= t["exact_fraction_bound"] <= 1 and t["repeats"] == 2
        assert 0 <= t["exact_fraction_in_sample"] <= 1
    assert set(result.combined["0.75"]) == {"top_three", "near_flank", "far_flank"}
    for s in result.combined["0.75"].values():
        for key in ("success_bound", "success_in_sample", "one_throw_bound"):
            assert 0 <= s[key] <= 1
        assert s["n_heights"] > 0 and s["n_states"] >= 1
    result.save(tmp_path)
    assert pb.PhysicsBoundsResult.load(tmp_path / "physics_bounds.json").to_json() == (
        result.to_json()
    )
    assert "| actions |" in (tmp_path / "physics_bounds.md").read_text()


def test_the_robot_s_throws_resume_and_are_shared_by_name(tmp_path):
    kw = dict(table_z=0.75, step=0.2, repeats=2, jitter=0.003, horizon=2, progress=False)
    first = InlineExecutor()
    outcomes = pb.robot_throws(tmp_path, executor=first, **kw)
    assert first.submitted == len(outcomes) >= 2 and 1023 in outcomes
    again = InlineExecutor()
    assert pb.robot_throws(tmp_path, executor=again, **kw).keys() == outcomes.keys()
    assert again.submitted == 0
    (folder,) = tmp_path.glob("robot_throws_*_seed1")
    next((folder / "layer-1").glob("chunk-*.npz")).unlink()
    resumed = InlineExecutor()
    redone = pb.robot_throws(tmp_path, executor=resumed, **kw)
    assert resumed.submitted == 1
    assert all(np.array_equal(redone[s], outcomes[s]) for s in outcomes)
    other = InlineExecutor()
    pb.robot_throws(tmp_path, executor=other, seed=2, **kw)  # another seed: other throws
    assert other.submitted > 0 and len(list(tmp_path.glob("robot_throws_*"))) == 2


def test_cross_fitted_values_average_both_splits():
    # start 0 -> goal 1 with two actions: one half favours action 0, the other action 1
    t = torch.zeros(2, 2, 2, 2, dtype=torch.float64)  # (half, s, a, s')
    t[0, 0, 0], t[0, 0, 1] = torch.tensor([0.0, 1.0]), torch.tensor([0.6, 0.4])
    t[1, 0, 0], t[1, 0, 1] = torch.tensor([0.8, 0.2]), torch.tensor([0.1, 0.9])
    t[:, 1, :, 1] = 1.0
    held, in_sample = pb.cross_fitted_values((t[0], t[1]), 1, 1)
    assert held[1, 0].item() == pytest.approx((0.2 + 0.4) / 2)
    assert in_sample[1, 0].item() == pytest.approx((1.0 + 0.9) / 2)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("repeats", 1),
        ("combined_repeats", 1),
        ("combined_repeats", 3),
        ("step", 0.0),
        ("step", 5.0),
        ("table_z", ()),
        ("table_z", (0.75, -1.0)),
        ("horizon", 0),
    ],
)
def test_config_names_the_field_at_fault(field, value):
    with pytest.raises(ConfigError, match=f"^{field}: ") as raised:
        pb.PhysicsBoundsConfig(**{field: value})
    assert raised.value.field == field
