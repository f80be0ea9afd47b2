"""Demonstrations that do not record their action's parameter (the force of a tap).

The value is a hidden value of its step: against numerical integration over it of the
model's own joint (the value and its cluster given), one EM step's counts and cluster
means, and the fit on the same steps with every value recorded.
"""

from __future__ import annotations

import math

import pytest
import torch
from effect_networks.inference import fit, simulate
from effect_networks.inference.exact.enumeration import enumerate_model
from effect_networks.inference.watching import fit_demonstrations
from scipy.integrate import quad

from tests.networks import tap_data, tap_net


@pytest.fixture(scope="module")
def tapped():
    net = tap_net(bins=3, affects="pos", layout="grid")
    true = fit(net, tap_data(net, 400)).params
    rows = simulate(net, true, 200, seed=1)
    demos = [
        [
            {"visible": rows["initial.visible"][i]},
            {"visible": v, "pos": rows["end.pos"][i].tolist()},
        ]
        for i, v in enumerate(rows["end.visible"])
    ]
    return net, true, rows, demos


def _joint(net, params, step, action, cluster=None, force=None):
    """The model's joint of one step with its action (and cluster and force) given."""
    evidence = {
        "initial.visible": [step[0]["visible"]],
        "action": [action],
        "end.visible": [step[1]["visible"]],
        "end.pos": [step[1]["pos"]],
    }
    if cluster is not None:
        evidence |= {"cluster.force": [cluster], "param.force": [[force]]}
    else:
        evidence |= {"param.force": [[math.nan]]}
    return float(enumerate_model(net, params, net.encode(evidence)).log_evidence[0])


def _by_quadrature(net, params, step, label, recorded=None):
    """Per (action, cluster): the step's joint with the force integrated numerically, and the
    force's first moment; an action that ignores the force has one entry (cluster None). A
    recorded force: the actions that use it alone, its cluster its cell."""
    out = {}
    gauss = params["param.force"]
    if recorded is not None:
        cell = int(net.mixture("force").parameter.cluster_of(torch.tensor([[recorded]])))
        mass = math.exp(_joint(net, params, step, "tap", cell, recorded))
        return {("tap", cell): (mass, recorded * mass, recorded**2 * mass)}
    for action in [label] if label else net.actions:
        if action != "tap":
            out[action, None] = (math.exp(_joint(net, params, step, action)), 0.0, 0.0)
            continue
        for c in range(3):
            m = float(gauss.bias[c, 0])
            s = float(gauss.scale_tril[c, 0, 0])

            def density(x, c=c, action=action):
                return math.exp(_joint(net, params, step, action, c, x))

            lo, hi = m - 12 * s, m + 12 * s
            mass = quad(density, lo, hi, epsabs=0, epsrel=1e-12, limit=200)[0]
            first = quad(lambda x: x * density(x), lo, hi, epsabs=0, epsrel=1e-12, limit=200)[0]
            second = quad(lambda x: x * x * density(x), lo, hi, epsabs=0, epsrel=1e-12, limit=200)
            out[action, c] = (mass, first, second[0])
    return out


def test_one_em_step_integrates_the_unrecorded_force_as_quadrature_does(tapped):
    net, true, rows, demos = tapped
    steps = [demos[i] for i in range(5)]
    labels = [[rows["action"][i] if i % 3 == 0 else None] for i in range(5)]
    # one unlabelled tap step records its force
    shown = next(i for i in range(1, 5) if i % 3 and rows["action"][i] == "tap")
    force = float(rows["param.force"][shown, 0])
    records = [[{"force": [force]}] if i == shown else None for i in range(5)]
    got = fit_demonstrations(
        net, steps, labels, parameters=records, init=true, steps=1, tol=1e-300, pseudo_count=0.0
    )
    tables = [
        _by_quadrature(net, true, s, lab[0], force if i == shown else None)
        for i, (s, lab) in enumerate(zip(steps, labels, strict=True))
    ]
    want_ll = sum(math.log(sum(m for m, *_ in t.values())) for t in tables)
    assert got.log_likelihoods[0] == pytest.approx(want_ll, rel=1e-9, abs=1e-9)
    assert len(got.log_likelihoods) == 2 and got.log_likelihoods[1] >= got.log_likelihoods[0]
    # the M-step: the cluster table of tap and each cluster's mean force, from the
    # posterior over (action, cluster) and the force's conditional mean
    weight, first, second = (torch.zeros(3, dtype=torch.float64) for _ in range(3))
    for t in tables:
        total = sum(m for m, *_ in t.values())
        for (_action, c), (m, f, g) in t.items():
            if c is not None:
                weight[c] += m / total
                first[c] += f / total
                second[c] += g / total
    torch.testing.assert_close(
        got.params["cluster.force"].probs[net.action_index("tap")],
        weight / weight.sum(),
        rtol=0,
        atol=1e-8,
    )
    mean = first / weight
    torch.testing.assert_close(got.params["param.force"].bias[:, 0], mean, rtol=1e-7, atol=0)
    variance = got.params["param.force"].scale_tril[:, 0, 0] ** 2
    torch.testing.assert_close(variance, second / weight - mean**2, rtol=1e-6, atol=0)


def test_recorded_forces_fit_as_the_labelled_rows_do(tapped):
    net, true, rows, demos = tapped
    labels = [[a] for a in rows["action"]]
    given = [
        [{"force": f.tolist()}] if a == "tap" else None
        for a, f in zip(rows["action"], rows["param.force"], strict=True)
    ]
    got = fit_demonstrations(net, demos, labels, parameters=given).params
    want = fit(net, {k: v for k, v in rows.items() if k != "cluster.force"}).params
    for site in ("cluster.force", "end.visible", "action"):
        torch.testing.assert_close(got[site].probs, want[site].probs, rtol=0, atol=1e-9)
    for site in ("param.force", "end.pos"):
        torch.testing.assert_close(got[site].bias, want[site].bias, rtol=0, atol=1e-9)


def test_unrecorded_forces_never_lower_the_likelihood_and_keep_what_the_steps_show(tapped):
    net, true, rows, demos = tapped
    labels = [[a if i % 10 == 0 else None] for i, a in enumerate(rows["action"])]
    got = fit_demonstrations(net, demos, labels, restarts=0, steps=40)
    curve = got.log_likelihoods
    assert all(b >= a - 1e-9 for a, b in zip(curve, curve[1:], strict=False))
    full = fit(net, {k: v for k, v in rows.items() if k != "cluster.force"}).params
    # the action's share and the visibility table are read from what every step shows
    assert abs(float(got.params["action"].probs[1] - full["action"].probs[1])) < 0.05
    assert got.identifiable and got.agreement > 0.8


def test_what_stays_refused_is_named():
    net = tap_net(bins=3, affects="pos", layout="grid")
    step = [{"visible": 1}, {"visible": 0, "pos": [0.1]}]
    with pytest.raises(ValueError, match="'remove' does not use"):
        fit_demonstrations(net, [step], [["remove"]], parameters=[[{"force": [3.0]}]])
    with pytest.raises(ValueError, match="must map parameter names"):
        fit_demonstrations(net, [step], parameters=[[{"speed": [3.0]}]])
    with pytest.raises(ValueError, match="adaptive layout"):
        fit_demonstrations(tap_net(), [step])
