"""The results table, built from the experiments' JSON files so that it cannot drift.

``./reproduce`` writes each experiment's ``<name>.json`` into its results folder and a
record of the run itself (:class:`RunRecord`, ``run.json``: scale, commit, date, machine,
each step's wall time and the total). :func:`summary_markdown` reads them back and
states, beside the paper's figures, ours and the physics' own bound (the best action
found by simulation, :mod:`experiments.physics_bounds`); :func:`refresh_readme` puts
that text between the markers ``<!-- results:begin -->`` and ``<!-- results:end -->`` of
README.md.

The table is the concatenation of :data:`SECTIONS`: functions of the loaded results
(file stem -> JSON, a file that is absent is missing from the mapping) that return
table rows, or none when their experiment has not run. A new experiment adds its
function there.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import subprocess
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

from experiments.config import Result

__all__ = [
    "BEGIN",
    "END",
    "RunRecord",
    "SECTIONS",
    "load_results",
    "machine_description",
    "refresh_readme",
    "run_record",
    "summary_markdown",
    "write_summary",
]

BEGIN, END = "<!-- results:begin -->", "<!-- results:end -->"
RUN_FILE = "run.json"
TABLE_I_PROTOCOLS = {
    "counts": "one case per reachable desired count",
    "actions": "one case per count-changing action, the paper's wording",
}
COMBINED_SCENARIOS = {
    "top_three": "Table II, top three",
    "near_flank": "Table III, near flank",
    "far_flank": "Table IV, far flank",
}

Results = Mapping[str, dict]


@dataclass
class RunRecord(Result):
    """One run of the main job: ``scale``, ``commit`` (short hash, ``+`` when the work tree
    had uncommitted changes), ``date`` (UTC, ISO 8601), ``machine`` (words),
    ``step_seconds`` (wall time per step run, in order) and ``total_seconds``."""

    scale: str
    commit: str
    date: str
    machine: str
    step_seconds: dict[str, float]
    total_seconds: float

    def save(self, out) -> Path:
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

    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    parts = [f"{cores} cores"]
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


def run_record(scale: str, step_seconds: Mapping[str, float], root=None) -> RunRecord:
    """The record of a run that just ended, in the git work tree ``root`` (default: this
    package's repository)."""
    root = Path(root) if root is not None else Path(__file__).resolve().parents[1]
    commit = _git(root, "rev-parse", "--short", "HEAD") or "unknown"
    if commit != "unknown" and _git(root, "status", "--porcelain", "--untracked-files=no"):
        commit += "+"
    return RunRecord(
        scale=scale,
        commit=commit,
        date=datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        machine=machine_description(),
        step_seconds={k: float(v) for k, v in step_seconds.items()},
        total_seconds=float(sum(step_seconds.values())),
    )


def load_results(folder) -> dict[str, dict]:
    """Every ``*.json`` in ``folder`` and its subfolders, by file stem."""
    folder = Path(folder)
    files = sorted(folder.glob("*.json")) + sorted(folder.glob("*/*.json"))
    return {f.stem: json.loads(f.read_text()) for f in files}


def _percent(x: float | None, digits: int = 2) -> str:
    return "n/a" if x is None else f"{100 * x:.{digits}f} %"


def tap_rows(r: Results) -> list[str]:
    if (t := r.get("tap_and_remove")) is None:
        return []
    cells = "; ".join(f"{label} {rms:.4f} m" for label, rms in t["rms_m"].items())
    return [f"| §III tap: RMS prediction of the end position | qualitative | {cells} | |"]


def throwing_rows(r: Results) -> list[str]:
    if (t := r.get("throwing")) is None:
        return []
    return [
        f"| §IV-B throw: re-thrown RMS y / z (m) | {t['paper_rms_y_m']:.4f} / "
        f"{t['paper_rms_z_m']:.4f} | {t['rms_y_m']:.4f} / {t['rms_z_m']:.4f} "
        f"({t['n_clusters']} clusters; one Gaussian: {t['rms_y_m_single_gaussian']:.4f} / "
        f"{t['rms_z_m_single_gaussian']:.4f}; with release noise {t['rms_y_m_noisy']:.4f} / "
        f"{t['rms_z_m_noisy']:.4f} beside the noise's own scatter "
        f"{t['noise_scatter_y_m']:.4f} / {t['noise_scatter_z_m']:.4f}) | |"
    ]


def adaptive_throw_rows(r: Results) -> list[str]:
    """Beyond the paper: grid vs adaptive (EM) clusters, each by the inverse model and by
    the paper's posterior query, and active throw targets. The adaptive layout is shown
    at its best EM checkpoint fitted in under 2 s (the goal's), else its last; the noisy
    comparison at its own cluster count. (Results saved before the inverse model have the
    posterior query only, and one noise scatter for all rows.)"""
    if (t := r.get("adaptive_throw")) is None:
        return []
    k = max(row["n_clusters"] for row in t["layouts"])
    k_noisy = max((row.get("n_clusters", k) for row in t["noisy"]), default=k)

    def mine(rows, layout, query, size=k, steps=None):  # every EM checkpoint by default
        return [
            row
            for row in rows
            if row["layout"] == layout
            and row.get("query", "posterior") == query
            and row.get("n_clusters", size) == size
            and (steps is None or row["em_steps"] == steps)
        ]

    def last(rows, layout, query, size=k, steps=None):  # the last EM checkpoint by default
        rows = mine(rows, layout, query, size, steps)
        return rows[-1] if rows else None

    def goal_row(layout):  # the best checkpoint fitted within the goal's time, else the last
        rows = mine(t["layouts"], layout, "effect") or mine(t["layouts"], layout, "posterior")
        quick = [row for row in rows if row["fit_s"] < 2.0]
        if not quick:
            return rows[-1]
        return min(quick, key=lambda row: max(row["rms_y_m"], row["rms_z_m"]))

    def cm(row):
        return f"{100 * row['rms_y_m']:.4f} / {100 * row['rms_z_m']:.4f} cm"

    def ratio(row):
        if "ratio_y" in row:
            return f"{row['ratio_y']:.2f} / {row['ratio_z']:.2f}"
        return (
            f"{row['rms_y_m'] / t['noise_scatter_y_m']:.2f} / "
            f"{row['rms_z_m'] / t['noise_scatter_z_m']:.2f}"
        )

    layouts, noisy = [], []
    for layout in ("adaptive", "grid"):
        chosen = goal_row(layout)
        steps = chosen["em_steps"]
        post, effect = (last(t["layouts"], layout, q, steps=steps) for q in ("posterior", "effect"))
        fit = (
            f"fit {post['fit_s']:.1f} s, {post['em_steps']} EM steps"
            if layout == "adaptive"
            else f"fit {post['fit_s']:.2f} s"
        )
        if effect is None:
            layouts.append(f"{layout} {cm(post)} ({fit})")
        else:
            best = ""
            if "best_rms_y_m" in effect:
                pick = {"rms_y_m": effect["best_rms_y_m"], "rms_z_m": effect["best_rms_z_m"]}
                best = f"; best of its candidates {cm(pick)}"
            layouts.append(f"{layout} {cm(effect)} ({fit}; posterior query {cm(post)}{best})")
        post, effect = (last(t["noisy"], layout, q, k_noisy) for q in ("posterior", "effect"))
        if effect is None:
            noisy.append(f"{layout} {ratio(post)}")
        else:
            noisy.append(f"{layout} {ratio(effect)} (posterior query {ratio(post)})")
    bound = t.get("noisy_bound")
    floor = f"local Newton inverse of the training throws {cm(t['floor'])}"
    pieces = [row for row in t.get("pieces", ()) if row["n_clusters"] == k]
    if pieces:
        floor += f"; one best plane per cell (unclamped) leaves {cm(pieces[0])}"
    if bound is not None:
        floor += f"; with noise, the noise-free throw inverted: {ratio(bound)}"
    random, active = t["active"]["random"][-1], t["active"]["information"][-1]
    query = "inverse model" if last(t["layouts"], "grid", "effect") else "posterior query"
    return [
        f"| throw, beyond the paper: adaptive (EM) vs grid clusters, re-thrown RMS y / z "
        f"({k} clusters, noise-free, {query}; goal 0.01 cm, fit < 2 s) | - | "
        f"{', '.join(layouts)}; with release noise ({k_noisy} clusters), times the noise's "
        f"own scatter: "
        f"{', '.join(noisy)} (goal 1.05) | {floor} |",
        f"| throw, beyond the paper: active throw targets (expected information gain) vs "
        f"random, re-thrown RMS y / z after {active['n']} throws | - | active {cm(active)}, "
        f"random {cm(random)} | |",
    ]


def table_one_rows(r: Results) -> list[str]:
    """Table I under both protocols, each beside its bound."""
    c, b = r.get("can_tossing"), r.get("physics_bounds")
    if c is None and b is None:
        return []
    rows = []
    for protocol, words in TABLE_I_PROTOCOLS.items():
        paper = ours = bound = ""
        if c is not None:
            paper = f"{_percent(c['paper']['exact_fraction'])} of {c['paper']['n_cases']:,}"
            t = c["table_one"][protocol]
            head, other = t[c["rule"]], [rule for rule in t if rule != c["rule"]]
            ours = f"{_percent(head['exact_fraction'])} of {head['n_cases']:,}" + "".join(
                f" (tie-break {rule}: {_percent(t[rule]['exact_fraction'])})" for rule in other
            )
        bounds = (b or {}).get("table_one", {})
        if protocol in bounds:
            t = bounds[protocol]
            bound = (
                f"{_percent(t['exact_fraction_bound'])} held out, "
                f"{_percent(t['exact_fraction_in_sample'])} in sample ({t['repeats']} repeats)"
            )
        rows.append(f"| §IV-A cans, Table I exact: {words} | {paper} | {ours} | {bound} |")
    return rows


def can_rows(r: Results) -> list[str]:
    """Emulation and imitation."""
    if (c := r.get("can_tossing")) is None:
        return []
    e, i = c["emulation"], c["imitation"]

    def auc(x):
        return "n/a" if x is None else f"{x:.3f}"

    return [
        f"| cans: emulation, same end configuration | - | "
        f"{_percent(e['same_end_config'], 1)} of {e['n_demonstrations']} demonstrations "
        f"(the demonstrated field re-thrown: {_percent(e['reference_same_end_config'], 1)}) | |",
        f"| cans: imitation, ROC AUC of the surprise (failed = not the unperturbed throw's "
        f"outcome / none of the usual outcomes) | - | {auc(i['auc'])} / "
        f"{auc(i['auc_ordinary'])}; aim-pooled ({i['aim_sigma']:g} fields): "
        f"{auc(i['auc_pooled'])} / {auc(i['auc_ordinary_pooled'])} ({i['n_throws']} throws) | |",
    ]


def combined_rows(r: Results) -> list[str]:
    """The paper's three combined scenarios, each beside its bound at the same table."""
    m, b = r.get("combined"), r.get("physics_bounds")
    if m is None:
        return []
    table_z = str(m["angle_choice"].get("table_z", ""))
    bounds = (b or {}).get("combined", {}).get(table_z, {})
    rows = []
    for name, label in COMBINED_SCENARIOS.items():
        s = m["scenarios"][name]
        bound = ""
        if name in bounds:
            bound = (
                f"{_percent(bounds[name]['success_bound'], 1)} held out, "
                f"{_percent(bounds[name]['success_in_sample'], 1)} in sample"
            )
        rows.append(
            f"| §IV-C combined, {label} (table {table_z} m) | "
            f"{_percent(s['paper_success_rate'])} | {_percent(s['success_rate'])} (paper "
            f"planner); {_percent(s['success_rate_exact_planner'], 1)} (exact planner) | "
            f"{bound} |"
        )
    return rows


def all_goals_rows(r: Results) -> list[str]:
    """Beyond the paper: every goal the bound reaches, per table height, beside the bound."""
    if (a := r.get("all_goals")) is None:
        return []
    rows = []
    for t in a["tables"]:

        def mean(key, goals=t["goals"]):
            return sum(g[key] for g in goals) / len(goals) if goals else None

        rows.append(
            f"| combined, beyond the paper: every goal reachable within "
            f"{a['settings']['horizon']} throws (table {t['table_z']} m, {t['reachable']} "
            f"goals) | - | exact planner {_percent(mean('exact_measured'), 1)} mean success, "
            f"{_percent(t['exact_over_bound'], 1)} of the bound per goal on average "
            f"(goal {_percent(a['goal_ratio'], 0)}); paper planner "
            f"{_percent(mean('paper_measured'), 1)}, {_percent(t['paper_over_bound'], 1)} | "
            f"{_percent(mean('bound'), 1)} mean held out, "
            f"{_percent(mean('bound_in_sample'), 1)} in sample |"
        )
    return rows


def active_rows(r: Results) -> list[str]:
    """Beyond the paper: Table I learned from a fraction of the throws, per protocol (plain
    fit with tie-break ``aim``, and the fit pooled over neighbouring fields), at the budget
    nearest 10 % of the full data's throws."""
    if (a := r.get("active")) is None:
        return []
    k = min(range(len(a["fractions"])), key=lambda i: abs(a["fractions"][i] - 0.1))
    rows = []
    for protocol, words in TABLE_I_PROTOCOLS.items():
        learners = ", ".join(
            f"{name} {_percent(c[protocol]['aim'][k])} (pooled {_percent(c[protocol]['pooled'][k])})"
            for name, c in a["curves"].items()
        )
        reached = [
            name
            for name, g in a["goal"].items()
            if any(v is not None and v <= a["budgets"][k] for v in g[protocol].values())
        ]
        full = a["full"][protocol]
        rows.append(
            f"| cans, beyond the paper: Table I ({words}) learned by active exploration from "
            f"{_percent(a['fractions'][k], 0)} of the {a['n_pool']:,} 0° throws, exact on "
            f"{a['repeats']} held-out replays | - | {learners}; full data "
            f"{_percent(full['aim'])} (pooled {_percent(full['pooled'])}) (goal: within 1 "
            "point of the full data's best: "
            + (", ".join(reached) if reached else "not reached")
            + f") | {_percent(a['bound'][protocol])} held out |"
        )
    return rows


#: The table's sections, in order (see the module docstring).
SECTIONS: tuple[Callable[[Results], list[str]], ...] = (
    tap_rows,
    throwing_rows,
    adaptive_throw_rows,
    table_one_rows,
    can_rows,
    combined_rows,
    all_goals_rows,
    active_rows,
)


def summary_markdown(folder) -> str:
    """The run (scale, commit, date, machine), the results table and each step's time."""
    results = load_results(folder)
    run = results.get(Path(RUN_FILE).stem)
    if run is None:
        head = "Run: unknown (no run.json beside the results)."
    else:
        head = (
            f"Scale: {run['scale']}. Commit: {run['commit']}. Date: {run['date']}. "
            f"Machine: {run['machine']}."
        )
    lines = [
        head,
        "",
        "| experiment | paper | ours | physics bound (best action found by simulation) |",
        "|---|---|---|---|",
    ]
    for section in SECTIONS:
        lines += section(results)
    if run is not None:
        lines += ["", "| step | wall time (s) |", "|---|---:|"]
        lines += [f"| {name} | {s:.1f} |" for name, s in run["step_seconds"].items()]
        lines.append(f"| total | {run['total_seconds']:.1f} |")
    return "\n".join(lines) + "\n"


def write_summary(folder) -> Path:
    """Write :func:`summary_markdown` of ``folder`` to ``folder/summary.md``."""
    path = Path(folder) / "summary.md"
    path.write_text(summary_markdown(folder))
    return path


def refresh_readme(readme, text: str) -> bool:
    """Replace what lies between ``BEGIN`` and ``END`` in the file ``readme`` with ``text``.

    Returns whether the file changed. Raises a ``ValueError`` when the markers are not
    there once each, in order.
    """
    readme = Path(readme)
    old = readme.read_text()
    if old.count(BEGIN) != 1 or old.count(END) != 1 or old.index(BEGIN) > old.index(END):
        raise ValueError(f"{readme} needs one {BEGIN} line followed by one {END} line")
    before, rest = old.split(BEGIN)
    after = rest.split(END)[1]
    new = f"{before}{BEGIN}\n{text.rstrip()}\n{END}{after}"
    if new != old:
        readme.write_text(new)
    return new != old
