"""experiments.combined: the whole experiment at the tiny scale, and its settings' checks."""

import numpy as np
import pytest

from experiments.combined import (
    SCENARIOS,
    CombinedConfig,
    CombinedResult,
    field_link,
    run_combined,
)
from experiments.config import ConfigError
from sim2d import geometry
from sim2d.combined import CAN_BAND


def test_tiny_run_end_to_end(tiny_data_dir, tmp_path):
    config = CombinedConfig(
        scale="tiny",
        data_dir=tiny_data_dir,
        n_throws=3000,
        bins=6,
        episodes=2,
        horizon=2,
        progress=False,
    )
    result = run_combined(config)
    assert set(result.scenarios) == set(SCENARIOS) == {"top_three", "near_flank", "far_flank"}
    for s in result.scenarios.values():
        assert 0.0 <= s["success_rate"] <= 1.0 and 0.0 <= s["success_rate_exact_planner"] <= 1.0
        assert 0.0 <= s["exact_planner_predicted"] <= 1.0 + 1e-9
        first = s["rounds"][0]
        assert first["actions"] == first["success"] + first["fail_too_many"] + first[
            "fail_no_hit"
        ] + sum(first["intermediate"].values())
    assert result.angle_choice["chosen_angle"] in geometry.ANGLE_NAMES
    result.save(tmp_path)
    assert (tmp_path / "combined.md").read_text().count("success rate") == 3
    assert CombinedResult.load(tmp_path / "combined.json").to_json() == result.to_json()


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("n_throws", -10),
        ("bins", 0),
        ("horizon", 0),
        ("episodes", 0),
        ("table_z", -0.1),
        ("table_z", 1e9),
        ("jitter", -0.001),
        ("jitter", 1.0),
        ("proposals", "all"),
        ("seed", -3),
    ],
)
def test_config_names_the_field_at_fault(field, value):
    with pytest.raises(ConfigError, match=f"^{field}: ") as raised:
        CombinedConfig(**{field: value})
    assert raised.value.field == field


def test_field_link_reads_a_hit_as_the_nearest_field_in_the_band():
    """Each hit height goes to the field whose height is nearest; beside the band: none."""
    rng = np.random.default_rng(0)
    heights = np.full(195, np.nan)
    fields = np.sort(rng.choice(195, 12, replace=False))
    heights[fields] = rng.uniform(0.0, 0.4, 12)
    link, order = field_link(heights, fields)
    assert sorted(order.tolist()) == fields.tolist()
    z = rng.uniform(-0.1, 0.5, 200)
    y = rng.uniform(-2 * CAN_BAND, 2 * CAN_BAND, 200)
    got = link(np.stack([y, z], -1))
    nearest = fields[np.abs(heights[fields][None, :] - z[:, None]).argmin(-1)]
    want = [
        int(f) if abs(lateral) < CAN_BAND else link.none
        for f, lateral in zip(nearest, y, strict=True)
    ]
    assert got == want
