"""Missing discrete values: EM against the brute-force maximum, the marginal likelihood
and the gradient route."""

import math

import pytest
import torch
from effect_networks.inference import ConvergenceWarning, fit
from effect_networks.inference.fitting import em, missing
from effect_networks.models import Discrete, EffectNetwork
from effect_networks.models.declaration import DTYPE
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.networks import marginal_loss, tap3_rows, tap_data, tap_net


def test_em_keeps_the_missing_value_names():
    assert em.fit_missing is missing.fit_missing
    assert em.missing_log_likelihood is missing.missing_log_likelihood


SMALL = EffectNetwork(
    (Discrete("visible", (0, 1)), Discrete("colour", ("r", "g", "b"))),
    ("remove", "paint"),
    parents={
        "end.visible": ("initial.visible", "action"),
        "end.colour": ("initial.colour", "action"),
    },
)


def small_rows(n=400, seed=0):
    """Rows of SMALL, and masks: the initial visibility missing in 30 % of the rows, the
    action in 15 %, the end colour in 20 %."""
    g = torch.Generator().manual_seed(seed)
    v0 = (torch.rand(n, generator=g) < 0.7).long()
    c0 = torch.multinomial(torch.tensor([0.5, 0.3, 0.2]), n, True, generator=g)
    a = (torch.rand(n, generator=g) < 0.4).long()
    v1 = torch.where((a == 0) & (torch.rand(n, generator=g) < 0.8), 0, v0)
    c1 = torch.where((a == 1) & (torch.rand(n, generator=g) < 0.6), 2, c0)
    rows = SMALL.encode_indices(
        {
            "initial.visible": v0,
            "initial.colour": c0,
            "action": a,
            "end.visible": v1,
            "end.colour": c1,
        }
    )
    masks = {
        "initial.visible": torch.rand(n, generator=g) > 0.3,
        "action": torch.rand(n, generator=g) > 0.15,
        "end.colour": torch.rand(n, generator=g) > 0.2,
    }
    return rows, masks


def brute_force_maximum(rows, masks):
    """The maximum of the observed-data log-likelihood of SMALL, written out by hand
    (every joint assignment of the five sites, the rows' observed values picking theirs)
    and maximised by scipy over the tables' logits."""
    import itertools

    import numpy as np
    from scipy.optimize import minimize

    sizes = {
        "initial.visible": 2,
        "initial.colour": 3,
        "action": 2,
        "end.visible": 2,
        "end.colour": 3,
    }
    names = list(sizes)
    joint = torch.tensor(list(itertools.product(*(range(k) for k in sizes.values()))))  # (72, 5)
    consistent = torch.ones(rows.n_rows, len(joint), dtype=torch.bool)
    for j, name in enumerate(names):
        given = masks.get(name, torch.ones(rows.n_rows, dtype=torch.bool))
        consistent &= ~given[:, None] | (rows[name][:, None] == joint[None, :, j])
    shapes = {
        "initial.visible": (2,),
        "initial.colour": (3,),
        "action": (2,),
        "end.visible": (2, 2, 2),
        "end.colour": (3, 2, 3),
    }
    counts = [math.prod(s) for s in shapes.values()]

    def unpack(flat):
        tables, at = {}, 0
        for name, count in zip(names, counts, strict=True):
            tables[name] = flat[at : at + count].reshape(shapes[name]).log_softmax(-1)
            at += count
        return tables

    def negative_log_likelihood(flat_np):
        flat = torch.tensor(flat_np, dtype=DTYPE, requires_grad=True)
        t = unpack(flat)
        v0, c0, a, v1, c1 = joint.T
        log_joint = (
            t["initial.visible"][v0]
            + t["initial.colour"][c0]
            + t["action"][a]
            + t["end.visible"][v0, a, v1]
            + t["end.colour"][c0, a, c1]
        )
        per_row = torch.where(consistent, log_joint, -torch.inf).logsumexp(-1)
        loss = -per_row.sum()
        loss.backward()
        return float(loss.detach()), flat.grad.numpy()

    def score(params):
        """The hand-written log-likelihood of fitted tables."""
        flat = torch.cat([params[name].probs.log().reshape(-1) for name in names])
        return -negative_log_likelihood(flat.numpy())[0]

    found = minimize(
        negative_log_likelihood,
        np.zeros(sum(counts)),
        jac=True,
        method="L-BFGS-B",
        options={"ftol": 1e-15, "gtol": 1e-10, "maxiter": 10_000},
    )
    return {k: v.exp() for k, v in unpack(torch.tensor(found.x)).items()}, -found.fun, score


def test_missing_values_em_reaches_the_brute_force_maximum():
    rows, masks = small_rows()
    result = fit(SMALL, rows, masks=masks, pseudo_count=0.0, tol=1e-14, steps=5000)
    assert result.converged
    tables, best, score = brute_force_maximum(rows, masks)
    mine = score(result.params)
    assert mine >= best - 1e-7
    assert mine == pytest.approx(-result.losses[-1] * rows.n_rows, rel=1e-12)
    from effect_networks.inference.fitting.missing import missing_log_likelihood

    assert missing_log_likelihood(SMALL, result.params, rows, masks) == pytest.approx(
        mine, rel=1e-12
    )
    for site, table in tables.items():
        torch.testing.assert_close(result.params[site].probs, table, atol=1e-5, rtol=0)


def door_rows(n, seed=0):
    """The door world with the kind missing in 30 % of the rows and the end state in
    20 %; the continuous features follow their own initial values only (so that no
    configuration of a few rows makes a singular Gaussian, where the likelihood has
    no maximum)."""
    from tests.networks import handle_world

    own = {"end.handle": ("initial.handle",), "end.effort": ("initial.effort",)}
    net, data = handle_world(n=n, seed=seed, parents=own)
    g = torch.Generator().manual_seed(seed)
    masks = {
        "initial.kind": torch.rand(n, generator=g) > 0.3,
        "end.state": torch.rand(n, generator=g) > 0.2,
    }
    return net, net.encode(data), masks


def test_missing_values_em_never_lowers_the_likelihood_step_by_step():
    # each step's parameters scored by Pyro's own enumeration of the model, not EM's
    net, rows, masks = door_rows(300, seed=1)
    settings = dict(masks=masks, pseudo_count=0.0, min_variance=0.0, tol=1e-300)
    with pytest.warns(ConvergenceWarning):  # tol=1e-300: six steps are not enough
        curve = fit(net, rows, steps=6, **settings).losses
    scored = []
    for k in range(1, 7):
        with pytest.warns(ConvergenceWarning):
            params = fit(net, rows, steps=k, **settings).params
        scored.append(marginal_loss(net, params, rows, masks)[0])
    assert len(curve) == 7
    torch.testing.assert_close(torch.tensor(curve[1:]), torch.tensor(scored), rtol=1e-10, atol=0)
    assert all(b <= a for a, b in zip(curve, curve[1:], strict=False))
    assert curve[-1] < curve[0] - 1e-3  # and it moved


def test_missing_values_em_ends_at_a_stationary_point():
    # the gradient of the marginal likelihood (Pyro's, over every CPD's free tensors)
    # vanishes where EM stops
    net, rows, masks = door_rows(300, seed=2)
    result = fit(net, rows, masks=masks, pseudo_count=0.0, min_variance=0.0, tol=1e-13, steps=2000)
    assert result.converged
    loss, gradient = marginal_loss(net, result.params, rows, masks)
    assert loss == pytest.approx(result.losses[-1], rel=1e-10)
    assert gradient < 1e-5


def test_missing_values_fit_of_1000_rows_is_fast():
    # EM with exact E-steps: about 0.5 s on one thread (500 Adam steps took a minute and
    # stopped unconverged); the bound leaves room for a loaded machine
    import time

    net, rows, masks = door_rows(1000)
    start = time.perf_counter()
    result = fit(net, rows, masks=masks)
    assert time.perf_counter() - start < 4.0
    assert result.converged
    assert all(b <= a for a, b in zip(result.losses, result.losses[1:], strict=False))


def test_missing_values_with_a_parameter():
    # the tap world's force (grid layout) beside a missing initial visibility
    net = tap_net(layout="grid")
    rows = tap_data(net, n=300)
    masks = {"initial.visible": torch.rand(300, generator=torch.Generator().manual_seed(3)) > 0.4}
    result = fit(net, rows, masks=masks, pseudo_count=0.0, min_variance=0.0, tol=1e-13, steps=2000)
    assert result.converged
    assert all(b <= a for a, b in zip(result.losses, result.losses[1:], strict=False))
    loss, gradient = marginal_loss(net, result.params, rows, masks)
    assert loss == pytest.approx(result.losses[-1], rel=1e-10)
    assert gradient < 1e-5


def test_missing_actions_with_a_parameter():
    # a missing action is one of those that use exactly the parameters the row gives:
    # Pyro's enumeration of the model with that factor is the oracle
    net, rows, masks = tap3_rows()
    result = fit(net, rows, masks=masks, pseudo_count=0.0, min_variance=0.0, tol=1e-13, steps=2000)
    assert result.converged
    assert all(b <= a for a, b in zip(result.losses, result.losses[1:], strict=False))
    loss, gradient = marginal_loss(net, result.params, rows, masks, presence=True)
    assert loss == pytest.approx(result.losses[-1], rel=1e-10)
    assert gradient < 1e-5
    # tap and push told apart by their effects: the fitted tap moves the can as sqrt(f)
    pushed = fit(net, rows.rows(masks["action"]), pseudo_count=0.0, min_variance=0.0).params
    torch.testing.assert_close(
        result.params["end.pos"].weight[..., 1, :, :, :],
        pushed["end.pos"].weight[..., 1, :, :, :],
        atol=0.05,
        rtol=0.0,
    )


def test_missing_values_the_em_cannot_fill_are_refused():
    net = tap_net(layout="grid")
    rows = tap_data(net, n=50)
    gap = torch.arange(50) % 3 > 0
    with pytest.raises(ValueError, match=r"masks\['cluster.force'\].*cell"):
        fit(net, rows, masks={"cluster.force": gap})
    # every action uses the force: a row without a value agrees with none
    net, rows, masks = tap3_rows(n=50, users=("remove", "tap", "push"))
    rows = rows | {"param.force": rows["param.force"].clone()}
    missing = torch.nonzero(~masks["action"])[0, 0]
    rows["param.force"][missing] = float("nan")
    with pytest.raises(ValueError, match=rf"'action': row {int(missing)} is missing and gives no"):
        fit(net, rows, masks=masks)


@pytest.mark.filterwarnings(
    "ignore::effect_networks.inference.fitting.result.ConvergenceWarning"
)  # 5 steps only
def test_missing_values_e_step_in_row_chunks_is_the_same(monkeypatch):
    import effect_networks.inference.exact.enumeration as enumeration_module

    rows, masks = small_rows(n=200)
    whole = fit(SMALL, rows, masks=masks, steps=5, tol=1e-300)
    monkeypatch.setattr(enumeration_module, "CHUNK_ELEMENTS", 100)  # 100 / 12: 8 rows
    chunked = fit(SMALL, rows, masks=masks, steps=5, tol=1e-300)
    torch.testing.assert_close(
        torch.tensor(chunked.losses), torch.tensor(whole.losses), rtol=1e-13, atol=0
    )
    for site in whole.params.cpds:
        torch.testing.assert_close(
            chunked.params[site].probs, whole.params[site].probs, rtol=0, atol=1e-14
        )


@pytest.mark.filterwarnings(
    "ignore::effect_networks.inference.fitting.result.ConvergenceWarning"
)  # 20 steps at most
@settings(max_examples=15, deadline=None)
@given(
    cards=st.lists(st.integers(2, 3), min_size=1, max_size=2),
    n_actions=st.integers(1, 3),
    n=st.integers(20, 80),
    missing=st.sampled_from([0.1, 0.4, 0.8]),
    seed=st.integers(0, 2**16),
)
def test_missing_values_em_on_random_discrete_networks(cards, n_actions, n, missing, seed):
    from tests.helpers import discrete_network

    net = discrete_network(cards, n_actions)
    g = torch.Generator().manual_seed(seed)
    sites = [s for s in net.sites if s.discrete]
    rows = net.encode_indices({s.name: torch.randint(0, s.size, (n,), generator=g) for s in sites})
    masks = {s.name: torch.rand(n, generator=g) > missing for s in sites}
    for m in masks.values():
        m[0] = True  # at least one complete row to start from
    result = fit(net, rows, masks=masks, pseudo_count=0.0, steps=20, tol=1e-300)
    curve = result.losses
    assert all(b <= a for a, b in zip(curve, curve[1:], strict=False))
    assert marginal_loss(net, result.params, rows, masks)[0] == pytest.approx(curve[-1], rel=1e-10)
