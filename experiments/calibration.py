"""Whether a planner's predicted success is a probability: reliability bins and their error.

A planner that says "70 %" should succeed about 70 times in 100 when it says so. Over many
goals, each with a predicted success ``p`` and a measured success ``m`` (the fraction of
plays that reached it), :func:`reliability` bins the goals by ``p`` and compares, bin by
bin, the mean prediction with the mean measurement (a reliability diagram). Its summary
is the expected calibration error::

    ECE = sum over bins b of (n_b / n) |mean p in b - mean m in b|

beside the mean absolute gap per goal, the share of goals whose prediction lies within
``TOLERANCE`` of their measurement, and the mean prediction against the mean
measurement (a planner can be off goal by goal and right on average).
:func:`plot_reliability` draws the diagram. Nothing here knows the scene: the figures are
numbers in ``[0, 1]``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

__all__ = ["BINS", "TOLERANCE", "plot_reliability", "reliability"]

#: Equal-width bins of the predicted success.
BINS = 10
#: A prediction within this of its measurement counts as calibrated (5 points).
TOLERANCE = 0.05


def reliability(predicted: Sequence[float], measured: Sequence[float], bins: int = BINS) -> dict:
    """The reliability diagram of ``predicted`` against ``measured`` success, and its summaries.

    Parameters
    ----------
    predicted, measured
        One number in ``[0, 1]`` per goal, in the same order.
    bins
        Equal-width bins of ``[0, 1]`` by the prediction (the last closed at 1).

    Returns
    -------
    dict
        ``bins``: per non-empty bin ``low``, ``high``, ``n``, ``predicted`` and ``measured``
        (the bin's means); ``ece``; ``mean_abs`` (the mean absolute gap per goal);
        ``within`` (the share of goals within ``TOLERANCE``); ``mean_predicted``,
        ``mean_measured``; ``n``. With no goals, ``n`` is 0 and the rest None.
    """
    p = np.asarray(predicted, dtype=float)
    m = np.asarray(measured, dtype=float)
    if p.shape != m.shape or p.ndim != 1:
        raise ValueError(
            f"predicted and measured must be two equal 1-D sequences, got {p.shape} and {m.shape}"
        )
    if isinstance(bins, bool) or not isinstance(bins, int) or bins < 1:
        raise ValueError(f"bins must be an int >= 1, got {bins!r}")
    for name, x in (("predicted", p), ("measured", m)):
        if not np.all((x >= 0) & (x <= 1)):
            raise ValueError(f"{name} must lie in [0, 1]")
    if not len(p):
        keys = ("ece", "mean_abs", "within", "mean_predicted", "mean_measured")
        return {"n": 0, "bins": []} | dict.fromkeys(keys)
    which = np.minimum((p * bins).astype(int), bins - 1)
    rows, ece = [], 0.0
    for b in range(bins):
        mine = which == b
        if not mine.any():
            continue
        mean_p, mean_m = float(p[mine].mean()), float(m[mine].mean())
        rows.append(
            {"low": b / bins, "high": (b + 1) / bins, "n": int(mine.sum())}
            | {"predicted": mean_p, "measured": mean_m}
        )
        ece += mine.sum() / len(p) * abs(mean_p - mean_m)
    gap = np.abs(p - m)
    return {
        "n": len(p),
        "bins": rows,
        "ece": float(ece),
        "mean_abs": float(gap.mean()),
        "within": float(np.mean(gap <= TOLERANCE + 1e-12)),
        "mean_predicted": float(p.mean()),
        "mean_measured": float(m.mean()),
    }


def plot_reliability(panels: Sequence[tuple[str, Mapping[str, dict]]], path) -> Path:
    """Reliability diagrams, one panel each: ``(title, {predictor name: reliability(...)})``.

    Each predictor's bins as points (area by the goals in the bin) joined by a line, the
    diagonal of a calibrated prediction, and the ECE in the legend. Saved to ``path``.
    """
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5.2 * max(1, len(panels)), 4.8), layout="constrained")
    axes = fig.subplots(1, max(1, len(panels)), squeeze=False)[0]
    for ax, (title, curves) in zip(axes, panels, strict=False):
        ax.plot([0, 100], [0, 100], color="0.6", ls=":", lw=1, label="calibrated")
        for (name, r), colour in zip(curves.items(), ("C0", "C1", "C2", "C3"), strict=False):
            if not r["bins"]:
                continue
            x = [100 * b["predicted"] for b in r["bins"]]
            y = [100 * b["measured"] for b in r["bins"]]
            size = [12 + 10 * b["n"] for b in r["bins"]]
            ax.plot(x, y, "-", color=colour, lw=1)
            ax.scatter(x, y, s=size, color=colour, label=f"{name} (ECE {100 * r['ece']:.1f} pts)")
        ax.set(
            xlim=(0, 100), ylim=(0, 100), xlabel="predicted success (%)",
            ylabel="measured success (%)", title=title, aspect="equal",
        )  # fmt: skip
        ax.legend(fontsize=7, loc="upper left")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    return path
