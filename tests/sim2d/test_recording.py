"""Tests of recorded throws (sim2d/recording.py) and the pictures made of them."""

import pytest
from effect_networks.sim2d import geometry, render
from effect_networks.sim2d.field_throws import throw_at_field
from effect_networks.sim2d.recording import record_throw


def test_a_recorded_throw_ends_as_the_unrecorded_one():
    args = (geometry.FULL_PYRAMID, 12 * geometry.N_COLUMNS + 7, 1)
    recording = record_throw(*args, jitter=0.003, seed=0, frame_interval=0.1)
    assert recording.outcome == throw_at_field(*args, jitter=0.003, seed=0)
    n = len(recording.times)
    assert recording.cans.shape == (n, geometry.N_CANS, 3) and recording.ball.shape == (n, 2)
    with pytest.raises(ValueError, match="frame_interval=0"):
        record_throw(*args, frame_interval=0)


def test_the_throw_pictures_name_ball_and_cans():
    from matplotlib.figure import Figure

    ax = Figure().subplots()
    render._legend(ax)
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels == ["ball", "cans thrown off", "cans kept"]
    render._legend(ax, path=True)
    assert len(ax.get_legend().get_texts()) == 5
