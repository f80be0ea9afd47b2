"""Every query against a brute-force oracle, on random networks with a parameter.

Hypothesis draws small networks (one or two discrete features, maybe a continuous one,
two or three actions) with a parameter that some actions do not use, random parameters
whose cluster Gaussians may spill far out of their cells (and configurations of the
actions not using the parameter on unused clusters marked unseen, as a fit leaves them),
and evidence from ordinary values to large magnitudes. Each query's answer is compared
with an oracle written here from the parameters alone: the joint enumerated over the
discrete sites with ``itertools.product``, each site's density read off its container,
and an unknown parameter integrated out numerically (Gauss-Legendre quadrature around
the integrand's mode, found from three evaluations of its logarithm, which is quadratic
in the value). The model the oracle writes is the README's: the cluster given the action,
the value given the cluster (untruncated), a value given without its cluster observed in
its cell, an action not using the parameter on cluster 0 with probability one.

Every answer is the oracle's, every distribution sums to 1 within 1e-12, or the query
raises ``ValueError``.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from inference import (
    imitation_check,
    infer_action,
    infer_parameter,
    parameter_for_effect,
    predict,
)
from inference.compiled import compile_parameter_query
from inference.plausibility import IMPLAUSIBLE_BELOW
from models import Continuous, Discrete, EffectNetwork, Parameter, random_params
from models.cpds.linear_gaussian import LinearGaussian
from models.cpds.softmax import Softmax
from models.cpds.table import Table
from models.params import NetworkParams

#: The largest magnitude of a continuous evidence value the tests draw, to be widened
#: towards the accepted limit (``inference.fit.MAX_MAGNITUDE``, 1e150) once the queries
#: normalise each row in log space per configuration at any magnitude.
EVIDENCE_MAGNITUDE = 1e3

#: How far a returned distribution's sum may be from 1. The target is 1e-12 at every
#: accepted magnitude; normalising by ``exp(log p - log sum p)`` leaves the rounding of
#: log-weights of magnitude ~1e4 (a value far from a narrow cluster), about 1e-12 off,
#: so this is tightened to 1e-12 with the log-space normalisation per configuration.
SUM_TOL = 1e-9

PROB_TOL = 1e-8  # absolute, on probabilities
LOG_RTOL = 1e-9  # relative, on log-densities (and absolute below magnitude 1)


# ---------------------------------------------------------------------------- networks
@st.composite
def networks(draw, inverse: bool = False):
    """A random network; ``inverse``: the parameter acts on the continuous feature."""
    features = [Discrete("f0", tuple(range(draw(st.integers(2, 3)))))]
    if draw(st.booleans()):
        features.append(Discrete("f1", ("no", "yes")))
    continuous = inverse or draw(st.booleans())
    if continuous:
        features.append(Continuous("pos", 1))
    actions = tuple(f"a{i}" for i in range(draw(st.integers(2, 3))))
    using = draw(st.sets(st.sampled_from(actions), min_size=1, max_size=len(actions) - 1))
    choices = [("pos",), ("pos", "f0"), ("f0",)] if continuous else [("f0",)]
    affects = draw(st.sampled_from(choices[:2] if inverse else choices))
    bins = draw(st.integers(2, 3))
    parameter = Parameter(
        "force",
        0.0,
        float(bins),
        bins,
        tuple(sorted(using)),
        affects[0] if len(affects) == 1 else affects,
    )
    return EffectNetwork(tuple(features), actions, (parameter,))


def spilled(net: EffectNetwork, params: NetworkParams, spread: float) -> NetworkParams:
    """``params`` with the cluster Gaussians ``spread`` times wider (random_params puts
    them inside their cells) and, for actions not using the parameter, the end sites'
    configurations on clusters other than 0 marked unseen."""
    m = net.mixtures[0]
    cpds = dict(params.cpds)
    prior = cpds[m.value.site]
    cpds[m.value.site] = replace(prior, scale_tril=prior.scale_tril * spread)
    for site in m.affected:
        cpd = net.cpd(site)
        a, c = cpd.parents.index(m.action), cpd.parents.index(m.cluster.site)
        n = cpds[site].n.clone()
        for action in range(len(net.actions)):
            if not bool(m.uses[action]):
                index = [slice(None)] * n.dim()
                index[a], index[c] = action, slice(1, None)
                n[tuple(index)] = 0.0
        cpds[site] = replace(cpds[site], n=n)
    return NetworkParams(cpds, params.pseudo_count)


# ---------------------------------------------------------------------------- oracle
class Oracle:
    """The model's joint, written from the parameters, for one evidence row.

    ``evidence``: site -> state index (discrete) or float (continuous, dimension 1);
    ``param.force`` absent means unknown.
    """

    def __init__(self, net: EffectNetwork, params: NetworkParams):
        self.net, self.params = net, params
        self.m = net.mixtures[0]
        self.p = self.m.parameter

    def uses(self, action: int) -> bool:
        return bool(self.m.uses[action])

    def log_site(self, site: str, values: dict) -> float:
        """log-density of ``site``'s value given its parents in ``values``."""
        cpd, theta = self.net.cpd(site), self.params[site]
        index = tuple(values[s] for s in cpd.parents)
        inputs = []
        for s in cpd.inputs:  # an action not using the parameter ignores its value
            if s == self.m.value.site and not self.uses(values[self.m.action]):
                inputs.append(0.0)
            else:
                inputs.append(values[s])
        x = np.array(inputs, dtype=float)
        if isinstance(theta, Table):
            return float(np.log(theta.probs[(*index, values[site])].item()))
        if isinstance(theta, Softmax):
            logits = theta.weight[index].numpy() @ x + theta.bias[index].numpy()
            top = logits.max()
            return float(logits[values[site]] - top - np.log(np.exp(logits - top).sum()))
        assert isinstance(theta, LinearGaussian)
        mean = float(theta.weight[index].numpy()[0] @ x + theta.bias[index].numpy()[0])
        var = float(theta.covariance[index].numpy()[0, 0])
        return -0.5 * (values[site] - mean) ** 2 / var - 0.5 * math.log(2 * math.pi * var)

    def gaussian_of(self, site: str, values: dict) -> tuple[float, float]:
        """Mean and variance of a continuous site given ``values`` of its parents."""
        cpd, theta = self.net.cpd(site), self.params[site]
        index = tuple(values[s] for s in cpd.parents)
        x = np.array(
            [
                0.0
                if s == self.m.value.site and not self.uses(values[self.m.action])
                else values[s]
                for s in cpd.inputs
            ]
        )
        mean = float(theta.weight[index].numpy()[0] @ x + theta.bias[index].numpy()[0])
        return mean, float(theta.covariance[index].numpy()[0, 0])

    def latent_sites(self, evidence: dict, targets=()) -> list[str]:
        """The discrete sites to enumerate: initial ones not given, the action if not
        given, the cluster, and the discrete end sites asked for."""
        sites = []
        for spec in self.net.sites:
            if not spec.discrete or spec.name in evidence:
                continue
            if spec.role == "end" and spec.name not in targets:
                continue  # summing an unobserved end site out gives 1
            sites.append(spec.name)
        return sites

    def configurations(self, evidence: dict, targets=()):
        """Every assignment of the latent discrete sites, with ``evidence``; the cluster
        fixed where the value is given (its cell) or the action does not use it."""
        latent = self.latent_sites(evidence, targets)
        sizes = [self.net.site(s).size for s in latent]
        for states in itertools.product(*[range(k) for k in sizes]):
            values = dict(evidence) | dict(zip(latent, states, strict=True))
            c = values[self.m.cluster.site]
            if not self.uses(values[self.m.action]):
                if c != 0:
                    continue  # probability zero: cluster 0 with probability one
            elif self.m.value.site in evidence:
                cell = int(self.p.cluster_of(torch.tensor([[evidence[self.m.value.site]]]))[0])
                if c != cell:
                    continue  # a value given alone is observed in its cell
            yield values

    def log_weight(self, values: dict) -> float:
        """log p(every site in ``values``), the parameter integrated out if absent."""
        total = 0.0
        theta_site, y_site = self.m.value.site, "end.pos"
        integrate = (
            theta_site not in values
            and self.uses(values[self.m.action])
            and y_site in values
            and y_site in self.m.continuous
        )
        for spec in self.net.sites:
            s = spec.name
            if s not in values:
                continue
            if s == theta_site and not self.uses(values[self.m.action]):
                continue  # density left out
            if integrate and s == y_site:
                continue
            total += self.log_site(s, values)
        if integrate:
            total += self.log_integral(values)
        return total

    def log_integrand(self, values: dict, t: float) -> float:
        v = values | {self.m.value.site: t}
        return self.log_site(self.m.value.site, v) + self.log_site("end.pos", v)

    def quadrature(self, values: dict):
        """Nodes and log-weights over the unknown value's integrand (mode +- 12 sd)."""
        m = float(self.params[self.m.value.site].bias[values[self.m.cluster.site], 0])
        h = 1.0
        f0, f1, f2 = (self.log_integrand(values, m + k * h) for k in (-1, 0, 1))
        a = (f0 - 2 * f1 + f2) / (2 * h * h)  # the log integrand is a t^2 + b t + c
        b = (f2 - f0) / (2 * h)
        assert a < 0
        mode = m - b / (2 * a)
        sd = 1 / math.sqrt(-2 * a)
        nodes, weights = np.polynomial.legendre.leggauss(24)
        edges = np.linspace(mode - 12 * sd, mode + 12 * sd, 13)
        half = np.diff(edges)[:, None] / 2
        t = ((edges[:-1, None] + half) + half * nodes).reshape(-1)
        return t, np.log((half * weights).reshape(-1))

    def log_integral(self, values: dict) -> float:
        t, log_w = self.quadrature(values)
        logs = np.array([self.log_integrand(values, x) for x in t]) + log_w
        return float(np.logaddexp.reduce(logs))

    def log_evidence(self, evidence: dict) -> float:
        return float(
            np.logaddexp.reduce([self.log_weight(v) for v in self.configurations(evidence)])
        )

    def posterior(self, evidence: dict, site: str) -> np.ndarray:
        """p(site | evidence) over its states."""
        k = self.net.site(site).size
        logs = [[] for _ in range(k)]
        for v in self.configurations(evidence, targets=(site,)):
            logs[v[site]].append(self.log_weight(v))
        logs = np.array([np.logaddexp.reduce(x) if x else -np.inf for x in logs])
        return np.exp(logs - np.logaddexp.reduce(logs))

    def theta_moments(self, values: dict) -> tuple[float, float]:
        """Mean and variance of the unknown value given ``values`` (cluster included)."""
        t, log_w = self.quadrature(values)
        logs = np.array([self.log_integrand(values, x) for x in t]) + log_w
        w = np.exp(logs - logs.max())
        w /= w.sum()
        mean = float((w * t).sum())
        return mean, float((w * (t - mean) ** 2).sum())

    def predicted_moments(self, values: dict) -> tuple[float, float]:
        """Mean and variance of end.pos given a configuration (the value integrated out
        numerically where unknown: its cluster's Gaussian, untruncated)."""
        theta_site = self.m.value.site
        if (
            theta_site in values
            or not self.uses(values[self.m.action])
            or ("end.pos" not in self.m.continuous)
        ):
            return self.gaussian_of("end.pos", values | {theta_site: values.get(theta_site, 0.0)})
        c = values[self.m.cluster.site]
        m = float(self.params[theta_site].bias[c, 0])
        s = math.sqrt(float(self.params[theta_site].covariance[c, 0, 0]))
        nodes, weights = np.polynomial.hermite_e.hermegauss(40)
        weights = weights / weights.sum()
        moments = [self.gaussian_of("end.pos", values | {theta_site: m + s * z}) for z in nodes]
        means = np.array([mu for mu, _ in moments])
        mean = float((weights * means).sum())
        var = float((weights * (np.array([v for _, v in moments]) + (means - mean) ** 2)).sum())
        return mean, var


# ---------------------------------------------------------------------------- evidence
def values(magnitude: float):
    ordinary = st.floats(-3.0, 3.0, allow_nan=False)
    large = st.floats(-magnitude, magnitude, allow_nan=False)
    return st.one_of(ordinary, large)


@st.composite
def cases(draw, inverse: bool = False):
    net = draw(networks(inverse))
    seed = draw(st.integers(0, 2**16))
    spread = draw(st.sampled_from([1.0, 4.0, 10.0]))
    params = spilled(net, random_params(net, seed), spread)
    ev = {}
    for f in net.features:
        if isinstance(f, Continuous):
            ev[f"initial.{f.name}"] = draw(values(EVIDENCE_MAGNITUDE))
        elif draw(st.integers(0, 3)) > 0:
            ev[f"initial.{f.name}"] = draw(st.integers(0, f.cardinality - 1))
    return net, params, ev


def encode(net: EffectNetwork, evidence: dict) -> dict:
    """The oracle's evidence as query evidence (labels, ``(1, 1)`` numbers)."""
    out = {}
    for site, value in evidence.items():
        spec = net.site(site)
        if spec.discrete:
            out[site] = [net.decode(site, torch.tensor([value]))[0]]
        else:
            out[site] = [[value]]
    return out


def close_log(got: float, want: float) -> bool:
    return abs(got - want) <= LOG_RTOL * max(1.0, abs(want))


def sums_to_one(probs: torch.Tensor) -> None:
    assert torch.isfinite(probs).all()
    assert (probs.sum(-1) - 1).abs().max() <= SUM_TOL


CASE_SETTINGS = settings(
    max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)


# ---------------------------------------------------------------------------- the queries
@CASE_SETTINGS
@given(cases(), st.data())
def test_infer_action_is_the_oracle(case, data):
    net, params, ev = case
    oracle = Oracle(net, params)
    for f in net.features:
        if data.draw(st.booleans(), label=f"observe end.{f.name}"):
            site = f"end.{f.name}"
            ev[site] = (
                data.draw(values(EVIDENCE_MAGNITUDE), label=site)
                if isinstance(f, Continuous)
                else data.draw(st.integers(0, f.cardinality - 1), label=site)
            )
    if data.draw(st.booleans(), label="force given"):
        ev["param.force"] = data.draw(values(EVIDENCE_MAGNITUDE), label="force")
    if not ev:
        with pytest.raises(ValueError, match="evidence is empty"):
            infer_action(net, params, {})
        return
    got = infer_action(net, params, encode(net, ev))
    sums_to_one(got.probs)
    want = oracle.posterior(ev, "action")
    assert np.abs(got.probs[0].numpy() - want).max() <= PROB_TOL, (got.probs, want)
    assert close_log(float(got.log_evidence[0]), oracle.log_evidence(ev))
    # unseen: p(an observed end site's configuration no row reached | action, evidence)
    ends = [s for s in ev if s.startswith("end.")]
    for a in range(len(net.actions)):
        if want[a] < 1e-6:
            continue
        mass, total = 0.0, []
        for v in oracle.configurations(ev | {"action": a}):
            w = oracle.log_weight(v)
            unseen = any(
                not bool(net.cpd(s).seen(params[s])[tuple(v[q] for q in net.cpd(s).parents)])
                for s in ends
            )
            total.append((w, unseen))
        top = max(w for w, _ in total)
        norm = sum(math.exp(w - top) for w, _ in total)
        mass = sum(math.exp(w - top) for w, u in total if u) / norm
        assert abs(float(got.unseen[0, a]) - mass) <= 1e-6, (a, got.unseen, mass)


@CASE_SETTINGS
@given(cases(), st.data())
def test_predict_is_the_oracle(case, data):
    net, params, ev = case
    oracle = Oracle(net, params)
    action = data.draw(st.integers(0, len(net.actions) - 1), label="action")
    ev["action"] = action
    if oracle.uses(action) and data.draw(st.booleans(), label="force given"):
        ev["param.force"] = data.draw(values(EVIDENCE_MAGNITUDE), label="force")
    got = predict(net, params, encode(net, ev))
    sums_to_one(got.discrete["f0"])
    for f in net.features:
        site = f"end.{f.name}"
        if not isinstance(f, Continuous):
            want = oracle.posterior(ev, site)
            probs = got.discrete[f.name][0].numpy()
            assert np.abs(probs - want).max() <= PROB_TOL, (f.name, probs, want)
            continue
        mixture = got.continuous[f.name]
        sums_to_one(mixture.weights)
        moments = []
        for v in oracle.configurations(ev):
            moments.append((oracle.log_weight(v), *oracle.predicted_moments(v)))
        logs = np.array([w for w, _, _ in moments])
        w = np.exp(logs - np.logaddexp.reduce(logs))
        means = np.array([mu for _, mu, _ in moments])
        mean = float((w * means).sum())
        var = float((w * (np.array([s for _, _, s in moments]) + (means - mean) ** 2)).sum())
        scale = max(1.0, abs(mean), math.sqrt(var))
        assert abs(float(mixture.mean[0, 0]) - mean) <= 1e-9 * scale
        assert abs(float(mixture.cov[0, 0, 0]) - var) <= 1e-9 * scale**2
    # a non-using action sits on cluster 0 (and is unseen only where its own configuration is)
    if not oracle.uses(action):
        assert float(got.unseen[0]) == 0.0 or any(
            not bool(net.cpd(f"end.{f.name}").seen(params[f"end.{f.name}"]).all())
            for f in net.features
        )


@CASE_SETTINGS
@given(cases(), st.data())
def test_imitation_check_is_the_oracle(case, data):
    net, params, ev = case
    oracle = Oracle(net, params)
    action = data.draw(st.integers(0, len(net.actions) - 1), label="action")
    ev["action"] = action
    observed = []
    for f in net.features:
        site = f"end.{f.name}"
        if isinstance(f, Continuous):
            if data.draw(st.booleans(), label=f"observe {site}"):
                ev[site] = data.draw(values(EVIDENCE_MAGNITUDE), label=site)
                observed.append(site)
        elif not observed or data.draw(st.booleans(), label=f"observe {site}"):
            ev[site] = data.draw(st.integers(0, f.cardinality - 1), label=site)
            observed.append(site)
    got = imitation_check(net, params, encode(net, ev), n_samples=1)
    prior = {s: v for s, v in ev.items() if s not in observed}
    log_lik = oracle.log_evidence(ev) - oracle.log_evidence(prior)
    assert close_log(float(got.log_likelihood[0]), log_lik)
    if all(net.site(s).discrete for s in observed):
        # surprise: the probability of an outcome strictly more likely than the observed
        outcomes = []
        sizes = [net.site(s).size for s in observed]
        for states in itertools.product(*[range(k) for k in sizes]):
            o = prior | dict(zip(observed, states, strict=True))
            outcomes.append(oracle.log_evidence(o) - oracle.log_evidence(prior))
        assume(all(abs(o - log_lik) > 1e-6 for o in outcomes if o != log_lik))
        want = sum(math.exp(o) for o in outcomes if o > log_lik + 1e-9)
        assert abs(float(got.surprise[0]) - want) <= PROB_TOL
    # implausible: the discrete ends' probability given the rest, and the continuous
    # end's chi-square tail under its closest possible component
    discrete = [s for s in observed if net.site(s).discrete]
    p_discrete = 1.0
    if discrete:
        rest = {s: v for s, v in ev.items() if s not in observed}
        with_d = rest | {s: ev[s] for s in discrete}
        p_discrete = math.exp(oracle.log_evidence(with_d) - oracle.log_evidence(rest))
    tail = 1.0
    if "end.pos" in observed:
        closest = math.inf
        for v in oracle.configurations(ev):
            mean, var = oracle.predicted_moments({k: x for k, x in v.items() if k != "end.pos"})
            closest = min(closest, (ev["end.pos"] - mean) ** 2 / var)
        tail = math.erfc(math.sqrt(closest / 2))
    for value in (p_discrete, tail):
        assume(abs(value - IMPLAUSIBLE_BELOW) > 1e-6 * IMPLAUSIBLE_BELOW)
    want_flag = p_discrete < IMPLAUSIBLE_BELOW or tail < IMPLAUSIBLE_BELOW
    assert bool(got.implausible[0]) == want_flag, (p_discrete, tail)


@st.composite
def inverse_cases(draw):
    net, params, ev = draw(cases(inverse=True))
    for f in net.features:
        if not isinstance(f, Continuous):
            ev[f"initial.{f.name}"] = ev.get(f"initial.{f.name}", 0)
    ev["action"] = draw(st.integers(0, len(net.actions) - 1))
    ev["end.pos"] = draw(values(EVIDENCE_MAGNITUDE))
    if draw(st.booleans()):
        f0 = net.feature("f0")
        ev["end.f0"] = draw(st.integers(0, f0.cardinality - 1))
    return net, params, ev


@CASE_SETTINGS
@given(inverse_cases())
def test_infer_parameter_is_the_oracle(case):
    net, params, ev = case
    oracle = Oracle(net, params)
    if not oracle.uses(ev["action"]):
        with pytest.raises(ValueError, match="does not use"):
            infer_parameter(net, params, "force", encode(net, ev))
        return
    got = infer_parameter(net, params, "force", encode(net, ev), mixture=True)
    sums_to_one(got.cluster_probs)
    want = oracle.posterior(ev, "cluster.force")
    assert np.abs(got.cluster_probs[0].numpy() - want).max() <= PROB_TOL, (got.cluster_probs, want)
    assume(np.sort(want)[-1] - np.sort(want)[-2] > 1e-6)  # the best cluster is not a tie
    best = int(np.argmax(want))
    assert int(got.best_cluster[0]) == best
    mean, var = oracle.theta_moments(ev | {"cluster.force": best})
    scale = max(1.0, abs(mean))
    assert abs(float(got.mean[0, 0]) - mean) <= 1e-8 * scale
    assert abs(float(got.cov[0, 0, 0]) - var) <= 1e-8 * max(var, 1e-300) + 1e-12 * scale**2
    sums_to_one(got.mixture.weights)
    # the compiled query: the same answer, or a ValueError naming what it does not serve
    try:
        compiled = compile_parameter_query(net, params, "force")
    except ValueError:
        return
    fast = compiled.infer(encode(net, ev))
    sums_to_one(fast.cluster_probs)
    assert np.abs(fast.cluster_probs[0].numpy() - want).max() <= 1e-6


@CASE_SETTINGS
@given(inverse_cases())
def test_parameter_for_effect_is_the_oracle(case):
    net, params, ev = case
    oracle = Oracle(net, params)
    if not oracle.uses(ev["action"]):
        with pytest.raises(ValueError, match="does not use"):
            parameter_for_effect(net, params, "force", encode(net, ev))
        return
    got = parameter_for_effect(net, params, "force", encode(net, ev))
    cpd = params["end.pos"]
    parents = net.cpd("end.pos").parents
    for c in range(net.mixtures[0].parameter.n_clusters):
        # the value under which the effect is most likely given cluster c: its line hits y
        values = ev | {"cluster.force": c, "param.force": 0.0}
        offset, _ = oracle.gaussian_of("end.pos", values)
        slope = float(cpd.weight[tuple(values[s] for s in parents)][0, -1])
        assume(abs(slope) > 1e-3)
        theta = (ev["end.pos"] - offset) / slope
        got_c = float(got.candidates[0, c, 0])
        assert abs(got_c - theta) <= 1e-6 * max(1.0, abs(theta)), (c, got_c, theta)
        # scored by its exact joint density with the evidence (its cell its cluster)
        want = oracle.log_evidence(ev | {"param.force": got_c})
        assert close_log(float(got.candidate_log_density[0, c]), want) or (
            abs(float(got.candidate_log_density[0, c]) - want) <= 1e-6 * max(1.0, abs(want))
        )
