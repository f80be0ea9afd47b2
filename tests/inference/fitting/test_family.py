"""Family scores: each end site's term of the fitted network's log-likelihood, in closed
form, and its BIC / AIC / BDeu against pgmpy and numpy."""

import logging
import math

import numpy as np
import pandas as pd
import pytest
from effect_networks.inference import fit, log_likelihood, simulate
from effect_networks.inference.fitting import family_scores
from effect_networks.models import Continuous, Discrete, EffectNetwork, Parameter, random_params
from effect_networks.models.cpds import TableCPD
from effect_networks.models.model import effect_model
from hypothesis import given, settings
from hypothesis import strategies as st
from pyro import poutine

logging.getLogger("pgmpy").setLevel(logging.ERROR)

FEATURES = (
    Discrete("shape", ("ball", "box", "cylinder")),
    Continuous("size", 1),
    Discrete("moved", (False, True)),
    Continuous("velocity", 2),
)
ACTIONS = ("grasp", "tap", "touch")
FORCE = Parameter("force", (0.0,), (1.0,), (3,), ("tap",), ("velocity",))
HIT = Parameter("hit", (0.0,), (1.0,), (2,), ("touch",), ("moved",))

#: Parent sets of the end sites each example may draw (the action is required where a
#: parameter acts: the velocity's and the moved's families always hold it).
MOVED = [("action",), ("initial.shape", "action"), ("initial.size", "action"),
         ("initial.shape", "initial.size", "action")]  # fmt: skip
VELOCITY = [("action",), ("initial.size", "action"), ("initial.shape", "action", "end.moved"),
            ("initial.shape", "initial.size", "action", "end.moved")]  # fmt: skip
SHAPE = [(), ("initial.shape",), ("initial.shape", "initial.size", "action")]
SIZE = [(), ("initial.size",), ("initial.shape", "initial.size", "end.moved")]


def traced_end_logliks(net, params, rows) -> dict[str, float]:
    """Each end site's log-likelihood term in the Pyro model itself (a traced run with
    every site observed)."""
    trace = poutine.trace(effect_model).get_trace(net, params, net.encode(rows))
    trace.compute_log_prob()
    return {
        s.name: float(trace.nodes[s.name]["log_prob_sum"]) for s in net.sites if s.role == "end"
    }


@settings(max_examples=8, deadline=None)
@given(
    moved=st.sampled_from(MOVED),
    velocity=st.sampled_from(VELOCITY),
    shape=st.sampled_from(SHAPE),
    size=st.sampled_from(SIZE),
    parameters=st.sampled_from([(), (FORCE,), (FORCE, HIT)]),
    seed=st.integers(0, 1000),
)
def test_family_logliks_are_the_fitted_networks_terms(
    moved, velocity, shape, size, parameters, seed
):
    """With ``pseudo_count=0`` the fit is the maximum-likelihood one; each family's
    log-likelihood is the end site's term of the traced model's log-likelihood under it
    (tables, softmax and linear Gaussians; parameters' sites in the families)."""
    parents = {"end.moved": moved, "end.velocity": velocity, "end.shape": shape, "end.size": size}
    net = EffectNetwork(FEATURES, ACTIONS, parameters, parents=parents)
    rows = simulate(net, random_params(net, seed), 1500, seed=seed)
    scores = family_scores(net, rows, score="loglik")
    traced = traced_end_logliks(net, fit(net, rows, pseudo_count=0.0).params, rows)
    assert list(scores) == list(traced)
    for site in scores:
        # the softmax optimum to its Newton tolerance; the rest to float64 sums
        assert scores[site] == pytest.approx(traced[site], rel=1e-9, abs=1e-6), site


def numpy_gaussian_loglik(y, x, groups):
    """Per group, least squares of y on [x, 1] and the MLE residual covariance: the
    Gaussian log-likelihood, in numpy."""
    total = 0.0
    for g in np.unique(groups):
        yg = y[groups == g]
        zg = np.column_stack([x[groups == g], np.ones(len(yg))])
        beta, *_ = np.linalg.lstsq(zg, yg, rcond=None)
        resid = yg - zg @ beta
        cov = resid.T @ resid / len(yg)
        d = y.shape[1]
        _, logdet = np.linalg.slogdet(cov)
        total += -0.5 * len(yg) * (d * math.log(2 * math.pi) + logdet + d)
    return total


def test_gaussian_family_is_the_numpy_least_squares_and_bic_counts_its_numbers():
    rng = np.random.default_rng(3)
    n = 800
    shape = rng.integers(0, 3, n)
    size = rng.normal(2.0, 0.5, (n, 1))
    moved = rng.integers(0, 2, n)
    action = rng.integers(0, 3, n)
    velocity = np.column_stack([size[:, 0] * (1 + shape), -size[:, 0] + moved])
    velocity = velocity + rng.normal(0, 0.3, (n, 2)) @ np.array([[1.0, 0.4], [0.0, 1.0]])
    net = EffectNetwork(
        FEATURES,
        ACTIONS,
        parents={"end.velocity": ("initial.shape", "initial.size", "end.moved")},
    )
    labels = FEATURES[0].states
    rows = {
        "initial.shape": [labels[i] for i in shape],
        "initial.size": size,
        "initial.moved": rng.integers(0, 2, n).astype(bool),
        "initial.velocity": rng.normal(size=(n, 2)),
        "action": [ACTIONS[a] for a in action],
        "end.shape": [labels[i] for i in shape],
        "end.size": size,
        "end.moved": moved.astype(bool),
        "end.velocity": velocity,
    }
    loglik = family_scores(net, rows, score="loglik")["end.velocity"]
    expected = numpy_gaussian_loglik(velocity, size, shape * 2 + moved)
    assert loglik == pytest.approx(expected, rel=1e-10)
    # per configuration (3 shapes x 2 moved): 2 x (1 slope + 1 offset) + 3 covariance
    free = 6 * (2 * 2 + 3)
    bic = family_scores(net, rows, score="bic")["end.velocity"]
    assert bic == pytest.approx(expected - 0.5 * math.log(n) * free, rel=1e-10)
    aic = family_scores(net, rows, score="aic")["end.velocity"]
    assert aic == pytest.approx(expected - free, rel=1e-10)


def discrete_rows(seed: int, n: int):
    """A discrete network's rows; ``end.b`` never shows its third state (pgmpy must be
    told the declared states)."""
    rng = np.random.default_rng(seed)
    a, b = rng.integers(0, 3, n), rng.integers(0, 2, n)
    action = rng.integers(0, 2, n)
    end_a = np.where(rng.random(n) < 0.8, (a + action) % 3, rng.integers(0, 3, n))
    end_b = np.where(rng.random(n) < 0.7, end_a % 2, b)
    return {
        "initial.a": a,
        "initial.b": b,
        "action": np.array(["push", "pull"])[action],
        "end.a": end_a,
        "end.b": end_b,
    }


DISCRETE = (Discrete("a", (0, 1, 2)), Discrete("b", (0, 1, 2)))


def pgmpy_local(score_class, rows, net, site, **kwargs):
    frame = pd.DataFrame({k: np.asarray(v).astype(str) for k, v in rows.items()})
    states = {
        "initial.a": ["0", "1", "2"],
        "initial.b": ["0", "1", "2"],
        "end.a": ["0", "1", "2"],
        "end.b": ["0", "1", "2"],
        "action": ["push", "pull"],
    }
    scorer = score_class(frame, state_names=states, **kwargs)
    cpd = net.cpd(site)
    return scorer.local_score(site, tuple(cpd.parents))


@settings(max_examples=6, deadline=None)
@given(
    seed=st.integers(0, 1000),
    parents=st.sampled_from(
        [(), ("initial.a",), ("initial.a", "action"), ("initial.b", "end.a", "action")]
    ),
)
def test_discrete_family_scores_equal_pgmpys_bic_and_bdeu(seed, parents):
    from pgmpy.structure_score import BIC, BDeu, LogLikelihood

    rows = discrete_rows(seed, 300)
    end_a = tuple(q for q in parents if q != "end.a")
    net = EffectNetwork(DISCRETE, ("push", "pull"), parents={"end.b": parents, "end.a": end_a})
    for site, score, cls, kwargs in (
        ("end.b", "loglik", LogLikelihood, {}),
        ("end.b", "bic", BIC, {}),
        ("end.a", "bic", BIC, {}),
        # pgmpy's BDeu drops the cells of a child state no row shows (its counts table
        # has no row for it) and still subtracts their prior: compared where every
        # state of the child is seen
        ("end.a", "bdeu", BDeu, {"equivalent_sample_size": 5.0}),
    ):
        ours = family_scores(net, rows, score=score, ess=5.0)[site]
        theirs = pgmpy_local(cls, rows, net, site, **kwargs)
        assert ours == pytest.approx(theirs, rel=1e-9), (site, score)


def test_scores_refuse_what_they_cannot_score():
    rows = discrete_rows(0, 50)
    net = EffectNetwork(DISCRETE, ("push", "pull"))
    with pytest.raises(ValueError, match="score must be one of"):
        family_scores(net, rows, score="k2")
    mixed = EffectNetwork(FEATURES, ACTIONS)
    with pytest.raises(ValueError, match="bdeu.*continuous sites.*initial.size"):
        family_scores(mixed, {}, score="bdeu")
    with pytest.raises(ValueError, match="ess"):
        family_scores(net, rows, score="bdeu", ess=0.0)
    gappy = dict(rows, **{"end.b": [None, *rows["end.b"][1:]]})
    with pytest.raises(ValueError, match=r"complete rows.*\['end.b'\]"):
        family_scores(net, gappy)

    class Counted(TableCPD):  # a kind of the user's: not what the scores compute
        name = "counted"

    own = EffectNetwork(DISCRETE, ("push", "pull"), kinds={"end.a": Counted})
    with pytest.raises(ValueError, match="'end.a' is declared of kind 'counted'"):
        family_scores(own, rows)


def test_bic_counts_reachable_configurations_and_free_weights_of_a_parameter():
    """``end.velocity`` with the action and the force: 3 actions x 3 force cells, of which
    tap reaches 3 and grasp and touch cell 0 only (5 configurations); each has 2 x (1
    slope + 1 offset) + 3 covariance numbers, less the 2 force weights fixed at zero
    where the action does not use the force: 3 x 7 + 2 x 5 = 31."""
    net = EffectNetwork(FEATURES, ACTIONS, (FORCE,), parents={"end.velocity": ("action",)})
    rows = simulate(net, random_params(net, 0), 400, seed=0)
    loglik = family_scores(net, rows, score="loglik")["end.velocity"]
    bic = family_scores(net, rows, score="bic")["end.velocity"]
    assert bic == pytest.approx(loglik - 0.5 * math.log(400) * 31, rel=1e-12)


@settings(max_examples=4, deadline=None)
@given(
    declarations=st.lists(
        st.tuples(st.sampled_from(MOVED), st.sampled_from(VELOCITY), st.sampled_from(SIZE)),
        min_size=3,
        max_size=3,
    ),
    seed=st.integers(0, 1000),
)
def test_family_bics_add_up_to_the_networks_bic_score(declarations, seed):
    """``log_likelihood(...).bic_score`` (pgmpy's sign: the whole network's log-likelihood
    less ``ln n / 2`` per free parameter, by its own count) less the end sites' family
    BICs is the roots' and the parameter's share: the same for every declaration of the
    same features, actions and parameter."""
    truth = EffectNetwork(FEATURES, ACTIONS, (FORCE,))
    rows = simulate(truth, random_params(truth, seed), 1500, seed=seed)
    shares = []
    for moved, velocity, size in declarations:
        parents = {"end.moved": moved, "end.velocity": velocity, "end.size": size}
        net = EffectNetwork(FEATURES, ACTIONS, (FORCE,), parents=parents)
        whole = log_likelihood(net, fit(net, rows, pseudo_count=0.0).params, rows).bic_score
        shares.append(whole - sum(family_scores(net, rows).values()))
    assert shares == pytest.approx([shares[0]] * 3, rel=1e-9, abs=1e-6)


def test_a_data_frame_scores_as_its_rows():
    from effect_networks.models.frames import to_frame

    net = EffectNetwork(FEATURES, ACTIONS, (FORCE,))
    rows = simulate(net, random_params(net, 2), 300, seed=2)
    assert family_scores(net, to_frame(net, rows)) == family_scores(net, rows)
