"""Action-query speed on a can-sized discrete network, beside pgmpy and a raw torch gather.

Network: ``config`` (42 states, initial and end sites), ``count`` (11 states, end site
only), ``action`` (195 states); tables fitted on 74,000 random rows. Query: the posterior
over actions, and the best action, given the initial configuration and the desired end
count. Run::

    .venv/bin/python benchmarks/queries.py [--n-queries 10000] [--pgmpy-queries 200]

Goals: batched <= 1.5 us per query amortised (within 5x of the raw gather), one query
<= 50 us, fitting the 74,000-row table <= 5 ms.

Query patterns, on the can network's structure (config 42 and count 11 both
initial and end features, action 195): the initial state observed, partly observed (the
count unknown), latent (the end state only), each timed beside pgmpy's
VariableElimination on the same rows. Goal: within 2x of pgmpy per query, or faster.

Imitation check with a continuous end feature (``--imitation-rows``, default 10,000;
``--imitation-only`` skips the rest): a 1-D one-Gaussian network (the surprise in closed
form; goal: 10,000 rows under 0.5 s), and README's tap network with the force unknown (a
mixture of 8 clusters per row: the quadrature), each row's surprise deterministic.

Scaling with the number of features (``--scaling-only`` skips the rest, ``--no-scaling``
leaves it out): k = 8 ... 32 binary features, each end feature's parents its own initial
value and the action (``parents=``), the initial state latent and the end state observed;
``infer_action`` on one query and on a batch of 1,000, and the compiled tables
(``inference.compile(net, params).infer_action``) on one query, beside pgmpy's
VariableElimination on the same network and rows (its answers checked equal). Goals:
batched, at least 10x below pgmpy per query at every k; one query alone at or below
pgmpy.

Pyro's ``Predictive`` on README's tap network (``--predictive-only`` skips the rest): 100
draws of 5 rows, one model run per draw (the default) beside one vectorised run
(``parallel=True``, README's form).
"""

from __future__ import annotations

import argparse
import functools
import platform
import time

import numpy as np
import torch
from effect_networks.inference import fit, imitation_check, infer_action
from effect_networks.models import (
    Continuous,
    Discrete,
    EffectNetwork,
    Evidence,
    Parameter,
    random_params,
)
from effect_networks.models.can_pyramid import can_network
from effect_networks.models.declaration import DTYPE
from scipy import stats
from timing import (  # benchmarks/timing.py, beside this script
    add_out,
    median_seconds,
    print_also_to,
)

from effect_networks import inference

# evidence sites per pattern, and the rows timed (fewer where a query costs more)
PATTERNS = {
    "initial state observed": (("initial.config", "initial.count", "end.count"), 1.0),
    "partly observed (count unknown)": (("initial.config", "end.config", "end.count"), 0.3),
    "latent (end state only)": (("end.config", "end.count"), 0.1),
}


def network() -> EffectNetwork:
    return EffectNetwork(
        (Discrete("config", tuple(range(42))), Discrete("count", tuple(range(11)), initial=False)),
        tuple(f"field{i}" for i in range(195)),
    )


def random_rows(net: EffectNetwork, n: int, seed: int) -> Evidence:
    g = torch.Generator().manual_seed(seed)
    return net.encode_indices(
        {
            "initial.config": torch.randint(0, 42, (n,), generator=g),
            "action": torch.randint(0, 195, (n,), generator=g),
            "end.config": torch.randint(0, 42, (n,), generator=g),
            "end.count": torch.randint(0, 11, (n,), generator=g),
        }
    )


def pgmpy_network(params):
    from pgmpy.factors.discrete import TabularCPD
    from pgmpy.inference import VariableElimination

    try:
        from pgmpy.models import DiscreteBayesianNetwork as BN
    except ImportError:
        from pgmpy.models import BayesianNetwork as BN
    bn = BN(
        [
            ("config", "end_config"),
            ("action", "end_config"),
            ("config", "end_count"),
            ("action", "end_count"),
        ]
    )
    bn.add_cpds(TabularCPD("config", 42, params["initial.config"].probs.numpy().reshape(-1, 1)))
    bn.add_cpds(TabularCPD("action", 195, params["action"].probs.numpy().reshape(-1, 1)))
    for site, var, k in (("end.config", "end_config", 42), ("end.count", "end_count", 11)):
        values = params[site].probs.numpy().reshape(-1, k).T
        bn.add_cpds(
            TabularCPD(var, k, values, evidence=["config", "action"], evidence_card=[42, 195])
        )
    return VariableElimination(bn)


def patterns(args: argparse.Namespace) -> list[tuple[str, float, float, float, float, float]]:
    """Per pattern: (name, traced us/query, compiled us/query, the compiled pattern's
    one-off build in s, pgmpy us/query, max diff)."""
    from effect_networks.models.interop import to_pgmpy
    from pgmpy.inference import VariableElimination

    net = can_network(range(42))
    g = torch.Generator().manual_seed(2)
    sites = ("initial.config", "initial.count", "action", "end.config", "end.count")

    def rows(n):
        return net.encode_indices(
            {s: torch.randint(0, net.site(s).size, (n,), generator=g) for s in sites}
        )

    params = fit(net, rows(74_000)).params
    compiled = inference.compile(net, params)
    assert compiled.action_tables is not None  # built here, not in the first pattern's time
    ve = VariableElimination(to_pgmpy(net, params).model)
    queries = rows(args.pattern_rows)
    out = []
    for name, (given, share) in PATTERNS.items():
        evidence = queries.without(*[s for s in queries if s not in given])
        m = max(10, int(args.pattern_rows * share))
        ev = evidence.rows(slice(0, m))
        t0 = time.perf_counter()
        compiled.infer_action(ev.rows(slice(0, 1)))  # builds this pattern's tables once
        build_s = time.perf_counter() - t0
        traced_us = median_seconds(lambda ev=ev: infer_action(net, params, ev), 3) / m * 1e6
        compiled_us = median_seconds(lambda ev=ev: compiled.infer_action(ev), 3) / m * 1e6
        k = min(m, args.pgmpy_pattern_queries)
        labels = [{s: net.decode(s, ev[s][i : i + 1])[0] for s in given} for i in range(k)]
        t0 = time.perf_counter()
        results = [ve.query(["action"], evidence=e, show_progress=False) for e in labels]
        pgmpy_us = (time.perf_counter() - t0) / k * 1e6
        theirs = torch.tensor(np.stack([r.values for r in results]), dtype=DTYPE)
        ours = infer_action(net, params, ev.rows(slice(0, k))).probs
        fast = compiled.infer_action(ev.rows(slice(0, k))).probs
        diff = max(float((ours - theirs).abs().max()), float((fast - theirs).abs().max()))
        out.append((f"{name}, {m} rows", traced_us, compiled_us, build_s, pgmpy_us, diff))
    return out


SCALING_K = (8, 12, 16, 20, 24, 32)


def sparse_network(k: int) -> EffectNetwork:
    """``k`` binary features, each end feature's parents its own initial value and the
    action."""
    return EffectNetwork(
        tuple(Discrete(f"f{i}", (0, 1)) for i in range(k)),
        ("push", "lift", "wait"),
        parents={f"end.f{i}": (f"initial.f{i}", "action") for i in range(k)},
    )


def scaling(batch: int, pgmpy_queries: int) -> list[tuple[int, float, float, float, float, float]]:
    """Per k: (k, ours us/query batched, ours us for one query, the compiled tables' us
    for one query (``inference.compile(net, params).infer_action``, after a first call
    that builds the pattern's plan), pgmpy us/query, largest difference from pgmpy)."""
    from effect_networks.models.interop import to_pgmpy
    from pgmpy.inference import VariableElimination

    out = []
    for k in SCALING_K:
        net = sparse_network(k)
        params = random_params(net, k)
        g = torch.Generator().manual_seed(k)
        ends = {f"end.f{i}": torch.randint(0, 2, (batch,), generator=g) for i in range(k)}
        evidence = net.encode_indices(ends)
        one = evidence.rows(slice(0, 1))
        run = functools.partial(infer_action, net, params)
        batched_us = median_seconds(lambda run=run, ev=evidence: run(ev), 3) / batch
        single_us = median_seconds(lambda run=run, ev=one: run(ev), 20)
        compiled = inference.compile(net, params)
        compiled.infer_action(one)  # builds the tables and the pattern's plan
        compiled_us = median_seconds(lambda c=compiled, ev=one: c.infer_action(ev), 20)
        ve = VariableElimination(to_pgmpy(net, params).model)
        m = min(batch, pgmpy_queries)
        labels = [{s: int(v[i]) for s, v in ends.items()} for i in range(m)]
        ve.query(["action"], evidence=labels[0], show_progress=False)  # a warm-up call
        t0 = time.perf_counter()
        results = [ve.query(["action"], evidence=e, show_progress=False) for e in labels]
        pgmpy_us = (time.perf_counter() - t0) / m
        theirs = torch.tensor(np.stack([r.values for r in results]), dtype=DTYPE)
        ours = infer_action(net, params, evidence.rows(slice(0, m))).probs
        fast = compiled.infer_action(evidence.rows(slice(0, m))).probs
        diff = max(float((ours - theirs).abs().max()), float((fast - theirs).abs().max()))
        out.append((k, batched_us * 1e6, single_us * 1e6, compiled_us * 1e6, pgmpy_us * 1e6, diff))
    return out


def _print_scaling(batch: int, pgmpy_queries: int) -> dict[str, float]:
    print(
        f"\nscaling: k binary features, sparse parents (own initial value, action), initial "
        f"state latent, end state observed; infer_action, us per query; batch of {batch}, "
        f"pgmpy on {pgmpy_queries} of its rows"
    )
    print(
        f"{'k':>3}{'ours batched':>14}{'ours one':>10}{'compiled one':>14}{'pgmpy':>10}"
        f"{'pgmpy/batched':>15}{'pgmpy/one':>11}{'pgmpy/compiled':>16}{'max diff':>10}"
        "  verdict (batched >= 10x; one <= pgmpy: traced, compiled)"
    )
    figures = {}
    for k, batched, one, fast, theirs, diff in scaling(batch, pgmpy_queries):
        verdict = f"{'met' if theirs >= 10 * batched else 'missed'}; "
        verdict += f"{'met' if one <= theirs else 'missed'}, "
        verdict += "met" if fast <= theirs else "missed"
        print(
            f"{k:>3}{batched:>14.2f}{one:>10.0f}{fast:>14.0f}{theirs:>10.0f}"
            f"{theirs / batched:>14.0f}x{theirs / one:>10.2f}x{theirs / fast:>15.2f}x"
            f"{diff:>10.1e}  {verdict}"
        )
        assert diff <= 1e-12, f"k = {k}: ours and pgmpy differ by {diff:.1e}"
        figures |= {f"scaling_{k}_batched_us": batched, f"scaling_{k}_one_us": one}
        figures |= {f"scaling_{k}_compiled_one_us": fast}
        figures |= {f"scaling_{k}_pgmpy_us": theirs, f"scaling_{k}_max_diff": diff}
    return figures


def imitation(rows: int) -> dict[str, float]:
    """Seconds of ``imitation_check`` on ``rows`` rows: one Gaussian, and a mixture."""
    rng = np.random.default_rng(0)
    line = EffectNetwork((Continuous("pos", 1),), ("a", "b"))
    one = {
        "initial.pos": rng.normal(size=(rows, 1)),
        "action": ["a"] * rows,
        "end.pos": rng.normal(size=(rows, 1)),
    }
    line_params = random_params(line, 0)
    tap = _tap_network()
    mixed = {
        "initial.visible": [True] * rows,
        "initial.position": np.zeros((rows, 1)),
        "action": ["tap"] * rows,
        "end.position": rng.normal(size=(rows, 1)),
    }
    tap_params = random_params(tap, 1)
    g = line_params["end.pos"]  # action "a": the end position's one Gaussian

    def by_hand():
        # the peer: the same closed form written out in numpy and scipy, no model traced
        mean = one["initial.pos"][:, 0] * float(g.weight[0, 0, 0]) + float(g.bias[0, 0])
        z = (one["end.pos"][:, 0] - mean) / float(g.scale_tril[0, 0, 0])
        return stats.chi2.cdf(z**2, 1)

    ours = imitation_check(line, line_params, one).surprise.numpy()
    return {
        "imitation_one_gaussian_s": median_seconds(
            lambda: imitation_check(line, line_params, one), 5
        ),
        "imitation_scipy_by_hand_s": median_seconds(by_hand, 5),
        "imitation_scipy_max_difference": float(np.abs(ours - by_hand()).max()),
        "imitation_mixture_s": median_seconds(lambda: imitation_check(tap, tap_params, mixed), 1),
    }


def main(args: argparse.Namespace) -> dict[str, float]:
    torch.set_num_threads(args.threads)
    if args.imitation_only:
        return _print_imitation(args.imitation_rows)
    if args.predictive_only:
        return _print_predictive()
    if args.scaling_only:
        return _print_scaling(args.scaling_batch, args.scaling_pgmpy_queries)
    net = network()
    rows = random_rows(net, 74_000, 0)
    fit_s = median_seconds(lambda: fit(net, rows), 7)
    params = fit(net, rows).params
    compiled = inference.compile(net, params)
    assert compiled.action_tables is not None  # built here, not in the first query's time
    queries = random_rows(net, args.n_queries, 1)
    evidence = queries.without("action", "end.config")
    one = evidence.rows(slice(0, 1))

    # the raw gather: log p(a) + log p(count | config, a), normalised, argmax
    log_prior = params["action"].probs.log()
    log_table = params["end.count"].probs.log()  # (config, action, count)

    def raw(ev):
        logits = log_prior + log_table[ev["initial.config"], :, ev["end.count"]]
        probs = logits.softmax(-1)
        return probs, probs.argmax(-1)

    n = args.n_queries
    figures = {
        "fit_74000_rows_ms": fit_s * 1e3,
        "raw_gather_batched_us": median_seconds(lambda: raw(evidence), 20) / n * 1e6,
        "compiled_batched_us": median_seconds(lambda: compiled.infer_action(evidence), 20)
        / n
        * 1e6,
        "traced_batched_us": median_seconds(lambda: infer_action(net, params, evidence), 5)
        / n
        * 1e6,
        "raw_gather_single_us": median_seconds(lambda: raw(one), 200) * 1e6,
        "compiled_single_us": median_seconds(lambda: compiled.infer_action(one), 200) * 1e6,
        "traced_single_us": median_seconds(lambda: infer_action(net, params, one), 50) * 1e6,
    }
    ours = compiled.infer_action(evidence)
    ref, ref_best = raw(evidence)
    agree = float((ours.probs - ref).abs().max())
    figures["max_abs_diff_vs_raw"] = agree
    figures["best_agrees_with_raw"] = float((ours.best == ref_best).float().mean())

    try:
        ve = pgmpy_network(params)
    except ImportError:
        ve = None
    if ve is not None:
        m = args.pgmpy_queries
        cfg, cnt = queries["initial.config"][:m].tolist(), queries["end.count"][:m].tolist()
        t0 = time.perf_counter()
        results = [
            ve.query(["action"], evidence={"config": c, "end_count": e}, show_progress=False)
            for c, e in zip(cfg, cnt, strict=True)
        ]
        figures["pgmpy_query_us"] = (time.perf_counter() - t0) / m * 1e6
        mm = max(1, m // 10)
        t0 = time.perf_counter()
        best = [
            ve.map_query(["action"], evidence={"config": c, "end_count": e}, show_progress=False)
            for c, e in zip(cfg[:mm], cnt[:mm], strict=True)
        ]
        figures["pgmpy_map_query_us"] = (time.perf_counter() - t0) / mm * 1e6
        theirs = torch.tensor(np.stack([r.values for r in results]), dtype=ours.probs.dtype)
        figures["max_abs_diff_vs_pgmpy"] = float((ours.probs[:m] - theirs).abs().max())
        figures["best_agrees_with_pgmpy"] = float(
            sum(int(b["action"]) == int(o) for b, o in zip(best, ours.best[:mm], strict=True)) / mm
        )

    print(
        f"machine: {platform.machine()}, {platform.processor() or 'cpu'}, torch {torch.__version__}, threads {torch.get_num_threads()}"
    )
    print(f"network: config 42 x action 195 -> end count 11; {n} action queries\n")
    print(f"{'what':<44}{'measured':>14}{'goal':>16}")
    rows_out = [
        ("fit, 74,000 rows (ms)", figures["fit_74000_rows_ms"], 5.0),
        ("raw torch gather, batched (us/query)", figures["raw_gather_batched_us"], None),
        ("compiled, batched (us/query)", figures["compiled_batched_us"], 1.5),
        ("traced Pyro model, batched (us/query)", figures["traced_batched_us"], None),
        ("raw torch gather, one query (us)", figures["raw_gather_single_us"], None),
        ("compiled, one query (us)", figures["compiled_single_us"], 50.0),
        ("traced Pyro model, one query (us)", figures["traced_single_us"], None),
    ]
    if ve is not None:
        rows_out += [
            ("pgmpy VariableElimination.query (us)", figures["pgmpy_query_us"], None),
            ("pgmpy VariableElimination.map_query (us)", figures["pgmpy_map_query_us"], None),
        ]
    for what, value, goal in rows_out:
        print(f"{what:<44}{value:>14.3f}{_verdict(value, goal):>16}")
    ratio = figures["compiled_batched_us"] / figures["raw_gather_batched_us"]
    print(f"\ncompiled / raw gather, batched: {ratio:.2f}x")
    print(
        f"max |ours - raw gather| = {figures['max_abs_diff_vs_raw']:.2e}; best action agrees on {figures['best_agrees_with_raw']:.1%}"
    )
    if ve is not None:
        print(
            f"max |ours - pgmpy| = {figures['max_abs_diff_vs_pgmpy']:.2e}; best action agrees with map_query on {figures['best_agrees_with_pgmpy']:.1%}"
        )
    if ve is not None and args.pattern_rows:
        print(
            "\nquery patterns, can network structure (config 42, count 11, action 195), "
            "us per query; goal: within 2x of pgmpy"
        )
        print(
            "(build: the compiled pattern's tables and answers, once per pattern; break-even:"
            " the queries after which compiled, build included, has cost less than pgmpy)"
        )
        print(
            f"{'pattern':<46}{'traced':>10}{'compiled':>10}{'build s':>9}{'pgmpy':>10}"
            f"{'break-even':>11}  verdict (traced, compiled)"
        )
        for name, traced_us, compiled_us, build_s, pgmpy_us, diff in patterns(args):
            verdicts = ", ".join(_verdict(x, 2 * pgmpy_us) for x in (traced_us, compiled_us))
            gain_us = pgmpy_us - compiled_us
            even = f"{build_s * 1e6 / gain_us:>11,.0f}" if gain_us > 0 else f"{'never':>11}"
            print(
                f"{name:<46}{traced_us:>10.1f}{compiled_us:>10.1f}{build_s:>9.2f}"
                f"{pgmpy_us:>10.1f}{even}  {verdicts}"
            )
            figures[f"pattern {name}"] = diff
        diffs = [v for k, v in figures.items() if k.startswith("pattern ")]
        print(f"max |ours - pgmpy| over the patterns = {max(diffs):.2e}")
    if args.imitation_rows:
        figures |= _print_imitation(args.imitation_rows)
    figures |= _print_predictive()
    if not args.no_scaling:
        figures |= _print_scaling(args.scaling_batch, args.scaling_pgmpy_queries)
    return figures


def _tap_network() -> EffectNetwork:
    return EffectNetwork(
        (Discrete("visible", (False, True)), Continuous("position", 1)),
        ("look", "remove", "tap"),
        (Parameter("force", low=0.0, high=20.0, bins=8, actions=("tap",), affects="position"),),
    )


def _print_predictive() -> dict[str, float]:
    """Seconds of ``Predictive(effect_model, num_samples=100)`` on 5 rows, one run per
    draw and vectorised (``parallel=True``)."""
    from effect_networks.models import effect_model
    from pyro.infer import Predictive

    net = _tap_network()
    params = random_params(net, 0)
    sites = [site.name for site in net.sites]
    figures = {}
    for name, parallel in (("sequential", False), ("parallel", True)):
        run = Predictive(effect_model, num_samples=100, parallel=parallel, return_sites=sites)
        figures[f"predictive_{name}_s"] = median_seconds(
            lambda run=run: run(net, params, n_rows=5), 3
        )
    print("\nPredictive(effect_model, num_samples=100), 5 rows (s)")
    print(f"{'one model run per draw (default)':<44}{figures['predictive_sequential_s']:>14.3f}")
    print(f"{'parallel=True (README)':<44}{figures['predictive_parallel_s']:>14.3f}")
    return figures


def _print_imitation(rows: int) -> dict[str, float]:
    figures = imitation(rows)
    goal = 0.5 * rows / 10_000
    print(f"\nimitation_check, {rows} rows, a continuous end feature (s)")
    print(f"{'what':<44}{'measured':>14}{'goal':>16}")
    one, mixture = figures["imitation_one_gaussian_s"], figures["imitation_mixture_s"]
    print(f"{'one Gaussian (closed form)':<44}{one:>14.3f}{_verdict(one, goal):>16}")
    peer = figures["imitation_scipy_by_hand_s"]
    print(f"{'  peer: scipy chi2.cdf, distances by hand':<44}{peer:>14.3f}{'reference':>16}")
    print(f"  largest |ours - scipy| = {figures['imitation_scipy_max_difference']:.1e}")
    print(f"{'8-cluster mixture (quadrature)':<44}{mixture:>14.3f}{_verdict(mixture, None):>16}")
    return figures


def _verdict(value: float, goal: float | None) -> str:
    if goal is None:
        return "reference"
    return f"<= {goal:.3g}: {'met' if value <= goal else 'missed'}"


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--n-queries", type=int, default=10_000)
    parser.add_argument("--pgmpy-queries", type=int, default=200)
    parser.add_argument(
        "--pattern-rows", type=int, default=300, help="rows per query pattern (0: skip them)"
    )
    parser.add_argument("--pgmpy-pattern-queries", type=int, default=10)
    parser.add_argument(
        "--threads", type=int, default=1, help="torch threads (1: per-core figures)"
    )
    parser.add_argument(
        "--imitation-rows", type=int, default=10_000, help="imitation_check rows (0: skip)"
    )
    parser.add_argument("--imitation-only", action="store_true", help="time imitation_check alone")
    parser.add_argument("--predictive-only", action="store_true", help="time Predictive alone")
    parser.add_argument("--scaling-only", action="store_true", help="the scaling table alone")
    parser.add_argument("--no-scaling", action="store_true", help="leave the scaling table out")
    parser.add_argument("--scaling-batch", type=int, default=1000, help="rows of the batch")
    parser.add_argument(
        "--scaling-pgmpy-queries", type=int, default=50, help="pgmpy queries timed per k"
    )
    add_out(parser)
    return parser.parse_args(argv)


if __name__ == "__main__":
    args = parse_args()
    print_also_to(args.out, __file__)
    main(args)
