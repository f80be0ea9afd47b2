"""Learning from watching: demonstrations with a tenth of their steps labelled, beside the
fit on the same demonstrations fully labelled.

Worlds (:mod:`experiments.switch_worlds`, sparse): 4 and 6 switches, actions ``flip_i``
and ``wait``; 200 demonstrations of 5 steps drawn from the true tables
(:func:`inference.sequences.demonstration.simulate_demonstrations`), every state shown,
10 % of the steps labelled at random. Run::

    .venv/bin/python benchmarks/watching.py [--out DIR]

Figures, each beside its goal:

* per table, the total variation between the learned table and the labelled fit's, per
  parent configuration: the mean weighted by the configurations' counts in the data
  (goal <= 0.05) and the largest (configurations the data barely reach);
* the plan for the world's goal (3 switches on, horizon 5) made on each fit, both
  policies evaluated exactly under the true tables (goal: within 2 points);
* one EM step on 1,000 demonstrations of 10 steps at 16 switches (goal < 5 s);
* the 4-switch world again with a fifth of the state values hidden (after the first
  state), fitted exactly by forward-backward over each time's hidden configurations,
  beside the fit on the same demonstrations fully shown and labelled;
* beside each total variation, the bound the ambiguous steps leave (a failed flip looks
  like ``wait``): the *oracle*, the M-step on the true tables' posterior over each
  unlabelled step's action (what a watcher who knew the true network would count), and
  EM run to its fixed point from the true tables, with its log-likelihood beside the
  learned fit's. Where the oracle is as far from the labelled fit as the learned one, and
  EM from the truth settles no higher in likelihood, the distance is the likelihood's own
  (the demonstrations do not say which steps were failed flips), not EM's start.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from effect_networks.experiments.switch_worlds import switch_world
from effect_networks.inference import plan, transitions
from effect_networks.inference.sequences.demonstration import simulate_demonstrations
from effect_networks.inference.sequences.dynamic_programming import policy_value
from effect_networks.inference.watching import fit_demonstrations
from effect_networks.models import random_params
from timing import add_out, print_also_to  # benchmarks/timing.py


def _mark(ok: bool) -> str:
    return "met" if ok else "MISSED"


def _true_success(world, route, truth) -> float:
    """The plan's policy, read on every full state, evaluated under the true tables."""
    space = truth.space
    rows = route.policy.shape[0] - 1
    policy = torch.stack(
        [
            torch.tensor(
                [int(route.policy[min(h, rows), route.space.index_of(s)]) for s in space.states]
            )
            for h in range(route.horizon + 1)
        ]
    )
    value = policy_value(truth.probs, policy, space.mask(world.goal), route.horizon)
    return float(value[route.horizon, space.index_of(world.start)])


def tables_and_plans(k: int, seed: int, hidden: float = 0.0) -> dict[str, float]:
    world = switch_world(k, "sparse")
    states, actions = simulate_demonstrations(world.net, world.params, 200, 5, seed=seed)
    rng = np.random.default_rng(seed)
    labels = np.where(rng.random(actions.shape) < 0.1, actions, None)
    t0 = time.perf_counter()
    full = fit_demonstrations(world.net, states, actions).params
    t1 = time.perf_counter()
    shown = states
    if hidden:  # a share of the state values after the first state hidden
        shown = {}
        for name, values in states.items():
            mask = rng.random(values.shape) < hidden
            mask[:, 0] = False
            shown[name] = np.where(mask, None, values)
    got = fit_demonstrations(world.net, shown, labels)
    t2 = time.perf_counter()
    worst_mean, worst_site, worst_max = _farthest(got.params, full)
    # the bound: the true posterior's counts, and EM's fixed point from the true tables
    oracle = fit_demonstrations(world.net, shown, labels, init=world.params, steps=1, tol=1e-300)
    from_truth = fit_demonstrations(world.net, shown, labels, init=world.params)
    oracle_tv, oracle_site, _ = _farthest(oracle.params, full)
    truth_tv, truth_site, _ = _farthest(from_truth.params, full)
    gain = from_truth.log_likelihoods[-1] - got.log_likelihoods[-1]
    print(
        f"{k} switches, 200 x 5 steps, {got.labelled} of {got.steps} labelled, "
        f"{100 * hidden:.0f} % of the state values hidden: fit "
        f"{t2 - t1:.2f} s (fully labelled {t1 - t0:.2f} s), {len(got.log_likelihoods) - 1} EM "
        f"steps; recognises {100 * got.agreement:.1f} % of the labelled steps "
        f"(mean posterior {got.confidence:.3f})"
    )
    print(
        f"  largest count-weighted total variation from the labelled fit: {worst_mean:.4f} "
        f"({worst_site}; goal <= 0.05: {_mark(worst_mean <= 0.05)}); largest at one "
        f"configuration {worst_max:.4f}"
    )
    print(
        f"  the bound the ambiguous steps leave: the true posterior's counts (oracle) "
        f"{oracle_tv:.4f} ({oracle_site}); EM from the true tables {truth_tv:.4f} "
        f"({truth_site}), its log-likelihood {gain:+.2f} nats beside the learned fit's"
    )
    truth = transitions(world.net, world.params)
    ours = _true_success(world, plan(world.net, got.params, world.start, world.goal, 5), truth)
    theirs = _true_success(world, plan(world.net, full, world.start, world.goal, 5), truth)
    gap = theirs - ours
    print(
        f"  plan (goal {world.goal}, horizon 5) under the true tables: learned "
        f"{100 * ours:.2f} %, labelled {100 * theirs:.2f} % ({100 * gap:.2f} points; goal "
        f"<= 2: {_mark(gap <= 0.02)})"
    )
    return {
        f"tv_{k}_{hidden}": worst_mean,
        f"plan_gap_{k}_{hidden}": gap,
        f"oracle_tv_{k}_{hidden}": oracle_tv,
        f"from_truth_tv_{k}_{hidden}": truth_tv,
        f"from_truth_gain_{k}_{hidden}": gain,
    }


def _farthest(params, full) -> tuple[float, str, float]:
    """The table farthest from ``full`` by count-weighted total variation, and the largest
    total variation at one parent configuration."""
    worst_mean, worst_max, worst_site = 0.0, 0.0, ""
    for site in full.cpds:
        d = (params[site].probs - full[site].probs).abs().sum(-1) / 2
        n = full[site].n
        mean = float((d * n).sum() / n.sum())
        if mean > worst_mean:
            worst_mean, worst_site = mean, site
        worst_max = max(worst_max, float(d.max()))
    return worst_mean, worst_site, worst_max


def one_em_step(k: int = 16, n: int = 1000, steps: int = 10) -> float:
    world = switch_world(k, "sparse")
    states, _ = simulate_demonstrations(world.net, world.params, n, steps, seed=0)
    init = random_params(world.net, 1)
    timed = []
    for em_steps in (1, 3):
        t0 = time.perf_counter()
        fit_demonstrations(world.net, states, init=init, steps=em_steps, tol=1e-300)
        timed.append(time.perf_counter() - t0)
    per_step = (timed[1] - timed[0]) / 2
    print(
        f"{k} switches, {n} demonstrations x {steps} steps: one EM step {per_step:.2f} s "
        f"(goal < 5 s: {_mark(per_step < 5)}); reading the rows and the first step "
        f"{timed[0]:.2f} s"
    )
    return per_step


def main(args: argparse.Namespace) -> dict[str, float]:
    import warnings

    torch.set_num_threads(args.threads)
    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        for k in (4, 6):
            out |= tables_and_plans(k, args.seed)
        out |= tables_and_plans(4, args.seed, hidden=0.2)
        out["em_step_s"] = one_em_step()
    return out


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seed", type=int, default=1, help="the demonstrations' seed")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    add_out(parser)
    return parser.parse_args(argv)


if __name__ == "__main__":
    args = parse_args()
    print_also_to(args.out, __file__)
    main(args)
