"""Reliability bins and the expected calibration error, by hand and as properties."""

import numpy as np
import pytest
from effect_networks.experiments.calibration import TOLERANCE, plot_reliability, reliability
from hypothesis import given
from hypothesis import strategies as st


def test_reliability_by_hand():
    predicted = [0.05, 0.08, 0.55, 0.95, 1.0]
    measured = [0.0, 0.2, 0.5, 1.0, 0.9]
    r = reliability(predicted, measured, bins=10)
    assert [(b["low"], b["n"]) for b in r["bins"]] == [(0.0, 2), (0.5, 1), (0.9, 2)]
    first = r["bins"][0]
    assert first["predicted"] == pytest.approx(0.065) and first["measured"] == pytest.approx(0.1)
    # bins: |0.065 - 0.1| = 0.035 (2 goals), 0.05 (1), |0.975 - 0.95| = 0.025 (2)
    assert r["ece"] == pytest.approx((2 * 0.035 + 0.05 + 2 * 0.025) / 5)
    assert r["mean_abs"] == pytest.approx((0.05 + 0.12 + 0.05 + 0.05 + 0.1) / 5)
    assert r["within"] == pytest.approx(3 / 5)  # gaps of exactly 5 points count
    assert r["mean_predicted"] == pytest.approx(np.mean(predicted))
    assert r["n"] == 5


def test_a_calibrated_prediction_has_no_error_and_no_goals_give_none():
    r = reliability([0.2, 0.2, 0.7], [0.2, 0.2, 0.7])
    assert r["ece"] == 0 and r["mean_abs"] == 0 and r["within"] == 1
    empty = reliability([], [])
    assert empty["n"] == 0 and empty["ece"] is None and empty["bins"] == []


@given(
    st.lists(st.tuples(st.floats(0, 1), st.floats(0, 1)), min_size=1, max_size=60),
    st.integers(1, 20),
)
def test_ece_lies_between_the_mean_gap_of_the_means_and_the_mean_gap(pairs, bins):
    """Binning averages before the gap is taken: never more than the mean gap per goal, never
    less than the gap between the overall means."""
    p, m = map(list, zip(*pairs, strict=True))
    r = reliability(p, m, bins=bins)
    assert sum(b["n"] for b in r["bins"]) == len(p)
    assert (
        abs(r["mean_predicted"] - r["mean_measured"]) - 1e-12 <= r["ece"] <= r["mean_abs"] + 1e-12
    )
    assert 0 <= r["within"] <= 1
    assert r["within"] == pytest.approx(np.mean(np.abs(np.subtract(p, m)) <= TOLERANCE + 1e-12))


def test_bad_input_is_a_value_error():
    with pytest.raises(ValueError, match="equal"):
        reliability([0.1, 0.2], [0.1])
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        reliability([1.2], [0.1])
    with pytest.raises(ValueError, match="bins"):
        reliability([0.1], [0.1], bins=0)


def test_the_diagram_is_drawn(tmp_path):
    r = reliability([0.1, 0.5, 0.9], [0.0, 0.6, 1.0])
    path = plot_reliability(
        [("a", {"model": r}), ("b", {"model": r, "other": r})], tmp_path / "r.png"
    )
    assert path.stat().st_size > 5_000
