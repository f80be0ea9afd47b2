"""The main job (:mod:`experiments.harness.reproduce`): each step forked, isolated and measured.

Its command line and a step run as a script are tested with the scripts (tests/examples).
"""

import json
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from effect_networks.experiments.harness import reproduce

ROOT = Path(__file__).resolve().parents[3]


ALLOCATES_AND_SIMULATES = """
import argparse, time
import numpy as np
from effect_networks.experiments.harness.config import run_script
from effect_networks.sim2d.clock import simulating

def main(args):
    block = np.ones(50_000_000)  # 400 MB, every page touched
    with simulating():
        time.sleep(0.3)
        with simulating():  # nested: counted once
            time.sleep(0.1)
    time.sleep(0.2)  # not simulation
    return int(block[0]) - 1

run_script(main, argparse.Namespace())
"""


MEASURES_STEPS = """
import json, sys, time
from effect_networks.experiments.harness import reproduce
out = {}
for name in sys.argv[1:]:
    start = time.perf_counter()
    run = reproduce.run_step(name)
    m = run.measure
    out[name] = [run.code, time.perf_counter() - start, m and m.peak_bytes,
                 m and m.children_peak_bytes, m and m.simulation_seconds]
print(json.dumps(out))
"""


def _measured(tmp_path, **steps) -> dict:
    """Each step (name -> script text) run in turn by reproduce's ``run_step`` in a small
    process of its own: name -> [code, wall, peak, children's peak, simulation]."""
    paths = []
    for name, text in steps.items():
        paths.append(tmp_path / f"{name}.py")
        paths[-1].write_text(text)
    done = subprocess.run(
        [sys.executable, "-c", MEASURES_STEPS, *map(str, paths)],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    found = json.loads(done.stdout.splitlines()[-1])
    return {Path(k).stem: v for k, v in found.items()}, done.stderr


def test_reproduce_measures_a_step_s_simulation_time_and_peak_memory(tmp_path):
    """A step that allocates 400 MB and sleeps 0.4 s inside the simulation clock (0.2 s
    outside it): reproduce reads at least that peak and that simulation time, and less
    than the whole wall time as simulation. The same step without the array: its own
    peak, not that of one before it. A script that writes no record: none."""
    small = ALLOCATES_AND_SIMULATES.replace("50_000_000", "1")
    found, _ = _measured(tmp_path, big=ALLOCATES_AND_SIMULATES, small=small, idle="import sys")
    code, wall, peak, children, sim = found["big"]
    assert code == 0 and peak >= 400e6
    assert 0.4 <= sim <= wall - 0.2
    code, wall, peak, children, sim = found["small"]
    assert code == 0 and peak < 300e6 and children == 0
    assert found["idle"][0] == 0 and found["idle"][2] is None  # no script, no record


FAILS = """
import sys
from effect_networks.experiments.harness.config import run_script
def main(args):
    raise RuntimeError("step broke")
run_script(main, None)
"""


def test_reproduce_isolates_a_failing_step(tmp_path):
    """A step that raises, one killed by a signal and one that exits 3 are each reported
    with their status; the steps after them still run and are measured."""
    killed = "import os, signal; os.kill(os.getpid(), signal.SIGKILL)"
    found, err = _measured(
        tmp_path,
        fails=FAILS,
        killed=killed,
        three="import sys; sys.exit(3)",
        after=ALLOCATES_AND_SIMULATES.replace("50_000_000", "1"),
    )
    assert found["fails"][0] == 1 and "RuntimeError: step broke" in err
    assert found["fails"][2] is not None  # it measured itself as it failed
    assert found["killed"][0] == -signal.SIGKILL and found["three"][0] == 3
    assert found["after"][0] == 0 and found["after"][4] >= 0.4


def test_reproduce_runs_its_steps_forked_after_one_import(tmp_path, monkeypatch, capsys):
    """The main job imports once and forks each step from itself: a step finds the
    modules already imported and ends as a script does (its exit handlers run); a failing step is reported and the next one still runs,
    both are left out of the record, and the start-up counts in the total."""
    seen = tmp_path / "seen"
    step = f"import sys; open({str(seen)!r}, 'a').write(str('colorsys' in sys.modules))\n"
    (tmp_path / "a.py").write_text(step + "sys.exit(4)\n")
    (tmp_path / "b.py").write_text(
        step
        + f"import atexit; atexit.register(lambda: open({str(seen)!r}, 'a').write(' exit'))\n"
        + "from effect_networks.experiments.harness.config import run_script\nrun_script(lambda args: 0, None)\n"
    )
    monkeypatch.setattr(reproduce, "EXAMPLES", tmp_path)
    monkeypatch.setattr(reproduce, "PRELOAD", ("colorsys",))
    monkeypatch.setattr(reproduce, "steps", lambda args: [("a", []), ("b", [])])
    monkeypatch.delitem(sys.modules, "colorsys", raising=False)
    out = tmp_path / "out"
    args = reproduce.parse_args(["--quick", "--out", str(out)])
    assert reproduce.run_steps(args) == 4
    captured = capsys.readouterr()
    assert "a failed with exit code 4" in captured.err
    # both steps ran, each with it imported; b's exit handler ran as it ended
    assert seen.read_text() == "TrueTrue exit"
    record = json.loads((out / "run.json").read_text())
    assert list(record["step_seconds"]) == ["b"] and record["startup_seconds"] > 0
    assert record["total_seconds"] == pytest.approx(
        record["step_seconds"]["b"] + record["startup_seconds"]
    )
    assert record["peak_bytes"]["b"] > 0
