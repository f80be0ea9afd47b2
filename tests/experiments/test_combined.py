"""experiments.combined: the whole experiment at the tiny scale, and its settings' checks."""

import math
from dataclasses import replace

import numpy as np
import pytest
from effect_networks.experiments.cans import can_dataset
from effect_networks.experiments.combined import (
    SCENARIOS,
    CombinedConfig,
    CombinedResult,
    face_height_spread,
    field_link,
    hit_gaussians,
    run_combined,
)
from effect_networks.experiments.harness.config import ConfigError
from effect_networks.inference.sequences.chaining import link_probabilities
from effect_networks.sim2d import geometry, materials
from effect_networks.sim2d.combined import CAN_BAND
from effect_networks.sim2d.field_throws import aim_offset, launch_state


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
        assert 0.0 <= s["exact_planner_predicted_sharp"] <= 1.0 + 1e-9
        assert s["first_field_ties"] >= 1 and s["first_throw_speed"] > 0
        assert -90 < s["first_throw_deg"] < 0  # the ball descends onto the pyramid
        transfer = s["transfer"]
        assert transfer["field"] == s["exact_planner_first_field"] and transfer["repeats"] == 24
        assert transfer["values"]["planner"] == pytest.approx(
            s["exact_planner_predicted"], abs=1e-12
        )
        first = s["rounds"][0]
        assert first["actions"] == first["success"] + first["fail_too_many"] + first[
            "fail_no_hit"
        ] + sum(first["intermediate"].values())
    assert result.angle_choice["chosen_angle"] in geometry.ANGLE_NAMES
    angle = geometry.ANGLE_NAMES.index(result.angle_choice["chosen_angle"])
    data = can_dataset(tiny_data_dir, "tiny", progress=False)
    assert result.angle_choice["boundary_sd"] == face_height_spread(data, angle) > 0
    result.save(tmp_path)
    assert (tmp_path / "combined.md").read_text().count("success rate") == 3
    assert (tmp_path / "combined.md").read_text().count("with sharp field boundaries") == 3
    assert (tmp_path / "combined.md").read_text().count("the robot's throw there arrives") == 3
    assert (tmp_path / "combined.md").read_text().count("| the robot's throw does") == 3
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
        ("boundary_spread", "wide"),
        ("transfer_repeats", 0),
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


class FixedHits:
    """A robot stand-in whose predicted hit is given: means ``(n, 2)``, covariances ``(n, 2, 2)``."""

    def __init__(self, mean, cov):
        self.mean, self.cov = np.asarray(mean, float), np.asarray(cov, float)

    def hit_distribution(self, aims):
        return self.mean, self.cov


def normal_cdf(x, mean, sd):
    return 0.5 * (1 + math.erf((x - mean) / (sd * math.sqrt(2))))


def slice_chance(low, high, mean, sd):
    """The chance that a normal height falls in ``[low, high)``."""
    return normal_cdf(high, mean, sd) - normal_cdf(low, mean, sd)


@pytest.mark.parametrize("spread", [0.0, 0.002, 0.006])
def test_field_spread_integrates_over_the_fields_boundaries(spread):
    """A hit read with the fields' boundaries moved together by a normal offset of sd
    ``spread``: each field's chance is the integral, over the offset, of the chance that the
    hit's height falls in the field's moved slice (trapezoid rule here) times the chance
    that it falls in the can band."""
    heights = np.full(195, np.nan)
    fields = np.array([3, 17, 40, 41, 77, 120])
    heights[fields] = [0.100, 0.104, 0.105, 0.111, 0.130, 0.200]
    link, order = field_link(heights, fields)
    table_z = 0.75
    mean = np.array([[0.001, table_z + 0.104], [-0.003, table_z + 0.112], [0.0, table_z + 0.3]])
    cov = np.array([np.diag([1e-6, 4e-6]), np.diag([4e-6, 1e-8]), np.diag([1e-6, 1e-6])])
    got = link_probabilities(
        link, hit_gaussians(FixedHits(mean, cov), None, table_z, boundary_sd=spread)
    )
    h = heights[order]
    edges = np.concatenate([[-np.inf], (h[1:] + h[:-1]) / 2, [np.inf]])
    offsets = np.linspace(-9, 9, 3601) * spread
    weight = (
        np.exp(-0.5 * (offsets / spread) ** 2) / (spread * math.sqrt(2 * math.pi))
        if spread
        else None
    )
    for row, ((y, z), c) in enumerate(zip(mean, cov, strict=True)):
        z, sd_y, sd_z = z - table_z, math.sqrt(c[0, 0]), math.sqrt(c[1, 1])
        band = slice_chance(-CAN_BAND, CAN_BAND, y, sd_y)
        for k, f in enumerate(order):
            if spread:
                chances = [slice_chance(edges[k] + u, edges[k + 1] + u, z, sd_z) for u in offsets]
                want = np.trapezoid(weight * np.array(chances), offsets)
            else:
                want = slice_chance(edges[k], edges[k + 1], z, sd_z)
            assert float(got.prob(int(f))[row]) == pytest.approx(band * want, abs=1e-7)
        assert float(got.none[row]) == pytest.approx(1 - band, abs=1e-12)
    if spread:  # the boundaries' spread reaches fields that the hit alone does not
        sharp = link_probabilities(link, hit_gaussians(FixedHits(mean, cov), None, table_z))
        assert float(got.prob(40)[1]) > 0.01 > float(sharp.prob(40)[1])


def test_face_height_spread_is_where_the_training_throws_crossed_the_near_face(tiny_data_dir):
    """Against each throw flown from its own jittered launch state to the near face; only
    throwable throws at the angle count, and the outcomes play no part."""
    data = can_dataset(tiny_data_dir, "tiny", progress=False)
    jitter = data.metadata["jitter"]
    for angle in range(len(geometry.ANGLES)):
        sel = np.flatnonzero((data.angle == angle) & data.throwable)
        shifts = []
        for i in sel:
            field, seed = int(data.field[i]), int(data.seed[i])
            crossings = []
            for offset in (aim_offset(jitter, seed), (0.0, 0.0)):
                (x0, z0), (vx, vz) = launch_state(field, angle, offset=offset)
                t = (geometry.PYRAMID_X - x0) / vx
                crossings.append(z0 + vz * t - 0.5 * materials.GRAVITY * t * t)
            shifts.append(crossings[0] - crossings[1])
        want = math.sqrt(np.mean(np.square(shifts)))
        assert face_height_spread(data, angle) == pytest.approx(want, rel=1e-9)
        assert jitter / 2 < want < 3 * jitter  # the jitter per axis, seen along the throw
    rng = np.random.default_rng(1)
    shuffled = replace(
        data,
        end_config=rng.permutation(data.end_config),
        thrown_off=rng.permutation(data.thrown_off),
        hit_any_can=rng.permutation(data.hit_any_can),
    )
    assert face_height_spread(shuffled, 1) == face_height_spread(data, 1)
    no_jitter = replace(data, metadata=data.metadata | {"jitter": 0.0})
    assert face_height_spread(no_jitter, 1) == 0.0


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_top_three_exact_planner_near_its_bound_at_full_scale(seed):
    """Table II at the full scale (the physics bound: 99 % held out). A sharp link read
    each aim as one field's three throws, and at seed 0 the plan took the luckiest field
    (16 %)."""
    result = run_combined(CombinedConfig(seed=seed, progress=False))
    assert result.scenarios["top_three"]["success_rate_exact_planner"] >= 0.9
