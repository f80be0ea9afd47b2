"""sim2d.clock counts the wall time spent simulating, nested entry points once."""

import time

import numpy as np
from effect_networks.sim2d import clock
from effect_networks.sim2d.analytic_throw import throw


def test_nested_intervals_count_once_and_time_outside_does_not_count():
    before = clock.simulation_seconds()
    start = time.perf_counter()
    with clock.simulating():
        time.sleep(0.05)
        with clock.simulating():
            time.sleep(0.05)
    inside = time.perf_counter() - start
    time.sleep(0.05)
    counted = clock.simulation_seconds() - before
    assert 0.1 <= counted <= inside


def test_an_open_interval_counts_up_to_now():
    before = clock.simulation_seconds()
    with clock.simulating():
        time.sleep(0.05)
        assert clock.simulation_seconds() - before >= 0.05


def test_a_simulating_entry_point_is_counted():
    before = clock.simulation_seconds()
    throw(np.zeros((20_000, 2)) + [0.0, 1.0])
    assert clock.simulation_seconds() > before


def slow_chunk(seconds: float) -> dict:
    time.sleep(seconds)
    return {"x": np.zeros(1)}


def test_chunks_computed_count_and_chunks_read_back_do_not(tmp_path):
    """The wait on an executor's chunks counts as simulation; reading finished chunks
    back does not."""
    from effect_networks.sim2d.chunks import run_chunks

    from tests.helpers import InlineExecutor

    run = dict(executor=InlineExecutor(), progress=False)
    before = clock.simulation_seconds()
    run_chunks(tmp_path / "parts", {"p": 1}, slow_chunk, [(0.1,), (0.1,)], **run)
    assert clock.simulation_seconds() - before >= 0.2
    before = clock.simulation_seconds()
    start = time.perf_counter()
    run_chunks(tmp_path / "parts", {"p": 1}, slow_chunk, [(0.1,), (0.1,)], **run)
    assert clock.simulation_seconds() - before <= time.perf_counter() - start < 0.1
