"""Priors and online updates beside pgmpy, in one run.

Network: k binary features (each end feature's parents its own initial value and the
action, 3 actions), rows drawn from random parameters. For each prior (BDeu with an
equivalent sample size of 10, K2, and a symmetric Dirichlet pseudo-count of 2) the
toolkit's fit (``fit(net, rows, prior=...)``, the posterior mean) beside pgmpy's
``BayesianEstimator`` on the same rows: the largest difference between their tables and
the time of each. Then ``fit_update`` (a fit on the first half of the rows continued
with the second half) beside one fit on all rows: the largest difference and the times.
Run::

    .venv/bin/python benchmarks/priors.py [--ks 4 8 12] [--rows 5000] [--out DIR]

Goals: the prior fits equal pgmpy's to 1e-12; ``fit_update`` equals one fit on all rows
to 1e-12.
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
import pandas as pd
import torch
from effect_networks.inference import K2, BDeu, fit, fit_update, simulate
from effect_networks.models import random_params
from effect_networks.models.interop import to_pgmpy
from queries import sparse_network  # benchmarks/queries.py, beside this script
from timing import add_out, print_also_to

GOAL = 1e-12


def pgmpy_tables(net, params, rows: dict, **options) -> dict[str, torch.Tensor]:
    """Every site's table as pgmpy's BayesianEstimator gives it, in the toolkit's axes."""
    model, _ = to_pgmpy(net, params)
    names = {s.name: net.decode(s.name, torch.arange(s.size)) for s in net.sites}
    frame = pd.DataFrame({k: list(v) for k, v in rows.items()})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)  # pgmpy's estimator is deprecated
        from pgmpy.estimators import BayesianEstimator

        estimator = BayesianEstimator(model, frame, state_names=names)
        tables = {}
        for spec in net.sites:
            ours = list(net.cpd(spec.name).parents)
            theirs = sorted(ours)  # pgmpy orders a node's parents by name
            found = estimator.estimate_cpd(spec.name, **options)
            sizes = [net.site(p).size for p in theirs]
            values = found.get_values().T.reshape(*sizes, spec.size)
            back = np.moveaxis(values, range(len(theirs)), [ours.index(p) for p in theirs])
            tables[spec.name] = torch.as_tensor(np.ascontiguousarray(back))
    return tables


def largest_difference(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> float:
    return max(float((a[s] - b[s]).abs().max()) for s in a)


def timed(fn, *args, **kwargs):
    start = time.perf_counter()
    value = fn(*args, **kwargs)
    return value, time.perf_counter() - start


def verdict(value: float) -> str:
    return "met" if value <= GOAL else "not met"


def main(args: argparse.Namespace) -> None:
    torch.set_num_threads(1)
    priors = {
        "BDeu(10)": (BDeu(10.0), {"prior_type": "BDeu", "equivalent_sample_size": 10}),
        "K2": (K2(), {"prior_type": "K2"}),
        "Dirichlet 2": (2.0, {"prior_type": "dirichlet", "pseudo_counts": 2}),
    }
    print(f"rows {args.rows}, one torch thread; goal: every difference <= {GOAL:g}")
    print(
        "| k | prior | ours (s) | pgmpy (s) | largest difference | goal |\n"
        "|---:|---|---:|---:|---:|---|"
    )
    for k in args.ks:
        net = sparse_network(k)
        truth = random_params(net, k)
        rows = simulate(net, truth, args.rows, seed=k)
        for name, (ours, theirs) in priors.items():
            fitted, t_ours = timed(fit, net, rows, prior=ours)
            tables, t_pgmpy = timed(pgmpy_tables, net, truth, rows, **theirs)
            diff = largest_difference({s: fitted.params[s].probs for s in tables}, tables)
            print(f"| {k} | {name} | {t_ours:.3f} | {t_pgmpy:.3f} | {diff:.1e} | {verdict(diff)} |")
    print(
        "\nfit_update: the first half fitted, continued with the second half, beside one fit"
        " on all rows\n\n| k | one fit (s) | update (s) | largest difference | goal |\n"
        "|---:|---:|---:|---:|---|"
    )
    for k in args.ks:
        net = sparse_network(k)
        rows = simulate(net, random_params(net, k), args.rows, seed=k)
        half = args.rows // 2
        first = {s: v[:half] for s, v in rows.items()}
        second = {s: v[half:] for s, v in rows.items()}
        whole, t_whole = timed(fit, net, rows, prior=BDeu(10.0))
        start = fit(net, first, prior=BDeu(10.0)).params
        updated, t_update = timed(fit_update, net, start, second, prior=BDeu(10.0))
        diff = largest_difference(
            {s.name: updated.params[s.name].probs for s in net.sites},
            {s.name: whole.params[s.name].probs for s in net.sites},
        )
        print(f"| {k} | {t_whole:.3f} | {t_update:.3f} | {diff:.1e} | {verdict(diff)} |")


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ks", type=int, nargs="+", default=[4, 8, 12])
    parser.add_argument("--rows", type=int, default=5000)
    add_out(parser)
    return parser.parse_args(argv)


if __name__ == "__main__":
    args = parse_args()
    print_also_to(args.out, __file__)
    main(args)
