"""Reproduce the paper's experiments end to end and write ``results/``.

Runs each example script in turn (each can also be run alone): the §III illustration,
the worlds' pictures, throwing (§IV-B) and beyond the paper its adaptive clusters and
active throw targets, can tossing (§IV-A, Table I), the combined system (§IV-C, Tables
II-IV), the physics' own bounds, and beyond the paper Table I learned from a fraction of
the throws by active exploration (:mod:`experiments.active`) and the combined system on
every goal the physics reaches (:mod:`experiments.all_goals`). The can data set is generated
once under ``--data-dir`` (resumable) and reused. Then writes ``run.json`` (scale,
commit, date, machine, each step's wall time) and ``summary.md`` (the paper's numbers
beside ours and the bounds: :mod:`experiments.summary`); a full-scale run of every step
also refreshes the results block of README.md.

    ./reproduce              # full scale
    ./reproduce --quick      # a first look in a few minutes
    ./reproduce --executor dask://scheduler:8786   # the simulations on a Dask cluster
"""

from __future__ import annotations

import argparse
import contextlib
import signal
import subprocess
import sys
import time
from pathlib import Path

from experiments.config import check_executor, config_or_exit, run_script
from experiments.summary import refresh_readme, run_record, summary_markdown

HERE = Path(__file__).resolve().parent
README = HERE.parent / "README.md"


def steps(args: argparse.Namespace) -> list[tuple[str, list[str]]]:
    """``(script name, its arguments)`` in order; a new experiment adds its step here."""
    out, data, quick = args.out, args.data_dir, args.quick
    scale = ["--scale", "quick" if quick else "full", "--data-dir", data, "--out", out]
    executor = ["--executor", args.executor] if args.executor else []
    return [
        ("tap_and_remove", ["--out", f"{out}/tap_and_remove"] + (["--n", "600"] if quick else [])),
        (
            "can_world",  # fewer GIF frames at the quick scale (same throw, same pictures)
            ["--out", f"{out}/can_world"]
            + (["--frame-interval", "0.04", "--fps", "12"] if quick else []),
        ),
        ("throw_kinematics", ["--out", f"{out}/throw"]),
        ("throwing", ["--out", out] + (["--quick"] if quick else [])),
        ("adaptive_throw", ["--out", out] + (["--quick"] if quick else [])),
        ("can_tossing", [*scale, *executor] + (["--n-demos", "100"] if quick else [])),
        (
            "combined",
            [*scale, *executor] + (["--n-throws", "5000", "--episodes", "10"] if quick else []),
        ),
        (
            "physics_bounds",
            [*scale, *executor]
            + (["--repeats", "8", "--step", "0.01", "--combined-repeats", "4"] if quick else []),
        ),
        ("active", [*scale, *executor] + (["--quick"] if quick else [])),
        (
            "all_goals",  # the quick scale: the standard table only
            ["--data-dir", data, "--out", out, *executor]
            + (["--quick", "--table-z", "0.75"] if quick else []),
        ),
    ]


def run_step(command: list[str]) -> tuple[int, signal.Signals | None]:
    """Run one step as a child process: its exit status, and the signal that stopped us.

    SIGTERM (``kill``, the end of a batch job) is passed on to the step, which saves the
    chunks it finished and releases the data set's lock; Ctrl-C reaches the step from
    the terminal itself. Either way this process waits for the step to end, and the
    caller starts no further step.
    """
    stopped: list[signal.Signals] = []
    children: list[subprocess.Popen] = []

    def stop(signum, frame):
        stopped.append(signal.Signals(signum))
        if signum == signal.SIGTERM:
            for child in children:
                with contextlib.suppress(ProcessLookupError):
                    child.send_signal(signum)

    previous = {s: signal.signal(s, stop) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        child = subprocess.Popen(command)
        children.append(child)
        if signal.SIGTERM in stopped:  # it came while the step was starting
            child.send_signal(signal.SIGTERM)
        code = child.wait()
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    return code, (stopped[0] if stopped else None)


def main(args: argparse.Namespace) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    times: dict[str, float] = {}
    for name, argv in steps(args):
        if args.only and name not in args.only:
            continue
        print(f"\n=== {name} {' '.join(argv)}", flush=True)
        start = time.perf_counter()
        code, stopped = run_step([sys.executable, str(HERE / f"{name}.py"), *argv])
        times[name] = time.perf_counter() - start
        if stopped is not None:
            print(
                f"stopped by {stopped.name} during {name}; run it again to resume",
                file=sys.stderr,
            )
            return 128 + stopped
        if code != 0:
            print(f"{name} failed with exit code {code}", file=sys.stderr)
            return code
    run_record("quick" if args.quick else "full", times).save(out)
    text = summary_markdown(out)
    (out / "summary.md").write_text(text)
    print("\n" + text)
    if not args.quick and not args.only:
        note = f"Generated by `./reproduce` from `{out}/*.json` ({out}/summary.md).\n\n"
        if refresh_readme(README, note + text):
            print(f"refreshed the results block of {README}")
    return 0


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--quick", action="store_true", help="small scale, a few minutes")
    parser.add_argument("--out", default="results")
    parser.add_argument("--data-dir", default="data")
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


if __name__ == "__main__":
    run_script(main, parse_args())
