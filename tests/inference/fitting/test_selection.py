"""Choosing a parameter's clusters: on an effect that steps where the force crosses a
quarter, the scores prefer the four cells that resolve the steps, and not more."""

import numpy as np
import pytest
from effect_networks.inference import fit
from effect_networks.inference.fitting.scores import cross_validate, log_likelihood, n_parameters
from effect_networks.inference.fitting.selection import select_clusters
from effect_networks.models import Continuous, EffectNetwork, Parameter


def step_network(bins=(1,), layout="grid"):
    return EffectNetwork(
        (Continuous("shift", 1, initial=False),),
        ("push",),
        (Parameter("force", (0.0,), (1.0,), bins, ("push",), "shift", layout=layout),),
    )


def step_rows(n=400, seed=0):
    """The shift is 0 or 1 by the force's quarter (0, 1, 0, 1), with noise of 0.05."""
    rng = np.random.default_rng(seed)
    force = rng.uniform(0, 1, (n, 1))
    level = np.array([0.0, 1.0, 0.0, 1.0])[np.minimum((4 * force[:, 0]).astype(int), 3)]
    shift = level[:, None] + rng.normal(0, 0.05, (n, 1))
    return {"action": ["push"] * n, "param.force": force, "end.shift": shift}


CANDIDATES = [1, 2, 3, 4, 6, 8, 12]


def test_bic_chooses_the_cells_that_resolve_the_steps():
    rows = step_rows()
    choice = select_clusters(step_network(), rows, CANDIDATES, score="bic")
    assert choice.chosen.bins == (4,) and choice.chosen.layout == "grid"
    table = {row["bins"]: row for row in choice.table()}
    assert [row["chosen"] for row in choice.table()] == [b == 4 for b in CANDIDATES]
    for b in CANDIDATES:  # each row is the BIC of the fit on all rows
        net = step_network((b,))
        ll = log_likelihood(net, fit(net, rows).params, rows)
        assert table[(b,)]["log_likelihood"] == pytest.approx(ll.total)
        assert table[(b,)]["bic"] == pytest.approx(ll.bic)
        assert table[(b,)]["n_parameters"] == n_parameters(net)
    # the finer grids resolve the steps too: the penalty tells them apart
    assert table[(8,)]["log_likelihood"] > table[(3,)]["log_likelihood"]
    assert "| **4** | **grid** |" in choice.to_markdown()


def test_heldout_prefers_resolving_cells_and_matches_cross_validation():
    rows = step_rows(300, seed=1)
    choice = select_clusters(step_network(), rows, [2, 3, 4, 8], folds=3, seed=2)
    assert choice.chosen.bins in {(4,), (8,)}
    assert choice.candidates[0].log_likelihood < choice.chosen.log_likelihood - 100
    expected = cross_validate(step_network((3,)), rows, 3, 2).total
    assert choice.candidates[1].log_likelihood == pytest.approx(expected)


def test_layouts_and_a_factory():
    rows = step_rows(300, seed=3)
    choice = select_clusters(
        lambda bins, layout: step_network(bins, layout),
        rows,
        [(2,), (4,)],
        layouts=("grid", "adaptive"),
        score="bic",
        steps=5,
    )
    assert [(c.bins, c.layout) for c in choice.candidates] == [
        ((2,), "grid"),
        ((2,), "adaptive"),
        ((4,), "grid"),
        ((4,), "adaptive"),
    ]
    assert choice.chosen.bins == (4,)


def test_refusals_name_the_argument():
    rows = step_rows(20)
    net = step_network()
    with pytest.raises(ValueError, match="score must be one of"):
        select_clusters(net, rows, [2], score="aic")
    with pytest.raises(ValueError, match="layouts must be some of"):
        select_clusters(net, rows, [2], layouts=("cells",))
    with pytest.raises(ValueError, match="parameter 'speed' is not one of"):
        select_clusters(net, rows, [2], parameter="speed")
    with pytest.raises(ValueError, match="candidate 0: expected a positive int"):
        select_clusters(net, rows, [0])
    with pytest.raises(ValueError, match="candidates is empty"):
        select_clusters(net, rows, [])
    with pytest.raises(ValueError, match="data is Evidence, encoded for one network"):
        select_clusters(net, net.encode(rows), [2])
    with pytest.raises(ValueError, match="data gives 'cluster.force'"):
        select_clusters(net, rows | {"cluster.force": [0] * 20}, [2])
    with pytest.raises(ValueError, match="data gives 'cluster.force'"):
        select_clusters(
            lambda b, layout: step_network(b), rows | {"cluster.force": [0] * 20}, [(2,)]
        )


def load_benchmark():
    import importlib.util
    import sys
    from pathlib import Path

    folder = Path(__file__).resolve().parents[3] / "benchmarks"
    spec = importlib.util.spec_from_file_location(
        "benchmark_select_clusters", folder / "select_clusters.py"
    )
    module = importlib.util.module_from_spec(spec)
    sys.path.insert(0, str(folder))  # the benchmarks import their neighbours
    try:
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(folder))
    return module


def test_the_throw_benchmark_runs_small():
    bench = load_benchmark()
    result = bench.compare(400, [1, 3], folds=2, seed=1)
    assert [row["bins"] for row in result["table"]] == [1, 3]
    assert result["heldout_choice"] in (1, 3) and result["best_range"]
    assert "| 3 |" in bench.report(result, 400, True)


@pytest.mark.slow
def test_on_noisy_throws_the_chosen_grid_re_throws_near_the_best():
    """29,000 throws with release noise (the throwing experiment's size): both scores
    choose a grid whose validation re-throw RMS is within 5 % of the best grid's."""
    result = load_benchmark().compare(29_000, [4, 6, 8, 10, 12, 14, 16, 20], seed=0)
    assert result["heldout_choice"] in result["best_range"]
    assert result["bic_choice"] in result["best_range"]


def test_rows_with_gaps_are_scored_as_fit_reads_them():
    # a fifth of the shifts not measured: every candidate is fitted by EM over them and
    # scored with them integrated out
    rows = step_rows(300, seed=5)
    shift = rows["end.shift"].copy()
    shift[np.random.default_rng(5).random(300) < 0.2] = np.nan
    rows = rows | {"end.shift": shift}
    choice = select_clusters(step_network(), rows, [2, 4, 8], score="bic")
    assert choice.chosen.bins == (4,)
    for candidate in choice.candidates:
        net = step_network(candidate.bins)
        ll = log_likelihood(net, fit(net, rows).params, rows)
        assert np.isfinite(ll.total) and ll.n_rows == 300
        assert candidate.bic == pytest.approx(ll.bic)
