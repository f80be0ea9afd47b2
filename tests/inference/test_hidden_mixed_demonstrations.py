"""EM over demonstrations that hide discrete state values beside continuous features and
training rows, against the brute-force joint.

The brute force enumerates every joint completion of a demonstration (each hidden
discrete state value at each time, each unlabelled step's action, each hidden discrete
outcome) and of each training row (its missing action and values) with
``itertools.product``, weights it by the product of the network's entries over every
step's row, the linear Gaussians' densities included (a hidden continuous outcome is a
leaf: its density integrates to 1, and its expected moments are its conditional mean's
plus its covariance), and accumulates the expected counts and moments written out by
hand.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch
from effect_networks.inference.fitting.sufficient_statistics import params_from_statistics
from effect_networks.inference.hidden_demonstrations import (
    MIN_VARIANCE,
    completed_steps,
    fit_hidden_states,
)
from effect_networks.inference.watching import fit_demonstrations
from effect_networks.models import Continuous, Discrete, EffectNetwork, random_params
from effect_networks.models.cpds import Counts, Moments
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.networks import drawn_demonstrations

ALPHA = 0.01  # fit_demonstrations' pseudo-count
STATES = ("off", "on")


def _mixed(outcome: bool = True) -> EffectNetwork:
    """Two discrete state features, ``x`` whose initial node reads ``a``, an outcome ``y``."""
    features = [Discrete("a", STATES), Discrete("b", STATES), Continuous("x", 1)]
    tables = ("initial.a", "initial.b", "action")  # not x: a table, not a softmax
    parents = {
        "end.a": tables,
        "end.b": tables,
        "initial.x": ("initial.a",),
        "end.x": ("initial.x", "initial.b", "action"),
    }
    if outcome:
        features.append(Continuous("y", 1, initial=False))
        parents["end.y"] = ("initial.b", "action")
    return EffectNetwork(tuple(features), ("push", "pull", "wait"), parents=parents)


def _index(net, site, row) -> tuple[int, ...]:
    """The flat parent configuration's index (row-major over the discrete parents)."""
    cpd = net.cpd(site)
    digits = [int(row[q]) for q in cpd.parents]
    return (int(np.ravel_multi_index(digits, cpd.card)),) if digits else (0,)


def _row_weight(net, params, row) -> float:
    """The row's density: its tables' entries times its shown continuous values' densities."""
    w = 1.0
    for spec in net.sites:
        cpd, value = net.cpd(spec.name), row.get(spec.name)
        if spec.discrete:
            w *= float(params[spec.name].probs[tuple(int(row[q]) for q in cpd.parents) + (value,)])
        elif value is not None:  # a hidden leaf integrates to 1
            mean, cov = _gaussian(net, params, spec.name, row)
            w *= math.exp(float(torch.distributions.MultivariateNormal(mean, cov).log_prob(value)))
    return w


def _gaussian(net, params, site, row):
    cpd, p = net.cpd(site), params[site]
    at = tuple(int(row[q]) for q in cpd.parents)
    weight = p.weight[at]
    mean = p.bias[at]
    if cpd.inputs:
        x = torch.cat([torch.as_tensor(row[q], dtype=torch.float64) for q in cpd.inputs])
        mean = weight @ x + mean
    return mean, p.covariance[at]


def _empty(net, params):
    out = {}
    for spec in net.sites:
        cpd = net.cpd(spec.name)
        if spec.discrete:
            out[spec.name] = Counts(torch.zeros_like(params[spec.name].probs))
        else:
            g, d, q = math.prod(cpd.card), spec.size, len(cpd.inputs) + 1

            def z(*shape):
                return torch.zeros(shape, dtype=torch.float64)

            out[spec.name] = Moments(z(g, q, q), z(g, q, d), z(g, d, d), z(g))
    return out


def _add(net, params, stats, row, w) -> None:
    """``w`` times the row's sums (a hidden leaf's by its conditional moments)."""
    for spec in net.sites:
        cpd = net.cpd(spec.name)
        if spec.discrete:
            at = tuple(int(row[q]) for q in cpd.parents) + (row[spec.name],)
            stats[spec.name].counts[at] += w
            continue
        g = _index(net, spec.name, row)[0]
        z = torch.cat(
            [
                *(torch.as_tensor(row[q], dtype=torch.float64) for q in cpd.inputs),
                torch.ones(1, dtype=torch.float64),
            ]
        )
        y = row.get(spec.name)
        if y is None:
            mean, cov = _gaussian(net, params, spec.name, row)
            yy = torch.outer(mean, mean) + cov
            y = mean
        else:
            y = torch.as_tensor(y, dtype=torch.float64)
            yy = torch.outer(y, y)
        m = stats[spec.name]
        m.zz[g] += w * torch.outer(z, z)
        m.zy[g] += w * torch.outer(z, y)
        m.yy[g] += w * yy
        m.n[g] += w


def _brute_force(net, params, demos, labels, rows=()):
    """Expected statistics by site and the summed log-likelihood, every completion enumerated.

    ``rows``: training rows ``{site: index, numbers or None}``.
    """
    stats = _empty(net, params)
    log_lik = 0.0
    for demo, marks in zip(demos, labels, strict=True):
        unknowns = []
        for t, state in enumerate(demo):
            for f in net.features:
                if isinstance(f, Discrete) and (f.initial or t) and state.get(f.name) is None:
                    unknowns.append(((t, f.name), f.cardinality))
        unknowns += [((t, "action"), 3) for t, m in enumerate(marks) if m is None]
        completions = []
        for values in itertools.product(*(range(k) for _, k in unknowns)):
            chosen = {key: v for (key, _), v in zip(unknowns, values, strict=True)}
            steps, w = [], 1.0
            for t in range(len(demo) - 1):
                row = {"action": chosen.get((t, "action"), marks[t])}
                for f in net.features:
                    for site, at in ((f"initial.{f.name}", t), (f"end.{f.name}", t + 1)):
                        if site == f"initial.{f.name}" and not f.initial:
                            continue
                        given = demo[at].get(f.name)
                        if isinstance(f, Discrete):
                            row[site] = (
                                chosen[(at, f.name)] if given is None else f.states.index(given)
                            )
                        else:
                            row[site] = (
                                None if given is None else torch.tensor(given, dtype=torch.float64)
                            )
                w *= _row_weight(net, params, row)
                steps.append(row)
            completions.append((steps, w))
        total = sum(w for _, w in completions)
        log_lik += math.log(total)
        for steps, w in completions:
            for row in steps:
                _add(net, params, stats, row, w / total)
    for given in rows:
        unknowns = [
            (s, net.site(s).size) for s, v in given.items() if net.site(s).discrete and v is None
        ]
        completions = []
        for values in itertools.product(*(range(k) for _, k in unknowns)):
            row = given | {s: v for (s, _), v in zip(unknowns, values, strict=True)}
            completions.append((row, _row_weight(net, params, row)))
        total = sum(w for _, w in completions)
        log_lik += math.log(total)
        for row, w in completions:
            _add(net, params, stats, row, w / total)
    return stats, log_lik


def _assert_statistics(net, got, want):
    for spec in net.sites:
        g, w = got.sites[spec.name], want[spec.name]
        if spec.discrete:
            torch.testing.assert_close(g.counts, w.counts, rtol=0, atol=1e-10)
        else:
            for name in ("zz", "zy", "yy", "n"):
                torch.testing.assert_close(
                    getattr(g, name), getattr(w, name), rtol=1e-10, atol=1e-10
                )


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.booleans(), st.integers(0, 2**16), st.data())
def test_one_e_step_is_the_brute_force_counts_and_moments(outcome, seed, data):
    """The expected counts and the linear Gaussians' weighted moments of every joint
    completion (hidden discrete states carried over time, unlabelled actions, hidden
    continuous outcomes), and the log-likelihood with the continuous densities."""
    net = _mixed(outcome)
    init = random_params(net, seed)
    demos, labels = drawn_demonstrations(net, np.random.default_rng(seed), data)
    want, log_lik = _brute_force(net, init, demos, labels)
    got = completed_steps(net, init, demos, labels)
    assert got.log_likelihood == pytest.approx(log_lik, rel=1e-10, abs=1e-10)
    _assert_statistics(net, got.statistics(net), want)


def _training_rows(net, g):
    """Training rows: an action, a state value or the outcome missing in some."""
    rows = []
    for k in range(4):
        row = {}
        for f in net.features:
            for site in ((f"initial.{f.name}",) if f.initial else ()) + (f"end.{f.name}",):
                if isinstance(f, Discrete):
                    row[site] = None if (k + len(site)) % 3 == 0 else int(g.integers(2))
                else:
                    row[site] = torch.tensor([float(g.normal(0.0, 2.0))], dtype=torch.float64)
        row["action"] = None if k % 2 else int(g.integers(3))
        rows.append(row)
    if "end.y" in rows[0]:
        rows[1]["end.y"] = None
    return rows


def _as_rows(net, rows):
    """The training rows by site, as fit_demonstrations takes them (labels, NaN)."""
    out = {}
    for site in rows[0]:
        if site == "action":
            out[site] = [None if r[site] is None else net.actions[r[site]] for r in rows]
        elif net.site(site).discrete:
            out[site] = [None if r[site] is None else STATES[r[site]] for r in rows]
        else:
            out[site] = np.array([[np.nan] if r[site] is None else r[site].tolist() for r in rows])
    return out


@pytest.mark.filterwarnings("ignore::effect_networks.inference.fitting.result.ConvergenceWarning")
@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 2**16), st.data())
def test_rows_beside_hidden_states_are_the_brute_force_objective_and_step(seed, data):
    """fit_demonstrations with rows= and hidden state values: its start's log-likelihood is
    the brute force over every completion of the demonstrations and the rows, and one EM
    step gives the closed form of their summed expected statistics."""
    net = _mixed()
    init = random_params(net, seed)
    g = np.random.default_rng(seed)
    demos, labels = drawn_demonstrations(net, g, data)
    demos[0][1]["a"] = None  # a hidden state value: the forward-backward's route
    rows = _training_rows(net, g)
    want, log_lik = _brute_force(net, init, demos, labels, rows)
    names = [[None if x is None else net.actions[x] for x in marks] for marks in labels]
    got = fit_demonstrations(
        net, demos, names, rows=_as_rows(net, rows), init=init, steps=1, tol=1e-300
    )
    assert got.log_likelihoods[0] == pytest.approx(log_lik, rel=1e-10, abs=1e-10)
    assert len(got.log_likelihoods) == 2, "from drawn tables, the step is taken"
    stats = completed_steps(net, init, demos, labels).statistics(net)  # for its structure only
    for site in stats.sites:
        stats.sites[site] = want[site]
    cpds = params_from_statistics(net, stats, ALPHA, MIN_VARIANCE)
    for site, cpd in cpds.items():
        for name in ("probs", "weight", "bias", "scale_tril"):
            if hasattr(cpd, name):
                torch.testing.assert_close(
                    getattr(got.params[site], name), getattr(cpd, name), rtol=1e-8, atol=1e-9
                )


@pytest.mark.filterwarnings("ignore::effect_networks.inference.fitting.result.ConvergenceWarning")
def test_the_log_likelihood_never_falls_with_continuous_features_and_rows():
    net = _mixed()
    g = np.random.default_rng(0)
    demos = []
    for _ in range(10):
        demo = []
        for t in range(4):
            state = {f: (None if g.random() < 0.3 else STATES[g.integers(2)]) for f in "ab"}
            state["x"] = [float(g.normal())]
            if t:
                state["y"] = None if g.random() < 0.3 else [float(g.normal(1.0))]
            demo.append(state)
        demos.append(demo)
    labels = [[None, None, 1] for _ in demos]
    rows = _training_rows(net, g)
    got = fit_demonstrations(
        net, demos, [[None, None, "pull"]] * 10, rows=_as_rows(net, rows), steps=40, tol=1e-300
    )
    curve = got.log_likelihoods
    assert len(curve) > 5
    assert all(b >= a for a, b in zip(curve, curve[1:], strict=False))
    # the returned tables score the last value: the demonstrations' and the rows' brute force
    _, want = _brute_force(net, got.params, demos, labels, rows)
    assert want == pytest.approx(curve[-1], rel=1e-10)


def test_a_hidden_continuous_state_value_is_refused_naming_it():
    net = _mixed(outcome=False)
    demo = [{"a": None, "b": "on", "x": [0.0]}, {"a": "on", "b": "off", "x": None}]
    with pytest.raises(ValueError, match=r"demonstration 0, time 1 hides continuous 'x'"):
        fit_demonstrations(net, [demo])
    with pytest.raises(ValueError, match="observed at every time"):
        fit_hidden_states(net, [demo], [[None]], init=random_params(net, 0))
