"""One-row action queries beside pgmpy's VariableElimination and pyAgrum's LazyPropagation.

Network: k binary features, each end feature's parents its own initial value and the
action (3 actions); the initial state latent, the end state observed. Per k and per
torch thread setting (one thread, torch's default): one free query
(``inference.infer_action`` in a loop of one-row calls: the factor tables it keeps per
network and parameters), one compiled query
(``inference.compile(net, params).infer_action``), and the batched traced query per row
(1,000 rows), beside pgmpy (``VariableElimination.query``, one inference object) and
pyAgrum (``LazyPropagation``, evidence set per query), all on the same tables; every
answer is checked equal to pgmpy's to 1e-12. Run::

    .venv/bin/python benchmarks/one_row.py [--ks 4 8 12 16 32] [--queries 30] [--out DIR]

Goals: one free query <= 1x pgmpy and <= 2x pyAgrum; the batched query per row >= 30x
ahead of pgmpy and >= 20x ahead of pyAgrum, and at k = 8 no slower per row than at
k = 12; one compiled query >= 5x ahead of pyAgrum.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np
import torch
from effect_networks.inference import infer_action
from effect_networks.models import random_params
from effect_networks.models.declaration import DTYPE
from effect_networks.models.interop import to_pgmpy
from queries import sparse_network  # benchmarks/queries.py, beside this script
from timing import add_out, median_seconds, print_also_to

from effect_networks import inference


def pyagrum_network(model):
    """A pyAgrum BayesNet with the pgmpy model's variables and tables."""
    import pyagrum as gum

    bn = gum.BayesNet()
    for cpd in model.get_cpds():
        states = [str(s) for s in cpd.state_names[cpd.variable]]
        bn.add(gum.LabelizedVariable(cpd.variable, cpd.variable, states))
    for cpd in model.get_cpds():
        for parent in cpd.variables[1:]:
            bn.addArc(parent, cpd.variable)
    for cpd in model.get_cpds():
        values = cpd.values  # (child, parents...)
        parents = cpd.variables[1:]
        for at in np.ndindex(*values.shape[1:]):
            bn.cpt(cpd.variable)[dict(zip(parents, at, strict=True))] = values[(slice(None), *at)]
    return bn


def per_query(run, rows: list, repeats: int = 3) -> float:
    """Median over ``repeats`` of the mean seconds per query of ``run(row)`` over ``rows``."""
    run(rows[0])  # a warm-up call
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for row in rows:
            run(row)
        times.append((time.perf_counter() - t0) / len(rows))
    return statistics.median(times)


def measure(k: int, queries: int, batch: int) -> dict[str, float]:
    """Seconds per query of each route at ``k`` features, and the largest difference."""
    import pyagrum as gum
    from pgmpy.inference import VariableElimination

    net = sparse_network(k)
    params = random_params(net, k)
    g = torch.Generator().manual_seed(k)
    ends = {f"end.f{i}": torch.randint(0, 2, (batch,), generator=g) for i in range(k)}
    evidence = net.encode_indices(ends)
    ones = [evidence.rows(slice(i, i + 1)) for i in range(queries)]
    labels = [{s: int(v[i]) for s, v in ends.items()} for i in range(queries)]
    compiled = inference.compile(net, params)
    model = to_pgmpy(net, params).model
    ve = VariableElimination(model)
    bn = pyagrum_network(model)
    lazy = gum.LazyPropagation(bn)

    def agrum(label):
        lazy.setEvidence({s: str(v) for s, v in label.items()})
        lazy.makeInference()
        return lazy.posterior("action").toarray()

    out = {
        "free": per_query(lambda ev: infer_action(net, params, ev), ones),
        "compiled": per_query(compiled.infer_action, ones),
        "batched": median_seconds(lambda: infer_action(net, params, evidence), 3) / batch,
        "pgmpy": per_query(lambda e: ve.query(["action"], evidence=e, show_progress=False), labels),
        "pyagrum": per_query(agrum, labels),
    }
    theirs = torch.tensor(
        np.stack([ve.query(["action"], evidence=e, show_progress=False).values for e in labels]),
        dtype=DTYPE,
    )
    agrums = torch.tensor(np.stack([agrum(e) for e in labels]), dtype=DTYPE)
    ours = torch.cat([infer_action(net, params, ev).probs for ev in ones])
    fast = torch.cat([compiled.infer_action(ev).probs for ev in ones])
    batched = infer_action(net, params, evidence).probs[:queries]
    out["max_diff"] = max(float((x - theirs).abs().max()) for x in (ours, fast, batched, agrums))
    return out


def main(args: argparse.Namespace) -> None:
    default_threads = torch.get_num_threads()
    print(
        f"one-row action queries, k binary features, sparse parents, initial state latent; "
        f"us per query; {args.queries} one-row queries, batch of {args.batch}; "
        f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f} at start"
    )
    print(
        f"{'threads':>7}{'k':>4}{'free':>9}{'compiled':>10}{'batched':>9}{'pgmpy':>9}"
        f"{'pyAgrum':>9}{'diff':>9}  goals"
    )
    batched: dict[tuple[int, int], float] = {}
    for threads in (1, default_threads):
        torch.set_num_threads(threads)
        for k in args.ks:
            m = measure(k, args.queries, args.batch)
            assert m["max_diff"] <= 1e-12, f"k = {k}: answers differ by {m['max_diff']:.1e}"
            us = {name: v * 1e6 for name, v in m.items() if name != "max_diff"}
            goals = [
                ("free <= pgmpy", us["free"] <= us["pgmpy"]),
                ("free <= 2x pyAgrum", us["free"] <= 2 * us["pyagrum"]),
                ("batched >= 30x pgmpy", us["pgmpy"] >= 30 * us["batched"]),
                ("batched >= 20x pyAgrum", us["pyagrum"] >= 20 * us["batched"]),
                ("compiled >= 5x pyAgrum", us["pyagrum"] >= 5 * us["compiled"]),
            ]
            verdict = "; ".join(f"{g}: {'met' if ok else 'not met'}" for g, ok in goals)
            batched[threads, k] = us["batched"]
            print(
                f"{threads:>7}{k:>4}{us['free']:>9.0f}{us['compiled']:>10.0f}"
                f"{us['batched']:>9.2f}{us['pgmpy']:>9.0f}{us['pyagrum']:>9.0f}"
                f"{m['max_diff']:>9.1e}  {verdict}"
            )
    torch.set_num_threads(default_threads)
    for threads in (1, default_threads):
        if (threads, 8) in batched and (threads, 12) in batched:
            eight, twelve = batched[threads, 8], batched[threads, 12]
            print(
                f"batched per row, {threads} thread(s): k = 8 {eight:.2f} us, k = 12 "
                f"{twelve:.2f} us; k = 8 no slower: {'met' if eight <= twelve else 'not met'}"
            )
    print(
        "\nfree: a one-row query reads the factor tables the free function keeps per (network, "
        "parameters), summed once per evidence pattern; a batch of more rows is traced once "
        "for all its rows (batched)."
    )
    print(f"load average at the end: {os.getloadavg()[0]:.2f}")


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--ks", type=int, nargs="+", default=[4, 8, 12, 16, 32])
    parser.add_argument("--queries", type=int, default=30, help="one-row queries timed")
    parser.add_argument("--batch", type=int, default=1000, help="rows of the batched query")
    add_out(parser)
    return parser.parse_args(argv)


if __name__ == "__main__":
    args = parse_args()
    print_also_to(args.out, __file__)
    main(args)
