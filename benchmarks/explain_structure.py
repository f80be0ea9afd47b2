"""Speed of ``explain`` by structure: only what a demonstration hides is summed.

World: ``k`` binary features ``f0 .. f{k-1}``, actions ``flip_i`` (one per feature) and
``wait``; each end feature's parents are its own initial value, the action and its right
neighbour's initial value. ``flip_i`` flips ``f_i`` 9 times in 10; ``flip_{i+1}`` drags
``f_i`` along 1 time in 20 where ``f_{i+1}`` is on; ``wait`` changes nothing. The
network is fitted on ``--rows`` rows drawn from these rules (uniform starts and actions).
Demonstrations: ``--n`` (default 100) of ``--steps`` (default 10) steps drawn from the
fitted model, read fully observed and with each discrete value hidden with probability
0.2.

Goals: fully observed at ``k = 32`` under 0.1 s; 20 % hidden at ``k = 16`` under 2 s;
equal to the dense route (every state at every time,
:func:`inference.sequences.dense_explanation.explain_dense`) at ``k <= 8`` to 1e-10.
The dense route is timed beside wherever it runs (it refuses past ``2**22`` entries a
step table: ``k = 10`` with its 11 actions). One torch thread by default (``--threads``):
the routes' time is in many small tensor operations, and on cores that other work shares
the threads of one operation wait on each other. Run::

    .venv/bin/python benchmarks/explain_structure.py [--n 100] [--steps 10] [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from functools import partial

import numpy as np
import torch
from effect_networks.inference import fit
from effect_networks.inference.sequences.demonstration import simulate_demonstrations
from effect_networks.inference.sequences.dense_explanation import explain_dense
from effect_networks.inference.sequences.explanation import explain
from effect_networks.inference.sequences.hidden_steps import MAX_STEP_TABLE
from effect_networks.models import Discrete, EffectNetwork
from timing import add_out, print_also_to  # benchmarks/timing.py, beside

GOAL_OBSERVED_S = 0.1  # fully observed, k = 32
GOAL_HIDDEN_S = 2.0  # 20 % hidden, k = 16
GOAL_EQUAL = 1e-10  # beside the dense route, k <= 8
HIDDEN = 0.2


def flip_world(k: int) -> EffectNetwork:
    """``k`` binary features, ``flip_i`` and ``wait``; parents: own, action, right neighbour."""
    features = tuple(Discrete(f"f{i}", (False, True)) for i in range(k))
    actions = tuple(f"flip_{i}" for i in range(k)) + ("wait",)
    parents = {
        f"end.f{i}": (f"initial.f{i}", "action", *((f"initial.f{i + 1}",) if i + 1 < k else ()))
        for i in range(k)
    }
    return EffectNetwork(features=features, actions=actions, parents=parents)


def flip_rows(k: int, n: int, seed: int) -> dict[str, np.ndarray]:
    """``n`` rows drawn from the world's rules: uniform starts and actions."""
    rng = np.random.default_rng(seed)
    start = rng.random((n, k)) < 0.5
    action = rng.integers(0, k + 1, n)
    end = start.copy()
    rows = np.arange(n)
    flipped = (action < k) & (rng.random(n) < 0.9)
    end[rows[flipped], action[flipped]] ^= True
    left = action - 1  # the neighbour dragged along: f_{j-1} under flip_j
    dragged = (action < k) & (left >= 0) & (rng.random(n) < 0.05)
    dragged &= start[rows, np.clip(action, 0, k - 1)]
    end[rows[dragged], left[dragged]] ^= True
    names = [f"flip_{i}" for i in range(k)] + ["wait"]
    out = {"action": np.array(names, dtype=object)[action]}
    for i in range(k):
        out[f"initial.f{i}"] = start[:, i]
        out[f"end.f{i}"] = end[:, i]
    return out


def hide(states: dict, share: float, seed: int) -> dict:
    """Each value hidden (``None``) with probability ``share``."""
    rng = np.random.default_rng(seed)
    return {
        f: np.where(rng.random(x.shape) < share, None, x).astype(object) for f, x in states.items()
    }


def demonstrations(k: int, n: int, steps: int, rows: int):
    net = flip_world(k)
    params = fit(net, flip_rows(k, rows, seed=k)).params
    states, _ = simulate_demonstrations(net, params, n, steps, seed=1)
    return net, params, states


def largest_difference(a, b) -> float:
    fields = ("probs", "state_probs", "log_likelihood")
    worst = max(float((getattr(a, f) - getattr(b, f)).abs().max()) for f in fields)
    same = torch.equal(a.implausible, b.implausible) and torch.equal(a.best, b.best)
    return worst if same else float("inf")


def seconds(fn, repeats: int) -> tuple[float, float]:
    """Median wall and CPU seconds of ``fn()`` over ``repeats`` calls, after a warm-up.

    The CPU time is this process's: on a machine shared with other work the wall time
    also counts the waits for a core.
    """
    fn()
    wall, cpu = [], []
    for _ in range(repeats):
        began, used = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - began)
        cpu.append(time.process_time() - used)
    return statistics.median(wall), statistics.median(cpu)


def measure(k: int, label: str, share: float, world, repeats: int) -> str:
    """One line: the structured route's time, beside the goal and the dense route."""
    net, params, demo = world
    wall, cpu = seconds(partial(explain, net, params, demo), repeats)
    goal = {
        (32, 0.0): f" (goal {GOAL_OBSERVED_S} s)",
        (16, HIDDEN): f" (goal {GOAL_HIDDEN_S:.0f} s)",
    }
    line = (
        f"k = {k:2d}, {label:14s}: {wall:7.3f} s wall, {cpu:7.3f} s CPU{goal.get((k, share), '')}"
    )
    a = len(net.actions)
    if (2**k) ** 2 * a > MAX_STEP_TABLE:
        return line + f"; dense route refuses ({2**k} x {a} x {2**k} entries a step)"
    dense_wall, dense_cpu = seconds(partial(explain_dense, net, params, demo), repeats)
    differ = largest_difference(explain(net, params, demo), explain_dense(net, params, demo))
    return line + (
        f"; dense route {dense_wall:7.3f} s wall, {dense_cpu:7.3f} s CPU, largest "
        f"difference {differ:.1e} (goal {GOAL_EQUAL:.0e})"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=100)
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--rows", type=int, default=20_000, help="rows the network is fitted on")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--features", type=int, nargs="+", default=[4, 8, 12, 16, 24, 32], help="values of k"
    )
    parser.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch's intra-op threads (on cores other work shares, more threads wait on "
        "each other)",
    )
    add_out(parser)
    args = parser.parse_args()
    print_also_to(args.out, __file__)
    torch.set_num_threads(args.threads)
    print(
        f"python {platform.python_version()}, {platform.machine()}, torch {torch.__version__}, "
        f"{torch.get_num_threads()} thread(s), {os.cpu_count()} cores"
    )
    print(
        f"explain by structure, flip world, {args.n} demonstrations x {args.steps} steps, "
        f"fitted on {args.rows} rows; {HIDDEN:.0%} hidden: each value hidden with that "
        "probability (up to k = 16)"
    )
    for k in args.features:
        net, params, states = demonstrations(k, args.n, args.steps, args.rows)
        print(measure(k, "fully observed", 0.0, (net, params, states), args.repeats), flush=True)
        if k <= 16:
            hidden = (net, params, hide(states, HIDDEN, seed=k))
            print(measure(k, f"{HIDDEN:.0%} hidden", HIDDEN, hidden, args.repeats), flush=True)


if __name__ == "__main__":
    main()
