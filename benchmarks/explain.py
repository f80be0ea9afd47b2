"""Speed of ``explain``: demonstrations of the door world read as action sequences.

Network: the door world (``door`` locked/shut/open, ``drawer`` shut/open, ``switch``
off/on: 12 states; actions press, pull, turn, wait), every initial feature and the
action behind every end feature, fitted on 5,000 rows drawn from random tables.
Demonstrations: ``--n`` (default 10,000) of ``--steps`` (default 5) steps drawn from the
fitted model (:func:`inference.sequences.demonstration.simulate_demonstrations`), read
fully observed and partly observed (each discrete value hidden with probability 0.3).
Goal: 10,000 demonstrations of 5 steps in under 1 s.

Peer: brute force over every action sequence and every latent state path, per
demonstration (numpy, from the fitted tables: ``4^5`` sequences times the consistent
paths), on ``--peer`` demonstrations, scaled to ``--n``; its answers are checked equal
to explain's on those demonstrations. ``--handle`` adds the door world with a
continuous handle angle (observed at every time; one step table per step), on
``--handle-n`` demonstrations. Run::

    .venv/bin/python benchmarks/explain.py [--n 10000] [--steps 5] [--peer 30]
"""

from __future__ import annotations

import argparse
import itertools
import platform
import time
import warnings

import numpy as np
from effect_networks.inference import OutsideTrainingData, fit, simulate
from effect_networks.inference.sequences.demonstration import simulate_demonstrations
from effect_networks.inference.sequences.explanation import explain
from effect_networks.models import Continuous, Discrete, EffectNetwork, random_params
from timing import (  # benchmarks/timing.py, beside this script
    add_out,
    median_seconds,
    print_also_to,
)

GOAL_S = 1.0
STATES = {"door": ("locked", "shut", "open"), "drawer": ("shut", "open"), "switch": ("off", "on")}
ACTIONS = ("press", "pull", "turn", "wait")


def door_world(handle: bool = False) -> tuple[EffectNetwork, object]:
    """The network and its parameters fitted on 5,000 rows drawn from random tables."""
    features = tuple(Discrete(name, states) for name, states in STATES.items())
    if handle:
        features += (Continuous("handle_angle", 1),)
    net = EffectNetwork(features=features, actions=ACTIONS)
    rows = simulate(net, random_params(net, 0), 5000, seed=1)
    return net, fit(net, rows).params


def hide(states: dict, share: float, seed: int) -> dict:
    """Each discrete value hidden (None) with probability ``share``."""
    rng = np.random.default_rng(seed)
    out = dict(states)
    for name in STATES:
        out[name] = np.where(rng.random(states[name].shape) < share, None, states[name])
    return out


def step_table(net, params) -> tuple[np.ndarray, np.ndarray, list[tuple]]:
    """From the fitted tables: ``log p(s')`` start ``(S,)`` and ``log p(a) p(s' | s, a)``
    ``(S, A, S)`` under the uniform action prior, with the states' index tuples."""
    states = list(itertools.product(*[range(len(v)) for v in STATES.values()]))
    names = list(STATES)
    start = np.array(
        [
            sum(
                np.log(params[f"initial.{f}"].probs[i].item())
                for f, i in zip(names, s, strict=True)
            )
            for s in states
        ]
    )
    a = len(net.actions)
    table = np.zeros((len(states), a, len(states)))
    for (i, s), act, (j, e) in itertools.product(enumerate(states), range(a), enumerate(states)):
        table[i, act, j] = np.log(1 / a) + sum(
            np.log(params[f"end.{f}"].probs[(*s, act, e[k])].item()) for k, f in enumerate(names)
        )
    return start, table, states


def brute_force(start, table, states, demo: dict, i: int):
    """One demonstration: every action sequence and consistent state path enumerated;
    ``(log-likelihood, per-step action posterior, most probable actions)``."""
    times = len(demo["door"][i])
    allowed = [
        [
            k
            for k, s in enumerate(states)
            if all(
                demo[f][i][t] is None or STATES[f].index(demo[f][i][t]) == s[j]
                for j, f in enumerate(STATES)
            )
        ]
        for t in range(times)
    ]
    paths = np.array(list(itertools.product(*allowed)))  # (P, T + 1)
    acts = np.array(list(itertools.product(range(table.shape[1]), repeat=times - 1)))  # (Q, T)
    first = start[paths[:, 0]]
    log_joint = first[:, None] - np.logaddexp.reduce(start[allowed[0]])
    for t in range(times - 1):
        log_joint = log_joint + table[paths[:, t, None], acts[None, :, t], paths[:, t + 1, None]]
    log_likelihood = np.logaddexp.reduce(log_joint.ravel())
    weights = np.exp(np.logaddexp.reduce(log_joint, 0) - log_likelihood)  # (Q,)
    posterior = np.stack(
        [np.bincount(acts[:, t], weights, table.shape[1]) for t in range(times - 1)]
    )
    best = acts[np.unravel_index(log_joint.argmax(), log_joint.shape)[1]]
    return log_likelihood, posterior, best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=10_000)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--peer", type=int, default=30, help="demonstrations brute force reads")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--handle", action="store_true", help="also the continuous handle world")
    parser.add_argument("--handle-n", type=int, default=1_000)
    add_out(parser)
    args = parser.parse_args()
    print_also_to(args.out, __file__)
    print(f"python {platform.python_version()}, {platform.machine()}")
    net, params = door_world()
    states, _ = simulate_demonstrations(net, params, args.n, args.steps, seed=2)
    start, table, index = step_table(net, params)
    for label, demo in (("fully observed", states), ("partly observed", hide(states, 0.3, 3))):
        seconds = median_seconds(lambda demo=demo: explain(net, params, demo), args.repeats)
        result = explain(net, params, demo)
        peer = min(args.peer, args.n)
        began = time.perf_counter()
        answers = [brute_force(start, table, index, demo, i) for i in range(peer)]
        brute = (time.perf_counter() - began) / peer * args.n
        for i, (log_likelihood, posterior, _) in enumerate(answers):
            assert abs(float(result.log_likelihood[i]) - log_likelihood) < 1e-8
            assert np.allclose(result.probs[i].numpy(), posterior, atol=1e-8)
        print(
            f"explain, door world, {args.n} demonstrations x {args.steps} steps, {label}: "
            f"{seconds:.3f} s (goal {GOAL_S:.0f} s); brute force over every action "
            f"sequence and path: {brute:.1f} s scaled from {peer} (answers equal)"
        )
    if args.handle:
        net, params = door_world(handle=True)
        states, _ = simulate_demonstrations(net, params, args.handle_n, args.steps, seed=2)
        with warnings.catch_warnings():  # chained random linear maps drift out of the rows
            warnings.simplefilter("ignore", OutsideTrainingData)
            seconds = median_seconds(lambda: explain(net, params, states), 1)
        print(
            f"explain, door world with a handle angle, {args.handle_n} demonstrations x "
            f"{args.steps} steps, fully observed: {seconds:.3f} s (no goal)"
        )


if __name__ == "__main__":
    main()
