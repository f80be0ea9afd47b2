"""experiments.tap_and_remove shows what the paper's §III says it shows."""

import pytest
from effect_networks.experiments.harness.config import ConfigError
from effect_networks.experiments.tap_and_remove import (
    TapAndRemoveConfig,
    TapAndRemoveResult,
    run_tap_and_remove,
)


def test_tap_and_remove(tmp_path):
    result = run_tap_and_remove(TapAndRemoveConfig(n=400, bins=4))
    no_param, one, many = result.rms_m.values()
    assert many < one < no_param  # the parameter site helps, and its clusters help more
    assert result.remove["best_action"] == "remove"
    assert result.remove["surprise_still_there"] > 0.9 > result.remove["surprise_vanished"]
    result.save(tmp_path)
    assert (tmp_path / "tap_and_remove.png").stat().st_size > 10_000
    loaded = TapAndRemoveResult.load(tmp_path / "tap_and_remove.json")
    assert loaded.to_json() == result.to_json()


def test_config_refuses_too_few_rows():
    with pytest.raises(ConfigError, match="^n: -10 is out of range"):
        TapAndRemoveConfig(n=-10)
