"""experiments.adaptive_throw runs end to end with tiny settings; its settings are checked."""

import dataclasses
import json
import re

import numpy as np
import pytest
import torch
from effect_networks.experiments.adaptive_throw import aiming
from effect_networks.experiments.adaptive_throw.active_curves import near_edge
from effect_networks.experiments.adaptive_throw.aiming import error_causes, error_tail
from effect_networks.experiments.adaptive_throw.report import summary_rows
from effect_networks.experiments.adaptive_throw.run import (
    AdaptiveThrowResult,
    local_inverse,
    plane_residuals,
    run_adaptive_throw,
)
from effect_networks.experiments.adaptive_throw.settings import CAUSES, AdaptiveThrowConfig
from effect_networks.experiments.harness.config import ConfigError
from effect_networks.experiments.harness.registry import experiment
from effect_networks.inference import infer_parameter
from effect_networks.sim2d.analytic_throw import TARGET_AREA

from tests.helpers import ADAPTIVE_THROW_TINY as TINY


def test_runs_and_writes_its_results(tmp_path):
    result = run_adaptive_throw(AdaptiveThrowConfig(**TINY, seed=2))
    experiment("adaptive_throw").save(result, tmp_path)
    saved = json.loads((tmp_path / "adaptive_throw.json").read_text())
    assert saved["pseudo_count"] == 0.0
    assert AdaptiveThrowResult.load(tmp_path / "adaptive_throw.json").to_json() == result.to_json()
    assert [(r["layout"], r["n_clusters"], r["query"]) for r in saved["layouts"]] == [
        (layout, k, query)
        for k, layouts in (
            (4, ("grid", "adaptive", "adaptive")),
            (9, ("grid", "adaptive", "adaptive")),
        )
        for layout in layouts
        for query in ("posterior", "effect")
    ]
    assert [(r["layout"], r["query"]) for r in saved["noisy"]] == [
        ("grid", "posterior"),
        ("grid", "effect"),
        ("adaptive", "posterior"),
        ("adaptive", "effect"),
    ]
    assert all(r["n_clusters"] == 4 for r in saved["noisy"])  # noisy_bins, not bins[-1]
    assert 0 <= saved["noisy_bound"]["miss_median_m"] <= saved["noisy_bound"]["miss_p90_m"]
    for row in [*saved["noisy"], saved["noisy_bound"]]:
        assert row["ratio_y"] == pytest.approx(row["rms_y_m"] / row["scatter_y_m"])
        assert row["scatter_y_m"] > 0 and row["scatter_z_m"] > 0
    for row in saved["layouts"]:  # the best candidate is at least as good as the chosen one
        assert ("best_rms_y_m" in row) == (row["query"] == "effect")
        if row["query"] == "effect":
            best = row["best_rms_y_m"] ** 2 + row["best_rms_z_m"] ** 2
            assert best <= row["rms_y_m"] ** 2 + row["rms_z_m"] ** 2 + 1e-15
    assert [r["n_clusters"] for r in saved["pieces"]] == [4, 9]
    assert all(r["rms_y_m"] >= 0 and r["rms_z_m"] > 0 for r in saved["pieces"])
    assert all(r["em_steps"] == 0 for r in saved["layouts"] if r["layout"] == "grid")
    assert all(1 <= r["em_steps"] <= 3 for r in saved["layouts"] if r["layout"] == "adaptive")
    curve = np.array(saved["em_log_likelihoods"])
    assert np.all(np.diff(curve) >= -1e-9)  # EM never lowers the likelihood
    assert set(saved["active"]) == {"random", "information", "variance"}
    for curve in saved["active"].values():
        assert [r["n"] for r in curve] == [40, 80]
        for r in curve:  # the mean of the two seeds' curves
            assert len(r["seeds_y_m"]) == 2
            assert r["rms_y_m"] == pytest.approx(np.mean(r["seeds_y_m"]))
    # every strategy starts from the same random targets, seed by seed
    first = {s: curve[0]["seeds_y_m"] for s, curve in saved["active"].items()}
    assert first["random"] == first["information"] == first["variance"]
    assert [(r["n"], r["bins"]) for r in saved["active_floor"]] == [(40, 2), (80, 2)]
    for curve in saved["active"].values():  # chosen targets near a cell's edge
        assert curve[0]["edge_share"] is None and 0 <= curve[1]["edge_share"] <= 1
    assert set(saved["goals"]) and all(isinstance(v, bool) for v in saved["goals"].values())
    assert (tmp_path / "adaptive_throw.png").stat().st_size > 10_000
    text = (tmp_path / "adaptive_throw.md").read_text()
    assert "| 9 | adaptive | effect |" in text and "physics' bound" in text
    assert "least-squares plane per equidistant cell" in text
    assert "the expected reduction of the predictive variance summed over the target area" in text
    assert "times the error of the same grid fitted on all 400 training throws" in text
    # where the inverse model's error lies: the causes' shares add up to the whole
    for row in saved["layouts"]:
        if row["query"] != "effect":
            continue
        tail = row["tail"]
        for axis in "yz":
            shares = [tail[f"share_{axis}_{c}"] for c in CAUSES]
            if shares[0] is not None:
                assert sum(shares) == pytest.approx(1.0)
                assert 0 <= tail[f"worst_share_{axis}"] <= 1 + 1e-12
        lengths = [np.hypot(h["error_y_m"], h["error_z_m"]) for h in tail["worst_hits"]]
        assert lengths == sorted(lengths, reverse=True)
    assert "Where the inverse model's squared re-throw error lies" in text


def test_near_edge_marks_the_outer_tenth_of_each_cell():
    low, high = np.asarray(TARGET_AREA.low), np.asarray(TARGET_AREA.high)
    width = (high - low) / 4
    centre = low + 1.5 * width
    points = np.stack([centre, centre + [0.45, 0.0] * width, centre + [0.0, -0.41] * width])
    assert near_edge(points, 4).tolist() == [False, True, True]
    uniform = np.random.default_rng(0).uniform(low, high, (200_000, 2))
    assert near_edge(uniform, 4).mean() == pytest.approx(1 - 0.8**2, abs=0.005)


def test_error_causes_in_their_order_of_precedence():
    error = np.array([[0.0, 4.0], [0.0, 4.0], [0.0, 4.0], [0.0, 4.0], [3.0, 0.0]])
    best = np.array([[0.0, 1.0], [0.0, 3.0], [0.0, 1.0], [0.0, 1.0], [0.0, 0.0]])
    outside = np.array([False, False, False, True, False])
    clamped = np.array([False, False, True, True, False])
    cause = error_causes(error, best, outside, clamped)
    # a better candidate (1 < 4 / 2); no much better one; clamped first; clipped before all
    assert [CAUSES[c] for c in cause] == ["choice", "curvature", "clamped", "clipped", "choice"]


def test_error_tail_by_hand():
    # squares on z: 16, 1, 1, 1, 1 (total 20); on y only the last hit, 9
    error = np.array([[0.0, 4.0], [0.0, 1.0], [0.0, -1.0], [0.0, 1.0], [3.0, 1.0]])
    desired = np.arange(10.0).reshape(5, 2)
    cause = np.array([CAUSES.index(c) for c in ("clamped", *["curvature"] * 3, "choice")])
    tail = error_tail(error, cause, desired, worst=0.2, shown=2)
    assert tail["n_worst"] == 1  # a fifth of five hits
    # the worst hit: the first, length 4 against the last's sqrt(10)
    assert tail["worst_share_z"] == pytest.approx(16 / 20) and tail["worst_share_y"] == 0.0
    assert tail["share_z_clamped"] == pytest.approx(16 / 20)
    assert tail["share_z_curvature"] == pytest.approx(3 / 20)
    assert tail["share_y_choice"] == 1.0 and tail["share_z_clipped"] == 0.0
    assert [h["cause"] for h in tail["worst_hits"]] == ["clamped", "choice"]
    assert tail["worst_hits"][1]["desired_y_m"] == 8.0
    # an axis without error (rounding only) has no shares
    flat = error_tail(error * [1e-9, 1.0], cause, desired)
    assert flat["share_y_choice"] is None and flat["worst_share_y"] is None


def test_plane_residuals_vanish_on_planes_and_match_a_parabola():
    """Exact per cell on a map that is a different plane in every cell; on a parabola,
    the residual RMS of a line over a cell of width h, a * h**2 / (6 * sqrt(5))."""
    rng = np.random.default_rng(1)
    targets = rng.uniform([-1.0, 0.4], [1.0, 2.4], (200_000, 2))
    cell = np.minimum((targets - [-1.0, 0.4]) // 0.5, 3).astype(int) @ [4, 1]  # 4 x 4 cells
    slopes = rng.normal(size=(16, 2, 2))
    hits = np.einsum("nij,nj->ni", slopes[cell], targets) + rng.normal(size=(16, 2))[cell]
    assert np.abs(plane_residuals(targets, hits, 4)).max() < 1e-9
    curved = np.column_stack([targets[:, 0], 0.1 * targets[:, 1] ** 2])
    residual = plane_residuals(targets, curved, 4)
    assert np.abs(residual[:, 0]).max() < 1e-9
    want = 0.1 * 0.5**2 / (6 * np.sqrt(5))
    assert np.sqrt(np.mean(residual[:, 1] ** 2)) == pytest.approx(want, rel=0.01)
    # a plane across the cells leaves the rows of one cell out: no residual there
    use = cell != 5
    residual = plane_residuals(targets, curved, 4, use=use)
    assert np.isnan(residual[~use]).all() and not np.isnan(residual[use]).any()
    few = plane_residuals(targets[:3], curved[:3], 1)
    assert np.isnan(few).all()  # three rows cannot fix a plane and its residual


@pytest.mark.parametrize(
    ("targets", "hits", "bins", "use", "match"),
    [
        (np.zeros((5, 2)), np.zeros((4, 2)), 2, None, "two \\(n, 2\\) arrays"),
        (np.zeros((5, 3)), np.zeros((5, 3)), 2, None, "two \\(n, 2\\) arrays"),
        (np.ones((5, 2)), np.ones((5, 2)), 2, np.ones(4, dtype=bool), "boolean mask"),
        (np.ones((5, 2)), np.ones((5, 2)), 2, np.ones(5), "boolean mask"),
        (np.ones((5, 2)), np.ones((5, 2)), 0, None, "bins"),
    ],
)
def test_plane_residuals_refuses_bad_input(targets, hits, bins, use, match):
    with pytest.raises(ValueError, match=match):
        plane_residuals(targets, hits, bins, use=use)


def test_the_local_inverse_is_exact_on_a_quadratic_map():
    """A quadratic forward map is fitted exactly, and Newton converges on its inverse."""
    rng = np.random.default_rng(0)
    targets = rng.uniform(-1, 1.2, (2000, 2)) + [0.0, 1.0]
    hits = np.column_stack([targets[:, 0] + 0.1 * targets[:, 1] ** 2, 0.5 * targets[:, 1]])
    want = rng.uniform(-0.5, 0.5, (20, 2)) + [0.0, 1.4]  # aims inside the target area
    desired = np.column_stack([want[:, 0] + 0.1 * want[:, 1] ** 2, 0.5 * want[:, 1]])
    aims = local_inverse(targets, hits, desired, want + 0.05, 12, iterations=8)
    assert np.allclose(aims, want, atol=1e-9)


def test_the_local_inverse_neighbours_are_the_nearest_by_the_pairs_sum():
    """The aims equal, bit for bit, those of the same Newton steps with each training
    throw's squared distance summed over the pair by numpy (``.sum(-1)``)."""

    def reference(targets, hits, desired, start, neighbours, iterations=4):
        aims = np.clip(np.array(start, dtype=np.float64), TARGET_AREA.low, TARGET_AREA.high)
        for i, goal in enumerate(desired):
            aim, best, best_miss = aims[i].copy(), aims[i].copy(), np.inf
            for _ in range(iterations + 1):
                d2 = ((targets - aim) ** 2).sum(-1)
                rows = np.argpartition(d2, neighbours - 1)[:neighbours]
                u = targets[rows] - aim
                design = np.column_stack(
                    [np.ones(len(u)), u, u[:, 0] ** 2, u[:, 0] * u[:, 1], u[:, 1] ** 2]
                )
                coef = np.linalg.lstsq(design, hits[rows], rcond=None)[0]
                miss = float(np.linalg.norm(goal - coef[0]))
                if miss < best_miss:
                    best, best_miss = aim.copy(), miss
                step = np.linalg.lstsq(coef[1:3].T, goal - coef[0], rcond=1e-3)[0]
                radius = float(np.sqrt(d2[rows].max()))
                norm = float(np.linalg.norm(step))
                if norm > radius:
                    step *= radius / norm
                aim = np.clip(aim + step, TARGET_AREA.low, TARGET_AREA.high)
            aims[i] = best
        return aims

    rng = np.random.default_rng(4)
    low, high = np.asarray(TARGET_AREA.low), np.asarray(TARGET_AREA.high)
    targets = rng.uniform(low, high, (500, 2))
    hits = np.column_stack([np.sin(targets[:, 0]) + targets[:, 1] ** 2, targets.prod(-1)])
    desired = hits[:15] + rng.normal(0, 0.01, (15, 2))
    start = targets[:15] + rng.normal(0, 0.05, (15, 2))
    got = local_inverse(targets, hits, desired, start, 12)
    assert np.array_equal(got, reference(targets, hits, desired, start, 12))


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("n_train", 10),
        ("em_steps", (0,)),
        ("em_steps", (5, 5)),
        ("tol", 0.0),
        ("neighbours", 3),
        ("bins", ()),
        ("bins", (0,)),
        ("budgets", (100, 100)),
        ("budgets", (5,)),
        ("pool", 10),
        ("noise_repeats", 0),
        ("pseudo_count", -0.1),
        ("noisy_bins", 0),
        ("pseudo_count", float("nan")),
    ],
)
def test_config_names_the_field_at_fault(field, value):
    with pytest.raises(ConfigError, match=f"^{field}: "):
        AdaptiveThrowConfig(**{field: value})


@pytest.mark.parametrize("layout", ["grid", "adaptive"])
def test_every_fit_takes_the_configured_pseudo_count(layout):
    """The fits are the library's with the config's pseudo-count, not its default."""
    from effect_networks.experiments.adaptive_throw.run import _fit, adaptive_throw_network
    from effect_networks.inference import fit, fit_em
    from effect_networks.models.humanoid_throw import throw_data, throw_network
    from effect_networks.sim2d.analytic_throw import sample_targets, throw

    targets = sample_targets(300, np.random.default_rng(0))
    train = (targets, throw(targets).hit)
    config = AdaptiveThrowConfig(**TINY | {"em_steps": (2,), "pseudo_count": 0.5})
    (net, params), _, _ = _fit(layout, 3, train, config)[-1]
    if layout == "grid":
        net = throw_network((3, 3))
        want = fit(net, throw_data(net, *train), pseudo_count=0.5).params
    else:
        net = adaptive_throw_network((3, 3))
        want = fit_em(net, throw_data(net, *train), steps=2, pseudo_count=0.5).params
    assert torch.allclose(params["cluster.target"].probs, want["cluster.target"].probs)
    for site in ("param.target", "end.hit"):
        assert torch.allclose(params[site].bias, want[site].bias)
        assert torch.allclose(params[site].covariance, want[site].covariance)


def test_each_posterior_answer_is_computed_once(monkeypatch):
    """The local fit starts from the largest grid's posterior answers of its row: one
    posterior query per posterior row of the tables and per point of the active curves,
    none repeated."""
    calls = []

    def counted(*args, **kwargs):
        calls.append(args[0])
        return infer_parameter(*args, **kwargs)

    monkeypatch.setattr(aiming, "infer_parameter", counted)
    result = run_adaptive_throw(AdaptiveThrowConfig(**TINY, seed=2))
    rows = [r for r in result.layouts + result.noisy if r["query"] == "posterior"]
    points = TINY["active_seeds"] * sum(len(curve) for curve in result.active.values())
    assert len(calls) == len(rows) + points + len(result.active_floor)


def test_the_summary_row_shown_does_not_depend_on_the_fit_times():
    """The adaptive layout is shown at its first EM checkpoint however fast it was fitted:
    the same results with other fit times give the same row, times apart."""
    result = run_adaptive_throw(AdaptiveThrowConfig(**TINY, seed=2))
    slow = dataclasses.replace(
        result, layouts=[{**row, "fit_s": 100.0 + row["fit_s"]} for row in result.layouts]
    )
    strip = lambda rows: [re.sub(r"fit [0-9.]+ s", "fit T", r) for r in rows]  # noqa: E731
    assert strip(summary_rows(result, {})) == strip(summary_rows(slow, {}))
    first = min(r["em_steps"] for r in result.layouts if r["layout"] == "adaptive")
    assert f"{first} EM steps" in " ".join(summary_rows(result, {}))
