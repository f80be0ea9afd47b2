"""The adaptive-throw experiment's report.

Its Markdown, its figure and its rows of the results table (:mod:`experiments.adaptive_throw`).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

from effect_networks.experiments.adaptive_throw.settings import (
    CAUSES,
    GOAL_RMS_M,
    QUERIES,
    STRATEGIES,
)
from effect_networks.experiments.harness.config import Result

if TYPE_CHECKING:
    from effect_networks.experiments.adaptive_throw.run import AdaptiveThrowResult

__all__ = ["figures", "markdown", "plot_adaptive_throw", "summary_rows"]


def markdown(result: AdaptiveThrowResult) -> str:
    """Both layouts side by side, the references, the active curves and the goals, in cm."""
    cm = 100.0
    lines = [
        f"# Adaptive clusters and active throw targets ({result.n_train} training throws, "
        f"{result.n_test} test hits)",
        "",
        f"Re-throw RMS (cm), noise-free; fit time on one torch thread; every fit with "
        f"pseudo-count {result.pseudo_count:g}:",
        "",
        "| clusters | layout | query | fit (s) | EM steps | y (cm) | z (cm) | median (cm) "
        "| 99 % (cm) | best candidate y / z (cm) |",
        "|---:|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in result.layouts:
        best = "-"
        if "best_rms_y_m" in row:
            best = f"{cm * row['best_rms_y_m']:.4f} / {cm * row['best_rms_z_m']:.4f}"
        lines.append(
            f"| {row['n_clusters']} | {row['layout']} | {row['query']} | "
            f"{row['fit_s']:.2f} | {row['em_steps']} | {cm * row['rms_y_m']:.4f} | "
            f"{cm * row['rms_z_m']:.4f} | {cm * row['median_m']:.4f} | "
            f"{cm * row['p99_m']:.3f} | {best} |"
        )
    f = result.floor
    lines += [
        f"| - | Newton on local quadratic fits to the {f['neighbours']} nearest training "
        f"throws (a reference) | - | - | - | {cm * f['rms_y_m']:.4f} | "
        f"{cm * f['rms_z_m']:.4f} | {cm * f['median_m']:.4f} | {cm * f['p99_m']:.3f} | - |",
        "",
        "Best candidate: the re-throw RMS had every hit taken the cluster candidate of the "
        "inverse model that the throw itself says misses least.",
        "",
        *_tail_lines(result),
        "What linear pieces leave of the map's curvature: RMS residual (cm) of one "
        "least-squares plane per equidistant cell through the unclamped training throws "
        "(an inverse answering with one piece re-throws with that piece's residual at "
        "its aim):",
        "",
        "| clusters | y (cm) | z (cm) |",
        "|---:|---:|---:|",
        *(
            f"| {r['n_clusters']} | {cm * r['rms_y_m']:.4f} | {cm * r['rms_z_m']:.4f} |"
            for r in result.pieces
        ),
        "",
        f"With release noise (trained with it; each desired hit re-thrown "
        f"{result.noisy_bound['repeats']} times with it); scatter: the same throws about "
        "their noise-free hits:",
        "",
        "| clusters | layout | query | y (cm) | z (cm) | scatter y | scatter z "
        "| y / scatter | z / scatter |",
        "|---:|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    bound = result.noisy_bound | {
        "n_clusters": "-",
        "layout": "the noise-free throw inverted by local Newton (the physics' bound)",
        "query": "-",
    }
    for row in [*result.noisy, bound]:
        lines.append(
            f"| {row['n_clusters']} | {row['layout']} | {row['query']} | "
            f"{cm * row['rms_y_m']:.3f} | {cm * row['rms_z_m']:.3f} | "
            f"{cm * row['scatter_y_m']:.3f} | {cm * row['scatter_z_m']:.3f} | "
            f"{row['ratio_y']:.3f} | {row['ratio_z']:.3f} |"
        )
    b = result.noisy_bound
    lines += [
        "",
        f"The bound's aims thrown without noise miss the desired hits by "
        f"{cm * b['miss_median_m']:.4f} cm (median) and {cm * b['miss_p90_m']:.3f} cm "
        "(90th percentile): those hits lie beyond what a noise-free throw reaches.",
        "",
        "Active throw targets (grid layout, about 30 throws per cluster), re-throw RMS y / z "
        f"(cm) against the number of throws, the mean of {_seeds(result)} seed(s)' curves "
        "(each seed's first budget thrown at the same random targets by every strategy): "
        "random targets; the expected information gain about the clusters' regressions; "
        "the expected reduction of the predictive variance summed over the target area "
        "(ALC); and the same grid fitted on all the training throws (the grid's floor). "
        "In brackets, the share of the targets chosen since the budget before that lie within "
        "a tenth of a cell's width of a cell's edge (uniform targets: 36 %):",
        "",
        "| throws | clusters per axis | "
        + " | ".join(STRATEGIES)
        + f" | the grid on all {result.n_train} throws |",
        "|---:|---:|" + "---:|" * (len(STRATEGIES) + 1),
    ]
    floors = result.active_floor or [None] * len(result.active["random"])
    for i, floor in enumerate(floors):
        first = result.active["random"][i]
        cells = [_pair(result.active[s][i], edges=True) for s in STRATEGIES if s in result.active]
        lines.append(
            f"| {first['n']} | {first['bins']} | {' | '.join(cells)} | "
            f"{'-' if floor is None else _pair(floor)} |"
        )
    lines += ["", *_why_random_is_hard_to_beat(result)]
    lines += ["", "Goals:", ""]
    lines += [f"- {name}: {'met' if ok else 'missed'}" for name, ok in result.goals.items()]
    return "\n".join(lines) + "\n"


def _pair(row: dict, edges: bool = False) -> str:
    text = f"{100 * row['rms_y_m']:.3f} / {100 * row['rms_z_m']:.3f}"
    if edges and row.get("edge_share") is not None:
        text += f" ({100 * row['edge_share']:.0f} %)"
    return text


def _seeds(result: AdaptiveThrowResult) -> int:
    return len(result.active["random"][0].get("seeds_y_m", [None]))


def _why_random_is_hard_to_beat(result: AdaptiveThrowResult) -> list[str]:
    """Where the random curve stands against the grid's floor, per budget, in words."""
    if not result.active_floor:
        return []
    gaps = []
    for r, f in zip(result.active["random"], result.active_floor, strict=True):
        gaps.append(max(r["rms_y_m"] / f["rms_y_m"], r["rms_z_m"] / f["rms_z_m"]))
    return [
        "Random targets are drawn from the distribution the re-throw error is measured on "
        "(the test hits are the hits of uniform targets). At each budget the random curve "
        f"is at most {max(gaps):.2f} times the error of the same grid fitted on all "
        f"{result.n_train} training throws: what is left is the linear cells' own misfit of "
        "a curved throw, which no choice of targets removes at a given grid. The "
        "variance-based rules score a linear model's variance; they favour the cells' edges, "
        "which weighs the least-squares planes away from the targets the inverse model is "
        "asked about, and so raises the misfit's error.",
    ]


def _share(value: float | None) -> str:
    return "-" if value is None else f"{100 * value:.0f}"


def _tail_lines(result: AdaptiveThrowResult) -> list[str]:
    """Where the inverse model's squared re-throw error lies: its worst hits and its causes."""
    rows = [row for row in result.layouts if "tail" in row]
    if not rows:
        return []
    tail = rows[0]["tail"]
    lines = [
        "Where the inverse model's squared re-throw error lies, % per axis y / z: the share "
        f"of the worst {100 * tail['worst_fraction']:g} % of the hits, and of each cause "
        "(first that applies: the answer lay outside the area and was clipped into it; the "
        "arm clamps at the aim, where the map has a kink; another cluster's candidate misses "
        "by less than half as much, a choice; else what the chosen linear piece leaves of "
        "the map's curvature):",
        "",
        "| clusters | layout | EM steps | worst hits | " + " | ".join(CAUSES) + " |",
        "|---:|---|---:|---:|" + "---:|" * len(CAUSES),
    ]
    for row in rows:
        t = row["tail"]
        cells = [f"{_share(t[f'share_y_{c}'])} / {_share(t[f'share_z_{c}'])}" for c in CAUSES]
        lines.append(
            f"| {row['n_clusters']} | {row['layout']} | {row['em_steps']} | "
            f"{_share(t['worst_share_y'])} / {_share(t['worst_share_z'])} | "
            + " | ".join(cells)
            + " |"
        )
    head = _headline(result.layouts)
    if head is not None:
        lines += [
            "",
            f"The headline row's ({head['n_clusters']} adaptive clusters, "
            f"{head['em_steps']} EM steps) largest errors (cm):",
            "",
            "| desired y | desired z | error y | error z | cause |",
            "|---:|---:|---:|---:|---|",
            *(
                f"| {100 * h['desired_y_m']:.2f} | {100 * h['desired_z_m']:.2f} | "
                f"{100 * h['error_y_m']:.4f} | {100 * h['error_z_m']:.4f} | {h['cause']} |"
                for h in head["tail"]["worst_hits"]
            ),
        ]
    return [*lines, ""]


def _headline(layouts: list[dict]) -> dict | None:
    """The adaptive inverse model's row at the most clusters and its first EM checkpoint.

    The row the results table shows (:func:`summary_rows`); None without one.
    """
    rows = [r for r in layouts if r["layout"] == "adaptive" and "tail" in r]
    if not rows:
        return None
    k = max(r["n_clusters"] for r in rows)
    return min((r for r in rows if r["n_clusters"] == k), key=lambda r: r["em_steps"])


def summary_rows(t: AdaptiveThrowResult, results: Mapping[str, Result]) -> list[str]:
    """Beyond the paper: grid vs adaptive (EM) clusters, and active throw targets.

    Each layout by the inverse model and by the paper's posterior query. The adaptive layout is
    shown at its first EM checkpoint (``em_steps[0]``, the goal's: 5 steps at full scale),
    whatever its fit time, which is reported beside it (the fit-time goal is judged in the
    experiment's own goals): the row shown does not depend on the speed of the machine. The
    noisy comparison at its own cluster count. A layout with no inverse-model row (``query`` ``"effect"``)
    is shown by its posterior query.
    """
    k = max(row["n_clusters"] for row in t.layouts)
    k_noisy = max((row.get("n_clusters", k) for row in t.noisy), default=k)

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

    def goal_row(layout):  # the first checkpoint (the fewest EM steps): not chosen by time
        rows = mine(t.layouts, layout, "effect") or mine(t.layouts, layout, "posterior")
        return min(rows, key=lambda row: row["em_steps"])

    def cm(row):
        return f"{100 * row['rms_y_m']:.4f} / {100 * row['rms_z_m']:.4f} cm"

    def ratio(row):
        return f"{row['ratio_y']:.2f} / {row['ratio_z']:.2f}"

    layouts, noisy = [], []
    for layout in ("adaptive", "grid"):
        chosen = goal_row(layout)
        steps = chosen["em_steps"]
        post, effect = (last(t.layouts, layout, q, steps=steps) for q in ("posterior", "effect"))
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
        post, effect = (last(t.noisy, layout, q, k_noisy) for q in ("posterior", "effect"))
        if effect is None:
            noisy.append(f"{layout} {ratio(post)}")
        else:
            noisy.append(f"{layout} {ratio(effect)} (posterior query {ratio(post)})")
    bound = t.noisy_bound
    floor = f"local Newton inverse of the training throws {cm(t.floor)}"
    pieces = [row for row in t.pieces or () if row["n_clusters"] == k]
    if pieces:
        floor += f"; one best plane per cell (unclamped) leaves {cm(pieces[0])}"
    if bound is not None:
        floor += f"; with noise, the noise-free throw inverted: {ratio(bound)}"
    last_point = {s: t.active[s][-1] for s in STRATEGIES if s in t.active}
    floor_text = ""
    if t.active_floor:
        floor_text = (
            f"the same {t.active_floor[-1]['bins']} x {t.active_floor[-1]['bins']} grid fitted "
            f"on all {t.n_train} training throws: {cm(t.active_floor[-1])}"
        )
    names = {"variance": "variance (ALC)", "information": "information gain", "random": "random"}
    query = "inverse model" if last(t.layouts, "grid", "effect") else "posterior query"
    return [
        f"| throw, beyond the paper: adaptive (EM) vs grid clusters, re-thrown RMS y / z "
        f"({k} clusters, noise-free, {query}; goal 0.01 cm, fit < 2 s) | - | "
        f"{', '.join(layouts)}; with release noise ({k_noisy} clusters), times the noise's "
        f"own scatter: "
        f"{', '.join(noisy)} (goal 1.05) | {floor} |",
        f"| throw, beyond the paper: active throw targets vs random, re-thrown RMS y / z after "
        f"{last_point['random']['n']} throws (mean of {_seeds(t)} seed{'s' * (_seeds(t) > 1)}) | - | "
        + ", ".join(f"{names[s]} {cm(row)}" for s, row in last_point.items())
        + f" | {floor_text} |",
    ]


def figures(result: AdaptiveThrowResult, out: Path) -> list[Path]:
    """Draw the comparison, ``adaptive_throw.png``, into the folder ``out``; its path."""
    return [plot_adaptive_throw(result, out / "adaptive_throw.png")]


def plot_adaptive_throw(result: AdaptiveThrowResult, path) -> Path:
    """Error against cluster count (both layouts, the references) and the active curves."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(13, 4.5), layout="constrained")
    ax, ax_ll, ax_active = fig.subplots(1, 3)
    steps = sorted({r["em_steps"] for r in result.layouts if r["layout"] == "adaptive"})
    series = [("grid", 0, "o")] + [("adaptive", s, "s") for s in steps]
    for layout, n_steps, marker in series:
        for query, ls in zip(QUERIES, ("--", "-"), strict=True):
            # each grid size's row after this many EM steps (or its last, if EM settled)
            rows = {}
            for r in result.layouts:
                if r["layout"] == layout and r["query"] == query and r["em_steps"] <= n_steps:
                    rows[r["n_clusters"]] = r
            rows = [rows[c] for c in sorted(rows)]
            label = layout if layout == "grid" else f"adaptive, {n_steps} EM steps"
            ax.plot(
                [r["n_clusters"] for r in rows],
                [100 * max(r["rms_y_m"], r["rms_z_m"]) for r in rows],
                marker=marker,
                ls=ls,
                label=f"{label}, {query}",
            )
    worst = max(result.floor["rms_y_m"], result.floor["rms_z_m"])
    ax.axhline(100 * worst, color="grey", ls=":", lw=1, label="local Newton (reference)")
    ax.plot(
        [r["n_clusters"] for r in result.pieces],
        [100 * max(r["rms_y_m"], r["rms_z_m"]) for r in result.pieces],
        color="grey",
        ls="-.",
        marker=".",
        label="best planes per cell, unclamped (curvature)",
    )
    ax.axhline(100 * GOAL_RMS_M, color="black", ls="-.", lw=1, label="goal")
    ax.set(
        xscale="log",
        yscale="log",
        xlabel="clusters",
        ylabel="re-throw RMS, worse axis [cm]",
        title="Error against cluster count (noise-free)",
    )
    _plain_ticks(ax, sorted({r["n_clusters"] for r in result.layouts}))
    shown = [*result.layouts, *result.pieces]
    low = min(100 * GOAL_RMS_M, *(100 * max(r["rms_y_m"], r["rms_z_m"]) for r in shown))
    ax.set_ylim(bottom=low / 40)  # room for the legend below the curves
    ax.legend(fontsize=7, loc="lower left")
    ax_ll.plot(result.em_log_likelihoods, "o-", ms=3)
    ax_ll.set(xlabel="EM step", ylabel="mean log-likelihood per row", title="EM, largest grid")
    colours = {"random": "tab:blue", "information": "tab:orange", "variance": "tab:green"}
    curves = [(s, result.active[s], colours[s]) for s in STRATEGIES if s in result.active]
    if result.active_floor:
        curves.append(("grid on all throws", result.active_floor, "grey"))
    for strategy, rows, color in curves:
        for key, ls in (("rms_y_m", "-"), ("rms_z_m", "--")):
            ax_active.plot(
                [r["n"] for r in rows],
                [100 * r[key] for r in rows],
                color=color,
                ls=ls,
                marker="o",
                label=f"{strategy} {key[4]}",
            )
    ax_active.set(
        xscale="log",
        yscale="log",
        xlabel="throws",
        ylabel="re-throw RMS [cm]",
        title="Active vs random throw targets",
    )
    _plain_ticks(ax_active, [r["n"] for r in result.active["random"]])
    ax_active.legend(fontsize=7)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    return path


def _plain_ticks(ax, values) -> None:
    """Log-scaled x axis labelled at ``values`` only, in plain numbers."""
    from matplotlib.ticker import NullFormatter

    ax.set_xticks(values, [str(v) for v in values])
    ax.xaxis.set_minor_formatter(NullFormatter())
