"""Priors: Dirichlet tables against pgmpy's BayesianEstimator, the NIW mode by hand, EM."""

import numpy as np
import pytest
import torch
from effect_networks.inference import K2, BDeu, NormalInverseWishart, fit, simulate
from effect_networks.models import Continuous, Discrete, EffectNetwork, Parameter, random_params
from effect_networks.models.interop import to_pgmpy
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.networks import declared_networks

# closed form throughout: a Gaussian under the action and a parameter's clusters
THROW = EffectNetwork(
    (Discrete("grip", ("loose", "firm")), Continuous("hit", 2, initial=False)),
    ("throw", "drop"),
    (Parameter("target", (0.0, 0.0), (1.0, 1.0), (2, 3), ("throw",), "hit"),),
)
SLIDE = EffectNetwork((Continuous("pos", 2),), ("push", "wait"))


def labels(net, site):
    """A discrete site's state labels, in its declared order."""
    return net.decode(site, torch.arange(net.site(site).size))


def pgmpy_tables(net, params, rows, **options):
    """Every site's table as pgmpy's BayesianEstimator estimates it, in our axis order."""
    pd = pytest.importorskip("pandas")
    pytest.importorskip("pgmpy")
    from pgmpy.estimators import BayesianEstimator

    model, _ = to_pgmpy(net, params)
    names = {s.name: labels(net, s.name) for s in net.sites}
    frame = pd.DataFrame({k: list(v) for k, v in rows.items()})
    estimator = BayesianEstimator(model, frame, state_names=names)
    tables = {}
    for spec in net.sites:
        cpd = net.cpd(spec.name)
        ours = list(cpd.parents)
        theirs = sorted(ours)  # pgmpy orders a node's parents by name
        extra = dict(options.get(spec.name, options.get("*", {})))
        if "pseudo_counts" in extra and not np.isscalar(extra["pseudo_counts"]):
            counts = np.asarray(extra["pseudo_counts"])  # ours: (P..., K)
            moved = np.moveaxis(counts, [ours.index(p) for p in theirs], range(len(theirs)))
            extra["pseudo_counts"] = moved.reshape(-1, cpd.size).T
        found = estimator.estimate_cpd(spec.name, **extra)
        values = found.get_values().T.reshape(*(net.cpd(p).size for p in theirs), cpd.size)
        back = np.moveaxis(values, range(len(theirs)), [ours.index(p) for p in theirs])
        tables[spec.name] = torch.as_tensor(np.ascontiguousarray(back))
    return tables


@settings(max_examples=15, deadline=None)
@given(
    net=declared_networks(),
    seed=st.integers(0, 10_000),
    n=st.integers(1, 60),
    kind=st.sampled_from(["dirichlet", "number", "BDeu", "K2"]),
    data=st.data(),
)
@pytest.mark.filterwarnings("ignore::FutureWarning")  # pgmpy moving its estimators
def test_tables_are_pgmpy_bayesian_estimates(net, seed, n, kind, data):
    rows = simulate(net, random_params(net, seed), n, seed=seed)
    sites = [s.name for s in net.sites]
    if kind == "dirichlet":
        rng = np.random.default_rng(seed)
        shapes = {s: (*net.cpd(s).card, net.cpd(s).size) for s in sites}
        alpha = {s: rng.uniform(0.1, 5.0, shapes[s]) for s in sites}
        prior = alpha
        options = {s: {"prior_type": "dirichlet", "pseudo_counts": alpha[s]} for s in sites}
    elif kind == "number":
        prior = data.draw(st.floats(0.05, 10.0))
        options = {"*": {"prior_type": "dirichlet", "pseudo_counts": prior}}
    elif kind == "BDeu":
        ess = data.draw(st.floats(0.5, 20.0))
        prior = BDeu(ess)
        options = {"*": {"prior_type": "BDeu", "equivalent_sample_size": ess}}
    else:
        prior = K2()
        options = {"*": {"prior_type": "K2"}}
    params = fit(net, rows, prior=prior).params
    theirs = pgmpy_tables(net, params, rows, **options)
    for site in sites:
        torch.testing.assert_close(params[site].probs, theirs[site], atol=1e-12, rtol=0)


def counts_by_hand(net, rows, site):
    """``(P..., K)`` counts of ``site`` per parent configuration, by a loop over rows."""
    cpd = net.cpd(site)
    enc = net.encode({q: rows[q] for q in (*cpd.parents, site)})
    out = np.zeros((*cpd.card, cpd.size))
    for i in range(enc.n_rows):
        out[tuple(int(enc[p][i]) for p in (*cpd.parents, site))] += 1
    return out


@settings(max_examples=10, deadline=None)
@given(net=declared_networks(), seed=st.integers(0, 10_000), n=st.integers(0, 40))
def test_map_tables_are_the_dirichlet_mode(net, seed, n):
    rows = simulate(net, random_params(net, seed), max(n, 1), seed=seed)
    rng = np.random.default_rng(seed)
    alpha = {
        s.name: rng.uniform(1.0, 4.0, (*net.cpd(s.name).card, net.cpd(s.name).size))
        for s in net.sites
    }
    params = fit(net, rows, prior=alpha, estimate="map").params
    for s in net.sites:
        shifted = counts_by_hand(net, rows, s.name) + alpha[s.name] - 1
        mode = shifted / shifted.sum(-1, keepdims=True)
        torch.testing.assert_close(params[s.name].probs, torch.as_tensor(mode), atol=1e-12, rtol=0)
    k2 = fit(net, rows, prior=K2(), estimate="map").params  # K2's mode: maximum likelihood
    ml = fit(net, rows, pseudo_count=0).params
    for s in net.sites:
        torch.testing.assert_close(k2[s.name].probs, ml[s.name].probs, atol=1e-12, rtol=0)


def niw_by_hand(x, y, groups, k, precision, dof, scale):
    """The NIW joint mode per group, in numpy: ``(weight, bias, covariance)`` per group."""
    d, q = y.shape[1], x.shape[1] + 1
    out = []
    for g in range(k):
        z = np.hstack([x[groups == g], np.ones((int((groups == g).sum()), 1))])
        yg = y[groups == g]
        lam = z.T @ z + precision * np.eye(q)
        b = np.linalg.solve(lam, z.T @ yg)
        s = scale + yg.T @ yg - b.T @ lam @ b
        out.append((b[:-1].T, b[-1], s / (len(yg) + dof + d + 1 + q)))
    return out


@settings(max_examples=15, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    n=st.integers(0, 30),
    precision=st.floats(0.01, 10.0),
    dof=st.floats(0.0, 5.0),
    diagonal=st.floats(0.01, 2.0),
)
def test_linear_gaussian_map_is_the_niw_mode_by_hand(seed, n, precision, dof, diagonal):
    rows = simulate(SLIDE, random_params(SLIDE, seed), max(n, 1), seed=seed)
    scale = np.array([[diagonal, 0.1 * diagonal], [0.1 * diagonal, 2 * diagonal]])
    prior = {"end.pos": NormalInverseWishart(precision, dof, scale)}
    params = fit(SLIDE, rows, prior=prior, min_variance=0.0).params
    groups = np.array([SLIDE.actions.index(a) for a in rows["action"]])
    x, y = np.asarray(rows["initial.pos"]), np.asarray(rows["end.pos"])
    fitted = params["end.pos"]
    for g, (w, b, cov) in enumerate(niw_by_hand(x, y, groups, 2, precision, dof, scale)):
        torch.testing.assert_close(fitted.weight[g], torch.as_tensor(w), atol=1e-10, rtol=1e-10)
        torch.testing.assert_close(fitted.bias[g], torch.as_tensor(b), atol=1e-10, rtol=1e-10)
        torch.testing.assert_close(
            fitted.covariance[g], torch.as_tensor(cov), atol=1e-10, rtol=1e-10
        )


def test_an_unseen_configuration_gets_the_prior_mode():
    rows = simulate(SLIDE, random_params(SLIDE, 0), 20, seed=0)
    rows = {
        k: [v for v, a in zip(rows[k], rows["action"], strict=True) if a == "push"] for k in rows
    }
    prior = NormalInverseWishart(precision=2.0, dof=3.0, scale=0.5)
    fitted = fit(SLIDE, rows, prior={"end.pos": prior}).params["end.pos"]
    assert torch.equal(fitted.weight[1], torch.zeros(2, 2, dtype=torch.float64))
    assert torch.equal(fitted.bias[1], torch.zeros(2, dtype=torch.float64))
    expected = 0.5 * torch.eye(2, dtype=torch.float64) / (3.0 + 2 + 1 + 3)
    torch.testing.assert_close(fitted.covariance[1], expected, atol=1e-15, rtol=1e-12)


GAPPY = EffectNetwork(
    (Discrete("a", (0, 1)), Discrete("b", ("u", "v", "w")), Continuous("c", 1)),
    ("push", "wait"),
    parents={
        "end.a": ("initial.a", "action"),
        "end.b": ("initial.b", "action"),
        "end.c": ("initial.c", "action"),
    },
)


def test_priors_are_honoured_in_em_over_gaps():
    """Only end.b has gaps: end.a's and end.c's families are given in every row, so their
    expected statistics are their counts and sums, and EM's answer for them is the prior's
    closed form on all rows."""
    rows = simulate(GAPPY, random_params(GAPPY, 3), 300, seed=3)
    gappy = dict(rows)
    b = np.array(rows["end.b"], dtype=object)
    b[::7] = None
    gappy["end.b"] = b
    alpha = np.arange(1.0, 1.0 + 2 * 2 * 2).reshape(2, 2, 2)
    prior = {"end.a": alpha, "end.c": NormalInverseWishart(50.0, 2.0, 0.1)}
    em = fit(GAPPY, gappy, prior=prior)
    assert len(em.losses) > 1  # EM ran
    complete = fit(GAPPY, rows, prior=prior).params
    counts = counts_by_hand(GAPPY, rows, "end.a") + alpha
    torch.testing.assert_close(
        em.params["end.a"].probs,
        torch.as_tensor(counts / counts.sum(-1, keepdims=True)),
        atol=1e-12,
        rtol=0,
    )
    for name in ("weight", "bias", "scale_tril"):
        ours, theirs = getattr(em.params["end.c"], name), getattr(complete["end.c"], name)
        torch.testing.assert_close(ours, theirs, atol=1e-12, rtol=1e-12)
    plain = fit(GAPPY, rows).params["end.c"]
    assert not torch.allclose(em.params["end.c"].weight, plain.weight, atol=1e-6)


@pytest.mark.parametrize(
    ("prior", "match"),
    [
        ({"end.nothing": 1.0}, "not sites of this network"),
        ({"end.grip": np.ones((2, 2))}, r"shape \(2, 2\).*\(2, 2, 2\)"),
        ({"end.grip": -np.ones((2, 2, 2))}, "finite and >= 0"),
        ({"end.grip": NormalInverseWishart()}, "is for a linear Gaussian"),
        ({"end.hit": BDeu(1.0)}, "its prior is a number or a NormalInverseWishart"),
        (
            {"end.hit": NormalInverseWishart(scale=np.ones((3, 3)))},
            r"expected a number or \(2, 2\)",
        ),
        ({"end.hit": NormalInverseWishart(scale=-1.0)}, "positive semi-definite"),
        ({"end.hit": NormalInverseWishart(precision=-1.0)}, "precision must be finite and >= 0"),
        (BDeu(-1.0), "equivalent_sample_size must be a finite number >= 0"),
        ("BDeu", "prior must be a number, BDeu"),
    ],
)
def test_bad_priors_are_refused_naming_the_site(prior, match):
    rows = simulate(THROW, random_params(THROW, 0), 20, seed=0)
    with pytest.raises(ValueError, match=match):
        fit(THROW, rows, prior=prior)


def test_map_refuses_pseudo_counts_below_one_and_unknown_estimates():
    rows = simulate(THROW, random_params(THROW, 0), 20, seed=0)
    with pytest.raises(ValueError, match=r"MAP table needs every pseudo-count >= 1"):
        fit(THROW, rows, prior=BDeu(1.0), estimate="map")
    with pytest.raises(ValueError, match="estimate must be one of"):
        fit(THROW, rows, estimate="mode")


def test_a_number_is_the_pseudo_count():
    rows = simulate(THROW, random_params(THROW, 0), 50, seed=0)
    a, b = fit(THROW, rows, prior=0.7).params, fit(THROW, rows, pseudo_count=0.7).params
    assert a.pseudo_count == b.pseudo_count == 0.7
    for site in a.cpds:
        for x, y in zip(vars(a[site]).values(), vars(b[site]).values(), strict=False):
            if isinstance(x, torch.Tensor):
                assert torch.equal(x, y)
