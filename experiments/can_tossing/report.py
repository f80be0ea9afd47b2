"""The can-tossing experiment's report.

Its Markdown, its figures and its rows of the results table (:mod:`experiments.can_tossing`).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from effect_networks.experiments.can_tossing.settings import (
    PAPER_CASES,
    PAPER_PERCENT,
    PAPER_TABLE_I,
    TABLE_I_PROTOCOLS,
)
from effect_networks.experiments.evaluation import ACCURACY_BINS, roc_curve
from effect_networks.experiments.harness.config import Result, percent

if TYPE_CHECKING:
    from effect_networks.experiments.can_tossing.run import CanTossingResult

__all__ = [
    "can_rows",
    "figures",
    "markdown",
    "plot_bound_curve",
    "plot_roc",
    "plot_table_one",
    "summary_rows",
    "table_one_rows",
]


def markdown(r: CanTossingResult) -> str:
    """The report.

    Table I under both protocols and rules beside the paper's, emulation and imitation.
    """
    tabs = r.table_one
    cols = [(m, rule) for m in ("counts", "actions") for rule in ("index", "aim")]
    lines = [
        f"# Can tossing (scale {r.scale}; headline: cases {r.cases}, rule {r.rule})",
        "",
        "| accuracy | "
        + " | ".join(f"{m}/{rule} # | %" for m, rule in cols)
        + " | paper # | paper % |",
        "|---|" + "---:|---:|" * (len(cols) + 1),
    ]
    for b in ACCURACY_BINS:
        cells = []
        for m, rule in cols:
            t = tabs[m][rule]
            cells += [str(t["histogram"][b]), f"{100 * t['histogram'][b] / t['n_cases']:.2f}"]
        lines.append(
            f"| {b} | " + " | ".join(cells) + f" | {PAPER_TABLE_I[b]} | {PAPER_PERCENT[b]:.2f} |"
        )
    cells = [f"{tabs[m][rule]['n_cases']} | " for m, rule in cols]
    lines.append("| cases | " + " | ".join(cells) + f" | {PAPER_CASES} | |")
    lines.append("")
    for m, rule in cols:
        t = tabs[m][rule]
        line = f"- {m}/{rule}: exact {100 * t['exact_fraction']:.2f} %"
        if t["n_unreachable"] and t["exact_fraction_reachable"] is not None:
            line += (
                f"; {t['n_unreachable']} cases ask for a count no 0° training throw reached, "
                f"exact among the others {100 * t['exact_fraction_reachable']:.2f} %"
            )
        lines.append(line)
    e, i = r.emulation, r.imitation
    v = i["validation"]
    lines += [
        f"- emulation ({e['n_demonstrations']} demonstrations): same end configuration "
        f"{100 * e['same_end_config']:.1f} %, same count {100 * e['same_count']:.1f} % "
        f"(demonstrated field re-thrown: {100 * e['reference_same_end_config']:.1f} % / "
        f"{100 * e['reference_same_count']:.1f} %)",
        f"- imitation ({i['n_throws']} throws, aim error {100 * i['aim_error_m']:.1f} cm, "
        f"{i['n_failed']} failed): ROC AUC of surprise "
        + ("n/a (one class only)" if i["auc"] is None else f"{i['auc']:.3f}")
        + f"; against the intended throw's usual outcomes ({i['n_failed_ordinary']} failed): "
        + ("n/a" if i["auc_ordinary"] is None else f"{i['auc_ordinary']:.3f}"),
        f"- imitation, pooled surprise (aim error {i['aim_sigma']:g} fields): ROC AUC "
        + f"{_auc_text(i['auc_pooled'])}; against the usual outcomes "
        + f"{_auc_text(i['auc_ordinary_pooled'])}. Aim error chosen on a validation draw "
        + f"({v['n_throws']} throws, {v['n_failed']} / {v['n_failed_ordinary']} failed) by "
        + "the second AUC: "
        + ", ".join(
            f"{b['sigma']:g}: {_auc_text(b['auc'])} / {_auc_text(b['auc_ordinary'])}"
            for b in v["by_sigma"]
        ),
        *_threshold_lines(i),
        *_bound_lines(i),
        "",
    ]
    return "\n".join(lines)


def _auc_text(auc: float | None) -> str:
    return "n/a" if auc is None else f"{auc:.3f}"


#: Imitation's failure labels in the report's words.
FAILURE_WORDS = {
    "failed": "not the unperturbed throw's outcome",
    "failed_ordinary": "none of the usual outcomes",
}


def _of_bound(ours: float | None, bound: float | None) -> str:
    """``ours`` as a percentage of ``bound``, or n/a."""
    return "n/a" if ours is None or not bound else f"{100 * ours / bound:.1f} %"


def _threshold_lines(i: dict) -> list[str]:
    """The surprise's operating points, chosen on the validation draw."""
    lines = []
    for label, point in i.get("threshold", {}).items():
        if point is None:
            continue
        rates = (
            "n/a on the scored throws (one class only)"
            if point["tpr"] is None
            else f"flags {100 * point['tpr']:.1f} % of the failed throws and "
            f"{100 * point['fpr']:.1f} % of the others"
        )
        lines.append(
            f"- imitation threshold, failed = {FAILURE_WORDS[label]}: surprise >= "
            f"{point['threshold']:.4g} (chosen on the validation draw, largest true- minus "
            f"false-positive rate) {rates}"
        )
    return lines


def _bound_lines(i: dict) -> list[str]:
    """The surprise's physics bound and ours as a fraction of it (none in older results)."""
    if "bound" not in i:
        return []
    b = i["bound"]
    h = b["half_repeats"]
    return [
        f"- imitation's physics bound (the surprise under the simulator's own outcome "
        f"frequencies per aim, {b['repeats']} replays of every field from every start): "
        f"ROC AUC {_auc_text(b['auc'])} / {_auc_text(b['auc_ordinary'])} (failed = "
        f"{FAILURE_WORDS['failed']} / {FAILURE_WORDS['failed_ordinary']}); aim-pooled "
        f"({b['aim_sigma']:g} fields, chosen on the validation draw as ours): "
        f"{_auc_text(b['auc_pooled'])} / {_auc_text(b['auc_ordinary_pooled'])}; from "
        f"{h['repeats']} replays only: {_auc_text(h['auc'])} / {_auc_text(h['auc_ordinary'])}",
        f"- imitation, ours as a fraction of the bound: surprise "
        f"{_of_bound(i['auc'], b['auc'])} / {_of_bound(i['auc_ordinary'], b['auc_ordinary'])}; "
        f"aim-pooled {_of_bound(i['auc_pooled'], b['auc_pooled'])} / "
        f"{_of_bound(i['auc_ordinary_pooled'], b['auc_ordinary_pooled'])}",
        *_curve_lines(i),
    ]


def _curve_lines(i: dict) -> list[str]:
    """The bound as its replays grow, ours beside its end, and ours with more throws per aim."""
    if "bound_curve" not in i:  # results written before the curve was measured have none
        return []
    curve, more = i["bound_curve"], i["more_data"]
    last = curve[-1]
    return [
        "- imitation's bound as fresh replays of each scored throw's own aim grow (replays: "
        "AUC / AUC against the usual outcomes): "
        + ", ".join(
            f"{c['repeats']}: {_auc_text(c['auc'])} / {_auc_text(c['auc_ordinary'])}" for c in curve
        ),
        f"- imitation, ours as a fraction of the bound from {last['repeats']} replays: surprise "
        f"{_of_bound(i['auc'], last['auc'])} / "
        f"{_of_bound(i['auc_ordinary'], last['auc_ordinary'])}; aim-pooled "
        f"{_of_bound(i['auc_pooled'], last['auc'])} / "
        f"{_of_bound(i['auc_ordinary_pooled'], last['auc_ordinary'])}",
        f"- imitation, ours fitted on {more['throws_per_aim']} throws per aim (the bound's "
        f"replays) instead of the data set: surprise {_auc_text(more['auc'])} / "
        f"{_auc_text(more['auc_ordinary'])} ({_of_bound(more['auc'], last['auc'])} / "
        f"{_of_bound(more['auc_ordinary'], last['auc_ordinary'])} of the bound from "
        f"{last['repeats']} replays); aim-pooled ({more.get('aim_sigma', i['aim_sigma']):g} "
        f"fields) {_auc_text(more['auc_pooled'])} / "
        f"{_auc_text(more['auc_ordinary_pooled'])}",
    ]


def figures(result: CanTossingResult, out: Path) -> list[Path]:
    """``can_tossing_table1.png``, ``can_tossing_roc.png`` and ``can_tossing_bound_curve.png``.

    Drawn into the folder ``out``; the second and third when the imitation has both classes.
    """
    files = [plot_table_one(result, out / "can_tossing_table1.png")]
    if result.imitation["auc"] is not None:
        files.append(plot_roc(result.imitation, out / "can_tossing_roc.png"))
    if any(c["auc"] is not None for c in result.imitation.get("bound_curve", [])):
        files.append(plot_bound_curve(result.imitation, out / "can_tossing_bound_curve.png"))
    return files


def plot_bound_curve(result: dict, path) -> Path:
    """The imitation bound against replays per aim, ours beside it (``result``: :func:`imitation`'s).

    Saved to ``path``. Solid: the bound from the first ``R`` fresh replays of each scored
    throw's aim; dashed: ours from the data set; dotted: ours fitted on the bound's replays.
    """
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.0, 4.2))
    ax = fig.subplots()
    curve, more = result["bound_curve"], result["more_data"]
    repeats = [c["repeats"] for c in curve]
    for (key, label), colour in zip(FAILURE_WORDS.items(), ("C0", "C1"), strict=True):
        suffix = "" if key == "failed" else "_ordinary"
        points = [(c["repeats"], c[f"auc{suffix}"]) for c in curve if c[f"auc{suffix}"] is not None]
        if not points:
            continue
        ax.plot(*zip(*points, strict=True), "o-", color=colour, label=f"bound; failed: {label}")
        for value, style, name in (
            (result[f"auc{suffix}"], "--", "ours, data set"),
            (more[f"auc{suffix}"], ":", f"ours, {more['throws_per_aim']} throws per aim"),
        ):
            if value is not None:
                ax.axhline(value, linestyle=style, color=colour, label=f"{name} ({value:.3f})")
    ax.set_xscale("log", base=2)
    ax.set_xticks(repeats, [str(r) for r in repeats])
    ax.set_xlabel("replays per aim the bound is estimated from")
    ax.set_ylabel("ROC AUC of the surprise")
    ax.set_title("Imitation: the physics bound as its replays grow", fontsize=10)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    return Path(path)


def plot_table_one(result: CanTossingResult, path) -> Path:
    """Bar chart of Table I's bins: each protocol and rule beside the paper; saved to ``path``."""
    from matplotlib.figure import Figure

    tables = result.table_one
    series = {
        f"ours, {m}, {rule}": [100 * t["histogram"][b] / t["n_cases"] for b in ACCURACY_BINS]
        for m in tables
        for rule, t in tables[m].items()
    }
    series["paper"] = [PAPER_PERCENT[b] for b in ACCURACY_BINS]
    fig = Figure(figsize=(8, 4.2))
    ax = fig.subplots()
    x = np.arange(len(ACCURACY_BINS))
    width = 0.8 / len(series)
    for k, (label, values) in enumerate(series.items()):
        ax.bar(x + (k - (len(series) - 1) / 2) * width, values, width, label=label)
    ax.set_xticks(x, ACCURACY_BINS)
    ax.set_yscale("log")
    ax.set_xlabel("desired minus achieved count")
    ax.set_ylabel("% of cases (log scale)")
    ax.set_title("Table I: best field for a desired count, thrown at 0°")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    return Path(path)


def plot_roc(result: dict, path) -> Path:
    """ROC curves of the imitation surprise (``result``: :func:`imitation`'s); saved to ``path``."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5.6, 5.0))
    ax = fig.subplots()
    bound = result.get("bound", {"repeats": 0})
    for (key, label), colour in zip(FAILURE_WORDS.items(), ("C0", "C1"), strict=True):
        suffix = "" if key == "failed" else "_ordinary"
        for source, scores, style, name in (
            (result, "surprise", "-", "surprise"),
            (result, "pooled_surprise", "--", f"pooled, {result['aim_sigma']:g} fields"),
            (bound, "surprise", ":", f"physics bound, {bound['repeats']} replays"),
        ):
            auc = source.get(f"auc{suffix}" + ("_pooled" if scores == "pooled_surprise" else ""))
            if auc is not None:
                fpr, tpr = roc_curve(source[scores], result[key])
                ax.plot(fpr, tpr, style, color=colour, label=f"failed: {label}; {name} ({auc:.3f})")
        point = result.get("threshold", {}).get(key)
        if point is not None and point["tpr"] is not None:
            ax.plot(
                point["fpr"], point["tpr"], "o", color=colour,
                label=f"threshold {point['threshold']:.3g} (chosen on the validation draw)",
            )  # fmt: skip
    ax.plot([0, 1], [0, 1], "-.", color="0.6", label="chance")
    ax.set_xlabel("false-positive rate (successful throws flagged)")
    ax.set_ylabel("true-positive rate (failed throws flagged)")
    ax.set_title(
        f"Imitation: {result['n_throws']} throws aimed {100 * result['aim_error_m']:.0f} cm off",
        fontsize=10,
    )
    ax.legend(loc="lower right", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    return Path(path)


def table_one_rows(c: CanTossingResult | None, b: Result | None) -> list[str]:
    """Table I under both protocols, ours (``c``) beside the physics bound (``b``).

    Either may be missing; ``b`` is the physics bounds' result
    (:class:`experiments.physics_bounds.PhysicsBoundsResult`), of which its ``table_one`` is read.
    """
    if c is None and b is None:
        return []
    rows = []
    for protocol, words in TABLE_I_PROTOCOLS.items():
        paper = ours = bound = ""
        if c is not None:
            paper = f"{percent(c.paper['exact_fraction'])} of {c.paper['n_cases']:,}"
            t = c.table_one[protocol]
            head, other = t[c.rule], [rule for rule in t if rule != c.rule]
            ours = f"{percent(head['exact_fraction'])} of {head['n_cases']:,}" + "".join(
                f" (tie-break {rule}: {percent(t[rule]['exact_fraction'])})" for rule in other
            )
        bounds = b.table_one if b is not None else {}
        if protocol in bounds:
            t = bounds[protocol]
            bound = (
                f"{percent(t['exact_fraction_bound'])} held out, "
                f"{percent(t['exact_fraction_in_sample'])} in sample ({t['repeats']} repeats)"
            )
        rows.append(f"| §IV-A cans, Table I exact: {words} | {paper} | {ours} | {bound} |")
    return rows


def can_rows(c: CanTossingResult) -> list[str]:
    """Emulation and imitation."""
    e, i = c.emulation, c.imitation

    def auc(x):
        return "n/a" if x is None else f"{x:.3f}"

    bound = ""
    if "bound" in i:  # results written before the bound was measured have none
        b = i["bound"]
        bound = (
            f"{auc(b['auc'])} / {auc(b['auc_ordinary'])}; aim-pooled {auc(b['auc_pooled'])} / "
            f"{auc(b['auc_ordinary_pooled'])} (the simulator's own outcome frequencies, "
            f"{b['repeats']} replays per aim); ours {_of_bound(i['auc'], b['auc'])} / "
            f"{_of_bound(i['auc_ordinary'], b['auc_ordinary'])} of it"
        )
        if "bound_curve" in i:
            last, more = i["bound_curve"][-1], i["more_data"]
            bound += (
                f"; from {last['repeats']} fresh replays of each scored aim "
                f"{auc(last['auc'])} / {auc(last['auc_ordinary'])}, ours "
                f"{_of_bound(i['auc'], last['auc'])} / "
                f"{_of_bound(i['auc_ordinary'], last['auc_ordinary'])} of it (aim-pooled "
                f"{_of_bound(i['auc_pooled'], last['auc'])} / "
                f"{_of_bound(i['auc_ordinary_pooled'], last['auc_ordinary'])}; fitted on "
                f"{more['throws_per_aim']} throws per aim {_of_bound(more['auc'], last['auc'])} / "
                f"{_of_bound(more['auc_ordinary'], last['auc_ordinary'])})"
            )
    return [
        f"| cans: emulation, same end configuration | - | "
        f"{percent(e['same_end_config'], 1)} of {e['n_demonstrations']} demonstrations "
        f"(the demonstrated field re-thrown: {percent(e['reference_same_end_config'], 1)}) | |",
        f"| cans: imitation, ROC AUC of the surprise (failed = not the unperturbed throw's "
        f"outcome / none of the usual outcomes) | - | {auc(i['auc'])} / "
        f"{auc(i['auc_ordinary'])}; aim-pooled ({i['aim_sigma']:g} fields): "
        f"{auc(i['auc_pooled'])} / {auc(i['auc_ordinary_pooled'])} ({i['n_throws']} throws) | "
        f"{bound} |",
    ]


def summary_rows(result: CanTossingResult, results: Mapping[str, Result]) -> list[str]:
    """Table I under both protocols beside the physics bound, emulation, imitation."""
    return table_one_rows(result, results.get("physics_bounds")) + can_rows(result)
