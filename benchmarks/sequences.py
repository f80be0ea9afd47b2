"""Sequence questions by structure: the factored step and the planners, against the dense ones.

Worlds (:mod:`experiments.switch_worlds`): ``k`` binary switches, actions ``flip_i`` and
``wait``, each end feature reading its own initial value, the action and at most one
neighbour; a flip succeeds 9 times in 10, a neighbour flips 1 time in 20. World S
(sparse: pairs of neighbours, goal on 3 features, horizon 6); world C (coupled: a chain
of neighbours and every action disturbing 3 features, goal on 8 features, horizon 10).
Run::

    .venv/bin/python benchmarks/sequences.py [--repeats 3] [--threads 1] [--quick]

Figures, each beside its goal and beside today's dense route (``route="dense"``) measured
in the same run where that runs:

* ``step_model`` (the factored transitions) at k = 64: time and the bytes of its tables.
  Goal: under 0.1 s and 100 MB. At k = 10, beside today's dense ``transitions`` (time,
  size, and the largest difference from the factors' dense product).
* World S, ``plan``: the factored route against the dense planner at k = 8 and 10 (equal
  success to 1e-12, the speed-up; goal 1,000x at k = 10), and alone at k = 20 and 64
  (goal under 1 s), the process's peak memory after them (goal under 1 GB).
* World C, ``plan``: equal to the dense planner at k = 8 and 10; at k = 12 and 14 the
  exact factored plan beside the approximate route forced with ``budget=256`` (goal: its
  certified lower bound within 2 points of the exact optimum); at k = 16 and 32 the
  default route (approximate beyond ``budget``), time (goal under 10 s) and its
  certificate; at k = 16 beside the exact optimum computed with ``budget=2**16``.
"""

from __future__ import annotations

import argparse
import platform
import resource
import time

import torch
from effect_networks.experiments.switch_worlds import switch_world
from effect_networks.inference import plan, step_model, transitions
from timing import add_out, median_seconds, print_also_to  # benchmarks/timing.py


def _mark(ok: bool) -> str:
    return "met" if ok else "MISSED"


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def transitions_at_64(repeats: int) -> dict[str, float]:
    world = switch_world(64, "sparse")
    seconds = median_seconds(lambda: step_model(world.net, world.params), repeats)
    model = step_model(world.net, world.params)
    megabytes = sum(f.log_table.numel() * 8 for f in model.factors) / 1e6
    print(
        f"step_model, k = 64: {seconds * 1e3:.1f} ms, tables {megabytes:.2f} MB "
        f"(goal < 100 ms and < 100 MB: {_mark(seconds < 0.1 and megabytes < 100)}); the "
        f"dense tensor would hold {2**64 * 65 * 2**64:.2e} numbers"
    )
    small = switch_world(10, "sparse")  # where today's dense transitions still run
    factored_s = median_seconds(lambda: step_model(small.net, small.params), repeats)
    t0 = time.perf_counter()
    dense = transitions(small.net, small.params)
    dense_s = time.perf_counter() - t0
    diff = float((step_model(small.net, small.params).dense() - dense.probs).abs().max())
    print(
        f"  at k = 10 beside today's transitions: step_model {factored_s * 1e3:.1f} ms, "
        f"transitions {dense_s:.2f} s ({dense.probs.numel() * 8 / 1e6:.0f} MB); the factors' "
        f"dense product differs from it by {diff:.1e}"
    )
    return {"step_model_s": seconds, "step_model_mb": megabytes, "transitions_10_s": dense_s}


def sparse_world(repeats: int, quick: bool) -> dict[str, float]:
    out, fast = {}, {}
    for k in (8, 10, 20, 64):  # the factored route first: the peak memory is its own
        w = switch_world(k, "sparse")
        ask = lambda w=w: plan(w.net, w.params, w.start, w.goal, 6, route="factored")  # noqa: E731
        out[f"S{k}_factored_s"] = median_seconds(ask, repeats)
        fast[k] = ask()
        if k >= 20:
            print(
                f"world S, k = {k}, plan horizon 6: factored {out[f'S{k}_factored_s'] * 1e3:.1f} "
                f"ms, success {fast[k].success:.6f}, policy on {len(fast[k].features)} features "
                f"(goal < 1 s: {_mark(out[f'S{k}_factored_s'] < 1)})"
            )
    peak = _peak_mb()
    out["peak_mb"] = peak
    print(
        f"peak memory of the process after them: {peak:.0f} MB (goal < 1 GB: {_mark(peak < 1024)})"
    )
    for k in (8,) if quick else (8, 10):
        w = switch_world(k, "sparse")
        t0 = time.perf_counter()
        slow = plan(w.net, w.params, w.start, w.goal, 6, route="dense")
        dense_s = time.perf_counter() - t0
        factored_s = out[f"S{k}_factored_s"]
        diff = abs(fast[k].success - slow.success)
        ratio = dense_s / factored_s
        out[f"S{k}_dense_s"] = dense_s
        line = (
            f"world S, k = {k}, plan horizon 6: factored {factored_s * 1e3:.1f} ms, dense "
            f"(today's planner) {dense_s:.2f} s: {ratio:,.0f}x faster; success "
            f"{fast[k].success:.6f} vs {slow.success:.6f} (|diff| {diff:.1e})"
        )
        if k == 10:
            line += f" (goal 1,000x and 1e-12: {_mark(ratio >= 1000 and diff <= 1e-12)})"
        print(line)
    return out


def coupled_world(quick: bool) -> dict[str, float]:
    out = {}
    for k in (8, 10, 12, 14, 16, 32):
        if quick and k in (14, 32):
            continue
        w = switch_world(k, "coupled")
        ask = lambda w=w, **kw: plan(w.net, w.params, w.start, w.goal, 10, **kw)  # noqa: E731
        if k <= 10:
            t0 = time.perf_counter()
            fast = ask(route="factored")
            factored_s = time.perf_counter() - t0
            t0 = time.perf_counter()
            slow = ask(route="dense")
            dense_s = time.perf_counter() - t0
            diff = abs(fast.success - slow.success)
            print(
                f"world C, k = {k}, horizon 10: {fast.route} {factored_s:.2f} s, dense "
                f"{dense_s:.2f} s, success {fast.success:.6f} vs {slow.success:.6f} (|diff| "
                f"{diff:.1e}; goal equal: {_mark(diff <= 1e-12)})"
            )
        elif k <= 14:
            t0 = time.perf_counter()
            exact = ask(route="factored")
            exact_s = time.perf_counter() - t0
            t0 = time.perf_counter()
            rough = ask(budget=256)
            rough_s = time.perf_counter() - t0
            gap = exact.success - rough.success
            c = rough.certificate
            print(
                f"world C, k = {k}: exact ({exact.route}) {exact.success:.4f} in {exact_s:.2f} s; "
                f"approximate (budget 256, policy on {len(rough.features)} features) certified "
                f">= {c.lower:.4f} (estimate {c.estimate:.4f}, {c.episodes} runs, seed {c.seed}) "
                f"in {rough_s:.2f} s: {100 * gap:.2f} points below (goal <= 2: {_mark(gap <= 0.02)})"
            )
            out[f"C{k}_gap"] = gap
        else:
            t0 = time.perf_counter()
            got = ask()
            seconds = time.perf_counter() - t0
            c = got.certificate
            said = (
                f"certified >= {c.lower:.4f} (estimate {c.estimate:.4f}, the reduced model's "
                f"own {c.projected:.4f}, {c.episodes} runs, seed {c.seed})"
                if c
                else f"exact {got.success:.4f}"
            )
            print(
                f"world C, k = {k}: {got.route} on {len(got.features)} features, {said}, "
                f"{seconds:.2f} s (goal < 10 s: {_mark(seconds < 10)})"
            )
            out[f"C{k}_s"] = seconds
            if k == 16 and not quick:  # the exact optimum still fits a larger budget here
                t0 = time.perf_counter()
                exact = ask(budget=1 << 16)
                gap = exact.success - got.success
                print(
                    f"  beside the exact optimum ({exact.route}, budget 2^16) {exact.success:.4f} in "
                    f"{time.perf_counter() - t0:.2f} s: {100 * gap:.2f} points below "
                    f"(goal <= 2: {_mark(gap <= 0.02)})"
                )
    return out


def main(args: argparse.Namespace) -> dict[str, float]:
    torch.set_num_threads(args.threads)
    print(f"{platform.processor() or platform.machine()}, torch threads {args.threads}")
    out = sparse_world(args.repeats, args.quick)  # first: its peak memory is the factored route's
    out |= transitions_at_64(args.repeats)
    out |= coupled_world(args.quick)
    return out


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=3, help="timed calls (median)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--quick", action="store_true", help="small sizes only (a smoke run)")
    add_out(parser)
    return parser.parse_args(argv)


if __name__ == "__main__":
    args = parse_args()
    print_also_to(args.out, __file__)
    main(args)
