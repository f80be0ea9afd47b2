"""experiments.demonstration reads the door world's demonstrations as its rules say."""

import numpy as np
import pytest
from effect_networks.experiments.demonstration import (
    SHOWN,
    DemonstrationConfig,
    DemonstrationResult,
    door_network,
    door_rows,
    run_demonstration,
)
from effect_networks.experiments.harness.config import ConfigError
from effect_networks.inference import explain, fit


def test_the_shown_demonstration_follows_the_rules(tmp_path):
    result = run_demonstration(DemonstrationConfig(n=600, n_demos=40, steps=3))
    # switch off -> on: press; door shut -> open: turn; drawer shut -> open: pull; the
    # switch on -> off: press
    assert [result.shown["best"][t] for t in (0, 1, 2, 4)] == ["press", "turn", "pull", "press"]
    for t in (0, 1, 2, 4):
        assert max(result.shown["probs"][t]) > 0.9
    assert not any(result.shown["implausible"])
    for row in result.shown["probs"]:
        assert sum(row) == pytest.approx(1.0)
    d = result.drawn
    assert d["n_demos"] == 40 and d["steps"] == 3
    assert 0 <= d["viterbi"] <= 1 and d["viterbi_changed"] > d["viterbi"] > 0.3
    result.save(tmp_path)
    assert (tmp_path / "demonstration.png").stat().st_size > 10_000
    loaded = DemonstrationResult.load(tmp_path / "demonstration.json")
    assert loaded.to_json() == result.to_json()


def test_the_rows_follow_the_rules():
    rows = door_rows(2000, 1)
    waited = rows["action"] == "wait"
    for name in ("door", "drawer", "switch"):
        assert (rows[f"initial.{name}"][waited] == rows[f"end.{name}"][waited]).all()
    locked = rows["initial.door"] == "locked"
    assert (rows["end.door"][locked] == "locked").all()
    pressed = rows["action"] == "press"
    flipped = rows["initial.switch"][pressed] != rows["end.switch"][pressed]
    assert 0.85 < flipped.mean() < 0.95


def test_a_locked_door_opening_is_implausible():
    net = door_network()
    params = fit(net, door_rows(3000, 0)).params
    demo = [dict(SHOWN[0], door="locked"), dict(SHOWN[0], door="open")]
    assert bool(explain(net, params, demo).implausible[0, 0])
    assert not bool(explain(net, params, list(SHOWN[:2])).implausible[0, 0])


def test_config_refuses_bad_settings():
    with pytest.raises(ConfigError, match="^hidden: 1.5 is out of range"):
        DemonstrationConfig(hidden=1.5)
    with pytest.raises(ConfigError, match="^steps: 0 is out of range"):
        DemonstrationConfig(steps=0)
    assert np.isclose(DemonstrationConfig().hidden, 0.3)
