"""The active-exploration experiment's report: its Markdown and its figure.

Its Markdown, its figure and its rows of the results table (:mod:`experiments.active`).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from effect_networks.experiments.active.settings import (
    GOAL_FRACTION,
    GOAL_POINTS,
    POINT_GOAL_S,
    SCORES,
)
from effect_networks.experiments.can_tossing.settings import PROTOCOLS, TABLE_I_PROTOCOLS
from effect_networks.experiments.harness.config import Result, percent

if TYPE_CHECKING:
    from effect_networks.experiments.active.run import ActiveResult

__all__ = ["figures", "markdown", "plot_curves", "summary_rows"]


def markdown(r: ActiveResult) -> str:
    """The report: per protocol and rule, each learner's exact fraction at every budget."""
    lines = [
        f"# Active exploration of the can world (scale {r.scale})",
        "",
        f"Pool: the {r.n_pool:,} throwable 0° throws Table I fits on ({r.n_pairs:,} "
        f"(configuration, field) pairs; the whole data set has {r.n_dataset:,} throws). "
        f"Exact fraction of Table I's cases, each chosen field scored on {r.repeats} "
        "held-out replays. Goal: within 1 point of the full data's best score with at "
        f"most {100 * GOAL_FRACTION:.0f} % of its throws.",
        "",
    ]
    head = " | ".join(f"{100 * f:g} % ({b:,})" for f, b in zip(r.fractions, r.budgets, strict=True))
    for p in PROTOCOLS:
        for rule in SCORES:
            how = (
                f"tables pooled over neighbouring fields (sigma {r.settings['pool_sigma']:g} "
                f"cells, strength {r.settings['pool_strength']:g}), tie-break aim"
                if rule == "pooled"
                else f"plain fit, tie-break {rule}"
            )
            lines += [
                f"## {p} ({r.n_cases[p]:,} cases), {how}",
                "",
                f"| learner | {head} | fewest throws within 1 point |",
                "|---|" + "---:|" * (len(r.budgets) + 1),
            ]
            for name, c in r.curves.items():
                cells = " | ".join(f"{100 * v:.2f}" for v in c[p][rule])
                g = r.goal[name][p][rule]
                reached = "not reached" if g is None else f"{g:,} ({100 * g / r.n_pool:.1f} %)"
                lines.append(f"| {name} | {cells} | {reached} |")
            lines += [
                f"| full data ({r.n_pool:,}) | "
                + " | ".join(f"{100 * r.full[p][rule]:.2f}" for _ in r.budgets)
                + " | |",
                "",
            ]
        lines += [
            f"Physics bound ({p}): {100 * r.bound[p]:.2f} % (the simulator's best field "
            "chosen on half of the replays, scored on the other half); chosen on 1, 2, ... "
            "replays of every pair (1 per pair is "
            f"{100 * r.n_pairs / r.n_pool:.0f} % of the pool's throws): "
            + ", ".join(f"{100 * v:.2f}" for v in r.bound_by_repeats[p])
            + ". Cases whose desired "
            "count some chosen throw reached from their start, % at each budget: "
            + "; ".join(
                f"{name} " + ", ".join(f"{100 * v:.1f}" for v in seen[p])
                for name, seen in r.cases_seen.items()
            )
            + ".",
            "",
        ]
    lines += [
        f"Mean over {r.settings['n_seeds']} seed(s). Distinct (configuration, field) pairs "
        "played (mean): "
        + "; ".join(
            f"{name} " + ", ".join(f"{c:,.0f}" for c in np.mean(cov, 0))
            for name, cov in r.pairs_covered.items()
        )
        + ".",
        "Choosing time (CPU s, whole run): "
        + ", ".join(f"{name} {s:.1f}" for name, s in r.seconds.items())
        + ". Table I per budget point (CPU s, both fits and both protocols; goal under "
        f"{POINT_GOAL_S:g} s): "
        + "; ".join(
            f"{name} " + ", ".join(f"{t:.2f}" for t in times)
            for name, times in r.point_time_s.items()
        )
        + ".",
        "",
    ]
    return "\n".join(lines)


def plot_curves(result: ActiveResult, path) -> Path:
    """Exact fraction against throws used, one panel per protocol; saved to ``path``.

    Per learner the pooled fit solid, the plain fit with tie-break ``aim`` dashed and ``index``
    dotted; the full data's three as black lines of the same styles, the band within one point of
    its best, the physics bound grey.
    """
    from matplotlib.figure import Figure

    styles = {"pooled": "o-", "aim": "--", "index": ":"}
    fig = Figure(figsize=(11, 4.6), layout="constrained")
    axes = fig.subplots(1, len(PROTOCOLS))
    x = 100 * np.asarray(result.budgets) / result.n_pool
    for ax, p in zip(axes, PROTOCOLS, strict=True):
        for k, (name, c) in enumerate(result.curves.items()):
            for rule, style in styles.items():
                ax.plot(
                    x,
                    100 * np.asarray(c[p][rule]),
                    style,
                    color=f"C{k}",
                    ms=4,
                    label=name if rule == "pooled" else None,
                )
        for rule, style in styles.items():
            ax.axhline(
                100 * result.full[p][rule],
                color="k",
                ls=style.lstrip("o"),
                lw=1,
                label=f"full data ({result.n_pool:,} throws)" if rule == "pooled" else None,
            )
        best = 100 * max(result.full[p].values())
        ax.axhspan(best - 100 * GOAL_POINTS, best, color="0.85", label="within 1 point")
        ax.axhline(100 * result.bound[p], color="0.5", lw=2, alpha=0.6, label="physics bound")
        ax.axvline(100 * GOAL_FRACTION, color="0.5", ls=":", lw=1)
        ax.set_xscale("log")
        ax.set_xticks(x, [f"{v:.3g}" for v in x])
        ax.minorticks_off()
        ax.set_xlabel("throws used, % of the full data's 0° throws (log scale)")
        ax.set_ylabel("Table I exact, % of cases (held-out replays)")
        ax.set_title(
            f"{p} ({result.n_cases[p]:,} cases); solid: pooled fit, dashed / dotted: plain "
            "fit, tie-break aim / index",
            fontsize=9,
        )
    axes[0].legend(fontsize=8, loc="lower right")
    fig.savefig(path, dpi=120)
    return Path(path)


def figures(r: ActiveResult, out: Path) -> list[Path]:
    """Draw the learning curves, ``active.png``, into the folder ``out``; its path."""
    return [plot_curves(r, out / "active.png")]


def summary_rows(r: ActiveResult, results: Mapping[str, Result]) -> list[str]:
    """Per protocol, each learner at the budget nearest its goal.

    The goal is ``GOAL_FRACTION`` of the full data's throws; plain fit with tie-break ``aim``,
    and pooled, beside the bound.
    """
    k = min(range(len(r.fractions)), key=lambda i: abs(r.fractions[i] - GOAL_FRACTION))
    rows = []
    for protocol, words in TABLE_I_PROTOCOLS.items():
        learners = ", ".join(
            f"{name} {percent(c[protocol]['aim'][k])} (pooled {percent(c[protocol]['pooled'][k])})"
            for name, c in r.curves.items()
        )
        reached = [
            name
            for name, g in r.goal.items()
            if any(v is not None and v <= r.budgets[k] for v in g[protocol].values())
        ]
        full = r.full[protocol]
        rows.append(
            f"| cans, beyond the paper: Table I ({words}) learned by active exploration "
            f"from {percent(r.fractions[k], 0)} of the {r.n_pool:,} 0° throws, exact "
            f"on {r.repeats} held-out replays | - | {learners}; full data "
            f"{percent(full['aim'])} (pooled {percent(full['pooled'])}) (goal: within 1 "
            "point of the full data's best: "
            + (", ".join(reached) if reached else "not reached")
            + f") | {percent(r.bound[protocol])} held out |"
        )
    return rows
