"""Speed of the throw network: fitting on 29,000 throws, and the parameter posterior.

    python benchmarks/throw.py                  # 16 x 16 clusters (the example's choice)
    python benchmarks/throw.py --bins 12 --threads 2 --profile

Times :func:`inference.fit` on the training rows, and the parameter posterior (hit -> target:
cluster posterior by enumeration, best cluster, Gaussian conditioning) batched over the
test hits and one hit at a time, both through the traced Pyro model
(:func:`inference.infer_parameter`) and through its compiled tables
(:func:`inference.compile`, the same numbers, tested equal). Each
figure is the median over ``--repeats`` runs of ``time.perf_counter`` after one warm-up.
Goals: fit under 50 ms; the batched posterior at most 5 us per
query; one query at most 100 us. ``--profile`` prints where a query's time goes, stage by stage.
Also timed, without a goal: the inverse model (:func:`inference.parameter_for_effect`),
batched over ``--effect-rows`` hits, on the grid clusters and on the same clusters made
adaptive (5 EM steps), the latter beside the model scoring every cluster's candidate.
"""

from __future__ import annotations

import argparse
import cProfile
import os
import platform
import pstats
from unittest import mock

import numpy as np
import pyro
import torch
from effect_networks.experiments.adaptive_throw.run import adaptive_throw_network
from effect_networks.inference import fit, fit_em, infer_parameter, parameter_for_effect
from effect_networks.models.humanoid_throw import TARGET, throw_data, throw_network
from effect_networks.sim2d.analytic_throw import sample_targets, throw
from timing import (  # benchmarks/timing.py, beside this script
    add_out,
    median_seconds,
    print_also_to,
)

from effect_networks import inference

GOALS_S = {"fit": 50e-3, "batched": 5e-6, "single": 100e-6}


def machine() -> str:
    load = os.getloadavg() if hasattr(os, "getloadavg") else ("?",)
    return (
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"load average {load[0]:.2f}; Python {platform.python_version()}, torch "
        f"{torch.__version__} ({torch.get_num_threads()} threads), pyro {pyro.__version__}"
    )


def measure(net, data, hits, repeats: int, singles: int) -> dict[str, float]:
    """Seconds: one fit, one batched query per row, one single query."""
    params = fit(net, data).params
    fit_s = median_seconds(lambda: fit(net, data), repeats)
    batched_s = median_seconds(
        lambda: infer_parameter(net, params, TARGET, {"end.hit": hits}), repeats
    )
    one = [{"end.hit": hits[i : i + 1]} for i in range(min(singles, len(hits)))]

    def single_queries():
        for evidence in one:
            infer_parameter(net, params, TARGET, evidence)

    single_s = median_seconds(single_queries, repeats) / len(one)
    return {"fit": fit_s, "batched": batched_s / len(hits), "single": single_s}


def measure_compiled(net, data, hits, repeats: int, singles: int) -> dict[str, float]:
    """Seconds for the compiled query: build it once (as "fit"), then query it."""
    params = fit(net, data).params
    compile_s = median_seconds(
        lambda: inference.compile(net, params).parameter_query(TARGET), repeats
    )
    compiled = inference.compile(net, params)
    batched_s = median_seconds(lambda: compiled.infer_parameter(TARGET, {"end.hit": hits}), repeats)
    one = [{"end.hit": hits[i : i + 1]} for i in range(min(singles, len(hits)))]

    def single_queries():
        for evidence in one:
            compiled.infer_parameter(TARGET, evidence)

    single_s = median_seconds(single_queries, repeats) / len(one)
    return {"compile": compile_s, "batched": batched_s / len(hits), "single": single_s}


def measure_effect_adaptive(net, targets, hits, rows, repeats: int) -> dict[str, float]:
    """Seconds per hit of the inverse model on the same clusters made adaptive (5 EM
    steps), scored in closed form, beside the model scoring every candidate (the peer:
    what the query did before the closed form, and still does where it does not apply)."""
    adaptive = adaptive_throw_network(net.parameters[0].bins)
    params = fit_em(adaptive, throw_data(adaptive, targets, hits), steps=5).params
    n = len(rows["end.hit"])
    seconds = median_seconds(lambda: parameter_for_effect(adaptive, params, TARGET, rows), repeats)
    with mock.patch(
        "effect_networks.inference.queries.inverse._candidate_scores", return_value=None
    ):
        peer = median_seconds(lambda: parameter_for_effect(adaptive, params, TARGET, rows), 1)
    print(
        f"inverse model on the same clusters made adaptive (5 EM steps), per query: "
        f"{1e3 * seconds / n:.2f} ms; the model scoring every candidate (peer): "
        f"{1e3 * peer / n:.2f} ms ({peer / seconds:.1f}x)"
    )
    return {"effect_adaptive": seconds / n, "effect_adaptive_peer": peer / n}


#: Stages of one parameter posterior query, as (file suffix, function) in the profile.
STAGES = (
    ("inference/queries/parameter.py", "infer_parameter", "the whole query"),
    ("models/params.py", "check_params", "checking the parameters' shapes"),
    ("models/declaration.py", "encode", "validating and encoding the evidence"),
    ("inference/exact/enumeration.py", "enumerate_model", "tracing the model, summing log-probs"),
    ("models/model.py", "effect_model", "  running the Pyro model under trace+enum"),
    ("torch/distributions/distribution.py", "__init__", "  building distributions (+checks)"),
    ("pyro/poutine/trace_struct.py", "compute_log_prob", "  log-probabilities"),
    ("inference/exact/enumeration.py", "marginal", "cluster posterior from the log-weights"),
    ("models/cpds/mixture.py", "posterior", "Gaussian conditioning, best cluster"),
)


def profile_queries(net, data, hits, batch: int, n: int) -> str:
    """Where the time goes: cumulative time per stage of ``n`` queries of ``batch`` rows."""
    params = fit(net, data).params
    rows = [{"end.hit": hits[(i * batch) % len(hits) :][:batch]} for i in range(n)]
    profiler = cProfile.Profile()
    profiler.enable()
    for evidence in rows:
        infer_parameter(net, params, TARGET, evidence)
    profiler.disable()
    stats = pstats.Stats(profiler).stats  # (file, line, function) -> (cc, nc, tt, ct, callers)
    lines = [f"profile of {n} calls of {batch} row(s) (cProfile adds overhead), us per row:"]
    for suffix, function, label in STAGES:
        cumulative = sum(
            ct
            for (file, _, name), (_, _, _, ct, _) in stats.items()
            if name == function and file.endswith(suffix)
        )
        lines.append(f"  {label:44s} {1e6 * cumulative / (n * batch):8.1f}")
    return "\n".join(lines)


def report(label: str, seconds: dict[str, float]) -> None:
    print(label)
    for key, unit, scale, what in (
        ("fit", "ms", 1e3, "fit, all training rows"),
        ("batched", "us", 1e6, "parameter posterior, batched, per query"),
        ("single", "us", 1e6, "parameter posterior, one at a time"),
    ):
        ok = "met" if seconds[key] <= GOALS_S[key] else "missed"
        print(
            f"  {what:36s} {scale * seconds[key]:10.1f} {unit}   goal <= "
            f"{scale * GOALS_S[key]:g} {unit}: {ok}"
        )


def main(argv: list[str] | None = None) -> dict[str, float]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n-train", type=int, default=29_000)
    parser.add_argument("--n-test", type=int, default=1_000)
    parser.add_argument("--bins", type=int, default=16, help="clusters per axis")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--singles", type=int, default=200, help="single queries per repeat")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument(
        "--also-without-validation",
        action="store_true",
        help="repeat with Pyro's argument checks off, to show what they cost",
    )
    parser.add_argument("--profile", action="store_true", help="profile the queries")
    parser.add_argument(
        "--effect-rows", type=int, default=200, help="hits per parameter_for_effect timing"
    )
    add_out(parser)
    args = parser.parse_args(argv)
    print_also_to(args.out, __file__)

    threads = torch.get_num_threads()
    torch.set_num_threads(args.threads)
    try:
        rng = np.random.default_rng(args.seed)
        targets = sample_targets(args.n_train + args.n_test, rng)
        hits = throw(targets).hit
        net = throw_network((args.bins, args.bins))
        data = throw_data(net, targets[: args.n_train], hits[: args.n_train])
        test = torch.as_tensor(hits[args.n_train :])
        print(machine())
        print(
            f"{args.n_train} training rows, {args.n_test} test hits, "
            f"{args.bins} x {args.bins} clusters; median of {args.repeats}"
        )
        seconds = measure(net, data, test, args.repeats, args.singles)
        report("traced Pyro model (inference.infer_parameter):", seconds)
        compiled = measure_compiled(net, data, test, args.repeats, args.singles)
        print(
            f"compiled query (inference.compile(net, params).infer_parameter), built in {1e3 * compiled['compile']:.1f} ms:"
        )
        for key, what in (
            ("batched", "parameter posterior, batched, per query"),
            ("single", "parameter posterior, one at a time"),
        ):
            ok = "met" if compiled[key] <= GOALS_S[key] else "missed"
            print(
                f"  {what:36s} {1e6 * compiled[key]:10.1f} us   goal <= {1e6 * GOALS_S[key]:g} us: {ok}"
            )
        seconds |= {f"compiled_{k}": v for k, v in compiled.items()}
        params = fit(net, data).params
        rows = {"end.hit": test[: args.effect_rows]}
        effect_s = median_seconds(
            lambda: parameter_for_effect(net, params, TARGET, rows), min(args.repeats, 3)
        ) / len(rows["end.hit"])
        print(
            f"inverse model (inference.parameter_for_effect), batched over {len(rows['end.hit'])} "
            f"hits, per query: {1e3 * effect_s:.2f} ms (no goal; infer_parameter above is the "
            "paper's query)"
        )
        seconds["effect_batched"] = effect_s
        train = (targets[: args.n_train], hits[: args.n_train])
        seconds |= measure_effect_adaptive(net, *train, rows, min(args.repeats, 3))
        if args.also_without_validation:
            with pyro.validation_enabled(False):
                report(
                    "the same with Pyro's argument checks off (pyro.validation_enabled(False)):",
                    measure(net, data, test, args.repeats, args.singles),
                )
        if args.profile:
            print(profile_queries(net, data, test, len(test), 5))
            print(profile_queries(net, data, test, 1, 300))
        return seconds
    finally:
        torch.set_num_threads(threads)


if __name__ == "__main__":
    main()
