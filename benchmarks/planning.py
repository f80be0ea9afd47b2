"""Planning speed on the can network: its joint transitions from compiled tables, and an
exact plan over its states.

Network: the can network (:func:`models.can_pyramid.can_network`, paper Fig. 2) over
the physically possible configurations (:func:`sim2d.configurations.stable_configurations`,
107 with the default constants; cached after the first run), 195 fields; its tables
fitted, as :func:`experiments.cans.fit_can_network` fits them, on 74,000 synthetic rows
(a throw leaves the configuration standing, or knocks it down to a random stable subset
of itself). Its state is ``(config, count)``; the states that occur are the 107
configurations each with its own count (``states=``), the next state conditioned on
being one of them (``normalise=True``). Run::

    .venv/bin/python benchmarks/planning.py [--repeats 5] [--threads 1]

Figures, each beside its goal and its peer:

* ``compile(net, params).transitions(states=...)``: the ``(107, 195, 107)`` tensor from
  the compiled tables, warm (tables kept), and cold (the model traced first). Goal: under
  1 s. Peer: the same tensor written by hand from the two fitted tables (a gather and a
  product: the floor), checked equal.
* ``plan_on(model, start, goal, 6)``: the exact plan over 107 states and 195 actions,
  horizon 6, from the full pyramid to a goal configuration, on one core. Goal: under
  1 s. Peer: :func:`inference.sequences.dynamic_programming.exact_plan` alone on the raw tensor (the
  dynamic programme without labels, start or path), checked equal.
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np
import torch
from effect_networks.inference import fit
from effect_networks.inference.sequences.dynamic_programming import exact_plan
from effect_networks.inference.sequences.planner import plan_on
from effect_networks.models.can_pyramid import can_network, can_rows, n_cans
from effect_networks.sim2d.configurations import stable_configurations
from timing import (  # benchmarks/timing.py, beside this script
    add_out,
    median_seconds,
    print_also_to,
)

from effect_networks import inference

GOAL_S = 1.0


def can_model(n_rows: int, seed: int):
    """The can network over the stable configurations, fitted on synthetic throws."""
    masks = np.array(stable_configurations(), dtype=np.int64)
    net = can_network(masks.tolist())
    rng = np.random.default_rng(seed)
    start = rng.choice(masks, n_rows)
    field = rng.integers(0, 195, n_rows)
    subsets = [masks[(masks & m) == masks] for m in masks.tolist()]  # stable subsets
    by_mask = {int(m): s for m, s in zip(masks.tolist(), subsets, strict=True)}
    knocked = np.array([rng.choice(by_mask[int(m)]) for m in start])
    end = np.where(rng.random(n_rows) < 0.4, start, knocked)
    params = fit(net, can_rows(net, start, field, end)).params
    states = [(int(m), int(c)) for m, c in zip(masks, n_cans(masks), strict=True)]
    return net, params, states


def by_hand(net, params, states) -> torch.Tensor:
    """``P(config', count' | config, count, field)`` from the two end tables, restricted
    to the states and renormalised: the floor."""
    config = torch.tensor([net.feature("config").states.index(c) for c, _ in states])
    count = torch.tensor([k for _, k in states])
    pc = params["end.config"].probs[config, count]  # (S, A, configs)
    pk = params["end.count"].probs[config, count]  # (S, A, counts)
    t = pc[:, :, config] * pk[:, :, count]
    return t / t.sum(-1, keepdim=True)


def main(args: argparse.Namespace) -> dict[str, float]:
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    net, params, states = can_model(74_000, 0)
    setup_s = time.perf_counter() - t0
    s, a = len(states), len(net.actions)
    print(f"can network: {s} states (config, count), {a} fields; set-up {setup_s:.2f} s")
    print(f"{platform.processor() or platform.machine()}, torch threads {args.threads}")

    t0 = time.perf_counter()
    compiled = inference.compile(net, params)
    model = compiled.transitions(states=states, normalise=True)
    cold_s = time.perf_counter() - t0
    warm_s = median_seconds(
        lambda: compiled.transitions(states=states, normalise=True), args.repeats
    )
    floor = by_hand(net, params, states)
    hand_s = median_seconds(lambda: by_hand(net, params, states), args.repeats)
    diff = float((model.probs - floor).abs().max())
    print(
        f"transitions ({s}, {a}, {s}) from compiled tables: warm {warm_s:.3f} s, cold "
        f"{cold_s:.3f} s (goal < {GOAL_S:.0f} s: {'met' if warm_s < GOAL_S else 'MISSED'}); "
        f"by hand from the tables {hand_s:.3f} s; max diff {diff:.1e}"
    )

    full = max(m for m, _ in states)
    target = next(m for m, _ in states if bin(m).count("1") == 7 and m & full == m)
    start = (full, n_cans(np.array([full]))[0].item())
    goal = {"config": target}
    plan_s = median_seconds(lambda: plan_on(model, start, goal, 6), args.repeats)
    result = plan_on(model, start, goal, 6)
    goal_index = model.space.index_of((target, bin(target).count("1")))
    dp_s = median_seconds(lambda: exact_plan(model.probs, goal_index, 6), args.repeats)
    raw = exact_plan(model.probs, goal_index, 6)
    same = bool(torch.equal(raw.value, result.value))
    print(
        f"plan over {s} states, {a} actions, horizon 6: {plan_s:.3f} s (goal < "
        f"{GOAL_S:.0f} s: {'met' if plan_s < GOAL_S else 'MISSED'}); exact_plan on the raw "
        f"tensor {dp_s:.3f} s; same values: {same}; success {result.success:.3f}, "
        f"path of {len(result.path) // 2} actions"
    )
    return {
        "transitions_warm_s": warm_s,
        "transitions_cold_s": cold_s,
        "transitions_by_hand_s": hand_s,
        "plan_s": plan_s,
        "exact_plan_s": dp_s,
    }


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=5, help="timed calls (median)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    add_out(parser)
    return parser.parse_args(argv)


if __name__ == "__main__":
    args = parse_args()
    print_also_to(args.out, __file__)
    main(args)
