"""The link probabilities' accuracy against an exact oracle, in one run.

``link_probabilities`` on partitions whose boxes bound one dimension or two correlated
ones, beside the bivariate normal CDF written with Owen's T function (scipy's
``owens_t``; exact to float64 rounding): first the reported case (correlation 0.8, one
box bounding x and y, the others x only), then drawn guillotine partitions (correlations
in (-0.99999, 0.99999), means and scales far from the boxes). Run::

    .venv/bin/python benchmarks/link_accuracy.py [--cases 400] [--seed 0] [--out DIR]

Goals: every box within 1e-10 of the oracle, every probability in [0, 1], and each
component's probabilities and ``none`` summing to 1 within 1e-12.
"""

from __future__ import annotations

import argparse
import math

import numpy as np
import torch
from effect_networks.inference.queries.results import GaussianMixture
from effect_networks.inference.sequences.chaining import BoxPartition, link_probabilities
from scipy import special
from timing import add_out, print_also_to

INF = math.inf


def bvn_cdf(h, k, rho):
    """P(X < h, Y < k) for standard normals of correlation rho, by Owen's T (scipy)."""
    if h == -math.inf or k == -math.inf:
        return 0.0
    if h == math.inf:
        return special.ndtr(k)
    if k == math.inf:
        return special.ndtr(h)
    if h == 0.0 and k == 0.0:
        return 0.25 + math.asin(rho) / (2 * math.pi)
    r = math.sqrt((1 - rho) * (1 + rho))

    def t(x, y):  # T(x, (y - rho x) / (x r)), limit x -> 0 included
        if x == 0.0:
            return math.copysign(0.25, y)
        return special.owens_t(x, (y - rho * x) / (x * r))

    beta = 0.0 if (h * k > 0 or (h * k == 0 and h + k >= 0)) else 0.5
    return 0.5 * (special.ndtr(h) + special.ndtr(k)) - t(h, k) - t(k, h) - beta


def box_prob(mean, cov, lo, hi):
    s1, s2 = math.sqrt(cov[0][0]), math.sqrt(cov[1][1])
    rho = cov[0][1] / (s1 * s2)

    def z(v, m, s):
        return (v - m) / s

    a1, b1 = z(lo[0], mean[0], s1), z(hi[0], mean[0], s1)
    a2, b2 = z(lo[1], mean[1], s2), z(hi[1], mean[1], s2)
    return bvn_cdf(b1, b2, rho) - bvn_cdf(a1, b2, rho) - bvn_cdf(b1, a2, rho) + bvn_cdf(a1, a2, rho)


def run(boxes, mean, cov):
    link = BoxPartition.from_boxes(boxes, [b for b, _ in boxes])

    def t(a):
        return torch.as_tensor(np.asarray(a, dtype=np.float64))

    got = link_probabilities(link, GaussianMixture(t([[1.0]]), t([[mean]]), t([[cov]])))
    errs1, errs2 = [], []
    for k, (_, sides) in enumerate(boxes):
        lo = [a for a, _ in sides]
        hi = [b for _, b in sides]
        want = box_prob(mean, cov, lo, hi)
        (errs2 if all(lo[i] > -INF or hi[i] < INF for i in (0, 1)) else errs1).append(
            abs(got.probs[0, k].item() - want)
        )
    col = got.probs.sum().item() + got.none.item()
    return (
        got,
        max(errs1, default=0),
        max(errs2, default=0),
        abs(col - 1),
        got.probs.max().item(),
        got.none.min().item(),
    )


def cov_of(s1, s2, rho):
    return [[s1 * s1, rho * s1 * s2], [rho * s1 * s2, s2 * s2]]


def verdict(ok: bool) -> str:
    return "met" if ok else "not met"


def main(args: argparse.Namespace) -> None:
    print("the reported case (rho 0.8): one box bounds x and y, the others x only")
    for boxes in (
        [("x<9.5", [(-INF, 9.5), (-INF, INF)]), ("corner", [(9.5, INF), (0.0, INF)])],
        [("corner", [(-INF, -7.8), (0.0, INF)]), ("x>=-7.8", [(-7.8, INF), (-INF, INF)])],
    ):
        got, e1, e2, dev, pmax, nmin = run(boxes, [0.0, 0.0], cov_of(1.0, 1.0, 0.8))
        print(
            f"  {[b for b, _ in boxes]}: probs {got.probs[0].tolist()} none {got.none.item():.3g}"
            f" max err 1-D {e1:.2e} 2-D {e2:.2e}"
        )

    rng = np.random.default_rng(args.seed)
    worst = dict(e1=0.0, e2=0.0, dev=0.0, pmax=0.0, nmin=1.0)
    for _ in range(args.cases):
        # a guillotine partition: x strips, each x-only, none, or split in y (2-D boxes)
        xe = np.sort(rng.normal(0, 3, rng.integers(1, 5)))
        xe = [-INF, *xe, INF]
        boxes = []
        for a, b in zip(xe[:-1], xe[1:], strict=False):
            kind = rng.integers(3)
            if kind == 0:
                boxes.append((len(boxes), [(a, b), (-INF, INF)]))
            elif kind == 2:
                ye = [-INF, *np.sort(rng.normal(0, 3, rng.integers(1, 4))), INF]
                for c, d in zip(ye[:-1], ye[1:], strict=False):
                    if rng.random() < 0.8:
                        boxes.append((len(boxes), [(a, b), (c, d)]))
        if not boxes:
            continue
        rho = float(rng.choice([-1, 1]) * (1 - 10 ** rng.uniform(-5, 0)))
        s1, s2 = 10 ** rng.uniform(-2, 1, 2)
        mean = rng.normal(0, 5, 2)
        got, e1, e2, dev, pmax, nmin = run(boxes, mean, cov_of(s1, s2, rho))
        worst = dict(
            e1=max(worst["e1"], e1),
            e2=max(worst["e2"], e2),
            dev=max(worst["dev"], dev),
            pmax=max(worst["pmax"], pmax),
            nmin=min(worst["nmin"], nmin),
        )
    print(
        f"{args.cases} drawn cases (correlations in (-0.99999, 0.99999), means and scales far from the boxes):"
    )
    print(
        f"  max |error| of x-only boxes {worst['e1']:.2e}, of 2-D boxes {worst['e2']:.2e}, "
        f"max |probs + none - 1| {worst['dev']:.2e}, max prob {worst['pmax']!r}, min none {worst['nmin']!r}"
    )
    print(
        f"goals: every box within 1e-10: {verdict(max(worst['e1'], worst['e2']) <= 1e-10)}; "
        f"sums within 1e-12: {verdict(worst['dev'] <= 1e-12)}; "
        f"inside [0, 1]: {verdict(worst['pmax'] <= 1.0 and worst['nmin'] >= 0.0)}"
    )


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", type=int, default=400)
    parser.add_argument("--seed", type=int, default=0)
    add_out(parser)
    return parser.parse_args(argv)


if __name__ == "__main__":
    args = parse_args()
    print_also_to(args.out, __file__)
    main(args)
