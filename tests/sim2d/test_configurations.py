"""Tests of the physics enumeration of stable configurations (sim2d/configurations.py)."""

import contextlib
import errno
import itertools
import json
import os
from concurrent.futures import Future, ProcessPoolExecutor
from pathlib import Path

import pytest
from effect_networks.sim2d import configurations, geometry, materials
from effect_networks.sim2d.configurations import settles, stable_configurations

# Written out by hand from the pyramid sketch, not taken from the code under test.
RESTS_ON = {4: (0, 1), 5: (1, 2), 6: (2, 3), 7: (4, 5), 8: (5, 6), 9: (7, 8)}


def fully_supported_by_hand(members: set[int]) -> bool:
    return all(set(RESTS_ON[i]) <= members for i in members if i in RESTS_ON)


def some_can_floats(members: set[int]) -> bool:
    return any(not set(RESTS_ON[i]) & members for i in members if i in RESTS_ON)


ALL_SUBSETS = [
    set(c) for n in range(11) for c in itertools.combinations(range(10), n)
]  # 1024 subsets


def test_all_42_fully_supported_configurations_stand():
    supported = [m for m in ALL_SUBSETS if fully_supported_by_hand(m)]
    assert len(supported) == 42
    stable = set(stable_configurations())
    assert all(geometry.cans_to_mask(m) in stable for m in supported)
    assert 0 in stable and geometry.FULL_PYRAMID in stable


def test_no_configuration_with_an_unsupported_can_stands():
    stable = set(stable_configurations())
    floating = [geometry.cans_to_mask(m) for m in ALL_SUBSETS if some_can_floats(m)]
    assert floating and not stable & set(floating)


def test_direct_simulation():
    assert settles(geometry.FULL_PYRAMID) and settles(0)
    assert not settles(geometry.cans_to_mask([9])), "a can in the air falls"
    # a can that lost one supporter with nothing above it tips over
    assert not settles(geometry.cans_to_mask([0, 4]))


def test_enumeration_result():
    stable = stable_configurations()
    assert list(stable) == sorted(set(stable))
    assert 42 < len(stable) < 1024, "pinned cans add configurations beyond the 42"
    assert all(configurations.is_stable(m) for m in stable)


@pytest.fixture(scope="session")
def simulated_serially():
    """All 1024 subsets simulated once in this process, without the cache (seconds), shared
    by the tests that compare other ways of running the enumeration with it."""
    return stable_configurations(cache=False)


#: The executors' quick tests enumerate the 64 subsets of cans 0-5 (the bottom row and
#: two cans above it; 28 of them stand) in 8 batches: batching, order and flags go
#: through each executor as in the full run, which the tests marked slow repeat.
SUBSETS = 64


@contextlib.contextmanager
def first_64_subsets(monkeypatch):
    """The enumeration cut to the masks below 64. Inside it the on-disk cache must not be
    read: it would be refused as holding masks beyond 6 cans, and rewritten."""
    with monkeypatch.context() as patch:
        patch.setattr(geometry, "N_CANS", 6)
        patch.setattr(configurations, "_BATCH", 8)
        yield


def test_the_cache_is_the_serial_simulation(simulated_serially):
    assert simulated_serially == stable_configurations()


def test_enumeration_is_deterministic_serial_and_parallel(simulated_serially, monkeypatch):
    with first_64_subsets(monkeypatch), ProcessPoolExecutor(max_workers=2) as executor:
        parallel = stable_configurations(cache=False, executor=executor)
    assert parallel == tuple(m for m in simulated_serially if m < SUBSETS)
    assert 0 < len(parallel) < SUBSETS


@pytest.mark.slow
def test_enumeration_in_a_process_pool_on_all_1024_subsets(simulated_serially):
    with ProcessPoolExecutor(max_workers=2) as executor:
        parallel = stable_configurations(cache=False, executor=executor)
    assert parallel == simulated_serially


def test_enumeration_is_cached(tmp_path, monkeypatch, simulated_serially):
    # the simulation is the shared one: this test is about the cache around it
    monkeypatch.setattr(configurations, "_compute", lambda executor=None: simulated_serially)
    file = tmp_path / "stable.json"
    first = stable_configurations(path=file)
    assert first == simulated_serially
    assert json.loads(file.read_text())["stable"] == list(first)

    def no_simulation(executor=None):
        raise AssertionError("recomputed although cached")

    monkeypatch.setattr(configurations, "_compute", no_simulation)
    assert stable_configurations(path=file) == first
    # a cache written under other constants is not trusted
    data = json.loads(file.read_text())
    data["key"] = "other constants"
    file.write_text(json.dumps(data))
    monkeypatch.setattr(configurations, "_compute", lambda executor=None: (0,))
    assert stable_configurations(path=file) == (0,)


def test_cache_key_follows_the_constants(monkeypatch):
    key = configurations._cache_key()
    monkeypatch.setattr(materials, "FRICTION_CAN_CAN", 0.5)
    assert configurations._cache_key() != key


def test_bad_mask():
    with pytest.raises(ValueError, match=r"mask=-1 .*10-bit"):
        settles(-1)


def test_enumeration_on_a_dask_client_uses_only_submit_and_result(
    dask_executor, simulated_serially, monkeypatch
):
    from distributed import Client

    client = Client.current()  # a Dask client's own futures: truthy objects, not bools
    with first_64_subsets(monkeypatch):  # (the workers keep 10 cans: a mask means the same)
        found = stable_configurations(cache=False, executor=client)
    assert found == tuple(m for m in simulated_serially if m < SUBSETS)


@pytest.mark.slow
def test_enumeration_on_dask_uses_only_submit_and_result(dask_executor):
    """The full comparison: a fresh serial run, then a Dask client's futures and the opened
    Dask executor each simulate all 1024 subsets."""
    from distributed import Client

    serial = stable_configurations(cache=False)
    client = Client.current()  # a Dask client's own futures: truthy objects, not bools
    assert stable_configurations(cache=False, executor=client) == serial
    assert stable_configurations(cache=False, executor=dask_executor) == serial


def test_an_executor_returning_no_flags_is_refused():
    class Garbage:
        def submit(self, fn, batch):
            future = Future()
            future.set_result(["yes"] * len(batch))
            return future

    with pytest.raises(RuntimeError, match=r"returned 1024 results of types \['str'\]"):
        stable_configurations(cache=False, executor=Garbage())


def _cache_with(**fields) -> str:
    good = {"key": configurations._cache_key(), "n_stable": 2, "stable": [0, 15]}
    return json.dumps(good | fields)


BAD_CACHES = {
    "null": "null",
    "a list": "[0, 15]",
    "a number": "3",
    "stable null": _cache_with(stable=None),
    "stable of strings": _cache_with(stable=["0", "15"]),
    "a mask out of range": _cache_with(stable=[0, 4096]),
    "unsorted": _cache_with(stable=[15, 0]),
    "a count that disagrees": _cache_with(n_stable=3),
    "deeply nested": "[" * 100_000 + "]" * 100_000,
}


@pytest.mark.parametrize("text", BAD_CACHES.values(), ids=BAD_CACHES)
def test_a_cache_of_another_shape_is_recomputed_and_rewritten(tmp_path, monkeypatch, text):
    file = tmp_path / "stable.json"
    file.write_text(text)
    monkeypatch.setattr(configurations, "_compute", lambda executor=None: (0, 15, 1023))
    assert stable_configurations(path=file) == (0, 15, 1023)
    assert json.loads(file.read_text())["stable"] == [0, 15, 1023]

    def no_simulation(executor=None):
        raise AssertionError("recomputed although cached")

    monkeypatch.setattr(configurations, "_compute", no_simulation)
    assert stable_configurations(path=file) == (0, 15, 1023)


def test_a_good_cache_is_read_as_written(tmp_path, monkeypatch):
    file = tmp_path / "stable.json"
    file.write_text(_cache_with())
    monkeypatch.setattr(configurations, "_compute", lambda executor=None: (1,))
    assert stable_configurations(path=file) == (0, 15)


def test_a_cache_folder_that_cannot_be_written_is_named_and_the_result_stands(
    tmp_path, monkeypatch
):
    real_open = os.open

    def read_only(file, flags, *args, **kwargs):
        if tmp_path in Path(file).parents and flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(file))
        return real_open(file, flags, *args, **kwargs)

    monkeypatch.setattr(os, "open", read_only)
    monkeypatch.setattr(configurations, "_compute", lambda executor=None: (0, 15))
    file = tmp_path / "stable.json"
    with pytest.warns(UserWarning, match=r"could not cache .*stable\.json .*Read-only"):
        assert stable_configurations(path=file) == (0, 15)
    assert not file.exists()
