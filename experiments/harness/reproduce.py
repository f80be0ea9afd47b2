"""The main job: every experiment's script run in turn, measured, and the results summarised.

Runs the script of every experiment in :func:`experiments.harness.registry.experiments` in
turn (each can also be run alone; ``--quick`` gives each its quick settings): the §III
illustration, the worlds' pictures, throwing (§IV-B) and beyond the paper its adaptive
clusters and active throw targets, can tossing (§IV-A, Table I), the combined system
(§IV-C, Tables II-IV), the physics' own bounds, and beyond the paper the combined system
on every goal the physics reaches (:mod:`experiments.all_goals`) and Table I learned from
a fraction of the throws by active exploration (:mod:`experiments.active`). The can data
set is generated once under ``--data-dir`` (resumable; default: the cache folder, see
docs/data.md) and reused. The modules every step imports are imported once; each step
then runs as its own process forked from this one (a step that fails is reported and
the others still run) and is measured: its wall time, the part of it spent simulating,
and the peak resident memory of its largest process. Then writes ``run.json`` (scale,
commit, date, machine, the one-time start-up, those measures per step) and
``summary.md`` (the paper's numbers beside ours and the bounds, and the steps' measures
beside their goals: :mod:`experiments.harness.summary`); a full-scale run of every step also
refreshes the results table of docs/results.md.

``examples/reproduce.py`` (and ``./reproduce``, which sets up the environment first)
calls :func:`main`; the scripts it runs are ``examples/<name>.py``.
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import importlib
import multiprocessing
import os
import runpy
import signal
import sys
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

from effect_networks.experiments.harness.config import check_executor, config_or_exit, run_script
from effect_networks.experiments.harness.registry import experiments
from effect_networks.experiments.harness.steps import STEP_RECORD_ENV, StepMeasure, read_step_record
from effect_networks.experiments.harness.summary import (
    refresh_results,
    run_record,
    summary_markdown,
)

__all__ = ["main", "parse_args", "run_step", "run_steps", "steps"]

ROOT = Path(__file__).resolve().parents[2]
#: The folder of the experiments' scripts, ``<name>.py`` each.
EXAMPLES = ROOT / "examples"
RESULTS_PAGE = ROOT / "docs" / "results.md"


def steps(args: argparse.Namespace) -> list[tuple[str, list[str]]]:
    """``(script name, its arguments)`` for every experiment, in order.

    The order of :func:`experiments.harness.registry.experiments`.
    """
    result = []
    for name, exp in experiments().items():
        argv = ["--out", str(exp.out(args.out))] + (["--quick"] if args.quick else [])
        if "data_dir" in exp.fields and args.data_dir is not None:
            argv += ["--data-dir", args.data_dir]
        if "executor" in exp.fields and args.executor:
            argv += ["--executor", args.executor]
        result.append((name, argv))
    return result


#: What every step imports, loaded once by this process before the first step: each step
#: runs in a child forked from it (:func:`run_step`) and starts with them imported.
PRELOAD = (
    "numpy",
    "scipy.stats",
    "torch",
    "pyro",
    "matplotlib.pyplot",
    "effect_networks.inference",
    "effect_networks.models",
)


def preload() -> float:
    """Import :data:`PRELOAD` (matplotlib without a display); the wall time it took."""
    start = time.perf_counter()
    os.environ.setdefault("MPLBACKEND", "Agg")
    for module in PRELOAD:
        importlib.import_module(module)
    return time.perf_counter() - start


class StepRun(NamedTuple):
    """One step's run.

    ``code`` its exit status (``-N``: killed by signal ``N``), ``stopped`` the signal that stopped us (or None), and ``measure`` what it measured
    about itself as it exited (its simulation time and peak memory:
    :mod:`experiments.harness.steps`; None where it wrote nothing).
    """

    code: int
    stopped: signal.Signals | None
    measure: StepMeasure | None


#: The signals that stop the main job (see :func:`run_step`).
STOPS = (signal.SIGTERM, signal.SIGINT)


def _run_script(script: str, argv: list[str], record: str) -> None:
    """In the forked child: the script as ``python script argv...`` runs it.

    Its measures written to ``record``, and the exit handlers (``atexit``) it registers run
    as it ends (not those inherited from this process: they clean up after it).
    """
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, STOPS)  # one that came while forking: now
    os.environ[STEP_RECORD_ENV] = record
    sys.argv = [script, *argv]
    atexit._clear()
    try:
        runpy.run_path(script, run_name="__main__")
    finally:
        atexit._run_exitfuncs()


def run_step(script, argv=()) -> StepRun:
    """Run the script ``script`` with arguments ``argv`` as its own process, and measure it.

    The process is forked from this one, so it starts with :data:`PRELOAD` imported.

    The step is isolated: its exit status, an exception it raises (traceback on stderr,
    status 1) or a signal that kills it is reported in the result. Its peak memory is
    its own process's (``VmHWM``), which includes the pages it shares with this process
    (the imported modules), as a step started afresh would hold them too.

    SIGTERM (``kill``, the end of a batch job) is passed on to the step, which saves the
    chunks it finished and releases the data set's lock; Ctrl-C reaches the step from
    the terminal itself. Either way this process waits for the step to end, and the
    caller starts no further step.
    """
    stopped: list[signal.Signals] = []
    children: list[multiprocessing.Process] = []

    def stop(signum, frame):
        stopped.append(signal.Signals(signum))
        if signum == signal.SIGTERM:
            for child in children:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(child.pid, signum)

    previous = {s: signal.signal(s, stop) for s in STOPS}
    with tempfile.TemporaryDirectory() as folder:
        record = Path(folder) / "step.json"
        child = multiprocessing.get_context("fork").Process(
            target=_run_script, args=(str(script), [str(a) for a in argv], str(record))
        )
        try:
            # blocked while forking: the child unblocks them with its own handlers set,
            # this process once it knows the child (a SIGTERM meanwhile is passed on)
            signal.pthread_sigmask(signal.SIG_BLOCK, STOPS)
            try:
                child.start()
                children.append(child)
            finally:
                signal.pthread_sigmask(signal.SIG_UNBLOCK, STOPS)
            child.join()
        finally:
            for s, handler in previous.items():
                signal.signal(s, handler)
        measure = read_step_record(record)
    return StepRun(child.exitcode, stopped[0] if stopped else None, measure)


def run_steps(args: argparse.Namespace) -> int:
    """Run every step of ``args`` (:func:`parse_args`), write ``run.json`` and ``summary.md``.

    The exit status: 0, that of the first step that failed, or ``128 + N`` when signal
    ``N`` stopped the run.
    """
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    startup = preload()
    print(f"imported {', '.join(PRELOAD)} once: {startup:.1f} s", flush=True)
    times: dict[str, float] = {}
    simulation: dict[str, float] = {}
    peak: dict[str, int] = {}
    failed: dict[str, int] = {}
    for name, argv in steps(args):
        if args.only and name not in args.only:
            continue
        print(f"\n=== {name} {' '.join(argv)}", flush=True)
        start = time.perf_counter()
        run = run_step(EXAMPLES / f"{name}.py", argv)
        elapsed = time.perf_counter() - start
        code, stopped = run.code, run.stopped
        if stopped is not None:
            print(
                f"stopped by {stopped.name} during {name}; run it again to resume",
                file=sys.stderr,
            )
            return 128 + stopped
        if code != 0:  # reported; the other steps still run
            print(f"{name} failed with exit code {code}", file=sys.stderr, flush=True)
            failed[name] = code
            continue
        times[name] = elapsed
        if run.measure is not None:
            simulation[name] = run.measure.simulation_seconds
            peak[name] = run.measure.largest_bytes
    record = run_record("quick" if args.quick else "full", times, simulation, peak, startup)
    record.save(out)
    text = summary_markdown(out)
    (out / "summary.md").write_text(text)
    print("\n" + text)
    if failed:
        print(f"failed steps (exit codes): {failed}", file=sys.stderr)
        code = next(iter(failed.values()))
        return code if code > 0 else 1
    if not args.quick and not args.only:
        # the folder is the run's own (often a temporary one): named by its role, not path
        note = "Generated by `./reproduce` from its results' JSON files (its summary.md).\n\n"
        if refresh_results(RESULTS_PAGE, note + text):
            print(f"refreshed the results table of {RESULTS_PAGE}")
    return 0


def parse_args(argv=None, description: str | None = None) -> argparse.Namespace:
    """The command line ``argv`` checked; ``description`` heads its help (default: this module's)."""
    parser = argparse.ArgumentParser(
        description=description or __doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--quick", action="store_true", help="each experiment's quick settings, a few minutes"
    )
    parser.add_argument("--out", default="results")
    parser.add_argument(
        "--data-dir",
        default=None,
        help="generated data (default: data in the cache folder, $EFFECT_NETWORKS_CACHE or "
        "~/.cache/effect-networks; docs/data.md)",
    )
    parser.add_argument("--only", nargs="*", help="run only these steps")
    parser.add_argument(
        "--executor",
        default=None,
        help="where the can world is simulated: process:N | dask-local:N | dask://HOST:PORT | "
        "ray (default: every core here)",
    )
    args = parser.parse_args(argv)
    config_or_exit(parser, lambda: check_executor("executor", args.executor))
    names = [name for name, _ in steps(args)]
    unknown = sorted(set(args.only or []) - set(names))
    if unknown:
        parser.error(f"--only: unknown step(s) {unknown}; the steps are {names}")
    return args


def main(argv=None, description: str | None = None) -> None:
    """Parse the command line ``argv`` (default: ``sys.argv[1:]``), run the steps and exit.

    ``description`` heads the help (the script's docstring).
    """
    run_script(run_steps, parse_args(argv, description))
