"""Structure learning time: 10 features, 5,000 rows, beside the 10 s goal and pgmpy.

    python benchmarks/structure.py                       # discrete and mixed worlds
    python benchmarks/structure.py --worlds discrete --rows 2000 --repeats 1

Times :func:`inference.learn_structure` (BIC, ``search="auto"``, the default
``max_parents``) on one torch thread on rows drawn by :func:`inference.simulate` from a
network of ``--features`` features (each end site with two initial parents, the action,
and for every third feature a discrete end parent; random tables and linear Gaussians,
``models.random_params``), and beside it pgmpy's ``HillClimbSearch`` on the same rows
with the same constraints (initial sites and the action roots, no continuous end site a
parent, the same in-degree bound): ``bic-d`` on the discrete world, ``bic-cg`` on the
mixed one. Each figure is the median over ``--repeats`` runs of ``time.perf_counter``
after one warm-up; the edges each search recovers are printed beside it. Goal: under
10 s on one core for 10 features and 5,000 rows.
"""

from __future__ import annotations

import argparse
import logging

import numpy as np
import pandas as pd
import torch
from effect_networks.inference import learn_structure, simulate
from effect_networks.models import Continuous, Discrete, EffectNetwork, random_params
from throw import machine  # benchmarks/throw.py, beside this script
from timing import add_out, median_seconds, print_also_to

GOAL_S = 10.0
ACTIONS = ("grasp", "tap", "touch")


def world(kind: str, n_features: int, seed: int) -> EffectNetwork:
    """The true network: feature i's end site has the initial sites of features i and
    i + 1 and the action as parents, and every third one the end site of the discrete
    feature before it."""
    features = []
    for i in range(n_features):
        if kind == "discrete" or i % 2 == 0:
            features.append(Discrete(f"f{i}", (0, 1, 2)))
        else:
            features.append(Continuous(f"f{i}", 1))
    parents = {}
    for i, f in enumerate(features):
        ps = [f"initial.f{i}", f"initial.f{(i + 1) % n_features}", "action"]
        before = [g for g in features[:i] if isinstance(g, Discrete)]
        if i % 3 == 2 and before:
            ps.append(f"end.{before[-1].name}")
        parents[f"end.{f.name}"] = tuple(ps)
    return EffectNetwork(tuple(features), ACTIONS, parents=parents)


def pgmpy_search(net: EffectNetwork, rows: dict, max_parents: int, kind: str):
    """pgmpy's HillClimbSearch under the same constraints; returns the learned edges."""
    from pgmpy.causal_discovery import ExpertKnowledge, HillClimbSearch

    frame = {}
    for s in net.sites:
        value = np.asarray(rows[s.name])
        frame[s.name] = value[:, 0] if value.ndim == 2 else value
    frame = pd.DataFrame(frame)
    for s in net.sites:
        if s.discrete:
            frame[s.name] = pd.Categorical(frame[s.name].astype(str))
    roots = [s.name for s in net.sites if s.role != "end"]
    sinks = [s.name for s in net.sites if s.role == "end" and not s.discrete]
    names = [s.name for s in net.sites]
    forbidden = {(a, b) for b in roots for a in names if a != b}
    forbidden |= {(a, b) for a in sinks for b in names if a != b}
    climb = HillClimbSearch(
        scoring_method="bic-d" if kind == "discrete" else "bic-cg",
        max_indegree=max_parents,
        expert_knowledge=ExpertKnowledge(forbidden_edges=forbidden),
        return_type="dag",
        show_progress=False,
    )
    return set(climb.fit(frame).causal_graph_.edges())


def edges(net: EffectNetwork) -> set[tuple[str, str]]:
    out = set()
    for s in net.sites:
        if s.role == "end":
            cpd = net.cpd(s.name)
            out |= {(q, s.name) for q in (*cpd.parents, *cpd.inputs)}
    return out


def main(argv: list[str] | None = None) -> dict[str, dict[str, float]]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--features", type=int, default=10)
    parser.add_argument("--rows", type=int, default=5000)
    parser.add_argument("--worlds", nargs="+", default=["discrete", "mixed"])
    parser.add_argument("--max-parents", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--no-pgmpy", action="store_true", help="time learn_structure only")
    add_out(parser)
    args = parser.parse_args(argv)
    print_also_to(args.out, __file__)
    logging.getLogger("pgmpy").setLevel(logging.ERROR)
    threads = torch.get_num_threads()
    torch.set_num_threads(args.threads)
    try:
        print(machine())
        print(
            f"{args.features} features, {args.rows} rows, max {args.max_parents} parents; "
            f"median of {args.repeats}; goal: learn_structure under {GOAL_S:g} s"
        )
        out = {}
        for kind in args.worlds:
            true = world(kind, args.features, args.seed)
            rows = simulate(true, random_params(true, args.seed), args.rows, seed=args.seed)
            feats, acts = true.features, true.actions

            def ours(rows=rows, feats=feats, acts=acts):
                return learn_structure(rows, feats, acts, max_parents=args.max_parents)

            ours_s = median_seconds(ours, args.repeats)
            found = edges(ours())
            truth = edges(true)
            line = (
                f"{kind:9s} learn_structure {ours_s:7.2f} s (goal {GOAL_S:g} s), "
                f"{len(found & truth)}/{len(truth)} true edges, {len(found - truth)} others"
            )
            out[kind] = {"learn_structure": ours_s}
            if not args.no_pgmpy:

                def theirs(true=true, rows=rows, kind=kind):
                    return pgmpy_search(true, rows, args.max_parents, kind)

                theirs_s = median_seconds(theirs, args.repeats)
                found = theirs()
                line += (
                    f"; pgmpy HillClimbSearch {theirs_s:7.2f} s, {len(found & truth)}/"
                    f"{len(truth)} true edges, {len(found - truth)} others"
                )
                out[kind]["pgmpy"] = theirs_s
            print(line)
        return out
    finally:
        torch.set_num_threads(threads)


if __name__ == "__main__":
    main()
