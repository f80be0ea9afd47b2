"""Reproduce the paper's experiments end to end and write ``results/``.

Runs, in order, each as its own script (so each can also be run alone): the §III
illustration (``tap_and_remove.py``), the worlds' pictures (``can_world.py``,
``throw_kinematics.py``), the throwing experiment (``throwing.py``, §IV-B), the can
tossing experiment (``can_tossing.py``, §IV-A, Table I) and the combined system
(``combined.py``, §IV-C, Tables II-IV), then the physics' own bounds on Table I and the
combined scenarios (``physics_bounds.py``). The can data set is generated once under
``--data-dir`` (resumable) and reused. Writes ``results/summary.md`` with the paper's
numbers beside ours and each step's wall time.

    ./reproduce              # full scale (the can data set alone takes 2-5 min on 2 cores)
    ./reproduce --quick      # a first look in a few minutes
    ./reproduce --executor dask://scheduler:8786   # the simulations on a Dask cluster
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def steps(args: argparse.Namespace) -> list[tuple[str, list[str]]]:
    out, data = args.out, args.data_dir
    scale = "quick" if args.quick else "full"
    quick = ["--quick"] if args.quick else []
    executor = ["--executor", args.executor] if args.executor else []
    return [
        (
            "tap_and_remove",
            ["--out", f"{out}/tap_and_remove"] + (["--n", "600"] if args.quick else []),
        ),
        ("can_world", ["--out", f"{out}/can_world"]),
        ("throw_kinematics", ["--out", f"{out}/throw"]),
        ("throwing", ["--out", out, *quick]),
        ("can_tossing", ["--scale", scale, "--data-dir", data, "--out", out, *executor]),
        (
            "combined",
            ["--scale", scale, "--data-dir", data, "--out", out, *executor]
            + (["--n-throws", "5000", "--episodes", "10"] if args.quick else []),
        ),
        (
            "physics_bounds",
            ["--scale", scale, "--data-dir", data, "--out", out, *executor]
            + (
                ["--repeats", "8", "--step", "0.004", "--combined-repeats", "4"]
                if args.quick
                else []
            ),
        ),
    ]


def summary(out: Path, times: dict[str, float]) -> str:
    """The headline numbers, ours beside the paper's, from the steps' JSON files."""

    def load(name):
        path = out / name
        return json.loads(path.read_text()) if path.exists() else None

    bounds = load("physics_bounds.json")
    lines = [
        "| experiment | paper | ours | physics bound (best action by simulation) |",
        "|---|---|---|---|",
    ]
    if (t := load("throwing.json")) is not None:
        lines.append(
            f"| throw: re-thrown RMS y / z (m) | 0.0178 / 0.0305 | {t['rms_y_m']:.4f} / {t['rms_z_m']:.4f} "
            f"({t['n_clusters']} clusters; one Gaussian: {t['rms_y_m_single_gaussian']:.4f} / "
            f"{t['rms_z_m_single_gaussian']:.4f}) | |"
        )
    if (c := load("can_tossing.json")) is not None:
        bound = f"{100 * bounds['table_one']['exact_fraction_bound']:.2f} %" if bounds else ""
        lines.append(
            f"| cans, Table I: exact | 90.43 % of 8603 | {100 * c['exact_fraction']:.2f} % of {c['n_cases']} | {bound} |"
        )
    if (m := load("combined.json")) is not None:
        for name, label in (
            ("top_three", "Table II, top three"),
            ("near_flank", "Table III, near flank"),
            ("far_flank", "Table IV, far flank"),
        ):
            s = m["scenarios"][name]
            table_z = str(m["angle_choice"].get("table_z", ""))
            bound = ""
            if bounds and table_z in bounds["combined"]:
                bound = f"{100 * bounds['combined'][table_z][name]['success_bound']:.1f} %"
            lines.append(
                f"| combined, {label} | {100 * s['paper_success_rate']:.2f} % | {100 * s['success_rate']:.2f} % "
                f"(exact planner: {100 * s['success_rate_exact_planner']:.1f} %) | {bound} |"
            )
    lines += ["", "| step | wall time (s) |", "|---|---|"]
    lines += [f"| {k} | {v:.1f} |" for k, v in times.items()]
    return "\n".join(lines) + "\n"


def main(args: argparse.Namespace) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    times: dict[str, float] = {}
    for name, argv in steps(args):
        if args.only and name not in args.only:
            continue
        print(f"\n=== {name} {' '.join(argv)}", flush=True)
        start = time.perf_counter()
        code = subprocess.call([sys.executable, str(HERE / f"{name}.py"), *argv])
        times[name] = time.perf_counter() - start
        if code != 0:
            print(f"{name} failed with exit code {code}", file=sys.stderr)
            return code
    text = summary(out, times)
    (out / "summary.md").write_text(text)
    print("\n" + text)
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
    names = [name for name, _ in steps(args)]
    unknown = sorted(set(args.only or []) - set(names))
    if unknown:
        parser.error(f"--only: unknown step(s) {unknown}; the steps are {names}")
    return args


if __name__ == "__main__":
    sys.exit(main(parse_args()))
