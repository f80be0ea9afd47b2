"""experiments.harness.registry: every experiment declared once, in order, with settings that
make valid Configs; the shared can-data settings and the one home of generated data."""

import dataclasses
from pathlib import Path

import pytest
from effect_networks.experiments.cans import CanDataSettings, SimulationSettings, default_data_dir
from effect_networks.experiments.harness.config import ConfigError, Result
from effect_networks.experiments.harness.registry import experiment, experiments

ROOT = Path(__file__).resolve().parents[3]

#: ``./reproduce --quick`` as it was written by hand, step by step: the registry's quick
#: settings must give the same settings (an oracle the registry did not produce).
HAND_WRITTEN_QUICK = {
    "tap_and_remove": ["--n", "600"],
    "can_world": ["--frame-interval", "0.04", "--fps", "12"],
    "throw_kinematics": [],
    "throwing": ["--n-train", "1500", "--n-test", "200", "--bins", "2", "4", "6"],
    "adaptive_throw": [
        *["--n-train", "2000", "--n-test", "200", "--bins", "2", "4", "--noisy-bins", "4"],
        *["--em-steps", "2", "5", "--budgets", "120", "240", "480", "--batch", "40"],
        *["--pool", "400", "--noise-repeats", "3"],
    ],
    "can_tossing": [
        *["--scale", "quick", "--n-demos", "100", "--bound-repeats", "8"],
        *["--curve-repeats", "32"],
    ],
    "combined": ["--scale", "quick", "--n-throws", "5000", "--episodes", "10"],
    "physics_bounds": [
        *["--scale", "quick", "--repeats", "8", "--step", "0.01", "--combined-repeats", "4"],
    ],
    "all_goals": [
        *["--table-z", "0.75", "--step", "0.01", "--train-repeats", "2"],
        *["--bound-repeats", "4", "--episodes", "10", "--n-throws", "5000", "--bins", "8"],
    ],
    "active": [
        *["--scale", "quick", "--repeats", "8", "--fractions", "0.05", "0.1", "0.2", "0.5"],
        *["--batch-size", "20"],
    ],
}


def test_every_experiment_in_the_paper_s_order():
    """Those reproduce ran by hand, in its order (all_goals before active, both after the
    physics bounds whose simulations they reuse); a new experiment goes anywhere."""
    assert [n for n in experiments() if n in HAND_WRITTEN_QUICK] == list(HAND_WRITTEN_QUICK)
    orders = [e.order for e in experiments().values()]
    assert orders == sorted(set(orders))
    for name, exp in experiments().items():
        assert exp.name == name and issubclass(exp.result, Result)
        assert (ROOT / "examples" / f"{name}.py").exists(), name


def test_imitation_s_bound_and_table_one_s_share_their_replays():
    """At every scale the can-tossing bound asks for as many replays as the physics bounds,
    so the two read one simulation."""
    tossing, bounds = experiment("can_tossing"), experiment("physics_bounds")
    for settings in ("tiny", "quick"):
        assert (
            tossing.config(**getattr(tossing, settings)).bound_repeats
            == bounds.config(**getattr(bounds, settings)).repeats
        )
    assert tossing.config().bound_repeats == bounds.config().repeats


@pytest.mark.parametrize("name", list(HAND_WRITTEN_QUICK))
def test_quick_settings_are_those_reproduce_used(name):
    from effect_networks.experiments.harness import cli

    by_hand = cli.parse_args(name, HAND_WRITTEN_QUICK[name]).config
    assert experiment(name).config(**experiment(name).quick) == by_hand


@pytest.mark.parametrize("name", list(HAND_WRITTEN_QUICK))
def test_tiny_and_quick_settings_make_valid_configs(name):
    exp = experiment(name)
    for settings in (exp.tiny, exp.quick):
        config = exp.config(**settings)  # a ConfigError names what is wrong
        assert {k: getattr(config, k) for k in settings} == dict(settings)


def test_an_unknown_experiment_lists_the_known_ones():
    with pytest.raises(ValueError, match="no experiment 'can_tosing'; the experiments are"):
        experiment("can_tosing")


def test_generated_data_lives_in_the_cache_folder_whatever_the_current_directory(
    tmp_path, monkeypatch
):
    monkeypatch.setenv("EFFECT_NETWORKS_CACHE", str(tmp_path / "cache"))
    monkeypatch.chdir(tmp_path)
    assert default_data_dir() == tmp_path / "cache" / "data"
    for name, exp in experiments().items():
        if "data_dir" in exp.fields:
            assert exp.config().data_dir == tmp_path / "cache" / "data", name
            assert exp.config(data_dir="here").data_dir == Path("here"), name


def test_the_can_data_settings_are_written_once():
    """Every experiment on the can data set takes them from one base, with its checks."""
    can = [e for e in experiments().values() if "scale" in e.fields]
    assert {e.name for e in can} == {
        *("can_tossing", "combined", "physics_bounds", "active", "can_demonstration")
    }
    simulating = [e for e in experiments().values() if "executor" in e.fields]
    for exp in simulating:
        assert issubclass(exp.config, SimulationSettings), exp.name
        with pytest.raises(ConfigError, match="^executor: "):
            exp.config(executor="threads")
    for exp in can:
        assert issubclass(exp.config, CanDataSettings), exp.name
        with pytest.raises(ConfigError, match="^scale: 'huge' is not one of 'full'"):
            exp.config(scale="huge")
    shared = {f.name for f in dataclasses.fields(CanDataSettings)}
    assert shared == {"scale", "data_dir", "executor"}
