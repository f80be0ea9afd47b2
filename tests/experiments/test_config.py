"""experiments.config: the checks name the field, the value and what was expected; a
script turns them into a usage error naming the option; results round-trip through JSON."""

import argparse
import math
from dataclasses import dataclass

import numpy as np
import pytest

from experiments.config import (
    ConfigError,
    Result,
    check_choice,
    check_executor,
    check_float,
    check_int,
    config_or_exit,
)


@pytest.mark.parametrize(
    ("value", "message"),
    [
        (-10, "n_train: -10 is out of range; expected an integer >= 1"),
        (2.0, "n_train: 2.0 is not an integer; expected an integer >= 1"),
        (True, "n_train: True is a bool; expected an integer >= 1"),
        ("7", "n_train: '7' is not an integer; expected an integer >= 1"),
    ],
)
def test_check_int_refuses(value, message):
    with pytest.raises(ConfigError) as raised:
        check_int("n_train", value, 1)
    assert str(raised.value) == message and raised.value.field == "n_train"


def test_check_int_accepts_numpy_integers_and_bounds():
    assert check_int("k", np.int64(3), 1, 3) == 3
    with pytest.raises(ConfigError, match=r"expected an integer in 1\.\.3"):
        check_int("k", 4, 1, 3)


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf, 0.0, 1.5, "0.1", None, False])
def test_check_float_refuses(value):
    with pytest.raises(ConfigError, match=r"^aim_error: .*expected a number in \(0, 1\] m$"):
        check_float("aim_error", value, 0.0, 1.0, low_open=True, unit="m")


def test_check_float_accepts_the_closed_ends():
    assert check_float("x", 0, 0.0, 1.0) == 0.0
    assert check_float("x", np.float32(1.0), 0.0, 1.0) == 1.0


def test_check_choice_and_executor():
    assert check_choice("rule", "aim", ("index", "aim")) == "aim"
    with pytest.raises(ConfigError, match="rule: 'best' is not one of 'index', 'aim'"):
        check_choice("rule", "best", ("index", "aim"))
    assert check_executor("executor", None) is None
    assert check_executor("executor", "dask://host:8786") == "dask://host:8786"
    with pytest.raises(ConfigError, match="^executor: executor='threads' is not an executor"):
        check_executor("executor", "threads")


def test_config_or_exit_is_a_usage_error_naming_the_option(capsys):
    parser = argparse.ArgumentParser(prog="demo")
    with pytest.raises(SystemExit) as exited:
        config_or_exit(parser, lambda: check_int("n_train", -10, 1))
    assert exited.value.code == 2
    assert "demo: error: --n-train: -10 is out of range" in capsys.readouterr().err
    assert config_or_exit(parser, lambda: 5) == 5


@dataclass
class Toy(Result):
    name: str
    values: list[float]
    nested: dict[str, dict]


def test_result_round_trip_and_refusal(tmp_path):
    toy = Toy("a", [1.0, 2.5], {"x": {"y": None}})
    assert Toy.from_json(toy.to_json()) == toy
    (tmp_path / "toy.json").write_text(toy.to_json())
    assert Toy.load(tmp_path / "toy.json") == toy
    with pytest.raises(ValueError, match=r"not a Toy: the JSON lacks \['nested'\]"):
        Toy.from_json('{"name": "a", "values": []}')
