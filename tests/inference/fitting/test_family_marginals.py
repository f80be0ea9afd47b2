"""EM over gaps by elimination over the families: the same expected counts as the completed
rows, and the same optimum as an EM over the whole joint written out by hand."""

import itertools

import pytest
import torch
from effect_networks.inference.fitting import completion, family_marginals, missing
from effect_networks.inference.fitting.sufficient_statistics import statistics
from effect_networks.models import Discrete, EffectNetwork, random_params
from effect_networks.models.declaration import DTYPE
from hypothesis import given, settings
from hypothesis import strategies as st


@st.composite
def gapped_networks(draw):
    """A small discrete network with drawn parent sets, its random tables, and rows of
    random states with random gaps (one row complete, so that EM has a start)."""
    cards = draw(st.lists(st.integers(2, 3), min_size=1, max_size=3))
    n_actions = draw(st.integers(1, 3))
    feats = tuple(Discrete(f"f{i}", tuple(range(k))) for i, k in enumerate(cards))
    initials = [f"initial.f{i}" for i in range(len(cards))]
    parents = {}
    for i in range(len(cards)):
        pool = [*initials, "action", *[f"end.f{j}" for j in range(i)]]
        parents[f"end.f{i}"] = tuple(p for p in pool if draw(st.booleans()))
    net = EffectNetwork(feats, tuple(f"a{i}" for i in range(n_actions)), parents=parents)
    params = random_params(net, draw(st.integers(0, 2**16)))
    n = draw(st.integers(1, 40))
    share = draw(st.sampled_from([0.1, 0.4, 0.9]))
    g = torch.Generator().manual_seed(draw(st.integers(0, 2**16)))
    rows = net.encode_indices(
        {s.name: torch.randint(0, s.size, (n,), generator=g) for s in net.sites}
    )
    masks = {s.name: torch.rand(n, generator=g) > share for s in net.sites}
    for m in masks.values():
        m[0] = True
    return net, params, rows, masks


@settings(max_examples=40, deadline=None)
@given(gapped_networks())
def test_expected_counts_are_the_completed_rows(case):
    # the twin: the general route completes each row once per assignment of its gaps
    net, params, rows, masks = case
    assert family_marginals.covers(net)
    completed = completion.completed_rows(net, params, rows, masks)
    twin = statistics(net, completed.rows, completed.weights)
    found = family_marginals.family_counts(net, params, rows, masks)
    assert found.log_lik == pytest.approx(completed.log_lik, rel=1e-12, abs=1e-10)
    for spec in net.sites:
        torch.testing.assert_close(
            found.counts[spec.name], twin.sites[spec.name].counts, rtol=0, atol=1e-10
        )


def brute_force_counts(net, params, rows, masks):
    """Expected family counts and log-likelihood over the whole joint, every assignment
    of every site written out, the rows' observed values picking theirs (a table's zero
    read as float64's eps, as the model's categorical reads it)."""
    names = [s.name for s in net.sites]
    joint = torch.tensor(list(itertools.product(*(range(s.size) for s in net.sites))))
    column = {name: joint[:, j] for j, name in enumerate(names)}  # (C,) per site
    eps = torch.finfo(DTYPE).eps
    log_joint = torch.zeros(len(joint), dtype=DTYPE)
    for name in names:
        family = (*net.cpd(name).parents, name)
        log_joint += params[name].probs.clamp(eps, 1 - eps).log()[tuple(column[q] for q in family)]
    consistent = torch.ones(rows.n_rows, len(joint), dtype=torch.bool)
    for name in names:
        consistent &= ~masks[name][:, None] | (rows[name][:, None] == column[name][None, :])
    weights = torch.where(consistent, log_joint, -torch.inf)  # (n, C)
    norm = weights.logsumexp(-1, keepdim=True)
    posterior = (weights - norm).exp().sum(0)  # (C,) summed over the rows
    counts = {}
    for name in names:
        family = (*net.cpd(name).parents, name)
        c = torch.zeros_like(params[name].probs)
        counts[name] = c.index_put_([column[q] for q in family], posterior, accumulate=True)
    return counts, float(norm.sum())


def test_expected_counts_are_the_brute_force_joint():
    net = EffectNetwork(
        (Discrete("a", (0, 1)), Discrete("b", (0, 1, 2))),
        ("push", "wait"),
        parents={"end.a": ("initial.a", "action"), "end.b": ("initial.a", "initial.b", "end.a")},
    )
    params = random_params(net, 5)
    g = torch.Generator().manual_seed(1)
    n = 30
    rows = net.encode_indices(
        {s.name: torch.randint(0, s.size, (n,), generator=g) for s in net.sites}
    )
    masks = {s.name: torch.rand(n, generator=g) > 0.5 for s in net.sites}
    counts, log_lik = brute_force_counts(net, params, rows, masks)
    found = family_marginals.family_counts(net, params, rows, masks)
    assert found.log_lik == pytest.approx(log_lik, rel=1e-12)
    for site, c in counts.items():
        torch.testing.assert_close(found.counts[site], c, rtol=0, atol=1e-10)


TINY = EffectNetwork(
    (Discrete("visible", (0, 1)), Discrete("colour", ("r", "g", "b"))),
    ("remove", "paint"),
    parents={
        "end.visible": ("initial.visible", "action"),
        "end.colour": ("initial.colour", "action", "end.visible"),
    },
)


def tiny_rows(n=200, seed=0):
    params = random_params(TINY, seed)
    from effect_networks.inference import simulate

    rows = TINY.encode(simulate(TINY, params, n, seed=seed))
    g = torch.Generator().manual_seed(seed)
    masks = {s.name: torch.rand(n, generator=g) > 0.3 for s in TINY.sites}
    for m in masks.values():
        m[0] = True
    return rows, masks


def brute_force_em(net, init, rows, masks, steps, alpha):
    """EM over the whole joint: the brute-force counts, then (counts + alpha) / (n + K alpha)."""
    from effect_networks.models.cpds.table import TableParams
    from effect_networks.models.params import NetworkParams

    params, curve = init, []
    for _ in range(steps):
        counts, log_lik = brute_force_counts(net, params, rows, masks)
        curve.append(log_lik)
        cpds = {}
        for site, c in counts.items():
            total = c.sum(-1, keepdim=True) + c.shape[-1] * alpha
            probs = torch.where(total > 0, (c + alpha) / total, 1.0 / c.shape[-1])
            cpds[site] = TableParams(probs, c.sum(-1))
        params = NetworkParams(cpds, alpha, net)
    return params, curve


@pytest.mark.filterwarnings("ignore::effect_networks.inference.fitting.result.ConvergenceWarning")
def test_em_follows_the_brute_force_em_and_never_lowers_the_likelihood():
    rows, masks = tiny_rows()
    init = missing.available_case_start(TINY, rows, masks, 0.0, 1e-6)
    steps = 25
    result = missing.fit_missing(
        TINY, rows, masks, init=init, pseudo_count=0.0, steps=steps, tol=1e-300
    )
    brute, curve = brute_force_em(TINY, init, rows, masks, steps, 0.0)
    assert len(result.log_likelihoods) == steps + 1
    torch.testing.assert_close(
        torch.tensor(result.log_likelihoods[:-1]), torch.tensor(curve), rtol=1e-12, atol=0
    )
    assert all(b >= a for a, b in itertools.pairwise(result.log_likelihoods))
    for spec in TINY.sites:
        torch.testing.assert_close(
            result.params[spec.name].probs, brute[spec.name].probs, rtol=0, atol=1e-10
        )


def test_em_ends_at_a_fixed_point_of_the_brute_force_em():
    # the same optimum: one step of the EM over the whole joint moves the fit by nothing
    rows, masks = tiny_rows(seed=1)
    init = missing.available_case_start(TINY, rows, masks, 0.01, 1e-6)
    result = missing.fit_missing(TINY, rows, masks, init=init, tol=1e-13, steps=5000)
    assert result.converged
    assert result.tol == 1e-13 and result.max_steps == 5000
    moved, (log_lik,) = brute_force_em(TINY, result.params, rows, masks, 1, 0.01)
    assert log_lik == pytest.approx(result.log_likelihoods[-1], rel=1e-12)
    for spec in TINY.sites:
        torch.testing.assert_close(
            moved[spec.name].probs, result.params[spec.name].probs, rtol=0, atol=1e-8
        )


def test_the_fit_states_its_stopping_rule_and_the_route_its_scope():
    from effect_networks.inference import fit
    from effect_networks.models import Continuous

    rows, masks = tiny_rows(n=60)
    result = fit(TINY, rows, masks=masks)
    assert (result.tol, result.max_steps) == (missing.EM_TOL, 500)
    assert result.converged
    mixed = EffectNetwork((Discrete("visible", (0, 1)), Continuous("pos", 1)), ("remove",))
    assert family_marginals.covers(TINY) and not family_marginals.covers(mixed)
