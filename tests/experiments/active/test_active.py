"""experiments.active: the pool and its oracle are the data set's 0° throws, the whole
pool's learner is the full-data network, a tiny run end to end, and the settings' checks."""

import dataclasses

import numpy as np
import pytest
import torch
from effect_networks.experiments.active import run as ex
from effect_networks.experiments.active import settings as exs
from effect_networks.experiments.can_tossing.run import table_one_cases
from effect_networks.experiments.can_tossing.settings import PROTOCOLS, RULES
from effect_networks.experiments.cans import CanModel, can_dataset, fit_can_network
from effect_networks.experiments.harness.config import ConfigError
from effect_networks.experiments.harness.registry import experiment
from effect_networks.inference import compile as compile_queries
from effect_networks.inference import fit_pooled, grid_kernel
from effect_networks.models.can_pyramid import config_index
from effect_networks.sim2d import geometry


@pytest.fixture(scope="module")
def tiny_run(tiny_data_dir):
    config = exs.ActiveConfig(
        scale="tiny",
        data_dir=tiny_data_dir,
        repeats=2,
        fractions=(0.1, 0.5, 1.0),
        batch_size=16,
        n_seeds=2,
        progress=False,
    )
    return config, ex.run_active(config)


def test_the_pool_is_table_one_s_training_throws_and_the_oracle_replays_them(tiny_data_dir):
    data = can_dataset(tiny_data_dir, "tiny", progress=False)
    net, pool, oracle, rows = ex.can_pool(data)
    sel = (data.angle == 0) & data.throwable
    assert pool.n_rows == int(sel.sum())
    assert set(pool) == {"initial.config", "initial.count", "action"}
    index = np.array([5, 0, pool.n_rows - 1])
    ends = oracle(index)
    masks = np.asarray(net.feature("config").states)[ends["end.config"].numpy()]
    np.testing.assert_array_equal(masks, data.end_config[sel][index])
    np.testing.assert_array_equal(pool["action"].numpy()[index], data.field[sel][index])
    # the network and its fit on the whole pool are Table I's own
    full = fit_can_network(data, 0)
    assert net == full.net
    from effect_networks.inference import fit

    params = fit(net, rows).params
    for site in params.cpds:
        assert torch.equal(params[site].probs, full.params[site].probs), site


def test_bound_by_repeats_chooses_on_the_first_m_replays_and_scores_on_the_second_half():
    # one start (mask 7), three fields, 4 replays each: counts reached
    replays = np.array([[[2, 3, 3, 3], [3, 3, 2, 2], [2, 2, 3, 3]]])
    throwable = np.array([True, True, True])
    cases = {"counts": (np.array([7]), np.array([3]))}
    # held out (replays 3-4): fields 0 and 2 succeed, field 1 never. m = 1 and m = 2 both
    # choose field 1 (it succeeded on its first replays): held out 0
    got = ex.bound_by_repeats(replays, [7], cases, throwable)
    assert got == {"counts": [0.0, 0.0]}
    replays[0, 1] = [2, 2, 2, 2]  # m = 1: a three-way tie, the lowest field 0; m = 2: field 0
    got = ex.bound_by_repeats(replays, [7], cases, throwable)
    assert got == {"counts": [1.0, 1.0]}


def test_bound_by_repeats_of_cases_that_repeat_equals_a_case_by_case_count():
    """Many of Table I's cases share a start and a desired count: they are scored once and
    counted once per case, as a loop over the cases scores them."""
    rng = np.random.default_rng(5)
    configs = [3, 7, 11]
    replays = rng.integers(0, 4, size=(3, 6, 8))
    throwable = np.array([True, False, True, True, True, False])
    start = rng.choice(configs, size=40)
    desired = rng.integers(0, 4, size=40)
    got = ex.bound_by_repeats(replays, configs, {"p": (start, desired)}, throwable)["p"]
    want = []
    for m in range(1, 5):
        rates = []
        for s, d in zip(start, desired, strict=True):
            success = replays[configs.index(int(s))][throwable] == d  # (fields, repeats)
            rates.append(success[:, 4:].mean(-1)[success[:, :m].mean(-1).argmax()])
        want.append(np.mean(rates))
    assert got == pytest.approx(want, abs=1e-15)


def test_cases_seen_counts_cases_some_row_reached():
    rows = {"initial.config": torch.tensor([0, 0, 1]), "end.count": torch.tensor([3, 2, 5])}
    cases = (torch.tensor([0, 0, 1, 1]), torch.tensor([2, 4, 5, 3]))
    assert ex.cases_seen(rows, cases) == pytest.approx(0.5)


def test_a_tiny_run_end_to_end(tiny_run, tiny_data_dir, tmp_path):
    config, r = tiny_run
    data = can_dataset(tiny_data_dir, "tiny", progress=False)
    assert r.n_pool == int(((data.angle == 0) & data.throwable).sum())
    assert r.budgets == [round(f * r.n_pool) for f in config.fractions]
    assert set(r.curves) == set(exs.LEARNERS)
    net, _, _, rows = ex.can_pool(data)
    seen_by_all = {}
    for p in PROTOCOLS:
        start, desired = table_one_cases(data, p)
        case_rows = (config_index(net, start), torch.as_tensor(desired))
        seen_by_all[p] = ex.cases_seen(rows, case_rows)
    assert seen_by_all["actions"] > 0.9
    for p in PROTOCOLS:
        assert r.n_cases[p] == len(table_one_cases(data, p)[0])
        assert 0 <= r.bound[p] <= 1
        assert r.bound_by_repeats[p] == [pytest.approx(r.bound[p])]  # 2 replays: m = 1 only
        for name, c in r.curves.items():
            for rule in exs.SCORES:
                assert len(c[p][rule]) == len(r.budgets)
                assert all(0 <= v <= 1 for v in c[p][rule])
                per_seed = np.asarray(r.curves_by_seed[name][p][rule])
                assert per_seed.shape == (2, len(r.budgets))
                np.testing.assert_allclose(per_seed.mean(0), c[p][rule])
                # the whole pool, whatever the order of choice, is the full data
                assert c[p][rule][-1] == pytest.approx(r.full[p][rule])
            for p in PROTOCOLS:  # the whole pool: every case's count some throw reached
                assert r.cases_seen[name][p][-1] == pytest.approx(seen_by_all[p])
            assert all(cov[-1] == r.n_pairs for cov in r.pairs_covered[name])
    for name in r.curves:  # CPU seconds of each budget point's Table I evaluation
        assert len(r.point_time_s[name]) == len(r.budgets)
        assert all(t >= 0 for t in r.point_time_s[name])
    files = experiment("active").save(r, tmp_path)
    assert [f.name for f in files] == ["active.json", "active.md", "active.png"]
    assert ex.ActiveResult.load(tmp_path / "active.json").to_json() == r.to_json()
    text = (tmp_path / "active.md").read_text()
    assert "| eig |" in text and "Physics bound (counts)" in text
    assert "Table I per budget point (CPU s" in text


def test_the_learners_give_the_same_results_in_turn_as_on_every_core(tiny_run):
    """Each learner and seed is a task (experiments.harness.parallel): the fixture's run on every core
    and the same run in this process agree bit for bit but for the times."""
    from effect_networks.experiments.harness.compare import compare_values

    config, result = tiny_run
    alone = ex.run_active(dataclasses.replace(config, workers=1))
    assert compare_values(result.to_dict(), alone.to_dict(), "active") == []
    assert "workers" not in alone.settings


def test_the_choice_is_scored_on_the_replays_of_the_chosen_field(tiny_run, tiny_data_dir):
    """Brute force: one case at a time, the replays of the field Table I's choice names."""
    config, r = tiny_run
    data = can_dataset(tiny_data_dir, "tiny", progress=False)
    model = fit_can_network(data, 0)
    replays, configs = ex.replay_counts(config)
    cases = {p: table_one_cases(data, p) for p in PROTOCOLS}
    got = ex.table_one_on_replays(model, cases, replays, configs)
    from effect_networks.experiments.can_tossing.run import start_evidence
    from effect_networks.experiments.cans import choose

    for p, (start, desired) in cases.items():
        for rule in RULES:
            rates = []
            for s, d in zip(start, desired, strict=True):
                ev = start_evidence(model, np.array([s])) | {"end.count": torch.tensor([d])}
                f = int(choose(model, ev, rule)[0])
                rates.append(np.mean(replays[configs.index(int(s)), f] == d))
            assert got[p][rule] == pytest.approx(np.mean(rates)), (p, rule)
            assert got[p][rule] == pytest.approx(r.full[p][rule])
    assert config_index(model.net, np.array(configs)).shape == (len(configs),)


def test_the_pooled_score_is_table_one_on_the_pooled_fit(tiny_run, tiny_data_dir):
    """The full data's ``pooled`` figure: Table I (tie-break aim) of ``fit_pooled``'s
    tables with the config's kernel, and the goal is measured against the best score."""
    config, r = tiny_run
    data = can_dataset(tiny_data_dir, "tiny", progress=False)
    net, _, _, rows = ex.can_pool(data)
    kernel = grid_kernel((geometry.N_ROWS, geometry.N_COLUMNS), config.pool_sigma)
    params = fit_pooled(net, rows, kernel, strength=config.pool_strength).params
    throwable = fit_can_network(data, 0).throwable
    model = CanModel(0, net, params, compile_queries(net, params), throwable)
    replays, configs = ex.replay_counts(config)
    cases = {p: table_one_cases(data, p) for p in PROTOCOLS}
    got = ex.table_one_on_replays(model, cases, replays, configs)
    for p in PROTOCOLS:
        assert r.full[p]["pooled"] == pytest.approx(got[p]["aim"])
        best = max(r.full[p].values())
        for name in r.curves:
            for rule in exs.SCORES:
                first = next(
                    (
                        b
                        for b, v in zip(r.budgets, r.curves[name][p][rule], strict=True)
                        if v >= best - exs.GOAL_POINTS
                    ),
                    None,
                )
                assert r.goal[name][p][rule] == first


def test_the_scoring_network_answers_table_one_as_the_can_network_does(tiny_data_dir):
    """The curve points fit and query :func:`experiments.active.run.scoring_network` (the end
    configuration parentless); the can network itself, fitted on the same rows, gives the
    same tables where the query reads them and the same answers and scores, bit for bit."""
    data = can_dataset(tiny_data_dir, "tiny", progress=False)
    net, pool, _, rows = ex.can_pool(data)
    scoring = ex.scoring_network(net)
    assert scoring.cpd("end.config").parents == ()
    assert scoring.cpd("end.count").parents == net.cpd("end.count").parents
    config = exs.ActiveConfig(scale="tiny", data_dir=tiny_data_dir, repeats=2, progress=False)
    replays, configs = ex.replay_counts(config)
    cases = {p: table_one_cases(data, p) for p in PROTOCOLS}
    throwable = fit_can_network(data, 0).throwable
    kernel = grid_kernel((geometry.N_ROWS, geometry.N_COLUMNS), config.pool_sigma)
    order = np.random.default_rng(3).permutation(rows.n_rows)
    for n in (7, rows.n_rows // 3):  # a few throws: most rows unplayed
        chosen = rows.rows(torch.as_tensor(order[:n]))
        for pooling in (None, (kernel, config.pool_strength)):
            small = ex._model(scoring, chosen, pool, throwable, pooling)
            whole = ex._model(net, chosen, pool, throwable, pooling)
            for site in ("initial.config", "initial.count", "action", "end.count"):
                assert torch.equal(small.params[site].probs, whole.params[site].probs), site
            for p, (start, desired) in cases.items():
                evidence = {
                    "initial.config": start,
                    "initial.count": np.array([bin(int(m)).count("1") for m in start]),
                    "end.count": desired,
                }
                a = small.compiled.infer_action(evidence, allowed=throwable)
                b = whole.compiled.infer_action(evidence, allowed=throwable)
                for field in ("probs", "best", "log_evidence", "unseen", "implausible"):
                    assert torch.equal(getattr(a, field), getattr(b, field)), (n, p, field)
    got = ex._scores(scoring, chosen, pool, throwable, (kernel, 0.5), cases, replays, configs)
    want = ex._scores(net, chosen, pool, throwable, (kernel, 0.5), cases, replays, configs)
    assert got == want


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("fractions", ()),
        ("fractions", (0.5, 0.2)),
        ("fractions", (0.0, 0.5)),
        ("fractions", (0.5, 1.5)),
        ("learners", ("eig", "bandit")),
        ("learners", ()),
        ("sites", ("end.colour",)),
        ("prior_strength", 0.0),
        ("pool_sigma", 0.0),
        ("pool_strength", -1.0),
        ("batch_size", 0),
        ("repeats", 1),
        ("n_seeds", 0),
        ("scale", "huge"),
    ],
)
def test_settings_are_checked(field, value):
    with pytest.raises(ConfigError) as error:
        exs.ActiveConfig(**{field: value})
    assert error.value.field == field
