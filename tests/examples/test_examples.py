"""Every example runs with its experiment's tiny settings; bad numbers are usage errors.

The experiments themselves are tested in tests/experiments; here each script's command
line (:mod:`experiments.harness.cli`, derived from its settings) is run in this process with the
tiny settings the experiment declares, reproduce runs a script the way a user does (a
subprocess in the repository root), and every command line is checked.
"""

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from effect_networks.experiments.harness import cli, reproduce
from effect_networks.experiments.harness.registry import experiment, experiments
from effect_networks.sim2d.chunks import locked

ROOT = Path(__file__).resolve().parents[2]
SCRIPTS = sorted(p.stem for p in (ROOT / "examples").glob("*.py"))
EXPERIMENTS = list(experiments())


def run(name: str, *argv, check: bool = True) -> subprocess.CompletedProcess:
    done = subprocess.run(
        [sys.executable, str(ROOT / "examples" / f"{name}.py"), *map(str, argv)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        env=os.environ | {"PYTHONPATH": str(ROOT)},  # this checkout's packages, not an install's
    )
    if check:
        assert done.returncode == 0, done.stderr[-3000:]
    return done


def flags(settings) -> list[str]:
    """Command-line flags that give ``settings`` (field -> value)."""
    argv = []
    for name, value in settings.items():
        flag = "--" + name.replace("_", "-")
        if value is True:
            argv.append(flag)
        elif value is not False:
            values = value if isinstance(value, tuple) else (value,)
            argv += [flag, *map(str, values)]
    return argv


def tiny_arguments(name: str, out: Path, data: Path) -> list[str]:
    """The experiment's tiny settings as flags, its files under ``out``, its data in ``data``."""
    exp = experiment(name)
    argv = flags(exp.tiny) + ["--out", str(out), "--quiet"]
    return argv + (["--data-dir", str(data)] if "data_dir" in exp.fields else [])


def test_every_script_is_an_experiment_s_or_reproduce():
    assert set(SCRIPTS) == set(EXPERIMENTS) | {"reproduce"}
    for name in EXPERIMENTS:  # a script is its docstring and the call
        text = (ROOT / "examples" / f"{name}.py").read_text()
        assert f'main("{name}", __doc__)' in text, name
        assert len(text.split('"""', 2)[2].strip().splitlines()) <= 4, name


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_example_runs_with_its_tiny_settings(name, tmp_path, tiny_data_dir, capsys):
    """The script's command line, run in this process: its files, its report printed,
    and the result read back."""
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as exited:
        cli.main(name, argv=tiny_arguments(name, out, tiny_data_dir))
    assert exited.value.code == 0
    exp = experiment(name)
    result = exp.result.load(out / f"{name}.json")
    assert capsys.readouterr().out.strip() == exp.report(result).strip()
    assert (out / f"{name}.md").read_text() == exp.report(result)
    for row in exp.rows(result, {name: result}):
        assert row.startswith("| ") and row.endswith("|"), row


@pytest.mark.slow  # starts torch once per script; the test above runs the same command lines
@pytest.mark.parametrize("name", EXPERIMENTS)
def test_every_script_runs_as_a_user_runs_it(name, tmp_path, tiny_data_dir):
    out = tmp_path / "out"
    done = run(name, *tiny_arguments(name, out, tiny_data_dir))
    exp = experiment(name)
    assert exp.report(exp.result.load(out / f"{name}.json")).strip() in done.stdout


def test_reproduce_runs_a_step_as_a_script(tmp_path, tiny_data_dir):
    out = tmp_path / "out"
    run("reproduce", "--quick", "--only", "throw_kinematics", "--out", out)
    assert json.loads((out / "run.json").read_text())["scale"] == "quick"
    assert "| throw_kinematics |" in (out / "summary.md").read_text()
    for file in ("throw_kinematics.json", "target_to_hit.png", "flight_paths.png"):
        assert (out / "throw" / file).stat().st_size > 0, file


def test_a_bad_number_exits_with_a_usage_error():
    done = run("throwing", "--n-train", "-10", check=False)
    assert done.returncode == 2
    assert "error: --n-train: -10 is out of range; expected an integer >= 10" in done.stderr
    done = run("all_goals", "--bound-repeats", "5", check=False)
    assert done.returncode == 2 and "error: --bound-repeats: 5 is odd" in done.stderr


def parse(name: str, argv):
    """The command line of script ``name``, parsed."""
    if name == "reproduce":
        return reproduce.parse_args(argv)
    return cli.parse_args(name, argv)


@pytest.mark.parametrize(
    ("name", "argv", "words"),
    [
        ("can_tossing", ["--aim-error", "1e9"], "--aim-error: 1000000000.0 is out of range"),
        ("can_tossing", ["--n-demos", "0"], "--n-demos: 0 is out of range"),
        ("can_tossing", ["--scale", "huge"], "--scale: 'huge' is not one of 'full', 'quick'"),
        ("combined", ["--episodes", "-1"], "--episodes: -1 is out of range"),
        ("combined", ["--table-z", "nan"], "--table-z: nan is out of range"),
        ("physics_bounds", ["--repeats", "1"], "--repeats: 1 is out of range"),
        ("physics_bounds", ["--step", "0"], "--step: 0.0 is out of range"),
        ("physics_bounds", ["--executor", "threads"], "--executor: executor='threads'"),
        ("throwing", ["--bins", "4", "0"], "--bins: 0 is out of range"),
        ("throwing", ["--threads", "0"], "--threads: 0 is out of range"),
        ("throwing", ["--threads", "1000000000000"], "--threads: 1000000000000 is out of range"),
        ("throwing", ["--threads", "1e12"], "argument --threads: invalid int value: '1e12'"),
        ("adaptive_throw", ["--threads", str(10**12)], "--threads: 1000000000000 is out of"),
        ("adaptive_throw", ["--budgets", "100", "50"], "--budgets: (100, 50) must increase"),
        ("adaptive_throw", ["--batch", "50", "--pool", "10"], "--pool: 10 is out of range"),
        ("tap_and_remove", ["--n", "-10"], "--n: -10 is out of range"),
        ("can_world", ["--field", "999"], "--field: 999 is out of range"),
        ("throw_kinematics", ["--grid", "0"], "--grid: 0 is out of range"),
        ("active", ["--fractions", "0.5", "0"], "--fractions: 0.0 is out of range"),
        ("active", ["--fractions", "0.5", "0.2"], "--fractions: (0.5, 0.2) must increase"),
        ("active", ["--sites", "end.colour"], "--sites: 'end.colour' is not one of"),
        ("all_goals", ["--quick", "--bins", "0"], "--bins: 0 is out of range"),
        ("reproduce", ["--executor", "threads"], "--executor: executor='threads'"),
        ("reproduce", ["--only", "can_tossing", "can_tosing"], "unknown step(s) ['can_tosing']"),
    ],
)
def test_command_lines_are_checked(name, argv, words, capsys):
    with pytest.raises(SystemExit) as exited:
        parse(name, argv)
    assert exited.value.code == 2
    assert words in capsys.readouterr().err


def test_the_executor_and_the_data_folder_reach_every_simulating_step():
    argv = ["--quick", "--executor", "dask://s:8786", "--data-dir", "/d"]
    steps = dict(reproduce.steps(reproduce.parse_args(argv)))
    simulating = ("can_tossing", "combined", "physics_bounds", "all_goals", "active")
    for name in simulating:
        config = parse(name, steps[name]).config
        assert (config.executor, config.data_dir) == ("dask://s:8786", Path("/d")), name
    assert set(simulating) < set(steps) and list(steps) == EXPERIMENTS
    assert all(
        "--executor" not in a for a in dict(reproduce.steps(reproduce.parse_args([]))).values()
    )
    # every step's arguments parse, at both scales; --quick gives the quick settings
    for argv in ([], ["--quick"]):
        for name, step_argv in reproduce.steps(reproduce.parse_args(argv)):
            config = parse(name, step_argv).config
            expected = experiment(name).config(**(experiment(name).quick if argv else {}))
            assert config == expected, name


def test_a_flag_given_wins_over_the_quick_settings():
    assert parse("throwing", ["--quick", "--n-train", "700"]).config.n_train == 700
    assert parse("throwing", ["--quick"]).config.n_test == 200
    assert parse("active", ["--quick", "--scale", "tiny"]).config.scale == "tiny"


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_an_example_s_defaults_are_its_experiment_s(name):
    """A script with no arguments runs the library's default settings (progress aside)."""
    config = parse(name, []).config
    default = type(config)()
    differ = {
        f: (getattr(config, f), getattr(default, f))
        for f in config.__dataclass_fields__
        if f != "progress" and getattr(config, f) != getattr(default, f)
    }
    assert not differ, differ


def test_help_text_comes_from_the_settings_docstring():
    from effect_networks.experiments.combined import CombinedConfig

    helps = cli.field_help(CombinedConfig)
    assert helps["horizon"] == "Throws the exact planner may use, 1..MAX_HORIZON."
    assert helps["scale"].startswith("The can data set's scale")  # the shared settings'
    assert "progress bars" in helps["progress"].lower()
    usage = " ".join(cli.make_parser(experiment("combined")).format_help().split())
    assert "--n-throws" in usage and "Throws that train the throw network." in usage
    assert "(default: 29000)" in usage and "--progress" not in usage


def _default_signals():
    """A suite started in the background hands its children SIGINT ignored; the script
    under test must see the signals as a terminal would send them."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _wait_for(condition, seconds: float, what: str) -> None:
    deadline = time.monotonic() + seconds
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.1)


HOLDS_THE_LOCK = """
import sys, time
from effect_networks.sim2d.chunks import locked
with locked(sys.argv[1]):
    open(sys.argv[2], "w").close()
    time.sleep(120)
"""


def test_sigterm_to_reproduce_stops_its_running_step(tmp_path):
    """A step that holds a data set's lock, run as reproduce runs its steps: SIGTERM to
    reproduce ends the step too, and the lock is free at once."""
    psutil = pytest.importorskip("psutil")
    data, started = tmp_path / "d.npz", tmp_path / "started"
    step = tmp_path / "step.py"
    step.write_text(HOLDS_THE_LOCK)
    driver = (
        "import sys; from effect_networks.experiments.harness.reproduce import run_step; "
        f"run = run_step({str(step)!r}, {[str(data), str(started)]!r}); "
        "code, stopped = run[:2]; sys.exit(128 + stopped if stopped else code)"
    )
    proc = subprocess.Popen([sys.executable, "-c", driver], cwd=ROOT, preexec_fn=_default_signals)
    try:
        _wait_for(started.exists, 60, "the step started")
        children = psutil.Process(proc.pid).children(recursive=True)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 128 + signal.SIGTERM
    finally:
        if proc.poll() is None:
            proc.kill()
    gone, alive = psutil.wait_procs(children, timeout=10)
    assert not alive, "the step outlived reproduce"
    with locked(data):  # free: a RuntimeError here names the holder
        pass


@pytest.mark.slow  # starts torch twice and a data set's generation
def test_sigterm_to_reproduce_saves_the_data_set_and_releases_its_lock(tmp_path):
    psutil = pytest.importorskip("psutil")
    data, out = tmp_path / "data", tmp_path / "out"
    proc = subprocess.Popen(
        [sys.executable, str(ROOT / "examples" / "reproduce.py"), "--quick", "--only",
         "can_tossing", "--data-dir", str(data), "--out", str(out), "--executor", "process:1"],
        cwd=ROOT, stderr=subprocess.PIPE, text=True, preexec_fn=_default_signals,
        env=os.environ | {"PYTHONPATH": str(ROOT)},  # this checkout's packages
    )  # fmt: skip
    try:
        _wait_for(lambda: list(data.glob("*.parts/manifest.json")), 240, "the chunks started")
        time.sleep(1)
        children = psutil.Process(proc.pid).children(recursive=True)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert "interrupted; run it again to resume" in err  # the step saved what it finished
    assert "stopped by SIGTERM during can_tossing" in err
    _, alive = psutil.wait_procs(children, timeout=10)
    assert not alive, "the step or its workers outlived reproduce"
    assert not list(data.glob("*.lock"))


FILE_SIZE_LIMITED = """
import resource, runpy, signal, sys
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG
resource.setrlimit(resource.RLIMIT_FSIZE, (2000, 2000))
sys.argv = sys.argv[1:]
runpy.run_path(sys.argv[0], run_name="__main__")
"""


def test_a_failed_write_is_two_lines_not_a_traceback(tmp_path):
    """Files limited to 2 kB (as a full disk, the write itself fails): the script says what
    happened and that a rerun resumes."""
    argv = [str(ROOT / "examples" / "throw_kinematics.py"), "--grid", "2", "--n", "10"]
    done = subprocess.run(
        [sys.executable, "-c", FILE_SIZE_LIMITED, *argv, "--out", str(tmp_path)],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
        env=os.environ | {"PYTHONPATH": str(ROOT)},
    )  # fmt: skip
    assert done.returncode == 1, done.stderr[-3000:]
    lines = done.stderr.splitlines()
    assert len(lines) == 2, done.stderr[-3000:]
    assert lines[0] == "throw_kinematics.py: error: could not write a file: File too large"
    assert "run it again" in lines[1]


JUNK = ["-1", "0", "nan", "inf", "-inf", "1e12", "1e400", "x", "", "3.5"]


@pytest.mark.parametrize("name", SCRIPTS)
def test_every_option_takes_junk_with_a_usage_error_or_a_value(name, capsys):
    # --help, and each option of each example given junk: exit 0 for help, a usage error
    # (exit 2, one "error:" line) or parsed settings; never a traceback
    with pytest.raises(SystemExit) as exited:
        parse(name, ["--help"])
    assert exited.value.code == 0
    usage = capsys.readouterr().out
    options = sorted(set(re.findall(r"(--[a-z][a-z-]*)( [A-Z{])?", usage)) - {("--help", "")})
    assert options
    for option, takes_value in options:
        for argv in ([option, value] for value in JUNK) if takes_value else [[option]]:
            try:
                parse(name, argv)
            except SystemExit as refused:
                err = capsys.readouterr().err
                assert refused.code == 2 and "error: " in err and "Traceback" not in err, argv
