"""experiments.throwing runs end to end with tiny settings; its settings are checked."""

import json

import pytest
from effect_networks.experiments.harness.config import ConfigError
from effect_networks.experiments.throwing import ThrowingConfig, ThrowingResult, run_throwing


def test_throwing_runs_and_writes_its_results(tmp_path):
    result = run_throwing(ThrowingConfig(n_train=600, n_test=60, bins=(1, 3), seed=3))
    result.save(tmp_path)
    saved = json.loads((tmp_path / "throwing.json").read_text())
    assert saved == json.loads(result.to_json())
    assert ThrowingResult.load(tmp_path / "throwing.json").to_json() == result.to_json()
    assert (saved["n_train"], saved["n_test"]) == (600, 60)
    assert saved["n_clusters"] in (1, 9)
    assert [row["bins"] for row in saved["cluster_selection"]] == [1, 3]
    for key in ("rms_y_m", "rms_z_m", "rms_y_m_noisy", "noise_scatter_z_m", "timings_s"):
        assert key in saved, key
    assert all(len(p["hits"]) == len(p["error"]) == 60 for p in saved["per_hit"].values())
    assert (tmp_path / "throwing_errors.png").stat().st_size > 10_000
    assert "| paper (its x, y) | 1.780 | 3.050 |" in (tmp_path / "throwing.md").read_text()


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("n_train", -10),
        ("n_test", 0),
        ("seed", -1),
        ("bins", ()),
        ("bins", (4, 0)),
        ("bins", (51,)),
    ],
)
def test_config_names_the_field_at_fault(field, value):
    with pytest.raises(ConfigError, match=f"^{field}: "):
        ThrowingConfig(**{field: value})
