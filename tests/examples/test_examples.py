"""Every example runs as a script with tiny arguments; bad numbers are usage errors.

The experiments themselves are tested in tests/experiments; here each script is run the
way a user runs it (a subprocess in the repository root), and its command line is checked.
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

from sim2d.chunks import locked
from tests.helpers import load_example

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = sorted(p.stem for p in (ROOT / "examples").glob("*.py"))


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


def tiny_arguments(name: str, out: Path, data: Path) -> list:
    """Arguments that make each example run in seconds."""
    cans = ["--scale", "tiny", "--data-dir", data, "--out", out, "--quiet"]
    return {
        "tap_and_remove": ["--n", 100, "--bins", 2, "--out", out],
        "can_world": ["--frame-interval", 0.5, "--out", out],
        "throw_kinematics": ["--grid", 2, "--n", 10, "--out", out],
        "throwing": ["--n-train", 100, "--n-test", 10, "--bins", 1, 2, "--out", out, "--quiet"],
        "adaptive_throw": [
            *["--n-train", 300, "--n-test", 20, "--bins", 2, "--em-steps", 1, 2],
            *["--budgets", 40, 80, "--batch", 20, "--pool", 60, "--out", out, "--quiet"],
        ],
        "can_tossing": [*cans, "--n-demos", 2],
        "combined": [*cans, "--n-throws", 300, "--bins", 2, "--episodes", 1, "--horizon", 1],
        "physics_bounds": [*cans, "--repeats", 2, "--combined-repeats", 2, "--step", 0.1],
        "all_goals": [
            *["--step", 0.05, "--train-repeats", 1, "--bound-repeats", 2, "--horizon", 1],
            *["--episodes", 1, "--n-throws", 300, "--bins", 2, "--table-z", 0.75],
            *["--data-dir", data, "--out", out, "--quiet"],
        ],
        "active": [*cans, "--repeats", 2, "--fractions", 0.3, 1.0, "--batch-size", 20],
        "reproduce": ["--quick", "--only", "throw_kinematics", "--out", out, "--data-dir", data],
    }[name]


WRITES = {
    "tap_and_remove": ["tap_and_remove.json", "tap_and_remove.png"],
    "can_world": ["pyramid.png", "throw.png", "throw.gif"],
    "throw_kinematics": ["target_to_hit.png", "flight_paths.png"],
    "throwing": ["throwing.json", "throwing.md", "throwing_errors.png"],
    "adaptive_throw": ["adaptive_throw.json", "adaptive_throw.md", "adaptive_throw.png"],
    "can_tossing": ["can_tossing.json", "can_tossing.md", "can_tossing_table1.png"],
    "combined": ["combined.json", "combined.md"],
    "physics_bounds": ["physics_bounds.json", "physics_bounds.md"],
    "all_goals": ["all_goals.json", "all_goals.md", "all_goals.png"],
    "active": ["active.json", "active.md", "active.png"],
    "reproduce": ["run.json", "summary.md", "throw/flight_paths.png"],
}


def test_every_example_is_covered():
    assert set(EXAMPLES) == set(WRITES)


@pytest.mark.parametrize("name", EXAMPLES)
def test_example_runs_as_a_script(name, tmp_path, tiny_data_dir):
    out = tmp_path / "out"
    run(name, *tiny_arguments(name, out, tiny_data_dir))
    for file in WRITES[name]:
        assert (out / file).stat().st_size > 0, file
    if name == "reproduce":
        assert json.loads((out / "run.json").read_text())["scale"] == "quick"
        assert "| throw_kinematics |" in (out / "summary.md").read_text()


def test_a_bad_number_exits_with_a_usage_error():
    done = run("throwing", "--n-train", "-10", check=False)
    assert done.returncode == 2
    assert "error: --n-train: -10 is out of range; expected an integer >= 10" in done.stderr
    done = run("all_goals", "--bound-repeats", "5", check=False)
    assert done.returncode == 2 and "error: --bound-repeats: 5 is odd" in done.stderr


@pytest.mark.parametrize(
    ("name", "argv", "words"),
    [
        ("can_tossing", ["--aim-error", "1e9"], "--aim-error: 1000000000.0 is out of range"),
        ("can_tossing", ["--n-demos", "0"], "--n-demos: 0 is out of range"),
        ("combined", ["--episodes", "-1"], "--episodes: -1 is out of range"),
        ("combined", ["--table-z", "nan"], "--table-z: nan is out of range"),
        ("physics_bounds", ["--repeats", "1"], "--repeats: 1 is out of range"),
        ("physics_bounds", ["--step", "0"], "--step: 0.0 is out of range"),
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
        ("reproduce", ["--executor", "threads"], "--executor: executor='threads'"),
        ("reproduce", ["--only", "can_tossing", "can_tosing"], "unknown step(s) ['can_tosing']"),
    ],
)
def test_command_lines_are_checked(name, argv, words, capsys):
    with pytest.raises(SystemExit) as exited:
        load_example(name).parse_args(argv)
    assert exited.value.code == 2
    assert words in capsys.readouterr().err


def test_the_executor_reaches_every_simulating_step():
    reproduce = load_example("reproduce")
    steps = dict(reproduce.steps(reproduce.parse_args(["--quick", "--executor", "dask://s:8786"])))
    for name in ("can_tossing", "combined", "physics_bounds", "active"):
        i = steps[name].index("--executor")
        assert steps[name][i + 1] == "dask://s:8786", name
    assert all(
        "--executor" not in a for a in dict(reproduce.steps(reproduce.parse_args([]))).values()
    )
    # every step's arguments parse, at both scales
    for argv in ([], ["--quick"]):
        for name, step_argv in reproduce.steps(reproduce.parse_args(argv)):
            load_example(name).parse_args(step_argv)


@pytest.mark.parametrize("name", [n for n in EXAMPLES if n != "reproduce"])
def test_an_example_s_defaults_are_its_experiment_s(name):
    """A script with no arguments runs the library's default settings (progress aside)."""
    args = load_example(name).parse_args([])
    config = getattr(args, "config", None)
    if config is None:
        pytest.skip(f"{name} has no settings dataclass")
    default = type(config)()
    differ = {
        f: (getattr(config, f), getattr(default, f))
        for f in config.__dataclass_fields__
        if f != "progress" and getattr(config, f) != getattr(default, f)
    }
    assert not differ, differ


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
from sim2d.chunks import locked
with locked(sys.argv[1]):
    open(sys.argv[2], "w").close()
    time.sleep(120)
"""


def test_sigterm_to_reproduce_stops_its_running_step(tmp_path):
    """A step that holds a data set's lock, run as reproduce runs its steps: SIGTERM to
    reproduce ends the step too, and the lock is free at once."""
    psutil = pytest.importorskip("psutil")
    data, started = tmp_path / "d.npz", tmp_path / "started"
    step = [sys.executable, "-c", HOLDS_THE_LOCK, str(data), str(started)]
    driver = (
        "import sys; from tests.helpers import load_example; "
        f"code, stopped = load_example('reproduce').run_step({step!r}); "
        "sys.exit(128 + stopped if stopped else code)"
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


@pytest.mark.parametrize("name", EXAMPLES)
def test_every_option_takes_junk_with_a_usage_error_or_a_value(name, capsys):
    # --help, and each option of each example given junk: exit 0 for help, a usage error
    # (exit 2, one "error:" line) or parsed settings; never a traceback
    example = load_example(name)
    with pytest.raises(SystemExit) as exited:
        example.parse_args(["--help"])
    assert exited.value.code == 0
    usage = capsys.readouterr().out
    options = sorted(set(re.findall(r"(--[a-z][a-z-]*)( [A-Z{])?", usage)) - {("--help", "")})
    assert options
    for option, takes_value in options:
        for argv in ([option, value] for value in JUNK) if takes_value else [[option]]:
            try:
                example.parse_args(argv)
            except SystemExit as refused:
                err = capsys.readouterr().err
                assert refused.code == 2 and "error: " in err and "Traceback" not in err, argv
