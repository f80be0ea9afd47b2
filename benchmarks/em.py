"""Fit time of adaptive clusters (EM) on the throw data, beside the 2 s goal.

    python benchmarks/em.py                         # 64, 144, 256, 400 clusters, 5 EM steps
    python benchmarks/em.py --bins 16 --steps 20 --repeats 1

Times :func:`inference.fit_em` (the throw network with adaptive target clusters seeded by
a ``bins x bins`` grid, 29,000 noise-free throws, ``--steps`` EM steps, no early stop) on
one torch thread, and beside it the peer: the grid layout's closed-form
:func:`inference.fit` on the same rows. Each figure is the median over ``--repeats`` runs
of ``time.perf_counter`` after one warm-up. Goal: the fit under 2 s on
one core. Both fits use ``--pseudo-count`` (default 0, as the adaptive throw experiment).
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
from effect_networks.experiments.adaptive_throw.run import adaptive_throw_network
from effect_networks.inference import fit, fit_em
from effect_networks.models.humanoid_throw import throw_data, throw_network
from effect_networks.sim2d.analytic_throw import sample_targets, throw
from throw import machine  # benchmarks/throw.py, beside this script
from timing import add_out, median_seconds, print_also_to

GOAL_S = 2.0


def main(argv: list[str] | None = None) -> dict[int, dict[str, float]]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n-train", type=int, default=29_000)
    parser.add_argument("--bins", type=int, nargs="+", default=[8, 12, 16, 20])
    parser.add_argument("--pseudo-count", type=float, default=0.0)
    parser.add_argument("--steps", type=int, default=5, help="EM steps per fit")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    add_out(parser)
    args = parser.parse_args(argv)
    print_also_to(args.out, __file__)
    threads = torch.get_num_threads()
    torch.set_num_threads(args.threads)
    try:
        targets = sample_targets(args.n_train, np.random.default_rng(args.seed))
        hits = throw(targets).hit
        print(machine())
        print(
            f"{args.n_train} training throws, {args.steps} EM steps, pseudo-count "
            f"{args.pseudo_count:g}; median of {args.repeats}"
        )
        out = {}
        for k in args.bins:
            adaptive = adaptive_throw_network((k, k))
            rows = throw_data(adaptive, targets, hits)
            em_s = median_seconds(
                lambda net=adaptive, rows=rows: fit_em(
                    net, rows, steps=args.steps, tol=1e-300, pseudo_count=args.pseudo_count
                ),
                args.repeats,
            )
            grid = throw_network((k, k))
            grid_rows = throw_data(grid, targets, hits)
            grid_s = median_seconds(
                lambda g=grid, r=grid_rows: fit(g, r, pseudo_count=args.pseudo_count), args.repeats
            )
            ok = "met" if em_s < GOAL_S else "missed"
            print(
                f"  {k * k:4d} clusters: fit_em {em_s:6.2f} s   goal < {GOAL_S:g} s: {ok}   "
                f"(grid layout, closed form: {1e3 * grid_s:.1f} ms)"
            )
            out[k * k] = {"fit_em": em_s, "grid": grid_s}
        return out
    finally:
        torch.set_num_threads(threads)


if __name__ == "__main__":
    main()
