"""Every reachable goal: the learned and empirical transitions, and a tiny run end to end."""

import json

import numpy as np
import pytest
import torch
from effect_networks.experiments import aimed_heights, all_goals
from effect_networks.experiments import physics_bounds as pb
from effect_networks.experiments.all_goals import AllGoalsConfig, AllGoalsResult
from effect_networks.experiments.harness.config import ConfigError
from effect_networks.sim2d import geometry
from effect_networks.sim2d.combined import CAN_BAND, TABLE_TOP_Z, exact_throws
from scipy import stats


@pytest.fixture(scope="module")
def robot():
    return aimed_heights.train_robot(2000, 3, seed=0, noise=None)


def test_empirical_transition_counts_the_chosen_repeats():
    states = [0, 1, 3]
    outcomes = {
        3: np.array([[3, 1, 1, 0], [0, 0, 0, 0]]),
        1: np.array([[1, 1, 0, 0], [1, 0, 1, 0]]),
    }
    first = pb.empirical_transition(states, outcomes, slice(None, 2))
    assert first[2, 0].tolist() == [0.0, 0.5, 0.5] and first[2, 1].tolist() == [1.0, 0.0, 0.0]
    second = pb.empirical_transition(states, outcomes, slice(2, None))
    assert second[1, 1].tolist() == [0.5, 0.5, 0.0]
    assert first[0, :, 0].tolist() == [1.0, 1.0]  # no outcomes: the state stays
    assert torch.allclose(second.sum(-1), torch.ones(3, 2, dtype=torch.float64))


def test_learned_transition_is_a_distribution_and_keeps_a_quiet_world(robot):
    heights = exact_throws(0.05)[0]
    n_s = 4
    rng = np.random.default_rng(0)
    can = torch.as_tensor(rng.dirichlet(np.ones(n_s), size=(n_s, len(heights))))
    t, aims = aimed_heights.learned_transition(can, robot, heights, TABLE_TOP_Z)
    assert t.shape == (n_s, len(heights), n_s) and aims.shape == (len(heights), 2)
    assert torch.allclose(t.sum(-1), torch.ones(n_s, len(heights), dtype=torch.float64))
    # when no hit changes anything, no aim does
    still = torch.eye(n_s, dtype=torch.float64)[:, None, :].expand(n_s, len(heights), n_s)
    quiet, _ = aimed_heights.learned_transition(still, robot, heights, TABLE_TOP_Z)
    assert torch.allclose(quiet, still)


@pytest.mark.parametrize("boundary_sd", [0.0, 0.02])
def test_learned_transition_is_the_chained_sum_written_out(robot, boundary_sd):
    """Against the chain written term by term with scipy's normal CDFs: the hit's lateral
    coordinate in the can band times its height in each aim height's bin; with the bins'
    boundaries uncertain, the height's variance and the boundaries' add."""
    heights = exact_throws(0.05)[0]
    n_s, n_a = 3, len(heights)
    can = torch.as_tensor(np.random.default_rng(1).dirichlet(np.ones(n_s), size=(n_s, n_a)))
    t, aims = aimed_heights.learned_transition(can, robot, heights, TABLE_TOP_Z, boundary_sd)
    mean, cov = robot.hit_distribution(aims)
    half = np.diff(heights).mean() / 2
    want = np.zeros((n_s, n_a, n_s))
    for a in range(n_a):
        across = stats.norm(mean[a, 0], np.sqrt(cov[a, 0, 0]))
        up = stats.norm(mean[a, 1] - TABLE_TOP_Z, np.sqrt(cov[a, 1, 1] + boundary_sd**2))
        band = across.cdf(CAN_BAND) - across.cdf(-CAN_BAND)
        p = [band * (up.cdf(h + half) - up.cdf(h - half)) for h in heights]
        for s in range(n_s):
            want[s, a] = sum(p[b] * can[s, b].numpy() for b in range(n_a))
            want[s, a, s] += 1 - sum(p)
    np.testing.assert_allclose(t.numpy(), want, rtol=0, atol=1e-12)


def test_can_model_learns_a_deterministic_world():
    states = [0, 1, 3]
    heights = np.array([0.1, 0.2])
    outcomes = {3: np.array([[1, 1, 1], [3, 3, 3]]), 1: np.array([[0, 0, 0], [1, 1, 1]])}
    p = aimed_heights.can_model(states, heights, outcomes)
    assert p.shape == (3, 2, 3)
    assert p[2, 0].argmax() == 1 and p[2, 1].argmax() == 2 and p[1, 0].argmax() == 0
    # three throws and a prior of ROW_PRIOR throws spread over the three configurations
    a = aimed_heights.ROW_PRIOR / 3
    assert float(p[2, 0, 1]) == pytest.approx((3 + a) / (3 + 3 * a), rel=1e-12)
    assert float(p[2, 0, 0]) == pytest.approx(a / (3 + 3 * a), rel=1e-12)


@pytest.mark.parametrize(
    "field, value",
    [
        ("step", 0.0),
        ("bound_repeats", 3),
        ("episodes", 0),
        ("table_z", ()),
        ("table_z", (0.75, float("nan"))),
        ("jitter", -1.0),
        ("boundary_spread", "wide"),
        ("executor", "cluster"),
    ],
)
def test_config_names_the_bad_field(field, value):
    with pytest.raises(ConfigError, match=field) as error:
        AllGoalsConfig(**{field: value})
    assert error.value.field == field


def test_tiny_run_end_to_end(tmp_path):
    config = AllGoalsConfig(
        data_dir=tmp_path, table_z=(0.75,), step=0.05, train_repeats=1, bound_repeats=2,
        horizon=2, episodes=2, n_throws=500, bins=2, progress=False, executor="process:2",
    )  # fmt: skip
    result = all_goals.run_all_goals(config)
    (table,) = result.tables
    assert table["n_goals"] == len(all_goals.stable_configurations()) - 1  # all but the full
    assert 0 < table["reachable"] == len(table["goals"]) <= table["n_goals"]
    for g in table["goals"]:
        assert g["goal"] & ~geometry.FULL_PYRAMID == 0 and g["removed"]
        assert 0 < g["bound"] <= 1 and 0 < g["bound_in_sample"] <= 1
        assert 0 <= g["exact_measured"] <= 1 and 0 <= g["paper_measured"] <= 1
        assert 0 <= g["exact_predicted"] <= 1 + 1e-9 and 0 <= g["exact_throws"] <= 2
        # with the default spread the sharp prediction is another model's value of the policy
        assert 0 <= g["exact_predicted_sharp"] <= 1 + 1e-9 and 0 <= g["exact_physics"] <= 1 + 1e-9
    for name, key in all_goals.PREDICTIONS.items():
        r = table["calibration"][name]
        assert r["n"] == table["reachable"]
        assert r["mean_predicted"] == pytest.approx(np.mean([g[key] for g in table["goals"]]))
    files = result.save(tmp_path / "out")
    again = AllGoalsResult.load(files[0])
    assert json.loads(again.to_json()) == json.loads(result.to_json())
    text = result.to_markdown()
    assert "exact planner / bound" in text and text.count("\n| ") >= 2 + table["reachable"]
    assert files[2].stat().st_size > 10_000
    assert "**Calibration**" in text and "physics' own transitions" in text
    assert (tmp_path / "out" / "all_goals_reliability.png").stat().st_size > 10_000


def test_cross_fitted_bound_scores_each_half_s_plan_on_the_other():
    # state 0 (start) -> state 1 (goal); two actions whose success the halves disagree on
    def half(p0, p1):
        t = torch.zeros(2, 2, 2, dtype=torch.float64)
        t[0, 0] = torch.tensor([1 - p0, p0], dtype=torch.float64)
        t[0, 1] = torch.tensor([1 - p1, p1], dtype=torch.float64)
        t[1, :, 1] = 1.0
        return t

    held, in_sample = pb.cross_fitted_bound((half(1.0, 0.5), half(0.5, 1.0)), 1, 0, 1)
    assert held == pytest.approx(0.5) and in_sample == pytest.approx(1.0)
    same = half(0.3, 0.6)
    held, in_sample = pb.cross_fitted_bound((same, same), 1, 0, 2)
    assert held == pytest.approx(1 - 0.4**2) and in_sample == pytest.approx(held)
