"""experiments.can_tossing: Table I's cases on a hand-made slice, its bookkeeping against
independent re-throws, the whole experiment at the tiny scale, and its settings' checks."""

from types import SimpleNamespace

import numpy as np
import pytest
import torch
from effect_networks.experiments.can_tossing import run as ct
from effect_networks.experiments.can_tossing import settings as cts
from effect_networks.experiments.cans import can_dataset, fit_can_network
from effect_networks.experiments.evaluation import ACCURACY_BINS, roc_auc
from effect_networks.experiments.harness.config import ConfigError
from effect_networks.experiments.harness.registry import experiment
from effect_networks.sim2d import field_throws

from tests.helpers import InlineExecutor


@pytest.fixture(scope="module")
def tiny(tiny_data_dir):
    """The tiny data set (3 configurations x 195 fields x 3 angles, one repeat) and its model."""
    data = can_dataset(tiny_data_dir, "tiny", progress=False)
    return data, fit_can_network(data, 0)


def hand_slice():
    """Rows (start, field, angle, repeat, count_before, count_after, throwable)."""
    rows = [
        (3, 20, 0, 0, 2, 1, True),  # start 3 (cans 0, 1): 2 -> 1
        (3, 20, 0, 1, 2, 0, True),  # same field, 2nd repeat: 2 -> 0
        (3, 21, 0, 0, 2, 1, True),  # another field reaching 1
        (3, 22, 0, 0, 2, 2, True),  # unchanged
        (3, 23, 1, 0, 2, 0, True),  # 30deg: not 0deg data, ignored
        (3, 0, 0, 0, 2, 2, False),  # unthrowable, ignored
        (1, 20, 0, 0, 1, 0, True),  # start 1 (can 0): 1 -> 0; never unchanged at 0deg
        (0, 20, 0, 0, 0, 0, True),  # the empty start is left aside
    ]
    cols = list(zip(*rows, strict=True))
    names = ("start_config", "field", "angle", "repeat", "count_before", "count_after")
    data = {n: np.array(c) for n, c in zip(names, cols, strict=False)}
    data["throwable"] = np.array(cols[-1])
    return SimpleNamespace(**data)


def test_table_one_cases_counts():
    start, desired = ct.table_one_cases(hand_slice(), "counts")
    # start 1: reached 0, plus unchanged 1; start 3: reached 0, 1, 2 (2 is the unchanged one)
    assert list(zip(start.tolist(), desired.tolist(), strict=True)) == [
        (1, 0),
        (1, 1),
        (3, 0),
        (3, 1),
        (3, 2),
    ]


def test_table_one_cases_actions():
    start, desired = ct.table_one_cases(hand_slice(), "actions")
    # one case per (start, field) whose first repeat changed the count, plus one unchanged
    # per start: start 1 field 20 (0), start 3 fields 20 and 21 (1 each)
    assert list(zip(start.tolist(), desired.tolist(), strict=True)) == [
        (1, 0),
        (1, 1),
        (3, 1),
        (3, 1),
        (3, 2),
    ]


def test_table_one_cases_refuses_an_unknown_protocol():
    with pytest.raises(ValueError, match="mode: 'rows' is not one of 'counts', 'actions'"):
        ct.table_one_cases(hand_slice(), "rows")


def test_table_one_bookkeeping_matches_independent_rethrows(tiny):
    data, model = tiny
    cases = ct.play_table_one(model, data, "counts", seed=7, rule="aim", progress=False)
    n = len(cases["start"])
    assert n > 0
    assert all(field_throws.is_throwable(int(f), 0) for f in cases["field"])
    # the training seeds are never reused
    assert not set(cases["seed"].tolist()) & set(data.seed.tolist())
    achieved = [
        field_throws.throw_at_field(
            int(s), int(f), 0, jitter=data.metadata["jitter"], seed=int(k)
        ).count_after
        for s, f, k in zip(cases["start"], cases["field"], cases["seed"], strict=True)
    ]
    assert cases["achieved"].tolist() == achieved
    summary = ct.summarise(cases)
    diff = cases["desired"] - np.array(achieved)
    by_hand = [
        (diff <= -3).sum(),
        *[(diff == d).sum() for d in (-2, -1, 0, 1, 2)],
        (diff >= 3).sum(),
    ]
    assert list(summary["histogram"].values()) == by_hand
    assert summary["exact_fraction"] == pytest.approx((diff == 0).mean())
    assert summary["n_cases"] == n


def test_plays_in_chunks_on_an_executor_equal_the_plays_here(tiny, monkeypatch):
    data, _ = tiny
    start, desired = ct.table_one_cases(data, "counts")
    fields = np.full(len(start), 7 * 15 + 7)  # the middle field: throwable at 0deg
    seeds = ct.fresh_seeds(3, cts.TABLE_I, len(start))
    here = ct.play(start, fields, 0.003, seeds, "here", progress=False)
    monkeypatch.setattr(ct, "CHUNK", 4)
    executor = InlineExecutor()
    there = ct.play(start, fields, 0.003, seeds, "there", progress=False, executor=executor)
    np.testing.assert_array_equal(here, there)
    assert executor.submitted == -(-len(start) // 4)
    assert len(ct.play(start[:0], fields[:0], 0.003, seeds[:0], "none", False, executor)) == 0


def test_best_field_of_a_deterministic_case(tiny):
    # A desired count that every 0deg training throw from a start reached with one field
    # only is answered by that field, whichever tie-break.
    data, model = tiny
    sel = (data.angle == 0) & data.throwable
    start, count = data.start_config[sel], data.count_after[sel]
    for s in np.unique(start):
        for c in np.unique(count[start == s]):
            fields = np.unique(data.field[sel][(start == s) & (count == c)])
            if len(fields) == 1:
                ev = ct.start_evidence(model, np.array([s])) | {"end.count": torch.as_tensor([c])}
                for rule in cts.RULES:
                    assert int(ct.choose(model, ev, rule)[0]) == int(fields[0])
                return
    pytest.skip("no desired count reached by a single field in the tiny data set")


def test_run_at_tiny_scale(tiny_data_dir, tmp_path):
    config = cts.CanTossingConfig(
        scale="tiny",
        data_dir=tiny_data_dir,
        n_demos=30,
        bound_repeats=2,
        curve_repeats=3,
        progress=False,
    )
    result = ct.run_can_tossing(config)
    assert result.n_cases > 0
    assert tuple(result.histogram) == ACCURACY_BINS
    assert sum(result.histogram.values()) == result.n_cases
    assert 0.0 <= result.exact_fraction <= 1.0
    assert result.paper["n_cases"] == 8603
    assert set(result.table_one) == set(cts.PROTOCOLS)
    assert result.table_one["counts"]["aim"]["n_cases"] == result.n_cases  # the headline
    assert 0.0 <= result.emulation["same_end_config"] <= 1.0
    imitation = result.imitation
    assert len(imitation["surprise"]) == imitation["n_throws"] == 30
    # a throw that failed against the usual outcomes also failed against the unperturbed one
    assert not np.any(np.array(imitation["failed_ordinary"]) & ~np.array(imitation["failed"]))
    # the pooled surprise: its aim error chosen on the validation draw, scores in [0, 1]
    validation = imitation["validation"]
    assert [v["sigma"] for v in validation["by_sigma"]] == list(cts.AIM_SIGMAS)
    scored = [v for v in validation["by_sigma"] if v["auc_ordinary"] is not None]
    best = max(scored, key=lambda v: v["auc_ordinary"])["sigma"] if scored else cts.AIM_SIGMAS[0]
    assert imitation["aim_sigma"] == best
    pooled = np.array(imitation["pooled_surprise"])
    assert len(pooled) == 30 and np.all((pooled >= 0) & (pooled <= 1 + 1e-12))
    for key, label in (("auc_pooled", "failed"), ("auc_ordinary_pooled", "failed_ordinary")):
        positive = np.array(imitation[label])
        if 0 < positive.sum() < len(positive):
            assert imitation[key] == pytest.approx(roc_auc(pooled, positive))
        else:
            assert imitation[key] is None
    # the physics bound: the simulator's replays' surprise on the same throws and labels
    bound = imitation["bound"]
    assert bound["repeats"] == 2 and bound["half_repeats"]["repeats"] == 1
    replayed = np.array(bound["surprise"])
    assert len(replayed) == 30 and np.all((replayed >= 0) & (replayed <= 1 + 1e-12))
    for key, label in (("auc", "failed"), ("auc_ordinary", "failed_ordinary")):
        positive = np.array(imitation[label])
        if 0 < positive.sum() < len(positive):
            assert bound[key] == pytest.approx(roc_auc(replayed, positive))
        else:
            assert bound[key] is None
    assert set(imitation["threshold"]) == {"failed", "failed_ordinary"}
    # the bound as its fresh replays grow: from 2 and 3 replays of each scored throw's aim
    curve = imitation["bound_curve"]
    assert [c["repeats"] for c in curve] == [2, 3]
    for c in curve:
        for key, label in (("auc", "failed"), ("auc_ordinary", "failed_ordinary")):
            positive = np.array(imitation[label])
            assert (c[key] is None) == (not 0 < positive.sum() < len(positive))
            assert c[key] is None or 0.0 <= c[key] <= 1.0
    # ours fitted on the bound's replays: the same labels, its own AUCs
    more = imitation["more_data"]
    assert more["throws_per_aim"] == 2 and more["aim_sigma"] in cts.AIM_SIGMAS
    assert (more["auc"] is None) == (imitation["auc"] is None)

    files = experiment("can_tossing").save(result, tmp_path)
    assert {f.name for f in files} >= {"can_tossing.json", "can_tossing.md"}
    again = ct.CanTossingResult.load(tmp_path / "can_tossing.json")
    assert again.to_json() == result.to_json()
    report = (tmp_path / "can_tossing.md").read_text()
    assert "pooled surprise" in report and report.count("\n| ") >= 9
    assert "physics bound" in report and "fraction of the bound" in report
    assert "bound as fresh replays" in report and "throws per aim (the bound's" in report
    assert (tmp_path / "can_tossing_table1.png").stat().st_size > 10_000


@pytest.mark.slow
def test_quick_scale_imitation_has_its_physics_bound(tmp_path):
    """The quick-scale experiment (as ``./reproduce --quick`` runs it) measures the bound for
    both failure labels, and its summary row shows it beside ours."""
    exp = experiment("can_tossing")
    result = ct.run_can_tossing(exp.config(**exp.quick, progress=False))
    imitation, bound = result.imitation, result.imitation["bound"]
    for key in ("auc", "auc_ordinary", "auc_pooled", "auc_ordinary_pooled"):
        assert imitation[key] is not None and 0.5 < bound[key] <= 1.0
    assert bound["repeats"] == 8
    assert [c["repeats"] for c in imitation["bound_curve"]] == [2, 4, 8, 16, 32]
    assert all(0.5 < c["auc"] <= 1.0 for c in imitation["bound_curve"])
    row = exp.rows(result, {})[-1]
    assert "simulator's own outcome frequencies" in row and "of it" in row
    assert {f.name for f in exp.save(result, tmp_path)} >= {
        "can_tossing_roc.png",
        "can_tossing_bound_curve.png",
    }


@pytest.mark.parametrize(
    ("field", "value", "words"),
    [
        ("n_demos", -10, "expected an integer >= 1"),
        ("aim_error", 1e9, "expected a number in (0, 0.32] m"),
        ("aim_error", 0.0, "out of range"),
        ("aim_error", float("nan"), "out of range"),
        ("seed", -1, "expected an integer >= 0"),
        ("n_ordinary", 2.5, "not an integer"),
        ("bound_repeats", 1, "expected an integer >= 2"),
        ("scale", "huge", "not one of 'full', 'quick', 'tiny'"),
        ("cases", "rows", "not one of 'counts', 'actions'"),
        ("executor", "threads:4", "not an executor"),
    ],
)
def test_config_names_the_field_at_fault(field, value, words):
    with pytest.raises(ConfigError, match=field) as raised:
        cts.CanTossingConfig(**{field: value})
    assert raised.value.field == field and words in str(raised.value)
