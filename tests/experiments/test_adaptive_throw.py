"""experiments.adaptive_throw runs end to end with tiny settings; its settings are checked."""

import json

import numpy as np
import pytest

from experiments.adaptive_throw import (
    AdaptiveThrowConfig,
    AdaptiveThrowResult,
    local_inverse,
    run_adaptive_throw,
)
from experiments.config import ConfigError

TINY = {
    "n_train": 400,
    "n_test": 40,
    "bins": (2, 3),
    "em_steps": (1, 3),
    "budgets": (40, 80),
    "batch": 20,
    "pool": 60,
    "noise_repeats": 2,
    "progress": False,
}


def test_runs_and_writes_its_results(tmp_path):
    result = run_adaptive_throw(AdaptiveThrowConfig(**TINY, seed=2))
    result.save(tmp_path)
    saved = json.loads((tmp_path / "adaptive_throw.json").read_text())
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
    assert 0 <= saved["noisy_bound"]["miss_median_m"] <= saved["noisy_bound"]["miss_p90_m"]
    for row in [*saved["noisy"], saved["noisy_bound"]]:
        assert row["ratio_y"] == pytest.approx(row["rms_y_m"] / row["scatter_y_m"])
        assert row["scatter_y_m"] > 0 and row["scatter_z_m"] > 0
    assert all(r["em_steps"] == 0 for r in saved["layouts"] if r["layout"] == "grid")
    assert all(1 <= r["em_steps"] <= 3 for r in saved["layouts"] if r["layout"] == "adaptive")
    curve = np.array(saved["em_log_likelihoods"])
    assert np.all(np.diff(curve) >= -1e-9)  # EM never lowers the likelihood
    assert [r["n"] for r in saved["active"]["random"]] == [40, 80]
    assert [r["n"] for r in saved["active"]["information"]] == [40, 80]
    assert set(saved["goals"]) and all(isinstance(v, bool) for v in saved["goals"].values())
    assert (tmp_path / "adaptive_throw.png").stat().st_size > 10_000
    text = (tmp_path / "adaptive_throw.md").read_text()
    assert "| 9 | adaptive | effect |" in text and "physics' bound" in text


def test_the_local_inverse_is_exact_on_a_quadratic_map():
    """A quadratic forward map is fitted exactly, and Newton converges on its inverse."""
    rng = np.random.default_rng(0)
    targets = rng.uniform(-1, 1.2, (2000, 2)) + [0.0, 1.0]
    hits = np.column_stack([targets[:, 0] + 0.1 * targets[:, 1] ** 2, 0.5 * targets[:, 1]])
    want = rng.uniform(-0.5, 0.5, (20, 2)) + [0.0, 1.4]  # aims inside the target area
    desired = np.column_stack([want[:, 0] + 0.1 * want[:, 1] ** 2, 0.5 * want[:, 1]])
    aims = local_inverse(targets, hits, desired, want + 0.05, 12, iterations=8)
    assert np.allclose(aims, want, atol=1e-9)


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
    ],
)
def test_config_names_the_field_at_fault(field, value):
    with pytest.raises(ConfigError, match=f"^{field}: "):
        AdaptiveThrowConfig(**{field: value})
