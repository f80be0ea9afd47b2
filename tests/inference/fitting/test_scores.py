"""Scores: the log-likelihood against pgmpy, a closed form and a brute-force sum written
here from the fitted numbers; free parameters counted by hand; cross-validation folds."""

import dataclasses
import itertools
import math

import numpy as np
import pandas as pd
import pytest
import torch
from effect_networks.inference import fit, fit_em
from effect_networks.inference.fitting.missing import missing_log_likelihood
from effect_networks.inference.fitting.scores import (
    aic,
    bic,
    cross_validate,
    fold_of_rows,
    log_likelihood,
    n_parameters,
    take_rows,
)
from effect_networks.inference.queries.sampling import simulate
from effect_networks.models import (
    Continuous,
    Discrete,
    EffectNetwork,
    Parameter,
    random_params,
    to_frame,
)
from effect_networks.models.declaration import ACTION
from effect_networks.models.interop import to_pgmpy
from hypothesis import given, settings
from hypothesis import strategies as st
from pgmpy.structure_score import BIC, LogLikelihood
from scipy.special import log_softmax, logsumexp
from scipy.stats import multivariate_normal

from tests.helpers import brute_joint, discrete_network

# ------------------------------------------------------------------------ discrete: pgmpy
DISCRETE = {
    "fig1": EffectNetwork(
        (Discrete("a", (0, 1, 2)), Discrete("b", ("x", "y"))), ("push", "lift", "wait")
    ),
    "sparse": EffectNetwork(
        (Discrete("a", (0, 1, 2)), Discrete("b", ("x", "y"))),
        ("push", "lift"),
        parents={"end.a": ("action",), "end.b": ("initial.b", "action", "end.a")},
    ),
    "initial_chain": EffectNetwork(
        (Discrete("a", (0, 1, 2)), Discrete("b", ("x", "y")), Discrete("c", (True, False))),
        ("push", "lift"),
        parents={
            "initial.b": ("initial.a",),
            "end.c": ("initial.c",),
            "end.a": ("initial.a", "action"),
        },
    ),
}


def pgmpy_frame(model, rows):
    return pd.DataFrame({node: list(rows[node]) for node in model.nodes()})


@pytest.mark.parametrize("name", sorted(DISCRETE))
@pytest.mark.parametrize("n", [40, 600])
def test_discrete_scores_equal_pgmpy(name, n):
    """With the maximum-likelihood tables (pseudo-count 0, the counts pgmpy scores), the
    log-likelihood is pgmpy's ``LogLikelihood`` and ``bic_score`` its ``BIC`` (both over
    every node, the states declared: unseen configurations count as parameters)."""
    net = DISCRETE[name]
    rows = simulate(net, random_params(net, 3), n, seed=n)
    params = fit(net, rows, pseudo_count=0).params
    model, left_out = to_pgmpy(net, params)
    assert left_out == ()
    frame = pgmpy_frame(model, rows)
    states = {node: model.get_cpds(node).state_names[node] for node in model.nodes()}
    ll = log_likelihood(net, params, rows)
    assert ll.n_rows == n
    assert ll.total == pytest.approx(LogLikelihood(frame, states).score(model), rel=1e-12)
    assert ll.bic_score == pytest.approx(BIC(frame, states).score(model), rel=1e-12)
    assert bic(net, params, rows) == pytest.approx(-2 * BIC(frame, states).score(model))
    k = sum(
        (len(states[v]) - 1) * math.prod(len(states[p]) for p in model.get_parents(v))
        for v in model.nodes()
    )
    assert ll.n_parameters == n_parameters(net) == k
    assert aic(net, params, rows) == pytest.approx(-2 * ll.total + 2 * k)


def test_discrete_per_row_is_the_tables_product():
    net = DISCRETE["sparse"]
    params = random_params(net, 5)
    rows = simulate(net, params, 30, seed=1)
    enc = net.encode(rows)
    expected = np.zeros(30)
    for s in net.sites:
        probs = params[s.name].probs.numpy()
        index = tuple(enc[p].numpy() for p in net.cpd(s.name).parents) + (enc[s.name].numpy(),)
        expected += np.log(probs[index])
    got = log_likelihood(net, params, rows).per_row.numpy()
    np.testing.assert_allclose(got, expected, rtol=1e-12)


# ------------------------------------------------------------------- Gaussian: closed form
def test_linear_gaussian_equals_the_closed_form():
    """An end position given a continuous initial one and the action, and an outcome
    given both: the maximum-likelihood fit written in numpy (least squares per action,
    the residual covariance over n) and scipy's Gaussian log-densities."""
    net = EffectNetwork(
        (Continuous("pos", 2), Continuous("hit", 1, initial=False)), ("slide", "roll")
    )
    rng = np.random.default_rng(0)
    n = 300
    x = rng.normal([1.0, -2.0], [0.5, 2.0], size=(n, 2))
    a = rng.integers(0, 2, n)
    w = np.array([[[1.0, 0.3], [0.0, 0.8]], [[0.5, 0.0], [0.2, 1.1]]])
    end = np.einsum("nij,nj->ni", w[a], x) + rng.normal(0, 0.1, (n, 2)) + a[:, None]
    hit = x[:, :1] - 2 * a[:, None] + rng.normal(0, 0.3, (n, 1))
    rows = {
        "initial.pos": x,
        "action": [net.actions[i] for i in a],
        "end.pos": end,
        "end.hit": hit,
    }
    params = fit(net, rows, pseudo_count=0).params

    def gaussian(y):
        mean, cov = y.mean(0), np.cov(y.T, bias=True).reshape(y.shape[1], y.shape[1])
        return multivariate_normal(mean, cov).logpdf(y).reshape(-1)

    def regression(y, inputs):
        out = np.zeros(n)
        for k in range(2):
            z = np.c_[inputs[a == k], np.ones((a == k).sum())]
            beta = np.linalg.lstsq(z, y[a == k], rcond=None)[0]
            resid = y[a == k] - z @ beta
            cov = resid.T @ resid / len(resid)
            out[a == k] = multivariate_normal(np.zeros(y.shape[1]), cov).logpdf(resid)
        return out

    expected = gaussian(x) + np.log(np.bincount(a)[a] / n) + regression(end, x) + regression(hit, x)
    ll = log_likelihood(net, params, rows)
    np.testing.assert_allclose(ll.per_row.numpy(), expected, rtol=1e-9)
    # initial 2 + 3; action 1; end.pos 2 actions x (4 + 2 + 3); end.hit 2 x (2 + 1 + 1)
    assert ll.n_parameters == 5 + 1 + 18 + 8
    assert ll.bic == pytest.approx(-2 * expected.sum() + 32 * math.log(n))


# ------------------------------------------------------------------ mixed: brute force
def mixed_network(layout="grid"):
    """A discrete and a continuous feature, two actions, a force used by one of them on
    the position; ``end.seen`` is a softmax of the initial position."""
    return EffectNetwork(
        (Discrete("seen", ("no", "yes")), Continuous("pos", 1)),
        ("tap", "look"),
        (Parameter("force", (0.0,), (3.0,), (3,), ("tap",), "pos", layout=layout),),
    )


def log_normal(y, mean, tril):
    cov = tril @ tril.T
    return multivariate_normal(mean, cov).logpdf(y)


def brute_log_joint(net, params, row, skip=()):
    """log p of one full assignment: discrete sites as indices (the clusters included),
    continuous ones as 1-d arrays; every factor from the fitted numbers (those of the
    sites ``skip`` left out)."""
    total = 0.0
    for s in net.sites:
        if s.name in skip:
            continue
        cpd, p = net.cpd(s.name), params[s.name]
        index = tuple(row[q] for q in cpd.parents)
        if s.role in ("param", "cluster"):
            m = next(m for m in net.mixtures if s.name in m.sites)
            if not bool(m.uses[row[ACTION]]):
                if s.role == "cluster" and row[s.name] != 0:
                    return -math.inf
                continue
        if cpd.name == "table":
            total += math.log(p.probs.numpy()[index + (row[s.name],)])
            continue
        inputs = []
        for q in cpd.inputs:
            value = row[q]
            m = next((m for m in net.mixtures if q == m.value.site), None)
            if m is not None and not bool(m.uses[row[ACTION]]):
                value = np.zeros_like(value)  # ignored by an action not using it
            inputs.append(value)
        x = np.concatenate(inputs) if inputs else np.zeros(0)
        if cpd.name == "softmax":
            logits = p.weight.numpy()[index] @ x + p.bias.numpy()[index]
            total += log_softmax(logits)[row[s.name]]
        else:
            mean = p.weight.numpy()[index] @ x + p.bias.numpy()[index]
            total += log_normal(row[s.name], mean, p.scale_tril.numpy()[index])
    return total


def brute_log_likelihood(net, params, enc, latent_per_row):
    """Per row: ``logsumexp`` of the joint over the assignments of ``latent_per_row(i)``
    (a dict site -> candidate indices); a grid cluster not listed is the value's cell
    (0 for an action not using the parameter)."""
    out = []
    for i in range(enc.n_rows):
        base = {}
        for s in net.sites:
            if s.name in enc:
                v = enc[s.name][i]
                base[s.name] = int(v) if s.discrete else v.numpy()
        latent = latent_per_row(i)
        terms = []
        for values in itertools.product(*latent.values()):
            row = dict(base) | dict(zip(latent, values, strict=True))
            for m in net.mixtures:
                if m.cluster.site not in row:
                    uses = bool(m.uses[row[ACTION]])
                    theta = torch.as_tensor(row[m.value.site])[None]
                    row[m.cluster.site] = int(m.parameter.cluster_of(theta)[0]) if uses else 0
            terms.append(brute_log_joint(net, params, row))
        out.append(logsumexp(terms))
    return np.array(out)


def mixed_rows(net, params, n, seed):
    rows = simulate(net, params, n, seed=seed)
    rows.pop("cluster.force")  # the rows give the value; the model reads its cluster
    return rows


@pytest.mark.parametrize("seed", [0, 1])
def test_grid_mixture_per_row_equals_brute_force(seed):
    net = mixed_network("grid")
    params = random_params(net, seed)
    rows = mixed_rows(net, params, 25, seed)
    expected = brute_log_likelihood(net, params, net.encode(rows), lambda i: {})
    got = log_likelihood(net, params, rows).per_row.numpy()
    np.testing.assert_allclose(got, expected, rtol=1e-10)


def test_adaptive_mixture_sums_the_clusters_out():
    net = mixed_network("adaptive")
    params = random_params(net, 2)
    rows = mixed_rows(net, params, 25, 3)
    enc = net.encode(rows)
    clusters = net.mixture("force").cluster.size

    def latent(i):
        uses = bool(net.mixture("force").uses[enc[ACTION][i]])
        return {"cluster.force": range(clusters) if uses else [0]}

    expected = brute_log_likelihood(net, params, enc, latent)
    got = log_likelihood(net, params, rows).per_row.numpy()
    np.testing.assert_allclose(got, expected, rtol=1e-10)


def test_missing_values_are_summed_out():
    """A missing initial state, a missing end state and a missing action (only the actions
    that agree with the force being given count)."""
    net = mixed_network("grid")
    params = random_params(net, 4)
    rows = mixed_rows(net, params, 24, 5)
    n = 24
    masks = {
        "initial.seen": torch.arange(n) % 3 != 0,
        "end.seen": torch.arange(n) % 4 != 1,
        ACTION: torch.arange(n) % 5 != 2,
    }
    enc = net.encode(rows)
    uses = net.mixture("force").uses

    def latent(i):
        out = {}
        for site in ("initial.seen", "end.seen"):
            if not masks[site][i]:
                out[site] = range(2)
        if not masks[ACTION][i]:
            given = not bool(torch.isnan(enc["param.force"][i]).any())
            out[ACTION] = [a for a in range(2) if bool(uses[a]) == given]
        return out

    expected = brute_log_likelihood(net, params, enc, latent)
    got = log_likelihood(net, params, rows, masks=masks).per_row.numpy()
    np.testing.assert_allclose(got, expected, rtol=1e-10)
    assert not np.allclose(got, log_likelihood(net, params, rows).per_row.numpy())


def test_free_parameters_counted_by_hand():
    net = mixed_network("grid")
    # initial.seen 1; initial.pos 1 + 1; action 1; cluster.force: tap only, 3 - 1;
    # param.force: 3 clusters x (1 + 1); end.seen: softmax, 2 x 2 configurations x
    # (2 - 1)(1 + 1); end.pos: configurations (seen, action, cluster), 2 x 2 x 3, of which
    # look with clusters 1, 2 cannot happen: 8 reachable, each 1 x 2 weights + 1 + 1, less
    # the force's weight in the 2 configurations of look
    expected = 1 + 2 + 1 + 2 + 6 + 8 + (8 * 4 - 2)
    assert n_parameters(net) == expected
    assert n_parameters(mixed_network("adaptive")) == expected


def test_a_kind_without_a_count_is_named():
    from effect_networks.models.cpds import LinearGaussianCPD

    class Plain(LinearGaussianCPD):
        name = "plain"

        def n_free(self, reachable=None):
            return super(LinearGaussianCPD, self).n_free(reachable)

    net = EffectNetwork((Continuous("pos", 1),), ("tap",), kinds={"end.pos": Plain})
    with pytest.raises(NotImplementedError, match="'end.pos'.*n_free"):
        n_parameters(net)


# --------------------------------------------------------------------- cross-validation
def test_folds_partition_the_rows():
    for n, folds in [(10, 3), (11, 5), (7, 7)]:
        fold = fold_of_rows(n, folds, seed=4)
        sizes = torch.bincount(fold, minlength=folds)
        assert int(sizes.sum()) == n and int(sizes.max() - sizes.min()) <= 1
        assert torch.equal(fold, fold_of_rows(n, folds, seed=4))
    assert not torch.equal(fold_of_rows(50, 5, 0), fold_of_rows(50, 5, 1))
    with pytest.raises(ValueError, match="folds must be an int between 2 and the 4 rows"):
        fold_of_rows(4, 5, 0)
    with pytest.raises(ValueError, match="seed must be an int >= 0, got -1"):
        fold_of_rows(4, 2, -1)


def test_cross_validation_scores_each_fold_under_the_others_fit():
    net = DISCRETE["sparse"]
    rows = simulate(net, random_params(net, 1), 90, seed=2)
    cv = cross_validate(net, rows, folds=3, seed=7, pseudo_count=0.5)
    assert cv.folds == 3 and cv.per_fold.shape == (3,)
    assert cv.total == pytest.approx(float(cv.per_fold.sum()))
    assert torch.equal(cv.fold, fold_of_rows(90, 3, 7))
    for f in range(3):
        held = (cv.fold == f).nonzero().squeeze(-1).tolist()
        rest = (cv.fold != f).nonzero().squeeze(-1).tolist()
        train = {k: [v[i] for i in rest] for k, v in rows.items()}
        test = {k: [v[i] for i in held] for k, v in rows.items()}
        params = fit(net, train, pseudo_count=0.5).params
        assert float(cv.per_fold[f]) == pytest.approx(log_likelihood(net, params, test).total)
    # held out, the fit's own rows explain the data better than unseen ones
    in_sample = log_likelihood(net, fit(net, rows, pseudo_count=0.5).params, rows).total
    assert cv.total < in_sample


def test_cross_validation_of_adaptive_clusters_runs_em():
    grid = mixed_network("adaptive")
    net = EffectNetwork(  # closed forms only (no softmax): what fit_em fits
        grid.features, grid.actions, grid.parameters, parents={"end.seen": ("initial.seen",)}
    )
    rows = mixed_rows(net, random_params(net, 0), 120, 0)
    cv = cross_validate(net, rows, folds=2, seed=0, steps=3)
    assert cv.per_row.shape == (120,) and bool(torch.isfinite(cv.per_row).all())
    held = (cv.fold == 1).nonzero().squeeze(-1).tolist()
    rest = (cv.fold == 0).nonzero().squeeze(-1).tolist()
    params = fit_em(net, take_rows(rows, torch.tensor(rest)), steps=3).params
    expected = log_likelihood(net, params, take_rows(rows, torch.tensor(held))).total
    assert float(cv.per_fold[1]) == pytest.approx(expected)
    with pytest.raises(ValueError, match="masks: inference.fit_em"):
        cross_validate(net, rows, folds=2, masks={"initial.seen": [True] * 120})


def test_rows_fit_refuses_are_refused():
    net = mixed_network("grid")
    params = random_params(net, 0)
    rows = mixed_rows(net, params, 5, 0)
    del rows["end.pos"]
    with pytest.raises(ValueError, match="must give every site; missing \\['end.pos'\\]"):
        log_likelihood(net, params, rows)
    other = dataclasses.replace(net.parameters[0], bins=(4,))
    with pytest.raises(ValueError):
        log_likelihood(EffectNetwork(net.features, net.actions, (other,)), params, rows)


def test_the_scores_page_runs():
    """Every Python snippet of docs/scores.md, in order."""
    import re
    from pathlib import Path

    page = Path(__file__).resolve().parents[3] / "docs" / "scores.md"
    namespace: dict = {}
    for code in re.findall(r"^```python\n(.*?)^```", page.read_text(), re.S | re.M):
        exec(compile(code, str(page), "exec"), namespace)  # noqa: S102
    assert namespace["ll"].per_row.shape == (500,)
    assert namespace["ll_gaps"].total > namespace["ll"].total  # a value summed out
    # the gaps marked in the rows: the same labels summed out, and the positions' gaps
    # integrated out on top
    ll_rows = namespace["ll_rows"].per_row
    gapped = torch.isnan(torch.as_tensor(namespace["position"])).any(-1)
    assert torch.equal(ll_rows[~gapped], namespace["ll_gaps"].per_row[~gapped])
    assert not torch.allclose(ll_rows[gapped], namespace["ll_gaps"].per_row[gapped])
    assert namespace["cv"].per_fold.shape == (5,)
    assert namespace["choice"].chosen in namespace["choice"].candidates


@settings(max_examples=15, deadline=None)
@given(
    cards=st.lists(st.integers(2, 3), min_size=1, max_size=2),
    n_actions=st.integers(1, 3),
    seed=st.integers(0, 2**16),
)
def test_random_discrete_networks_with_gaps_sum_the_joint(cards, n_actions, seed):
    """Any Fig. 1 discrete network, any values missing: each row's likelihood is the
    brute-force joint summed over the assignments that agree with what it gives."""
    net = discrete_network(cards, n_actions)
    params = random_params(net, seed)
    n = 12
    rows = simulate(net, params, n, seed=seed)
    g = torch.Generator().manual_seed(seed)
    sites = [s.name for s in net.sites]
    masks = {s: torch.rand(n, generator=g) > 0.4 for s in sites}
    joint = brute_joint(net, params)
    enc = net.encode(rows)
    names = [f.name for f in net.features]

    def agrees(i, init, a, end):
        given = {f"initial.{f}": v for f, v in zip(names, init, strict=True)}
        given |= {f"end.{f}": v for f, v in zip(names, end, strict=True)} | {ACTION: a}
        return all(not masks[s][i] or int(enc[s][i]) == v for s, v in given.items())

    expected = [
        math.log(sum(p for (init, a, end), p in joint.items() if agrees(i, init, a, end)))
        for i in range(n)
    ]
    got = log_likelihood(net, params, rows, masks=masks).per_row.numpy()
    np.testing.assert_allclose(got, expected, rtol=1e-10, atol=1e-12)


def test_scores_take_a_frame_as_they_take_its_mapping():
    net = EffectNetwork(
        features=(Discrete("v", (False, True)), Continuous("p", 1)), actions=("a", "b")
    )
    rng = np.random.default_rng(0)
    n = 300
    act = rng.choice(net.actions, n)
    v = rng.random(n) < 0.5
    p = rng.normal(size=(n, 1))
    data = {
        "initial.v": v,
        "initial.p": p,
        "action": act,
        "end.v": v ^ (act == "a"),
        "end.p": p + (act == "b")[:, None] + rng.normal(0.0, 0.1, (n, 1)),
    }
    params = fit(net, data).params
    rows = simulate(net, params, 200, seed=1)
    frame = to_frame(net, rows)
    assert log_likelihood(net, params, frame).total == log_likelihood(net, params, rows).total
    held_frame = cross_validate(net, frame, folds=3).per_row
    held_rows = cross_validate(net, rows, folds=3).per_row
    assert torch.equal(held_frame, held_rows)


# ------------------------------------------------------- gaps marked in the rows themselves
def gapped_network(layout="grid"):
    """A discrete and a 2-d continuous feature, a force used by ``tap`` on the position;
    no discrete site reads a continuous one, so every gap has a closed form."""
    return EffectNetwork(
        (Discrete("seen", ("no", "yes")), Continuous("pos", 2)),
        ("tap", "look"),
        (Parameter("force", (0.0,), (3.0,), (3,), ("tap",), "pos", layout=layout),),
        parents={"end.seen": ("initial.seen", "action")},
    )


def punched(net, rows, seed, p=0.3):
    """``rows`` with None at discrete labels (the action included) and NaN at continuous
    dimensions, each with probability ``p``; the first two rows complete, the third
    missing every continuous dimension."""
    rng = np.random.default_rng(seed)
    out = dict(rows)
    n = len(rows[ACTION])
    for site in ("initial.seen", "end.seen", ACTION):
        labels = np.asarray(rows[site], dtype=object)
        labels[(rng.random(n) < p) & (np.arange(n) >= 2)] = None
        out[site] = labels
    for site in ("initial.pos", "end.pos"):
        values = np.array(rows[site], dtype=float)
        values[(rng.random(values.shape) < p) & (np.arange(n) >= 2)[:, None]] = np.nan
        values[2] = np.nan
        out[site] = values
    return out


def brute_gapped(net, params, rows):
    """Per row, by hand: the sum over the completions of its missing labels (a missing
    action among those that agree with the force being given; an adaptive cluster summed
    out, a grid one the value's cell) of the discrete factors times scipy's density of the
    observed continuous dimensions under the joint Gaussian of (initial.pos, end.pos),
    written here as its two blocks."""
    mixture = net.mixture("force")
    adaptive = mixture.parameter.adaptive
    p0, p1 = params["initial.pos"], params["end.pos"]
    mean0 = p0.bias.numpy()
    cov0 = p0.scale_tril.numpy() @ p0.scale_tril.numpy().T
    states = net.feature("seen").states
    labels = {"initial.seen": states, "end.seen": states, ACTION: net.actions}
    out = []
    for i in range(len(rows[ACTION])):
        force = np.asarray(rows["param.force"][i], dtype=float).reshape(1)
        given = not np.isnan(force).any()
        choices = {}
        for site, states in labels.items():
            v = rows[site][i]
            if v is None:
                ok = range(len(states))
                if site == ACTION:
                    ok = [a for a in ok if bool(mixture.uses[a]) == given]
                choices[site] = list(ok)
            else:
                choices[site] = [states.index(v)]
        value = np.concatenate([rows["initial.pos"][i], rows["end.pos"][i]])
        seen = ~np.isnan(value)
        terms = []
        for combo in itertools.product(*choices.values()):
            row = dict(zip(choices, combo, strict=True)) | {"param.force": force}
            uses = bool(mixture.uses[row[ACTION]])
            cells = [int(mixture.parameter.cluster_of(torch.as_tensor(force)[None])[0])]
            if adaptive:
                cells = list(range(mixture.cluster.size))
            for cluster in cells if uses else [0]:
                row["cluster.force"] = cluster
                log_discrete = brute_log_joint(net, params, row, skip=("initial.pos", "end.pos"))
                index = (row["initial.seen"], row[ACTION], cluster)
                w = p1.weight.numpy()[index]
                w_pos, w_force = w[:, :2], w[:, 2:]
                shift = p1.bias.numpy()[index] + (w_force @ force if uses else 0.0)
                noise = p1.scale_tril.numpy()[index]
                mean = np.concatenate([mean0, w_pos @ mean0 + shift])
                cov = np.block(
                    [
                        [cov0, cov0 @ w_pos.T],
                        [w_pos @ cov0, w_pos @ cov0 @ w_pos.T + noise @ noise.T],
                    ]
                )
                density = 0.0
                if seen.any():
                    marginal = multivariate_normal(mean[seen], cov[np.ix_(seen, seen)])
                    density = marginal.logpdf(value[seen])
                terms.append(log_discrete + density)
        out.append(logsumexp(terms))
    return np.array(out)


@pytest.mark.parametrize("layout", ["grid", "adaptive"])
def test_rows_with_gaps_score_as_the_joint_gaussian_by_hand(layout):
    net = gapped_network(layout)
    params = random_params(net, 3)
    rows = punched(net, mixed_rows(net, params, 30, 4), seed=5)
    ll = log_likelihood(net, params, rows)
    np.testing.assert_allclose(ll.per_row.numpy(), brute_gapped(net, params, rows), rtol=1e-9)
    # a complete row scores as it does alone, bit for bit
    complete = torch.tensor([0, 1])
    alone = log_likelihood(net, params, take_rows(rows, complete)).per_row
    assert torch.equal(ll.per_row[complete], alone)
    if layout == "grid":  # the quantity EM raises (which reads a grid cluster only)
        assert ll.total == pytest.approx(missing_log_likelihood(net, params, rows), rel=1e-12)


def test_labels_missing_in_the_rows_score_as_masks_do():
    net = gapped_network()
    params = random_params(net, 0)
    rows = mixed_rows(net, params, 20, 1)
    masks = {"initial.seen": torch.arange(20) % 3 != 0, ACTION: torch.arange(20) % 4 != 1}
    marked = dict(rows)
    for site, mask in masks.items():
        marked[site] = [v if keep else None for v, keep in zip(rows[site], mask, strict=True)]
    expected = log_likelihood(net, params, rows, masks=masks).per_row
    assert torch.equal(log_likelihood(net, params, marked).per_row, expected)


def test_gaps_without_a_closed_form_are_refused_by_name():
    net = mixed_network()  # end.seen is a softmax of initial.pos
    params = random_params(net, 0)
    rows = mixed_rows(net, params, 20, 0)
    pos = np.array(rows["initial.pos"], dtype=float)
    pos[3] = np.nan
    with pytest.raises(ValueError, match="'initial.pos': row 3 .*'end.seen' \\(softmax\\)"):
        log_likelihood(net, params, rows | {"initial.pos": pos})
    # a tap's force is never missing: NaN means that the action does not use it
    action = np.array(rows[ACTION], dtype=object)
    action[0] = "tap"
    with pytest.raises(ValueError, match="'param.force': row 0 has action 'tap', which uses"):
        log_likelihood(net, params, rows | {ACTION: action})


def test_cross_validation_keeps_each_folds_gaps_and_fits_by_em():
    net = gapped_network()
    rows = punched(net, mixed_rows(net, random_params(net, 1), 60, 2), seed=3, p=0.15)
    cv = cross_validate(net, rows, folds=2, seed=0)
    assert bool(torch.isfinite(cv.per_row).all())
    for f in range(2):
        held = (cv.fold == f).nonzero().squeeze(-1)
        rest = (cv.fold != f).nonzero().squeeze(-1)
        result = fit(net, take_rows(rows, rest))
        assert len(result.log_likelihoods) > 1  # EM ran over the training folds' gaps
        expected = log_likelihood(net, result.params, take_rows(rows, held)).per_row
        assert torch.equal(cv.per_row[held], expected)
    adaptive = gapped_network("adaptive")
    with pytest.raises(ValueError, match="missing values at \\['action', 'end.pos'"):
        cross_validate(adaptive, rows, folds=2)


def test_a_frame_with_gaps_scores_as_its_rows():
    net = gapped_network()
    params = random_params(net, 2)
    rows = punched(net, mixed_rows(net, params, 40, 3), seed=4)
    frame = to_frame(net, mixed_rows(net, params, 40, 3))
    frame["initial.seen"] = pd.Series(rows["initial.seen"], dtype=object)
    frame["action"] = pd.Series(rows[ACTION], dtype=object)
    frame["end.seen"] = pd.Series(rows["end.seen"], dtype=object)
    for site in ("initial.pos", "end.pos"):
        for d in range(2):
            frame[f"{site}[{d}]"] = rows[site][:, d]
    got = log_likelihood(net, params, frame).per_row
    assert torch.equal(got, log_likelihood(net, params, rows).per_row)
    assert bool(torch.isfinite(got).all())
