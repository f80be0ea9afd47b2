"""The results table, built from the experiments' JSON files so that it cannot drift.

``./reproduce`` writes each experiment's ``<name>.json`` into its results folder and a
record of the run itself (:class:`RunRecord`, ``run.json``: scale, commit, date, machine,
each step's wall time, simulation time and peak memory, and the total).
:func:`summary_markdown` reads them back and states, beside the paper's figures, ours
and the physics' own bound (the best action found by simulation,
:mod:`experiments.physics_bounds`), and each step's measures beside the main job's goals
(:func:`step_table`); :func:`refresh_results` puts
that text between the markers ``<!-- results:begin -->`` and ``<!-- results:end -->`` of
README.md.

The table is the concatenation of each saved result's rows
(:meth:`experiments.harness.registry.Experiment.rows`), in the registry's order
(:mod:`experiments.harness.registry`); an experiment that has not run has none.
"""

from __future__ import annotations

import datetime
import json
import math
import os
import platform
import subprocess
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from effect_networks.experiments.harness.config import Result
from effect_networks.experiments.harness.registry import experiments
from effect_networks.sim2d.executors import available_cores

__all__ = [
    "BEGIN",
    "END",
    "RunRecord",
    "load_results",
    "machine_description",
    "refresh_results",
    "run_record",
    "summary_markdown",
    "write_summary",
]

BEGIN, END = "<!-- results:begin -->", "<!-- results:end -->"
RUN_FILE = "run.json"


#: The main job's goals: the share of its wall time that is not simulation (learning,
#: evaluation, start-up) at most this, and every process's peak memory below this.
REST_GOAL = 0.10
MEMORY_GOAL_BYTES = 2 * 10**9


@dataclass
class RunRecord(Result):
    """One run of the main job.

    ``scale``, ``commit`` (short hash, ``+`` when the work tree had uncommitted changes), ``date``
    (UTC, ISO 8601), ``machine`` (words), ``step_seconds`` (wall time per step run, in order),
    ``total_seconds``, ``simulation_seconds`` (per step, the wall time spent simulating:
    :mod:`sim2d.clock`) and ``peak_bytes`` (per step, the peak resident memory of its largest
    process: :mod:`experiments.harness.steps`). A record written before the last two were measured loads
    with them empty.
    """

    scale: str
    commit: str
    date: str
    machine: str
    step_seconds: dict[str, float]
    total_seconds: float
    simulation_seconds: dict[str, float] = field(default_factory=dict)
    peak_bytes: dict[str, int] = field(default_factory=dict)
    #: Wall time of the imports done once before the steps (counted in the total).
    startup_seconds: float = 0.0

    @classmethod
    def from_json(cls, text: str) -> RunRecord:
        """The record :meth:`to_json` wrote.

        Parameters
        ----------
        text
            The JSON text; a record written before the measures were added loads with
            ``simulation_seconds`` and ``peak_bytes`` empty.
        """
        try:
            data = json.loads(text)
        except (ValueError, RecursionError):
            data = None
        if isinstance(data, dict):  # the measures came later: absent in older records
            data = {"simulation_seconds": {}, "peak_bytes": {}, "startup_seconds": 0.0} | data
            text = json.dumps(data)
        return super().from_json(text)

    def save(self, out) -> Path:
        """Write the record into a folder.

        Parameters
        ----------
        out
            The folder; the record is written to ``run.json`` there.

        Returns
        -------
        Path
            The path written.
        """
        path = Path(out) / RUN_FILE
        path.write_text(self.to_json())
        return path


def _git(root: Path, *args: str) -> str | None:
    try:
        done = subprocess.run(
            ["git", *args], cwd=root, capture_output=True, text=True, timeout=30, check=True
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip()


def machine_description() -> str:
    """CPU cores usable here, memory, CPU model, OS, Python and torch."""
    import torch

    parts = [f"{available_cores()} cores"]
    try:
        memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        parts.append(f"{memory / 2**30:.0f} GiB")
    except (ValueError, OSError, AttributeError):
        pass
    model = platform.processor()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    if model:
        parts.append(model)
    parts += [
        f"{platform.system()} {platform.machine()}",
        f"Python {platform.python_version()}",
        f"torch {torch.__version__}",
    ]
    return ", ".join(parts)


def run_record(
    scale: str,
    step_seconds: Mapping[str, float],
    simulation_seconds: Mapping[str, float] | None = None,
    peak_bytes: Mapping[str, int] | None = None,
    startup_seconds: float = 0.0,
    root=None,
) -> RunRecord:
    """The record of a run that just ended, in the git work tree ``root``.

    ``root`` defaults to this package's repository; ``startup_seconds``, the imports
    done once before the steps, counts in the total.
    """
    root = Path(root) if root is not None else Path(__file__).resolve().parents[2]
    commit = _git(root, "rev-parse", "--short", "HEAD") or "unknown"
    if commit != "unknown" and _git(root, "status", "--porcelain", "--untracked-files=no"):
        commit += "+"
    return RunRecord(
        scale=scale,
        commit=commit,
        date=datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        machine=machine_description(),
        step_seconds={k: float(v) for k, v in step_seconds.items()},
        total_seconds=float(sum(step_seconds.values()) + startup_seconds),
        simulation_seconds={k: float(v) for k, v in (simulation_seconds or {}).items()},
        peak_bytes={k: int(v) for k, v in (peak_bytes or {}).items()},
        startup_seconds=float(startup_seconds),
    )


def load_results(folder) -> dict[str, Result]:
    """Every experiment's result saved below the results folder ``folder``, by name, in order.

    In the order of :func:`experiments.harness.registry.experiments`; an experiment that has not run is
    missing. A file of another shape raises a ``ValueError`` naming it.
    """
    found = {}
    for name, exp in experiments().items():
        path = exp.result_file(folder)
        if path.exists():
            found[name] = exp.result.load(path)
    return found


def summary_markdown(folder) -> str:
    """The run (scale, commit, date, machine), the results table and each step's time."""
    results = load_results(folder)
    path = Path(folder) / RUN_FILE
    run = RunRecord.load(path) if path.exists() else None
    if run is None:
        head = "Run: unknown (no run.json beside the results)."
    else:
        head = (
            f"Scale: {run.scale}. Commit: {run.commit}. Date: {run.date}. Machine: {run.machine}."
        )
    lines = [
        head,
        "",
        "| experiment | paper | ours | physics bound (best action found by simulation) |",
        "|---|---|---|---|",
    ]
    declared = experiments()
    for name, result in results.items():
        lines += declared[name].rows(result, results)
    if run is not None:
        lines += ["", *step_table(run)]
    return "\n".join(lines) + "\n"


def step_table(run: RunRecord) -> list[str]:
    """Per step: wall time, the part spent simulating, the rest, and the peak memory.

    The peak memory of its largest process; then the total and the goals beside the measured
    figures.
    """
    lines = [
        "| step | wall time (s) | simulation (s) | rest (s) | peak memory (MB) |",
        "|---|---:|---:|---:|---:|",
    ]

    def row(name: str, wall: float, sim: float | None, peak: int | None) -> str:
        sim_text = "-" if sim is None or math.isnan(sim) else f"{sim:.1f}"
        rest_text = "-" if sim is None or math.isnan(sim) else f"{wall - sim:.1f}"
        peak_text = "-" if peak is None else f"{peak / 1e6:,.0f}"
        return f"| {name} | {wall:.1f} | {sim_text} | {rest_text} | {peak_text} |"

    if run.startup_seconds > 0:  # the imports every step shares, done once
        lines.append(row("start-up (imports, once)", run.startup_seconds, 0.0, None))
    for name, wall in run.step_seconds.items():
        lines.append(row(name, wall, run.simulation_seconds.get(name), run.peak_bytes.get(name)))
    known = [s for s in run.simulation_seconds.values() if not math.isnan(s)]
    measured = len(known) == len(run.step_seconds) and bool(known)
    simulated = sum(known) if measured else None
    largest = max(run.peak_bytes.values()) if run.peak_bytes else None
    lines.append(row("total", run.total_seconds, simulated, largest))
    if simulated is None or largest is None:
        return lines
    rest = 1 - simulated / run.total_seconds if run.total_seconds > 0 else 0.0
    heaviest = max(run.peak_bytes, key=run.peak_bytes.get)
    lines += [
        "",
        f"Goals: the rest (learning, evaluation, start-up) at most "
        f"{100 * REST_GOAL:.0f} % of the total: {100 * rest:.1f} % "
        f"({'met' if rest <= REST_GOAL else 'not met'}); the largest process under "
        f"{MEMORY_GOAL_BYTES / 1e9:.0f} GB: {largest / 1e9:.2f} GB, {heaviest} "
        f"({'met' if largest < MEMORY_GOAL_BYTES else 'not met'}).",
    ]
    return lines


def write_summary(folder) -> Path:
    """Write :func:`summary_markdown` of ``folder`` to ``folder/summary.md``."""
    path = Path(folder) / "summary.md"
    path.write_text(summary_markdown(folder))
    return path


def refresh_results(page, text: str) -> bool:
    """Replace what lies between ``BEGIN`` and ``END`` in the file ``page`` with ``text``.

    Returns whether the file changed. Raises a ``ValueError`` when the markers are not
    there once each, in order.
    """
    page = Path(page)
    old = page.read_text()
    if old.count(BEGIN) != 1 or old.count(END) != 1 or old.index(BEGIN) > old.index(END):
        raise ValueError(f"{page} needs one {BEGIN} line followed by one {END} line")
    before, rest = old.split(BEGIN)
    after = rest.split(END)[1]
    new = f"{before}{BEGIN}\n{text.rstrip()}\n{END}{after}"
    if new != old:
        page.write_text(new)
    return new != old
