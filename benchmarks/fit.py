"""Fit time of the two fits without a closed form, beside their goals and the old route.

    python benchmarks/fit.py                      # both, with the old route once each
    python benchmarks/fit.py --no-old             # the new routes only (seconds)

The world: doors, drawers and switches (``kind``) that are closed, ajar or open
(``state``), with a handle height and the effort needed to move them (continuous);
actions pull, push and press. ``end.state`` is a softmax of the handle and the effort
per (kind, state, action), 27 configurations of 3 classes on 2 inputs.

* **Softmax** -- :func:`inference.fit` on ``--softmax-rows`` complete rows (Newton's
  method per configuration, :meth:`models.cpds.SoftmaxCPD.maximise`); goal under 0.2 s.
  Beside it the old route, ``fit_gradient`` (L-BFGS over the traced Pyro model) on the
  softmax site, and how far its optimum lies from Newton's.
* **Missing values** -- :func:`inference.fit` with ``masks``: ``kind`` missing in 30 %
  of ``--em-rows`` rows and ``end.state`` in 20 % (EM with exact E-steps,
  :func:`inference.fitting.em.fit_missing`); goal converged under 2 s. Beside it the old route,
  ``fit_gradient`` with the masks (500 Adam steps on the marginal likelihood), on
  ``--old-em-rows`` rows.

Figures are medians over ``--repeats`` runs after one warm-up, on one torch thread; the
old routes run once.
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
import torch
from effect_networks.inference import fit, fit_gradient, fit_statistics, params_from_statistics
from effect_networks.models import Continuous, Discrete, EffectNetwork
from effect_networks.models.params import NetworkParams
from throw import machine  # benchmarks/throw.py, beside this script
from timing import add_out, median_seconds, print_also_to

SOFTMAX_GOAL_S = 0.2
EM_GOAL_S = 2.0

KINDS = ("door", "drawer", "switch")
STATES = ("closed", "ajar", "open")
ACTIONS = ("pull", "push", "press")


def door_network() -> EffectNetwork:
    return EffectNetwork(
        (
            Discrete("kind", KINDS),
            Discrete("state", STATES),
            Continuous("handle", 1),
            Continuous("effort", 1),
        ),
        ACTIONS,
    )


def door_rows(n: int, seed: int) -> dict[str, np.ndarray]:
    """Rows of the door world: an action opens (or closes) an object when the effort it
    needs is small beside the action's strength for that kind."""
    rng = np.random.default_rng(seed)
    kind = rng.integers(0, 3, n)
    state = rng.integers(0, 3, n)
    action = rng.integers(0, 3, n)
    handle = rng.normal(1.0, 0.3, n) + 0.2 * kind
    effort = rng.gamma(2.0, 1.0, n)
    strength = np.array([[3.0, 1.0, 0.2], [2.5, 2.0, 0.1], [0.1, 0.5, 4.0]])[kind, action]
    opens = 1 / (1 + np.exp(-(2.0 * (strength - effort) - 0.5 * (handle - 1.2))))
    u = rng.random(n)
    target = np.where(action == 1, 0, 2)  # push closes, pull and press open
    end = np.where(u < opens, target, np.where(u < opens + 0.5 * (1 - opens), 1, state))
    return {
        "initial.kind": np.array(KINDS)[kind],
        "initial.state": np.array(STATES)[state],
        "initial.handle": handle[:, None],
        "initial.effort": effort[:, None],
        "action": np.array(ACTIONS)[action],
        "end.kind": np.array(KINDS)[kind],
        "end.state": np.array(STATES)[end],
        "end.handle": handle[:, None] + 0.01 * rng.normal(size=(n, 1)),
        "end.effort": effort[:, None] + 0.01 * rng.normal(size=(n, 1)),
    }


def door_masks(n: int, seed: int) -> dict[str, torch.Tensor]:
    """``kind`` missing in 30 % of the rows, ``end.state`` in 20 %."""
    g = torch.Generator().manual_seed(seed + 1)
    return {
        "initial.kind": torch.rand(n, generator=g) > 0.3,
        "end.state": torch.rand(n, generator=g) > 0.2,
    }


def once(fn) -> tuple[float, object]:
    start = time.perf_counter()
    out = fn()
    return time.perf_counter() - start, out


def main(argv: list[str] | None = None) -> dict[str, float]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--softmax-rows", type=int, default=3000)
    parser.add_argument("--em-rows", type=int, default=1000)
    parser.add_argument("--old-em-rows", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--no-old", action="store_true", help="skip the old routes")
    add_out(parser)
    args = parser.parse_args(argv)
    print_also_to(args.out, __file__)
    threads = torch.get_num_threads()
    torch.set_num_threads(args.threads)
    out: dict[str, float] = {}
    try:
        net = door_network()
        print(machine())
        print(f"median of {args.repeats} after a warm-up; old routes once")

        rows = door_rows(args.softmax_rows, args.seed)
        newton_s = median_seconds(lambda: fit(net, rows), args.repeats)
        new = fit(net, rows)
        ok = "met" if newton_s < SOFTMAX_GOAL_S else "missed"
        print(
            f"softmax, {args.softmax_rows} rows: fit {newton_s:.3f} s   goal < "
            f"{SOFTMAX_GOAL_S:g} s: {ok}   (converged: {new.converged})"
        )
        out["softmax"] = newton_s
        if not args.no_old:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                old_s, old = once(
                    lambda: fit_gradient(net, rows, init=new_start(net, rows), sites=["end.state"])
                )
            gap = (old.params["end.state"].weight - new.params["end.state"].weight).abs().max()
            print(
                f"  old route (L-BFGS over the traced model): {old_s:.2f} s, "
                f"{old_s / newton_s:.0f}x; largest slope difference {float(gap):.2e}; "
                f"largest gradient component of the summed objective (KKT): Newton "
                f"{kkt_gradient(net, rows, new.params, 'end.state'):.1e}, old route "
                f"{kkt_gradient(net, rows, old.params, 'end.state'):.1e}"
            )
            out["softmax_old"] = old_s

        rows = door_rows(args.em_rows, args.seed)
        masks = door_masks(args.em_rows, args.seed)
        em_s = median_seconds(lambda: fit(net, rows, masks=masks), args.repeats)
        em = fit(net, rows, masks=masks)
        ok = "met" if em_s < EM_GOAL_S and em.converged else "missed"
        print(
            f"missing values, {args.em_rows} rows: fit {em_s:.3f} s, {len(em.losses) - 1} EM "
            f"steps   goal converged < {EM_GOAL_S:g} s: {ok}   (converged: {em.converged})"
        )
        out["em"] = em_s
        if not args.no_old:
            n = args.old_em_rows
            small = door_rows(n, args.seed)
            masks = door_masks(n, args.seed)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                old_s, old = once(lambda: fit_gradient(net, small, masks=masks, steps=500))
            em_small_s, em_small = once(lambda: fit(net, small, masks=masks))
            print(
                f"  old route (500 Adam steps) on {n} rows: {old_s:.1f} s (converged: "
                f"{old.converged}, loss {old.losses[-1]:.6f}); EM on the same rows "
                f"{em_small_s:.3f} s (loss {em_small.losses[-1]:.6f})"
            )
            out["em_old"] = old_s
        return out
    finally:
        torch.set_num_threads(threads)


def kkt_gradient(net: EffectNetwork, rows, params, site: str, l2: float = 0.01) -> float:
    """The largest gradient component of the site's summed penalised negative
    log-likelihood at ``params``, by autograd on the kind's own distribution."""
    enc = net.encode(rows)
    cpd = net.cpd(site)
    weight = params[site].weight.clone().requires_grad_()
    bias = params[site].bias.clone().requires_grad_()
    fitted = type(params[site])(weight, bias, params[site].n)
    x = torch.cat([enc[s] for s in cpd.inputs], -1)
    fn = cpd.distribution(fitted, [enc[s] for s in cpd.parents], x, {})
    loss = -fn.log_prob(enc[site]).sum() + 0.5 * l2 * weight.square().sum()
    grads = torch.autograd.grad(loss, [weight, bias])
    return max(float(g.abs().max()) for g in grads)


def new_start(net: EffectNetwork, rows) -> NetworkParams:
    """The closed form's parameters with the softmax at its start (zero slopes)."""
    stats = fit_statistics(net, [rows])
    return NetworkParams(params_from_statistics(net, stats, 0.01, 1e-6), 0.01)


if __name__ == "__main__":
    main()
