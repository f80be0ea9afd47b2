"""Tests of the can data set's generation and format (sim2d/can_dataset.py)."""

import concurrent.futures

import numpy as np
import pytest

from sim2d import can_dataset, field_throws, geometry, materials
from sim2d.can_dataset import generate_dataset, load_dataset

BOTTOM_ROW = geometry.cans_to_mask([0, 1, 2, 3])
SMALL = {"configs": [BOTTOM_ROW, 0], "angles": (0, 2), "repeats": 2, "chunk_size": 97}
N_SMALL = 2 * 195 * 2 * 2


class SerialExecutor:
    """Runs each task at submission, in this process; counts and can fail tasks."""

    def __init__(self, fail_after: int | None = None):
        self.fail_after = fail_after
        self.submitted = 0

    def submit(self, fn, *args):
        future = concurrent.futures.Future()
        self.submitted += 1
        if self.fail_after is not None and self.submitted > self.fail_after:
            future.set_exception(KeyboardInterrupt())
        else:
            future.set_result(fn(*args))
        return future


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "small.npz"
    generate_dataset(path, executor=SerialExecutor(), progress=False, **SMALL)
    return path


def test_format(small):
    data = load_dataset(small)
    assert len(data) == N_SMALL
    raw = np.load(small)
    assert set(raw.files) == {*can_dataset._DTYPES, "metadata"}
    for name, dtype in can_dataset._DTYPES.items():
        assert getattr(data, name).shape == (N_SMALL,) and getattr(data, name).dtype == dtype
    meta = data.metadata
    assert meta["format_version"] == can_dataset.FORMAT_VERSION
    assert meta["jitter"] == 0.003 and meta["seed"] == 0 and meta["repeats"] == 2
    assert meta["configs"] == [0, BOTTOM_ROW] and meta["angles"] == [0, 2]
    assert meta["constants"] == materials.physical_constants()
    assert np.allclose(meta["geometry"]["can_positions"], geometry.can_positions())
    # rows ordered by config, field, angle, repeat
    assert np.all(np.diff(data.start_config) >= 0)
    assert list(data.repeat[:4]) == [0, 1, 0, 1] and list(data.angle[:4]) == [0, 0, 2, 2]


def test_rows_match_single_throws(small):
    data = load_dataset(small)
    throwable = np.flatnonzero(data.throwable & (data.start_config == BOTTOM_ROW))
    for k in throwable[:: len(throwable) // 12]:
        seed = field_throws.aim_seed(
            0, BOTTOM_ROW, int(data.field[k]), int(data.angle[k]), int(data.repeat[k])
        )
        assert data.seed[k] == seed
        o = field_throws.throw_at_field(
            BOTTOM_ROW, int(data.field[k]), int(data.angle[k]), jitter=0.003, seed=seed
        )
        assert (o.end_config, o.thrown_off, o.hit_any_can, o.touched) == (
            data.end_config[k], data.thrown_off[k], data.hit_any_can[k], data.touched[k]
        )  # fmt: skip
        assert o.count_after == data.count_after[k] and o.timed_out == data.timed_out[k]


def test_unthrowable_rows_are_flagged_and_unchanged(small):
    data = load_dataset(small)
    expected = np.array(
        [field_throws.is_throwable(f, a) for f, a in zip(data.field, data.angle, strict=True)]
    )
    assert np.array_equal(data.throwable, expected)
    gone = ~data.throwable
    assert gone.any() and np.all(data.end_config[gone] == data.start_config[gone])
    assert not data.hit_any_can[gone].any() and np.all(data.sim_time[gone] == 0)
    # the empty pyramid: nothing is ever hit
    assert not data.hit_any_can[data.start_config == 0].any()
    # the bottom row gets hit by low flat throws and never by flat throws over it
    flat = (data.start_config == BOTTOM_ROW) & data.throwable & (data.angle == 0)
    assert data.hit_any_can[flat & (data.field < 3 * 15)].mean() > 0.5
    assert not data.hit_any_can[flat & (data.field >= 8 * 15)].any()


def test_interrupted_run_resumes_without_redoing_work(tmp_path, small):
    path = tmp_path / "resumed.npz"
    with pytest.raises(KeyboardInterrupt):
        generate_dataset(path, executor=SerialExecutor(fail_after=3), progress=False, **SMALL)
    parts = path.with_name(path.name + ".parts")
    saved = sorted(parts.glob("chunk-*.npz"))
    assert len(saved) == 3 and not path.exists()
    n_chunks = -(-N_SMALL // SMALL["chunk_size"])
    resume = SerialExecutor()
    generate_dataset(path, executor=resume, progress=False, **SMALL)
    assert resume.submitted == n_chunks - 3
    assert not parts.exists()
    a, b = np.load(path), np.load(small)
    for name in a.files:
        assert np.array_equal(a[name], b[name]), name
    # a finished data set is not recomputed
    again = SerialExecutor()
    generate_dataset(path, executor=again, progress=False, **SMALL)
    assert again.submitted == 0


def test_parts_of_another_protocol_are_refused(tmp_path):
    path = tmp_path / "d.npz"
    with pytest.raises(KeyboardInterrupt):
        generate_dataset(path, executor=SerialExecutor(fail_after=1), progress=False, **SMALL)
    with pytest.raises(ValueError, match="different data set"):
        generate_dataset(path, executor=SerialExecutor(), progress=False, **SMALL | {"seed": 1})


def test_default_process_pool(tmp_path):
    path = generate_dataset(
        tmp_path / "pool.npz", configs=[geometry.cans_to_mask([1])], angles=(1,), repeats=1,
        chunk_size=50, progress=True,
    )  # fmt: skip
    data = load_dataset(path)
    assert len(data) == 195 and data.hit_any_can.any()


@pytest.mark.parametrize(
    ("kwargs", "pattern"),
    [
        ({"configs": [512]}, r"configs contains \[512\], not physically possible"),
        ({"angles": (3,)}, r"angles=3"),
        ({"repeats": 0}, r"repeats=0"),
        ({"jitter": 0.01}, r"jitter=0\.01"),
        ({"chunk_size": 0}, r"chunk_size=0"),
    ],
)
def test_bad_arguments(tmp_path, kwargs, pattern):
    with pytest.raises(ValueError, match=pattern):
        generate_dataset(tmp_path / "x.npz", progress=False, **kwargs)


def test_load_rejects_other_files(tmp_path):
    path = tmp_path / "other.npz"
    np.savez(path, x=np.zeros(3))
    with pytest.raises(ValueError, match="lacks arrays"):
        load_dataset(path)
