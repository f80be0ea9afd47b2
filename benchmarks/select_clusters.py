"""The throw network's cluster count chosen from the rows alone, beside the re-throw error.

    python benchmarks/select_clusters.py                      # 5,000 noisy throws
    python benchmarks/select_clusters.py --n-train 29000 --noise-free

The throwing experiment (:mod:`experiments.throwing`) chooses the clusters per axis by
re-throwing: fit on four fifths of the training throws, aim at the other fifth's hits,
throw, and keep the grid whose new hits miss least (:func:`experiments.throwing.select_bins`).
A user with logged trials has no simulator to re-throw in. This script scores the same
grids on the same rows without one (:func:`inference.select_clusters`, by the held-out
log-likelihood of ``--folds``-fold cross-validation and by BIC) and prints each grid's
re-throw RMS beside its scores, and whether each score's choice lies in the range the
re-throw measures best: the grids whose validation RMS is within ``--tolerance`` of the
smallest.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from effect_networks.experiments.throwing import BIN_CANDIDATES, get_data, select_bins
from effect_networks.inference import select_clusters
from effect_networks.models.humanoid_throw import THROW, throw_network
from effect_networks.sim2d.analytic_throw import ReleaseNoise
from timing import add_out, print_also_to  # benchmarks/timing.py, beside this script


def compare(n_train, bins, *, noise=True, folds=5, seed=0, tolerance=0.05):
    """Per grid size: re-throw RMS (m) and both scores; the re-throw's best range and
    each score's choice. One data set for all: ``n_train`` throws, seeded."""
    rng = np.random.default_rng(seed)
    release = ReleaseNoise() if noise else None
    targets, hits = get_data(n_train, rng, release)
    start = time.perf_counter()
    rethrow = select_bins(targets, hits, bins, rng, release, progress=False)
    rethrow_s = time.perf_counter() - start
    rows = {"action": [THROW] * n_train, "param.target": targets, "end.hit": hits}

    def factory(k, layout):
        return throw_network((k, k))

    start = time.perf_counter()
    heldout = select_clusters(factory, rows, bins, folds=folds, seed=seed)
    heldout_s = time.perf_counter() - start
    start = time.perf_counter()
    by_bic = select_clusters(factory, rows, bins, score="bic")
    bic_s = time.perf_counter() - start
    best = min(r["rms_m"] for r in rethrow)
    good = [r["bins"] for r in rethrow if r["rms_m"] <= (1 + tolerance) * best]
    table = [
        {"bins": r["bins"], "rethrow_rms_m": r["rms_m"], "heldout": h.log_likelihood, "bic": b.bic}
        for r, h, b in zip(rethrow, heldout.candidates, by_bic.candidates, strict=True)
    ]
    return {
        "table": table,
        "best_range": good,
        "heldout_choice": heldout.chosen.bins[0],
        "bic_choice": by_bic.chosen.bins[0],
        "seconds": {"rethrow": rethrow_s, "heldout": heldout_s, "bic": bic_s},
    }


def report(result, n_train, noise) -> str:
    lines = [
        f"{n_train} {'noisy' if noise else 'noise-free'} throws; clusters per axis against "
        "the validation re-throw RMS and the scores",
        "",
        "| clusters per axis | re-throw RMS (cm) | held-out log-likelihood | BIC |",
        "|---:|---:|---:|---:|",
    ]
    for row in result["table"]:
        lines.append(
            f"| {row['bins']} | {100 * row['rethrow_rms_m']:.3f} | {row['heldout']:.1f} | "
            f"{row['bic']:.1f} |"
        )
    good = result["best_range"]
    for name in ("heldout", "bic"):
        k = result[f"{name}_choice"]
        inside = "inside" if k in good else "outside"
        lines.append(f"\n{name}: {k} per axis, {inside} the re-throw's best range {good}")
    s = result["seconds"]
    lines.append(
        f"\nseconds: re-throw {s['rethrow']:.1f}, held-out {s['heldout']:.1f}, BIC {s['bic']:.1f}"
    )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n-train", type=int, default=5_000)
    parser.add_argument("--bins", type=int, nargs="+", default=list(BIN_CANDIDATES))
    parser.add_argument("--noise-free", action="store_true")
    parser.add_argument("--folds", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--tolerance", type=float, default=0.05)
    add_out(parser)
    args = parser.parse_args()
    print_also_to(args.out, __file__)
    result = compare(
        args.n_train,
        args.bins,
        noise=not args.noise_free,
        folds=args.folds,
        seed=args.seed,
        tolerance=args.tolerance,
    )
    print(report(result, args.n_train, not args.noise_free))


if __name__ == "__main__":
    main()
