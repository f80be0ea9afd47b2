"""Active exploration: the closed-form gain against numerical integration and Monte Carlo,
the closed-form update against a recount and ``fit``, resumption, refusals."""

import itertools
import math

import numpy as np
import pytest
import torch
from effect_networks.inference import fit, infer_action
from effect_networks.inference.design.active import (
    STRATEGIES,
    ExplorationState,
    dirichlet_eig,
    explore,
    predictive_entropy,
    with_pool_prior,
)
from effect_networks.models import Continuous, Discrete, EffectNetwork
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import integrate, stats

from tests.helpers import discrete_network


# ------------------------------------------------------------------------- the gain itself
def entropy(p):
    p = np.asarray(p, dtype=float)
    return float(-(p * np.log(np.where(p > 0, p, 1.0))).sum())


@pytest.mark.parametrize("a, b", [(0.5, 0.5), (1.0, 1.0), (2.0, 7.0), (0.01, 0.02), (30.0, 1.0)])
def test_eig_of_a_beta_row_equals_numerical_integration(a, b):
    """K = 2: I(theta; y) = H[E theta] - integral of H(theta) under Beta(a, b)."""
    mean = a / (a + b)

    def h(t):
        return 0.0 if t in (0.0, 1.0) else entropy([t, 1 - t])

    expected_h, _ = integrate.quad(lambda t: h(t) * stats.beta.pdf(t, a, b), 0, 1, limit=200)
    want = entropy([mean, 1 - mean]) - expected_h
    got = float(dirichlet_eig(torch.tensor([a, b], dtype=torch.float64)))
    assert got == pytest.approx(want, abs=1e-6)


@pytest.mark.parametrize(
    "alpha", [[1.0, 1.0, 1.0, 1.0], [0.3, 2.0, 5.0], [4.0, 0.5, 0.5, 0.5, 9.0], [0.05, 0.05, 3.0]]
)
def test_eig_equals_a_monte_carlo_expectation(alpha):
    """Draws of theta ~ Dirichlet(alpha): H[predictive] - mean H[Cat(theta)]."""
    theta = np.random.default_rng(0).dirichlet(alpha, size=400_000)
    h = -(theta * np.log(np.clip(theta, 1e-300, None))).sum(-1)
    mean = np.asarray(alpha) / sum(alpha)
    want = entropy(mean) - h.mean()
    stderr = h.std() / math.sqrt(len(h))
    got = float(dirichlet_eig(torch.tensor(alpha, dtype=torch.float64)))
    assert got == pytest.approx(want, abs=5 * stderr + 1e-4)


def test_eig_vanishes_for_a_known_row_and_is_bounded_by_log_k():
    known = torch.tensor([1e7, 3e7, 2e7], dtype=torch.float64)
    assert float(dirichlet_eig(known)) < 1e-6
    for alpha in ([0.01] * 5, [0.001] * 20, [1.0] * 3):
        a = torch.tensor(alpha, dtype=torch.float64)
        assert 0 < float(dirichlet_eig(a)) <= math.log(len(alpha))
    # more counts, less to learn; the predictive entropy of a fair known coin stays log 2
    coin = torch.tensor([[1.0, 1.0], [10.0, 10.0], [1e4, 1e4]], dtype=torch.float64)
    gains = dirichlet_eig(coin)
    assert bool((gains[1:] < gains[:-1]).all())
    assert predictive_entropy(coin).tolist() == pytest.approx([math.log(2)] * 3)


# --------------------------------------------------------------------- a small world
NET = discrete_network([3, 2], 4)  # features f0 (3 states), f1 (2), four actions


def world(seed=0, repeats=2):
    """A pool listing every (f0, f1, action) ``repeats`` times, with a fixed random outcome
    per candidate: a stateless oracle (its answer depends on the candidate only)."""
    rng = np.random.default_rng(seed)
    pairs = np.array(list(itertools.product(range(3), range(2), range(4))) * repeats)
    pool = NET.encode_indices(
        {"initial.f0": pairs[:, 0], "initial.f1": pairs[:, 1], "action": pairs[:, 2]}
    )
    # the outcome depends on the pair, noisily
    probs0 = rng.dirichlet(np.ones(3) * 0.5, size=(3, 2, 4))
    probs1 = rng.dirichlet(np.ones(2) * 0.5, size=(3, 2, 4))
    u = rng.random((len(pairs), 2))
    p0 = probs0[pairs[:, 0], pairs[:, 1], pairs[:, 2]].cumsum(-1)
    p1 = probs1[pairs[:, 0], pairs[:, 1], pairs[:, 2]].cumsum(-1)
    end0 = (u[:, :1] > p0).sum(-1).clip(0, 2)
    end1 = (u[:, 1:] > p1).sum(-1).clip(0, 1)

    def oracle(index):
        return NET.encode_indices({"end.f0": end0[index], "end.f1": end1[index]})

    return pool, oracle, (end0, end1)


@settings(max_examples=25, deadline=None)
@given(
    strategy=st.sampled_from(STRATEGIES),
    budget=st.integers(1, 48),
    batch=st.integers(1, 7),
    alpha=st.sampled_from([0.01, 0.5, 2.0]),
    strength=st.sampled_from([0.0, 3.0]),
    seed=st.integers(0, 5),
)
def test_closed_form_update_equals_fit_on_the_chosen_rows(
    strategy, budget, batch, alpha, strength, seed
):
    pool, oracle, (end0, end1) = world(seed)
    r = explore(
        NET, pool, oracle, budget, batch_size=batch, strategy=strategy, pseudo_count=alpha,
        prior_strength=strength, seed=seed,
    )  # fmt: skip
    assert len(r.chosen) == len(set(r.chosen.tolist())) == budget
    # the rows are the pool's candidates with the oracle's outcomes
    for s in ("initial.f0", "initial.f1", "action"):
        assert torch.equal(r.rows[s], pool[s][torch.as_tensor(r.chosen)])
    assert r.rows["end.f0"].tolist() == end0[r.chosen].tolist()
    # a brute-force recount of the end tables' counts
    want = np.zeros((3, 2, 4, 3))
    for i in r.chosen:
        f0, f1, a = (int(pool[s][i]) for s in ("initial.f0", "initial.f1", "action"))
        want[f0, f1, a, end0[i]] += 1
    assert np.array_equal(r.params["end.f0"].n.numpy(), want.sum(-1))
    fitted = fit(NET, r.rows, pseudo_count=alpha).params
    for site in fitted.cpds:
        assert torch.allclose(r.params[site].probs, fitted[site].probs, atol=1e-12), site
        assert torch.equal(r.params[site].n, fitted[site].n), site


def greedy_from_scratch(pool, oracle, budget, batch, alpha, strength, seed):
    """The greedy batch choice of ``eig`` with the shared prior, every candidate's score
    recomputed from the counts at every pick: no stored gains, no cached group sums."""
    rng = np.random.default_rng(seed)
    key = torch.stack([pool[s] for s in ("initial.f0", "initial.f1", "action")], 1).numpy()
    n = len(key)
    counts = {"end.f0": np.zeros((3, 2, 4, 3)), "end.f1": np.zeros((3, 2, 4, 2))}
    available = np.ones(n, dtype=bool)
    chosen = []

    def alpha_of(site, row, pending):
        c = counts[site]
        pooled = c[row[0], row[1]].sum(0)  # the start's plays, whatever the action
        m = (pooled + alpha) / (pooled.sum() + len(pooled) * alpha)
        return alpha + strength * m + c[tuple(row)] + pending[site].get(tuple(row), 0.0)

    while len(chosen) < budget:
        pending = {s: {} for s in counts}
        picks = []
        for _ in range(min(batch, budget - len(chosen))):
            score = np.full(n, -np.inf)
            for i in np.flatnonzero(available):
                score[i] = sum(
                    float(dirichlet_eig(torch.as_tensor(alpha_of(s, key[i], pending))))
                    for s in counts
                )
            best = score.max()
            ties = np.flatnonzero(score >= best - 1e-9 * max(1.0, abs(best)))
            pick = int(ties[rng.integers(len(ties))]) if len(ties) > 1 else int(ties[0])
            picks.append(pick)
            available[pick] = False
            for s in counts:
                a = alpha_of(s, key[pick], pending)
                row = tuple(key[pick])
                pending[s][row] = pending[s].get(row, 0.0) + a / a.sum()
        played = oracle(np.asarray(picks))
        for s in counts:
            for i, v in zip(picks, played[s].tolist(), strict=True):
                counts[s][(*key[i], v)] += 1
        chosen += picks
    return chosen


@pytest.mark.parametrize(("batch", "strength"), [(1, 3.0), (5, 3.0), (5, 0.0)])
def test_the_greedy_choice_equals_one_recomputed_from_scratch(batch, strength):
    """explore keeps each row's gain, updates the scores of a pick's row's candidates by
    the gain's change and sums the shared prior's group counts once per batch; the
    choices are those of scores recomputed from the counts at every pick."""
    pool, oracle, _ = world(4)
    r = explore(
        NET, pool, oracle, 30, batch_size=batch, strategy="eig", pseudo_count=0.5,
        prior_strength=strength, seed=2,
    )  # fmt: skip
    want = greedy_from_scratch(pool, oracle, 30, batch, 0.5, strength, seed=2)
    assert r.chosen.tolist() == want


def test_the_tables_are_built_on_first_access_to_params():
    """A caller that refits on prefixes of the rows never builds explore's own tables
    (over every parent configuration: 38 million values for the can network)."""
    pool, oracle, _ = world(2)
    r = explore(NET, pool, oracle, 12, batch_size=4, strategy="eig", seed=1)
    assert "params" not in vars(r)
    fitted = fit(NET, r.rows, pseudo_count=0.01).params
    assert torch.equal(r.params["end.f0"].n, fitted["end.f0"].n)
    assert vars(r)["params"] is r.params  # built once


@pytest.mark.parametrize("strategy", STRATEGIES)
def test_a_resumed_run_makes_the_choices_of_an_uninterrupted_one(tmp_path, strategy):
    pool, oracle, _ = world(3)
    kw = dict(batch_size=3, strategy=strategy, seed=7, prior_strength=1.0)
    whole = explore(NET, pool, oracle, 30, **kw)
    path = tmp_path / "state.pt"
    first = explore(NET, pool, oracle, 12, checkpoint=path, **kw)
    assert first.chosen.tolist() == whole.chosen[:12].tolist()
    saved = ExplorationState.load(path)
    assert saved.chosen.tolist() == first.chosen.tolist()
    assert saved.counts["end.f0"].sum() == 12
    resumed = explore(NET, pool, oracle, 30, checkpoint=path, **kw)
    assert resumed.chosen.tolist() == whole.chosen.tolist()
    for site in whole.params.cpds:
        assert torch.equal(resumed.params[site].probs, whole.params[site].probs)
    with pytest.raises(ValueError, match="checkpoint"):
        explore(NET, pool, oracle, 30, checkpoint=path, **(kw | {"seed": 8}))


def test_eig_prefers_what_it_has_not_seen_and_spreads_a_batch():
    """A pair played many times gains almost nothing; a batch of copies of one unseen pair
    is not spent on that pair alone (the expected-count update lowers its second play)."""
    net = discrete_network([2], 2)
    # candidates 0..19: pair (0, a0) 20 times; 20..39 pair (1, a1) 20 times
    pool = net.encode_indices({"initial.f0": [0] * 20 + [1] * 20, "action": [0] * 20 + [1] * 20})

    def oracle(index):
        return net.encode_indices({"end.f0": [0] * len(index)})

    first = explore(net, pool, oracle, 12, batch_size=1, strategy="eig")
    played = pool["initial.f0"][torch.as_tensor(first.chosen)].tolist()
    assert played.count(0) == played.count(1) == 6  # alternates between the two rows
    assert bool((np.diff(first.scores) <= 1e-12).all())  # gains shrink as counts grow
    batch = explore(net, pool, oracle, 2, batch_size=2, strategy="eig")
    assert sorted(pool["initial.f0"][torch.as_tensor(batch.chosen)].tolist()) == [0, 1]


def test_sites_restrict_the_gain_to_the_end_sites_named():
    pool, oracle, _ = world(1)
    r = explore(NET, pool, oracle, 10, strategy="eig", sites=("end.f1",))
    assert len(r.chosen) == 10
    with pytest.raises(ValueError, match="sites"):
        explore(NET, pool, oracle, 10, sites=("initial.f0",))


def test_refusals_name_the_problem():
    pool, oracle, _ = world(0)
    mixed = EffectNetwork((Discrete("v", (0, 1)), Continuous("x", 1)), ("a", "b"))
    with pytest.raises(ValueError, match="tables only"):
        explore(mixed, {"initial.v": [0], "initial.x": [[0.0]], "action": ["a"]}, oracle, 1)
    chained = EffectNetwork(
        (Discrete("v", (0, 1)), Discrete("w", (0, 1))),
        ("a", "b"),
        parents={"end.w": ("initial.w", "action", "end.v")},
    )
    with pytest.raises(ValueError, match="end sites"):
        explore(chained, {"initial.v": [0], "initial.w": [0], "action": ["a"]}, oracle, 1)
    with pytest.raises(ValueError, match="budget"):
        explore(NET, pool, oracle, pool.n_rows + 1)
    with pytest.raises(ValueError, match="budget"):
        explore(NET, pool, oracle, 0)
    with pytest.raises(ValueError, match="batch_size"):
        explore(NET, pool, oracle, 3, batch_size=0)
    with pytest.raises(ValueError, match="strategy"):
        explore(NET, pool, oracle, 3, strategy="greedy")
    with pytest.raises(ValueError, match="pseudo_count"):
        explore(NET, pool, oracle, 3, pseudo_count=-1.0)
    with pytest.raises(ValueError, match="pseudo_count must be > 0"):
        explore(NET, pool, oracle, 3, pseudo_count=0.0)
    assert len(explore(NET, pool, oracle, 3, pseudo_count=0.0, strategy="random").chosen) == 3
    with pytest.raises(ValueError, match="pool must give"):
        explore(NET, {"initial.f0": [0], "action": ["a0"]}, oracle, 1)
    with pytest.raises(ValueError, match="oracle"):
        explore(NET, pool, lambda index: NET.encode_indices({"end.f0": index * 0}), 2)


# ------------------------------------------------------------------ the design-free prior
def test_with_pool_prior_refits_the_initial_and_action_tables_on_the_pool():
    pool, oracle, _ = world(seed=4)
    run = explore(NET, pool, oracle, 10, batch_size=5, strategy="eig", seed=0)
    params = with_pool_prior(NET, run.params, pool)
    ends = {"end.f0": torch.zeros(pool.n_rows, dtype=torch.long)} | {
        "end.f1": torch.zeros(pool.n_rows, dtype=torch.long)
    }
    on_pool = fit(NET, pool | NET.encode_indices(ends)).params  # end values do not matter
    for site in ("initial.f0", "initial.f1", "action"):
        torch.testing.assert_close(params[site].probs, on_pool[site].probs)
    for site in ("end.f0", "end.f1"):
        assert params[site] is run.params[site]


def test_the_choice_frequency_does_not_steer_the_inverse_query():
    """Both actions always open the door; the design played push ten times, pull once."""
    door = EffectNetwork((Discrete("open", (False, True)),), ("push", "pull"))
    rows = {
        "initial.open": [False] * 11,
        "action": ["push"] * 10 + ["pull"],
        "end.open": [True] * 11,
    }
    pool = {"initial.open": [False] * 20, "action": ["push", "pull"] * 10}
    fitted = fit(door, rows).params
    evidence = {"initial.open": [False], "end.open": [True]}
    skewed = infer_action(door, fitted, evidence).probs[0]
    assert float(skewed[0]) > 0.9  # the design's ten to one
    fair = infer_action(door, with_pool_prior(door, fitted, pool), evidence).probs[0]
    # equal prior: only the likelihoods (10 + a) / (10 + 2a) and (1 + a) / (1 + 2a) differ
    like = torch.tensor([10.01 / 10.02, 1.01 / 1.02], dtype=fair.dtype)
    torch.testing.assert_close(fair, like / like.sum())


def test_with_pool_prior_refuses_a_non_table_initial_site():
    net = EffectNetwork((Continuous("x", 1),), ("a", "b"))
    with pytest.raises(ValueError, match="refits tables"):
        with_pool_prior(net, None, {"initial.x": [[0.0]], "action": ["a"]})


class _RunsCode:
    """Pickles as a call of ``exec``: what a crafted checkpoint can hold."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (exec, (f"open({self.marker!r}, 'w').write('ran')",))


def test_a_checkpoint_is_read_without_running_anything_in_it(tmp_path):
    pool, oracle, _ = world(3)
    marker, path = tmp_path / "ran", tmp_path / "state.pt"
    torch.save({"chosen": _RunsCode(marker)}, path)
    with pytest.raises(
        ValueError, match=r"checkpoint .*state.pt.* is not a state saved by explore"
    ):
        explore(NET, pool, oracle, 6, checkpoint=path)
    assert not marker.exists()
    # a state explore saved still resumes (its generator state and settings included)
    path.unlink()
    first = explore(NET, pool, oracle, 3, checkpoint=path, seed=3)
    again = ExplorationState.load(path)
    assert again.rng == first.state.rng and again.settings == first.state.settings
