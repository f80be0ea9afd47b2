"""experiments.harness.config: the checks name the field, the value and what was expected; a
script turns them into a usage error naming the option; results round-trip through JSON."""

import argparse
import errno
import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import pytest
from effect_networks.experiments.harness.config import (
    ConfigError,
    Result,
    check_choice,
    check_executor,
    check_float,
    check_int,
    check_threads,
    config_or_exit,
    run_script,
)
from effect_networks.sim2d.chunks import write_text
from effect_networks.sim2d.executors import ExecutorUnavailable


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


@dataclass
class Drawn(Result):
    experiment_name: ClassVar[str] = "drawn"

    value: float

    def to_markdown(self) -> str:
        return f"value {self.value}\n"

    def figures(self, out):
        return [write_text(out / "drawn.txt", "a figure")]


def test_save_writes_the_json_the_report_and_the_figures(tmp_path):
    out = tmp_path / "made" / "here"
    files = Drawn(2.5).save(out)
    assert files == [out / "drawn.json", out / "drawn.md", out / "drawn.txt"]
    assert Drawn.load(out / "drawn.json") == Drawn(2.5)
    assert (out / "drawn.md").read_text() == "value 2.5\n"
    assert not list(out.glob(".*"))  # no temporary file left
    assert Toy("a", [], {}).summary_rows({}) == [] and Toy("a", [], {}).figures(out) == []


@pytest.mark.parametrize(
    ("text", "why"),
    [
        ("null", "the JSON is a NoneType, not an object"),
        ("[1, 2]", "the JSON is a list, not an object"),
        ('{"name": ', r"unreadable JSON \(JSONDecodeError\)"),
        ("[" * 100_000 + "]" * 100_000, r"unreadable JSON \(RecursionError\)"),
    ],
)
def test_a_damaged_result_file_is_named(tmp_path, text, why):
    path = tmp_path / "toy.json"
    path.write_text(text)
    with pytest.raises(ValueError, match=rf"^{tmp_path}/toy\.json: not a Toy: {why}"):
        Toy.load(path)


def _raising(error: BaseException):
    def main(args):
        raise error

    return main


@pytest.mark.parametrize(
    ("error", "code", "words"),
    [
        (OSError(errno.ENOSPC, "No space left on device"), 1,
         "demo: error: could not write a file: No space left on device"),
        (OSError(errno.EROFS, "Read-only file system", "/data/x.npz"), 1,
         "demo: error: could not write /data/x.npz: Read-only file system"),
        (PermissionError(errno.EACCES, "Permission denied", "/results"), 1,
         "demo: error: could not write /results: Permission denied"),
        (ExecutorUnavailable("executor='dask://s:1': no Dask scheduler answers"), 2,
         "demo: error: executor='dask://s:1': no Dask scheduler answers"),
        (KeyboardInterrupt(), 130, "demo: interrupted; run it again to resume"),
    ],
)  # fmt: skip
def test_run_script_ends_what_a_user_can_remedy_with_a_short_message(
    error, code, words, capsys, monkeypatch
):
    monkeypatch.setattr("sys.argv", ["demo"])
    with pytest.raises(SystemExit) as exited:
        run_script(_raising(error), argparse.Namespace())
    assert exited.value.code == code
    err = capsys.readouterr().err
    assert err.startswith(words) and len(err.splitlines()) <= 2, err
    if code == 1:
        assert "run it again" in err


def test_run_script_passes_other_errors_and_the_exit_status_on():
    with pytest.raises(ConnectionResetError):  # not a write a user can remedy
        run_script(_raising(ConnectionResetError(errno.ECONNRESET, "reset")), None)
    for returned, code in ((3, 3), (None, 0), (Toy("a", [], {}), 0), (True, 0)):
        with pytest.raises(SystemExit) as exited:
            run_script(lambda args, r=returned: r, None)
        assert exited.value.code == code


def test_check_threads_is_bounded_by_the_cores(monkeypatch):
    monkeypatch.setattr("os.sched_getaffinity", lambda pid: {0, 1, 2}, raising=False)
    assert check_threads("threads", 3) == 3
    for value in (0, 4, 10**12):
        with pytest.raises(ConfigError, match=rf"^threads: {value} is out of range; .* 1\.\.3"):
            check_threads("threads", value)


@pytest.mark.parametrize("where", ["file", "file/sub"])
def test_run_script_says_a_file_in_the_way_of_the_output_folder_in_two_lines(
    where, tmp_path, capsys, monkeypatch
):
    # --out naming a file, or a folder below one: mkdir's own error, not a traceback
    (tmp_path / "file").write_text("")
    monkeypatch.setattr("sys.argv", ["demo"])

    def make_folder(args):
        (tmp_path / where).mkdir(parents=True, exist_ok=True)

    with pytest.raises(SystemExit) as exited:
        run_script(make_folder, None)
    assert exited.value.code == 1
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 2, lines
    assert lines[0].startswith(f"demo: error: could not write {tmp_path / where}: ")
    assert lines[0].endswith("(a file stands where a folder is needed)")
