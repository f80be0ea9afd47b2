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
from scipy import integrate, stats

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
