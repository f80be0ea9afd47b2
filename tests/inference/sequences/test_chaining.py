"""Chained networks: link probabilities against numerical integration and closed forms,
the Monte Carlo link within its stated error, chained transitions against a brute-force sum."""

import itertools
import math

import numpy as np
import pytest
import torch
from effect_networks.inference.queries.results import GaussianMixture
from effect_networks.inference.sequences.chaining import (
    BoxPartition,
    FunctionLink,
    LinkProbabilities,
    chain,
    link_probabilities,
)
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import integrate, special, stats

INF = math.inf


def mixture(weights, means, covs) -> GaussianMixture:
    """One row per entry of the lists: weights (M,), means (M, d), covs (M, d, d)."""
    t = lambda x: torch.as_tensor(np.asarray(x, dtype=np.float64))  # noqa: E731
    return GaussianMixture(t(weights), t(means), t(covs))


def mixture_pdf(weights, means, covs):
    """The density of one row's mixture, from scipy."""
    parts = [stats.multivariate_normal(m, c) for m, c in zip(means, covs, strict=True)]
    return lambda x: sum(w * p.pdf(x) for w, p in zip(weights, parts, strict=True))


def box_integral(pdf, sides):
    """A 2-D box's mass by scipy's dblquad; infinite sides cut at +-12 (beyond 1e-30)."""
    (l1, h1), (l2, h2) = [(max(lo, -12.0), min(hi, 12.0)) for lo, hi in sides]
    value, _ = integrate.dblquad(
        lambda y, x: pdf([x, y]), l1, h1, l2, h2, epsabs=1e-13, epsrel=1e-12
    )
    return value


# --- box partitions ----------------------------------------------------------------------

SLABS = [
    ("low", [(-INF, -0.5)]),
    ("mid", [(-0.5, 0.25)]),
    ("high", [(0.25, 1.0)]),
    ("low", [(2.0, INF)]),  # a label may own several boxes
]


@settings(max_examples=15, deadline=None)
@given(
    weights=st.lists(st.floats(0.05, 1.0), min_size=1, max_size=3),
    data=st.data(),
)
def test_1d_slabs_match_numerical_integration_of_the_mixture(weights, data):
    """Each label's mass and the rest (``none``, here [1, 2)) against scipy's quad."""
    m = len(weights)
    weights = np.array(weights) / sum(weights)
    means = data.draw(st.lists(st.floats(-3.0, 3.0), min_size=m, max_size=m))
    sds = data.draw(st.lists(st.floats(0.05, 2.0), min_size=m, max_size=m))
    covs = [[[s * s]] for s in sds]
    means = [[x] for x in means]
    link = BoxPartition.from_boxes(SLABS, ["low", "mid", "high"])
    got = link_probabilities(link, mixture([weights], [means], [covs]))
    pdf = mixture_pdf(weights, means, covs)

    def mass(lo, hi):
        return integrate.quad(lambda x: pdf([x]), lo, hi, epsabs=1e-13, epsrel=1e-12, limit=200)[0]

    want = {
        "low": mass(-INF, -0.5) + mass(2.0, INF),
        "mid": mass(-0.5, 0.25),
        "high": mass(0.25, 1.0),
    }
    assert got.method == "exact"
    for label, value in want.items():
        assert got.prob(label).item() == pytest.approx(value, abs=1e-9)
    assert got.none.item() == pytest.approx(mass(1.0, 2.0), abs=1e-9)
    assert (got.probs.sum(-1) + got.none).item() == pytest.approx(1.0, abs=1e-12)


BOXES_2D = [
    ("a", [(-INF, 0.0), (-INF, INF)]),  # bounded in x only
    ("b", [(0.0, 1.0), (-0.5, 0.0)]),
    ("c", [(0.0, 1.0), (0.0, INF)]),
    ("d", [(1.0, 2.5), (-1.0, -0.3)]),
]


@pytest.mark.parametrize("rho", [0.0, 0.4, -0.7, 0.95, -0.99])
def test_2d_boxes_match_numerical_integration(rho):
    """Two components, one correlated by ``rho``: exact (diagonal) or the quadrature."""
    weights = [0.7, 0.3]
    means = [[0.3, -0.2], [1.2, 0.4]]
    covs = [[[1.0, rho * 0.5], [rho * 0.5, 0.25]], [[0.3, 0.0], [0.0, 0.6]]]
    link = BoxPartition.from_boxes(BOXES_2D, "abcd")
    got = link_probabilities(link, mixture([weights], [means], [covs]))
    assert got.method == ("exact" if rho == 0.0 else "quadrature")
    pdf = mixture_pdf(weights, means, covs)
    for k, (label, sides) in enumerate(BOXES_2D):
        if k == 0:  # a half-plane: the x marginals' CDFs, exactly
            want = sum(
                w * stats.norm.cdf(0.0, m[0], math.sqrt(c[0][0]))
                for w, m, c in zip(weights, means, covs, strict=True)
            )
        else:
            want = box_integral(pdf, sides)
        assert got.prob(label).item() == pytest.approx(want, abs=1e-9), label
    assert got.none.item() == pytest.approx(1 - got.probs.sum().item(), abs=1e-15)


@pytest.mark.parametrize("rho", [-0.99999, -0.999, -0.6, 0.0, 0.3, 0.9, 0.999, 0.99999])
def test_2d_quadrature_matches_the_bivariate_orthant_closed_form(rho):
    """Quadrants of a centred bivariate normal: P(x > 0, y > 0) = 1/4 + asin(rho) / (2 pi)."""
    cov = [[2.0, rho * math.sqrt(2.0) * 0.5], [rho * math.sqrt(2.0) * 0.5, 0.25]]
    quadrants = [
        ("++", [(0.0, INF), (0.0, INF)]),
        ("--", [(-INF, 0.0), (-INF, 0.0)]),
        ("+-", [(0.0, INF), (-INF, 0.0)]),
    ]
    # the quadrants around the mean (1, -2)
    boxes = [(label, [(x0 + 1.0, x1 + 1.0), (y0 - 2.0, y1 - 2.0)])
             for label, [(x0, x1), (y0, y1)] in quadrants]  # fmt: skip
    got = link_probabilities(
        BoxPartition.from_boxes(boxes, ["++", "--", "+-"]),
        mixture([[1.0]], [[[1.0, -2.0]]], [[cov]]),
    )
    same = 0.25 + math.asin(rho) / (2 * math.pi)
    assert got.prob("++").item() == pytest.approx(same, abs=1e-10)
    assert got.prob("--").item() == pytest.approx(same, abs=1e-10)
    assert got.prob("+-").item() == pytest.approx(0.5 - same, abs=1e-10)
    assert got.none.item() == pytest.approx(0.5 - same, abs=1e-10)


def test_2d_diagonal_boxes_match_a_fine_grid():
    """A grid partition under a diagonal mixture: against a midpoint sum on a fine grid."""
    weights = [0.5, 0.5]
    means = [[0.0, 0.0], [0.8, -0.6]]
    covs = [np.diag([0.2, 0.5]), np.diag([0.4, 0.1])]
    edges_x, edges_y = [-1.0, 0.0, 0.7, 2.0], [-1.5, -0.2, 1.0]
    boxes = [
        ((i, j), [(edges_x[i], edges_x[i + 1]), (edges_y[j], edges_y[j + 1])])
        for i, j in itertools.product(range(3), range(2))
    ]
    labels = [label for label, _ in boxes]
    got = link_probabilities(
        BoxPartition.from_boxes(boxes, labels), mixture([weights], [means], [covs])
    )
    n = 400
    x = np.linspace(-1.0, 2.0, 3 * n + 1)
    y = np.linspace(-1.5, 1.0, 2 * n + 1)
    xm, ym = (x[1:] + x[:-1]) / 2, (y[1:] + y[:-1]) / 2
    grid = np.stack(np.meshgrid(xm, ym, indexing="ij"), -1)
    dens = mixture_pdf(weights, means, covs)(grid) * np.diff(x)[:, None] * np.diff(y)[None, :]
    for k, (label, [(x0, x1), (y0, y1)]) in enumerate(boxes):
        inside = ((xm >= x0) & (xm < x1))[:, None] & ((ym >= y0) & (ym < y1))[None, :]
        assert got.probs[0, k].item() == pytest.approx(dens[inside].sum(), abs=1e-5), label


def test_rows_of_a_batch_are_independent():
    """Several upper rows at once give each row's own answer."""
    link = BoxPartition.from_boxes(BOXES_2D, "abcd")
    rows = [([1.0], [[0.1 * r, -0.3 * r]], [[[1.0, 0.2], [0.2, 0.5]]]) for r in range(4)]
    batch = link_probabilities(link, mixture(*zip(*rows, strict=True)))
    for r, row in enumerate(rows):
        alone = link_probabilities(link, mixture(*([x] for x in row)))
        torch.testing.assert_close(batch.probs[r], alone.probs[0], rtol=0, atol=1e-15)


# --- every box by its exact route, against the bivariate normal CDF -----------------------


def bivariate_cdf(h, k, rho):
    """``P(z < h, v < k)`` for standard normals of correlation ``rho``: Owen's T closed form,
    ``Phi(h) / 2 + Phi(k) / 2 - T(h, a_h) - T(k, a_k) - beta`` (scipy's ``owens_t``)."""
    if h == -INF or k == -INF:
        return 0.0
    if h == INF or k == INF:
        return float(special.ndtr(min(h, k)))
    if h == 0.0 and k == 0.0:
        return 0.25 + math.asin(rho) / (2 * math.pi)
    r = math.sqrt((1 - rho) * (1 + rho))

    def t(x, y):  # T(x, (y - rho x) / (x r)), with its limit at x = 0
        return math.copysign(0.25, y) if x == 0.0 else special.owens_t(x, (y - rho * x) / (x * r))

    beta = 0.0 if (h >= 0) == (k >= 0) else 0.5  # signs, not h * k: that underflows
    return 0.5 * (special.ndtr(h) + special.ndtr(k)) - t(h, k) - t(k, h) - beta


def gaussian_box(mean, cov, sides):
    """A box's mass under one Gaussian in the (at most two) dimensions it bounds.

    One dimension: scipy's normal CDF difference; two: the bivariate CDF at the corners by
    inclusion-exclusion."""
    bounded = [i for i, (lo, hi) in enumerate(sides) if lo > -INF or hi < INF]
    if not bounded:
        return 1.0
    z = [[(side - mean[i]) / math.sqrt(cov[i][i]) for side in sides[i]] for i in bounded]
    if len(bounded) == 1:
        (lo, hi), = z  # fmt: skip
        return (
            stats.norm.sf(lo) - stats.norm.sf(hi)
            if lo > 0
            else stats.norm.cdf(hi) - stats.norm.cdf(lo)
        )
    i, j = bounded
    rho = cov[i][j] / math.sqrt(cov[i][i] * cov[j][j])
    (a1, b1), (a2, b2) = z
    return (bivariate_cdf(b1, b2, rho) - bivariate_cdf(a1, b2, rho)
            - bivariate_cdf(b1, a2, rho) + bivariate_cdf(a1, a2, rho))  # fmt: skip


def correlated(s1, s2, rho):
    return [[s1 * s1, rho * s1 * s2], [rho * s1 * s2, s2 * s2]]


@pytest.mark.parametrize("rho", [-0.99999, -0.9, 0.3, 0.8, 0.99999])
def test_the_bivariate_oracle_matches_dblquad_and_the_orthant_form(rho):
    """The tests' oracle is checked too: against P(z > 0, v > 0) and, where the ridge is
    wide enough for it, dblquad."""
    assert bivariate_cdf(0.0, 0.0, rho) == pytest.approx(0.25 + math.asin(rho) / (2 * math.pi))
    assert gaussian_box([0.0, 0.0], correlated(1.0, 1.0, rho), [(0.0, INF), (0.0, INF)]) == (
        pytest.approx(0.25 + math.asin(rho) / (2 * math.pi), abs=1e-15)
    )
    if abs(rho) > 0.99:
        return
    mean, cov = [0.3, -0.2], correlated(1.0, 0.5, rho)
    pdf = stats.multivariate_normal(mean, cov).pdf
    for sides in (
        [(0.5, 2.0), (0.0, INF)],
        [(-1.0, 0.4), (-0.6, 0.1)],
        [(-INF, 0.0), (-INF, -0.4)],
    ):
        want = box_integral(pdf, sides)
        assert gaussian_box(mean, cov, sides) == pytest.approx(want, abs=1e-10), sides


REPORTED = [  # rho 0.8: one box bounds x and y, the others x only
    [("left", [(-INF, -1.0), (-INF, INF)]), ("mid", [(-1.0, 0.5), (-INF, INF)]),
     ("corner", [(0.5, 2.0), (0.0, INF)]), ("right", [(2.0, INF), (-INF, INF)])],
    [("x<9.5", [(-INF, 9.5), (-INF, INF)]), ("corner", [(9.5, INF), (0.0, INF)])],
    [("corner", [(-INF, -7.8), (0.0, INF)]), ("x>=-7.8", [(-7.8, INF), (-INF, INF)])],
]  # fmt: skip


@pytest.mark.parametrize("boxes", REPORTED, ids=["around", "wide-left", "wide-right"])
def test_x_only_boxes_stay_exact_beside_a_correlated_box(boxes):
    """Regression: one box needing the quadrature sent every box through it, and a box
    spanning the Gaussian's bulk got 20 nodes over [-9, 9] (off by 1.1e-4, up to 1.00003).
    The x-only boxes are normal CDF differences, the corner within 1e-10, none >= 0."""
    mean, cov = [0.0, 0.0], correlated(1.0, 1.0, 0.8)
    got = link_probabilities(
        BoxPartition.from_boxes(boxes, [label for label, _ in boxes]),
        mixture([[1.0]], [[mean]], [[cov]]),
    )
    assert got.method == "quadrature"
    for k, (label, sides) in enumerate(boxes):
        want = gaussian_box(mean, cov, sides)
        tolerance = 1e-10 if label == "corner" else 1e-15
        assert got.probs[0, k].item() == pytest.approx(want, abs=tolerance), label
    assert 0.0 <= got.probs.min() and got.probs.max() <= 1.0 and got.none.item() >= 0.0
    assert got.probs.sum().item() + got.none.item() == pytest.approx(1.0, abs=1e-12)


@st.composite
def guillotine(draw):
    """Boxes of a 2-D partition: strips across one axis, each a box bounding that axis
    only, none, or split along the other axis into 2-D boxes (and none)."""
    first = draw(st.sampled_from([0, 1]))
    edges = draw(st.lists(st.floats(-8.0, 8.0), min_size=1, max_size=4, unique=True))
    boxes = []
    for lo, hi in itertools.pairwise([-INF, *sorted(edges), INF]):
        kind = draw(st.sampled_from(["box", "none", "split"]))
        if kind == "box":
            boxes.append([(lo, hi), (-INF, INF)])
        elif kind == "split":
            across = draw(st.lists(st.floats(-8.0, 8.0), min_size=1, max_size=3, unique=True))
            for c, d in itertools.pairwise([-INF, *sorted(across), INF]):
                if draw(st.booleans()):
                    boxes.append([(lo, hi), (c, d)])
    boxes = boxes or [[(lo, hi), (-INF, INF)]]  # at least one box: the last strip
    return [sides if first == 0 else sides[::-1] for sides in boxes]


@settings(max_examples=60, deadline=None)
@given(
    boxes=guillotine(),
    components=st.lists(
        st.tuples(
            st.floats(-0.99999, 0.99999),  # correlation
            st.floats(-30.0, 30.0), st.floats(-30.0, 30.0),  # mean, far from the boxes too
            st.floats(0.01, 20.0), st.floats(0.01, 20.0),  # scales
            st.floats(0.05, 1.0),  # weight
        ),
        min_size=1, max_size=3,
    ),
)  # fmt: skip
def test_every_box_within_its_documented_error_and_every_column_sums_to_one(boxes, components):
    """Drawn partitions (1-D and 2-D boxes mixed), correlations, means and scales: each
    component's and the mixture's box probabilities against the bivariate normal CDF
    (within 1e-10 per box), in [0, 1], summing with none to 1 within 1e-12."""
    labels = list(range(len(boxes)))
    link = BoxPartition.from_boxes(list(zip(labels, boxes, strict=True)), labels)
    means = [[mx, my] for _, mx, my, *_ in components]
    covs = [correlated(sx, sy, rho) for rho, _, _, sx, sy, _ in components]
    weights = np.array([w for *_, w in components]) / sum(w for *_, w in components)
    # one row per component alone, then the mixture
    rows = [([1.0], [m], [c]) for m, c in zip(means, covs, strict=True)]
    got = link_probabilities(
        link,
        mixture(
            [np.eye(len(means))[r] for r in range(len(means))] + [weights],
            [means] * (len(means) + 1),
            [covs] * (len(means) + 1),
        ),
    )
    want = np.array([[gaussian_box(m, c, sides) for sides in boxes] for _, (m,), (c,) in rows])
    want = np.vstack([want, weights @ want])
    assert np.abs(got.probs.numpy() - want).max() <= 1e-10
    assert (got.probs >= 0).all() and (got.probs <= 1).all()
    assert (got.none >= 0).all() and (got.none <= 1).all()
    assert ((got.probs.sum(-1) + got.none - 1).abs() <= 1e-12).all()
    assert np.abs(got.none.numpy() - (1 - want.sum(-1))).max() <= 1e-10 * len(boxes)
    two_d = any(all(lo > -INF or hi < INF for lo, hi in sides) for sides in boxes)
    quadrature = two_d and any(rho != 0 for rho, *_ in components)
    assert got.method == ("quadrature" if quadrature else "exact")


def test_boxes_bounding_different_pairs_of_three_correlated_dimensions_are_not_sampled():
    """Each box bounds at most two of three correlated dimensions: exact or quadrature per
    box, not Monte Carlo, and the four boxes fill the space."""
    cov = [[1.0, 0.6, -0.5], [0.6, 2.0, 0.3], [-0.5, 0.3, 0.5]]
    mean = [0.2, -0.1, 0.4]
    boxes = [
        ("a", [(-INF, 0.0), (-INF, 0.0), (-INF, INF)]),
        ("b", [(-INF, 0.0), (0.0, INF), (-INF, INF)]),
        ("c", [(0.0, INF), (-INF, INF), (-INF, 1.0)]),
        ("d", [(0.0, INF), (-INF, INF), (1.0, INF)]),
    ]
    got = link_probabilities(
        BoxPartition.from_boxes(boxes, "abcd"), mixture([[1.0]], [[mean]], [[cov]])
    )
    assert got.method == "quadrature"
    for k, (label, sides) in enumerate(boxes):
        pair = [i for i, (lo, hi) in enumerate(sides) if lo > -INF or hi < INF]
        want = gaussian_box([mean[i] for i in pair], [[cov[i][j] for j in pair] for i in pair],
                            [sides[i] for i in pair])  # fmt: skip
        assert got.probs[0, k].item() == pytest.approx(want, abs=1e-10), label
    assert got.probs.sum().item() == pytest.approx(1.0, abs=1e-12) and got.none.item() <= 1e-12


def test_a_mixture_without_a_density_is_refused():
    link = BoxPartition.from_boxes(BOXES_2D, "abcd")
    with pytest.raises(ValueError, match=r"rows \[1\] give undefined box probabilities"):
        link_probabilities(
            link, mixture([[1.0], [1.0]], [[[0.0, 0.0]], [[math.nan, 0.0]]], [[np.eye(2)]] * 2)
        )


def test_too_few_quadrature_nodes_are_refused():
    link = BoxPartition.from_boxes(BOXES_2D, "abcd")
    with pytest.raises(ValueError, match="nodes: 6; expected an integer of at least 12"):
        link_probabilities(link, mixture([[1.0]], [[[0.0, 0.0]]], [[np.eye(2)]]), nodes=6)


# --- Monte Carlo -------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_monte_carlo_link_is_within_its_stated_error_of_the_exact_box_answer(seed):
    """The same partition as a user function: within 4 standard errors (and 0.5/sqrt(N))."""
    weights = [[0.6, 0.4], [1.0, 0.0]]
    means = [[[0.3, -0.2], [1.2, 0.4]], [[0.5, 0.5], [0.0, 0.0]]]
    covs = [[[[1.0, 0.3], [0.3, 0.25]], np.diag([0.3, 0.6])], [np.diag([0.5, 0.2])] * 2]
    mix = mixture(weights, means, covs)
    boxes = BoxPartition.from_boxes(BOXES_2D, "abcd")
    exact = link_probabilities(boxes, mix)
    samples = 20_000
    mc = link_probabilities(FunctionLink(boxes, "abcd", dim=2), mix, samples=samples, seed=seed)
    assert mc.method == "monte carlo"
    bound = 4 * torch.sqrt(exact.probs * (1 - exact.probs) / samples) + 1e-12
    assert ((mc.probs - exact.probs).abs() <= bound).all()
    assert (mc.stderr <= 0.5 / math.sqrt(samples)).all()
    torch.testing.assert_close(mc.stderr, (mc.probs * (1 - mc.probs) / samples).sqrt())
    assert (mc.none - exact.none).abs().max() <= 4 * math.sqrt(0.25 / samples)
    again = link_probabilities(FunctionLink(boxes, "abcd", dim=2), mix, samples=samples, seed=seed)
    assert torch.equal(again.probs, mc.probs)  # seeded


def test_correlated_boxes_in_three_dimensions_fall_back_to_monte_carlo():
    """Octants of a centred trivariate normal against the closed form
    P(all > 0) = 1/8 + (asin r12 + asin r13 + asin r23) / (4 pi)."""
    r12, r13, r23 = 0.5, -0.3, 0.2
    cov = [[1.0, r12, r13], [r12, 1.0, r23], [r13, r23, 1.0]]
    octants = {"+++": [(0.0, INF)] * 3, "---": [(-INF, 0.0)] * 3}
    link = BoxPartition.from_boxes(list(octants.items()), list(octants))
    samples = 40_000
    got = link_probabilities(link, mixture([[1.0]], [[[0.0] * 3]], [[cov]]), samples=samples)
    want = 1 / 8 + (math.asin(r12) + math.asin(r13) + math.asin(r23)) / (4 * math.pi)
    assert got.method == "monte carlo"
    for label in octants:  # both octants have the same mass, by symmetry
        assert abs(got.prob(label).item() - want) <= 4 * math.sqrt(want * (1 - want) / samples)


@pytest.mark.parametrize("as_array", [False, True])
def test_function_link_reads_labels_as_a_list_or_an_array(as_array):
    """Integer actions with a string none label, returned either way, count alike."""

    def sign(points):
        labels = [0 if x < 0 else 1 if x < 1 else "none" for x in points[:, 0]]
        return np.array(labels, dtype=object) if as_array else labels

    link = FunctionLink(sign, (0, 1), dim=1)
    got = link_probabilities(link, mixture([[1.0]], [[[0.0]]], [[[[1.0]]]]), samples=4000)
    want = [stats.norm.cdf(0.0), stats.norm.cdf(1.0) - stats.norm.cdf(0.0)]
    assert (got.probs[0] - torch.tensor(want)).abs().max() <= 4 * math.sqrt(0.25 / 4000)
    strings = FunctionLink(lambda p: np.where(p[:, 0] < 0, "a", "b"), ("a", "b"), dim=1)
    index = strings.label_index(torch.tensor([[-1.0], [2.0], [-3.0]]))
    assert index.tolist() == [0, 1, 0]


def test_the_documentation_page_runs():
    """docs/chaining.md's code, run as written; its figures as the page states them."""
    import re
    from pathlib import Path

    page = Path(__file__).parents[3] / "docs" / "chaining.md"
    namespace = {}
    for block in re.findall(r"```python\n(.*?)```", page.read_text(), re.S):
        exec(block, namespace)  # noqa: S102
    assert namespace["link"].method == "exact" and namespace["sampled"].method == "monte carlo"
    assert 6.0 <= namespace["best"] <= 9.0 and namespace["success"] > 0.98


def test_function_link_rejects_unknown_labels():
    link = FunctionLink(lambda x: ["left"] * len(x), ("a", "b"), dim=1)
    with pytest.raises(ValueError, match="'left'"):
        link_probabilities(link, mixture([[1.0]], [[[0.0]]], [[[[1.0]]]]), samples=10)


# --- the partition's checks --------------------------------------------------------------


def test_overlapping_boxes_are_refused():
    with pytest.raises(ValueError, match="overlap"):
        BoxPartition.from_boxes([("a", [(0.0, 1.0)]), ("b", [(0.5, 2.0)])], "ab")


def test_labels_must_be_lower_actions():
    with pytest.raises(ValueError, match="not lower actions"):
        BoxPartition.from_boxes([("z", [(0.0, 1.0)])], "ab")


def test_the_mixture_must_match_the_links_dimension():
    link = BoxPartition.from_boxes(BOXES_2D, "abcd")
    with pytest.raises(ValueError, match=r"expected \(U, M, 2\)"):
        link_probabilities(link, mixture([[1.0]], [[[0.0]]], [[[[1.0]]]]))


def test_a_box_partition_labels_points_as_its_probabilities_count_them():
    link = BoxPartition.from_boxes(SLABS, ["low", "mid", "high"], none="nothing")
    assert link(np.array([[-3.0], [-0.5], [0.25], [1.5], [2.0]])) == [
        "low", "mid", "high", "nothing", "low",
    ]  # fmt: skip


# --- chained transitions -----------------------------------------------------------------


def random_link(generator, n_upper, n_lower, offered=None) -> LinkProbabilities:
    """Rows over the lower actions and none that sum to 1 (zero where not offered)."""
    p = torch.rand(n_upper, n_lower + 1, generator=generator, dtype=torch.float64)
    p /= p.sum(-1, keepdim=True)
    if offered is not None:
        p[~offered] = 0.0
    return LinkProbabilities(p[:, :-1], p[:, -1], tuple(range(n_lower)))


def random_lower(generator, n_states, n_lower) -> torch.Tensor:
    t = torch.rand(n_states, n_lower, n_states, generator=generator, dtype=torch.float64)
    return t / t.sum(-1, keepdim=True)


def brute_force(links, lower) -> torch.Tensor:
    """``T[s, u, s']`` summed term by term from the definition."""
    n_states, n_lower, _ = lower.shape
    n_upper = next(len(link.probs) for link in links if link is not None)
    t = torch.zeros(n_states, n_upper, n_states, dtype=torch.float64)
    for s, u, s2 in itertools.product(range(n_states), range(n_upper), range(n_states)):
        if links[s] is None:
            continue
        total = sum(links[s].probs[u, a] * lower[s, a, s2] for a in range(n_lower))
        t[s, u, s2] = total + (links[s].none[u] if s2 == s else 0.0)
    return t


def test_chained_transitions_match_the_brute_force_sum_and_rows_sum_to_one():
    g = torch.Generator().manual_seed(0)
    link, lower = random_link(g, 4, 3), random_lower(g, 5, 3)
    t = chain(link, lower)
    torch.testing.assert_close(t, brute_force([link] * 5, lower), rtol=0, atol=1e-15)
    torch.testing.assert_close(t.sum(-1), torch.ones(5, 4, dtype=torch.float64))


def test_a_link_per_state_as_a_list_or_a_function_and_none_for_no_actions():
    g = torch.Generator().manual_seed(1)
    lower = random_lower(g, 4, 3)
    offered = torch.tensor([True, False, True])
    links = [random_link(g, 3, 3, offered), None, random_link(g, 3, 3), random_link(g, 3, 3)]
    t = chain(links, lower)
    torch.testing.assert_close(t, brute_force(links, lower), rtol=0, atol=1e-15)
    assert torch.equal(chain(lambda s: links[s], lower), t)
    sums = t.sum(-1)
    assert torch.equal(sums[1], torch.zeros(3, dtype=torch.float64))  # no link: no actions
    assert torch.equal(sums[0, 1], torch.tensor(0.0, dtype=torch.float64))  # not offered
    torch.testing.assert_close(sums[[0, 0, 2, 2, 2, 3, 3, 3], [0, 2, 0, 1, 2, 0, 1, 2]],
                               torch.ones(8, dtype=torch.float64))  # fmt: skip


def test_box_partition_chain_end_to_end_against_integration():
    """A 1-D output read as two lower actions; the chained row against quad by hand."""
    link = BoxPartition.from_boxes([("left", [(-INF, -1.0)]), ("right", [(1.0, INF)])],
                                   ["left", "right"])  # fmt: skip
    probs = link_probabilities(link, mixture([[1.0], [1.0]], [[[0.0]], [[1.5]]], [[[[1.0]]]] * 2))
    lower = torch.tensor([[[0.0, 1.0], [0.5, 0.5]], [[1.0, 0.0], [0.2, 0.8]]], dtype=torch.float64)
    t = chain(probs, lower)
    for u, mean in enumerate([0.0, 1.5]):
        left = integrate.quad(stats.norm(mean).pdf, -INF, -1.0)[0]
        right = integrate.quad(stats.norm(mean).pdf, 1.0, INF)[0]
        stay = 1 - left - right
        want0 = [stay + 0.5 * right, left + 0.5 * right]  # from state 0
        assert t[0, u].tolist() == pytest.approx(want0, abs=1e-10)


def test_padded_rows_and_shape_checks():
    g = torch.Generator().manual_seed(2)
    link = random_link(g, 2, 3).padded([4, 1], 5)
    assert torch.equal(link.probs.sum(-1) + link.none > 0, torch.tensor([0, 1, 0, 0, 1]).bool())
    with pytest.raises(ValueError, match="3 lower actions"):
        chain(link, random_lower(g, 2, 4))
    with pytest.raises(ValueError, match="one per state"):
        chain([link], random_lower(g, 2, 3))
