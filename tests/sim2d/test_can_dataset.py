"""Tests of the can data set's generation and format (sim2d/can_dataset.py)."""

import concurrent.futures
import errno
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from effect_networks.sim2d import can_dataset, chunks, executors, field_throws, geometry, materials
from effect_networks.sim2d.can_dataset import generate_dataset, load_dataset
from effect_networks.sim2d.chunks import ChunkWarning, locked, read_npz, save_npz
from effect_networks.sim2d.generate import main as generate_main

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


class Counting:
    """Passes tasks on to another executor, counting them."""

    def __init__(self, executor):
        self.executor = executor
        self.submitted = 0

    def submit(self, fn, *args):
        self.submitted += 1
        return self.executor.submit(fn, *args)


N_CHUNKS = -(-N_SMALL // SMALL["chunk_size"])


def interrupted(path: Path, after: int = 3) -> Path:
    """Start generating ``path`` and stop after ``after`` chunks; the parts folder."""
    with pytest.raises(KeyboardInterrupt):
        generate_dataset(path, executor=SerialExecutor(fail_after=after), progress=False, **SMALL)
    parts = path.with_name(path.name + ".parts")
    assert len(list(parts.glob("chunk-*.npz"))) == after and not path.exists()
    return parts


def same_bytes(a: Path, b: Path) -> bool:
    return a.read_bytes() == b.read_bytes()


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


# --- executors -----------------------------------------------------------------------------


def test_a_dask_cluster_writes_the_same_file_byte_for_byte(tmp_path, small, dask_executor):
    path = generate_dataset(tmp_path / "dask.npz", executor=dask_executor, progress=False, **SMALL)
    assert same_bytes(path, small)


def test_an_interrupted_run_resumes_on_dask_without_redoing_saved_chunks(
    tmp_path, small, dask_executor
):
    path = tmp_path / "resumed.npz"
    interrupted(path)
    resume = Counting(dask_executor)
    generate_dataset(path, executor=resume, progress=False, **SMALL)
    assert resume.submitted == N_CHUNKS - 3
    assert same_bytes(path, small)


def test_a_process_pool_by_name_writes_the_same_file(tmp_path, small):
    path = generate_dataset(tmp_path / "p.npz", executor="process:2", progress=False, **SMALL)
    assert same_bytes(path, small)


@pytest.mark.slow  # starting Ray takes most of a minute here
def test_ray_writes_the_same_file(tmp_path, small):
    pytest.importorskip("ray")
    path = generate_dataset(tmp_path / "ray.npz", executor="ray", progress=False, **SMALL)
    assert same_bytes(path, small)


def test_command_line(tmp_path):
    out = tmp_path / "cli.npz"
    args = [sys.executable, "-m", "sim2d.generate", str(out), "--configs", "15", "--angles", "2"]
    run = subprocess.run(
        [*args, "--repeats", "1", "--chunk-size", "40", "--executor", "process:2", "--quiet"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 0, run.stderr
    data = load_dataset(out)
    assert len(data) == 195 and set(data.start_config.tolist()) == {15}
    assert f"{out}: 195 throws" in run.stdout
    bad = subprocess.run(
        [*args, "--executor", "spark:3"], capture_output=True, text=True, timeout=60
    )
    assert bad.returncode == 2 and "executor='spark:3'" in bad.stderr
    assert "process:N, dask-local:N, dask://HOST:PORT or ray" in bad.stderr


# --- nothing lost --------------------------------------------------------------------------


def _truncate(file: Path) -> None:
    file.write_bytes(file.read_bytes()[: file.stat().st_size // 2])


def _flip_a_byte(file: Path) -> None:
    data = bytearray(file.read_bytes())
    data[len(data) // 3] ^= 0xFF  # inside the arrays, not the zip directory at the end
    file.write_bytes(bytes(data))


@pytest.mark.parametrize("damage", [_truncate, _flip_a_byte])
def test_a_damaged_chunk_is_named_and_only_it_is_computed_again(tmp_path, small, damage):
    path = tmp_path / "d.npz"
    parts = interrupted(path)
    damage(parts / "chunk-000001.npz")
    resume = SerialExecutor()
    with pytest.warns(ChunkWarning, match=r"chunk-000001\.npz .*computed again"):
        generate_dataset(path, executor=resume, progress=False, **SMALL)
    assert resume.submitted == N_CHUNKS - 3 + 1
    assert same_bytes(path, small)


def test_a_chunk_of_other_throws_is_computed_again(tmp_path, small):
    path = tmp_path / "d.npz"
    parts = interrupted(path)
    shutil.copy(parts / "chunk-000000.npz", parts / "chunk-000002.npz")  # right protocol
    resume = SerialExecutor()
    with pytest.warns(ChunkWarning, match=r"chunk-000002\.npz holds other throws"):
        generate_dataset(path, executor=resume, progress=False, **SMALL)
    assert resume.submitted == N_CHUNKS - 3 + 1
    assert same_bytes(path, small)


def test_a_corrupt_manifest_is_named_and_no_chunk_is_lost(tmp_path, small):
    path = tmp_path / "d.npz"
    parts = interrupted(path)
    _truncate(parts / "manifest.json")
    resume = SerialExecutor()
    with pytest.warns(ChunkWarning, match=r"manifest\.json is truncated or corrupt"):
        generate_dataset(path, executor=resume, progress=False, **SMALL)
    assert resume.submitted == N_CHUNKS - 3
    assert same_bytes(path, small)


def test_a_damaged_data_set_is_named_and_generated_again(tmp_path, small):
    path = tmp_path / "d.npz"
    path.write_bytes(small.read_bytes())
    _truncate(path)
    with pytest.raises(ValueError, match=r"d\.npz is truncated or corrupt"):
        load_dataset(path)
    with pytest.warns(ChunkWarning, match=r"d\.npz is truncated or corrupt.*generating it again"):
        generate_dataset(path, executor=SerialExecutor(), progress=False, **SMALL)
    assert same_bytes(path, small)


def test_a_lock_keeps_a_second_generator_off_the_path(tmp_path):
    path = tmp_path / "d.npz"
    with locked(path):  # another generator, as far as the lock can tell
        with pytest.raises(RuntimeError, match=r"d\.npz\.lock is held by another generator"):
            generate_dataset(path, executor=SerialExecutor(), progress=False, **SMALL)
    assert not path.exists() and not Path(f"{path}.lock").exists()
    generate_dataset(path, executor=SerialExecutor(), progress=False, **SMALL)  # free again


def test_a_full_disk_leaves_no_temporary_file_and_keeps_finished_chunks(tmp_path, monkeypatch):
    path = tmp_path / "d.npz"
    parts = interrupted(path)
    real = np.lib.format.write_array
    writes = []

    def full_disk(fp, array, *args, **kwargs):
        writes.append(1)
        if len(writes) > 20:  # a chunk or two later, in the middle of an array
            fp.write(b"\0" * 100)
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(fp, array, *args, **kwargs)

    monkeypatch.setattr(np.lib.format, "write_array", full_disk)
    with pytest.raises(OSError, match="No space left"):
        generate_dataset(path, executor=SerialExecutor(), progress=False, **SMALL)
    monkeypatch.setattr(np.lib.format, "write_array", real)
    assert not [p for p in tmp_path.rglob("*") if ".tmp" in p.name]
    saved = sorted(parts.glob("chunk-*.npz"))
    assert len(saved) > 3 and not path.exists()
    with warnings.catch_warnings():
        warnings.simplefilter("error", ChunkWarning)  # every saved chunk is intact
        resume = SerialExecutor()
        generate_dataset(path, executor=resume, progress=False, **SMALL)
    assert resume.submitted == N_CHUNKS - len(saved)


def test_files_are_created_like_ordinary_files(tmp_path):
    umask = os.umask(0o022)
    try:
        path = tmp_path / "d.npz"
        parts = interrupted(path)
        modes = {p.name: p.stat().st_mode & 0o777 for p in parts.iterdir()}
        generate_dataset(path, executor=SerialExecutor(), progress=False, **SMALL)
        modes[path.name] = path.stat().st_mode & 0o777
    finally:
        os.umask(umask)
    assert set(modes.values()) == {0o644}, modes


def _children(pid: int) -> list[int]:
    psutil = pytest.importorskip("psutil")
    return [p.pid for p in psutil.Process(pid).children(recursive=True)]


def _default_signals():
    """A suite started in the background (nohup, ``cmd &``) hands its children SIGINT
    ignored; the generator under test must see the signals as a terminal would send them."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT, signal.SIGKILL])
def test_pool_workers_end_with_the_generator(tmp_path, sig):
    psutil = pytest.importorskip("psutil")
    out = tmp_path / "big.npz"
    parts = Path(f"{out}.parts")
    proc = subprocess.Popen(
        [sys.executable, "-m", "sim2d.generate", str(out), "--configs", "1023", "--angles", "1",
         "--repeats", "40", "--chunk-size", "10", "--executor", "process:2", "--quiet"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        preexec_fn=_default_signals,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while not list(parts.glob("chunk-*.npz")) and time.monotonic() < deadline:
            time.sleep(0.1)
        workers = _children(proc.pid)
        assert len(workers) >= 2, "the pool's workers run"
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode != 0
    if sig != signal.SIGKILL:  # a kill gives the generator no say
        assert "run it again to resume" in err
    deadline = time.monotonic() + 10
    while any(psutil.pid_exists(w) and psutil.Process(w).status() != "zombie" for w in workers):
        assert time.monotonic() < deadline, "pool workers outlived the generator"
        time.sleep(0.1)
    saved = list(parts.glob("chunk-*.npz"))
    assert saved and not out.exists()
    if sig != signal.SIGKILL:
        assert not Path(f"{out}.lock").exists()


# --- damage and odd folders ----------------------------------------------------------------


def _set_zip_field(file: Path, offset: int, value: int) -> None:
    """Set a 2-byte field of the first entry's central-directory record (where zipfile reads
    the compression method, at offset 10, the flags, 8, and the version needed, 6)."""
    data = bytearray(file.read_bytes())
    record = data.index(b"PK\x01\x02")
    data[record + offset : record + offset + 2] = value.to_bytes(2, "little")
    file.write_bytes(bytes(data))


# Each of these raised NotImplementedError or RuntimeError from zipfile, not a ValueError.
ZIP_DAMAGE = {
    "compression method 99": (10, 99),
    "compression method 1 (shrunk)": (10, 1),
    "strong encryption flag": (8, 1 << 6),
    "patched data flag": (8, 1 << 5),
    "encryption flag": (8, 1),
    "version needed 10.9": (6, 109),
}


@pytest.mark.parametrize("damage", ZIP_DAMAGE.values(), ids=ZIP_DAMAGE)
def test_a_chunk_with_damaged_zip_headers_is_named_and_computed_again(tmp_path, small, damage):
    path = tmp_path / "d.npz"
    parts = interrupted(path)
    _set_zip_field(parts / "chunk-000001.npz", *damage)
    resume = SerialExecutor()
    with pytest.warns(ChunkWarning, match=r"chunk-000001\.npz is truncated or corrupt"):
        generate_dataset(path, executor=resume, progress=False, **SMALL)
    assert resume.submitted == N_CHUNKS - 3 + 1
    assert same_bytes(path, small)


def test_read_npz_names_the_file_for_every_value_of_the_zip_header_fields(tmp_path):
    file = tmp_path / "chunk.npz"
    save_npz(file, {"a": np.arange(5, dtype=np.int16), "protocol": np.array("key")})
    good = file.read_bytes()
    for offset in (6, 8, 10):
        for bit in range(16):
            file.write_bytes(good)
            _set_zip_field(file, offset, 1 << bit)
            try:
                arrays = read_npz(file)
            except ValueError as error:
                assert str(file) in str(error)
            else:
                assert arrays["a"].tolist() == list(range(5))


def test_a_finished_data_set_in_a_read_only_folder_is_used(tmp_path, small, monkeypatch):
    folder = tmp_path / "read-only"
    folder.mkdir()
    path = folder / "d.npz"
    shutil.copy(small, path)
    real_open = os.open

    def read_only(file, flags, *args, **kwargs):  # the folder as a read-only mount has it
        if Path(file).parent == folder and flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(file))
        return real_open(file, flags, *args, **kwargs)

    monkeypatch.setattr(os, "open", read_only)
    run = SerialExecutor()
    assert generate_dataset(path, executor=run, progress=False, **SMALL) == path
    assert run.submitted == 0 and list(folder.iterdir()) == [path]
    with pytest.raises(OSError, match="Read-only"):  # one of other arguments is generated
        generate_dataset(path, executor=run, progress=False, **SMALL | {"seed": 1})


KILLED_IN_THE_MERGE = """
import concurrent.futures, os, signal, sys
from effect_networks.sim2d.can_dataset import generate_dataset

real = os.replace

def killed(src, dst):
    if os.path.basename(dst) == "d.npz":  # the merged file, written but not yet renamed
        os.kill(os.getpid(), signal.SIGKILL)
    real(src, dst)

os.replace = killed
with concurrent.futures.ThreadPoolExecutor(1) as executor:
    generate_dataset(sys.argv[1], configs=[0], angles=(0,), repeats=1, chunk_size=100,
                     executor=executor, progress=False)
"""


def test_a_kill_during_the_merge_leaves_no_temporary_file_for_good(tmp_path):
    path = tmp_path / "d.npz"
    killed = subprocess.run(
        [sys.executable, "-c", KILLED_IN_THE_MERGE, str(path)], capture_output=True, timeout=120
    )
    assert killed.returncode == -signal.SIGKILL, killed.stderr
    assert not path.exists() and list(tmp_path.glob(".d.npz.*.tmp"))
    parts = tmp_path / "d.npz.parts"
    (parts / ".chunk-000002.npz.k1ll3d.tmp").write_bytes(b"half a chunk")  # killed mid-chunk
    resume = SerialExecutor()
    generate_dataset(
        path, configs=[0], angles=(0,), repeats=1, chunk_size=100, executor=resume, progress=False
    )
    assert resume.submitted == 0  # every chunk was saved before the kill
    assert len(load_dataset(path)) == 195
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.npz"]


def _protocol_edited(manifest: Path) -> str:
    protocol = json.loads(manifest.read_text())
    return json.dumps(protocol | {"seed": 7})


MANIFEST_EDITS = {
    "null": lambda manifest: "null",
    "a list": lambda manifest: "[1, 2]",
    "an empty object": lambda manifest: "{}",
    "another seed": _protocol_edited,
    "deeply nested": lambda manifest: "[" * 100_000 + "]" * 100_000,
}


@pytest.mark.parametrize("edit", MANIFEST_EDITS.values(), ids=MANIFEST_EDITS)
def test_a_manifest_edited_into_other_json_is_rewritten_and_no_chunk_is_lost(tmp_path, small, edit):
    path = tmp_path / "d.npz"
    parts = interrupted(path)
    manifest = parts / "manifest.json"
    manifest.write_text(edit(manifest))
    resume = SerialExecutor()
    with pytest.warns(ChunkWarning, match=r"manifest\.json (does not describe|is truncated)"):
        generate_dataset(path, executor=resume, progress=False, **SMALL)
    assert resume.submitted == N_CHUNKS - 3
    assert same_bytes(path, small)


def test_a_folder_of_another_data_set_is_refused_naming_what_differs(tmp_path):
    path = tmp_path / "d.npz"
    interrupted(path)
    with pytest.raises(ValueError, match=r"3 chunk\(s\) of a different data set .*seed: 0 there"):
        generate_dataset(path, executor=SerialExecutor(), progress=False, **SMALL | {"seed": 1})
    # the same, with its manifest edited as well: its chunks still tell
    manifest = path.with_name("d.npz.parts") / "manifest.json"
    manifest.write_text("null")
    with pytest.raises(ValueError, match=r"different data set .*holds a JSON NoneType"):
        generate_dataset(path, executor=SerialExecutor(), progress=False, **SMALL | {"seed": 1})
    manifest.write_text('{"format_ver')  # or truncated: no chunk of the other data set is lost
    with pytest.raises(ValueError, match=r"different data set .*is truncated or corrupt"):
        generate_dataset(path, executor=SerialExecutor(), progress=False, **SMALL | {"seed": 1})
    assert len(list(manifest.parent.glob("chunk-*.npz"))) == 3


def test_a_data_set_with_deeply_nested_metadata_is_named(tmp_path, small):
    path = tmp_path / "d.npz"
    arrays = dict(np.load(small))
    save_npz(path, arrays | {"metadata": np.array("[" * 100_000 + "]" * 100_000)})
    with pytest.raises(ValueError, match=r"d\.npz.* has unreadable metadata"):
        load_dataset(path)
    save_npz(path, arrays | {"metadata": np.array("null")})
    with pytest.raises(ValueError, match=r"d\.npz.* has metadata of JSON type NoneType"):
        load_dataset(path)


def test_an_unreachable_dask_scheduler_fails_at_once_and_leaves_nothing(tmp_path):
    pytest.importorskip("distributed")
    import socket

    with socket.socket() as probe:  # a port nothing listens on
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    path = tmp_path / "d.npz"
    start = time.monotonic()
    with pytest.raises(
        executors.ExecutorUnavailable, match=rf"dask://127\.0\.0\.1:{port}.*no Dask sched"
    ):
        generate_dataset(path, executor=f"dask://127.0.0.1:{port}", progress=False, **SMALL)
    assert time.monotonic() - start < 5
    assert list(tmp_path.iterdir()) == []


def test_a_negative_seed_is_refused_naming_it(tmp_path):
    with pytest.raises(ValueError, match=r"seed=-1 is negative"):
        generate_dataset(tmp_path / "d.npz", seed=-1, progress=False, **SMALL)
    assert list(tmp_path.iterdir()) == []


CLI_SMALL = ["--configs", str(BOTTOM_ROW), "0", "--angles", "0", "2", "--repeats", "2",
             "--chunk-size", "97", "--quiet"]  # fmt: skip


def test_the_command_line_says_a_full_disk_in_two_lines_and_a_rerun_resumes(
    tmp_path, small, monkeypatch, capsys
):
    path = tmp_path / "d.npz"
    parts = interrupted(path)
    real = np.lib.format.write_array
    writes = []

    def full_disk(fp, array, *args, **kwargs):
        writes.append(1)
        if len(writes) > 20:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(fp, array, *args, **kwargs)

    monkeypatch.setattr(np.lib.format, "write_array", full_disk)
    with pytest.raises(SystemExit) as exited:
        generate_main([str(path), *CLI_SMALL, "--executor", "process:1"])
    assert exited.value.code == 1
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 2, lines
    assert re.fullmatch(
        r"python -m effect_networks\.sim2d\.generate: error: could not write \S+d\.npz\.parts/chunk-\d+\.npz: "
        r"No space left on device",
        lines[0],
    )
    assert "run it again to resume" in lines[1]
    saved = len(list(parts.glob("chunk-*.npz")))
    monkeypatch.setattr(np.lib.format, "write_array", real)
    assert generate_main([str(path), *CLI_SMALL, "--executor", "process:1"]) == 0
    assert same_bytes(path, small) and saved > 3


def test_the_command_line_says_a_read_only_folder_in_two_lines(tmp_path, monkeypatch, capsys):
    real_open = os.open

    def read_only(file, flags, *args, **kwargs):
        if Path(file).parent == tmp_path and flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(file))
        return real_open(file, flags, *args, **kwargs)

    monkeypatch.setattr(os, "open", read_only)
    with pytest.raises(SystemExit) as exited:
        generate_main([str(tmp_path / "d.npz"), *CLI_SMALL])
    assert exited.value.code == 1
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 2 and lines[0].endswith("d.npz.lock: Read-only file system"), lines


def test_the_command_line_says_a_path_it_cannot_write_in_two_lines(tmp_path, capsys):
    # a file where the data set's folder is needed
    (tmp_path / "file").write_text("")
    with pytest.raises(SystemExit) as exited:
        generate_main([str(tmp_path / "file" / "d.npz"), *CLI_SMALL])
    assert exited.value.code == 1
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 2, lines
    assert lines[0].startswith("python -m effect_networks.sim2d.generate: error: could not write ")
    assert "stands where" in lines[0] and "run it again" in lines[1]


def test_a_folder_as_the_data_set_is_refused_before_any_throw(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(can_dataset, "run_chunks", None)  # nothing may be computed
    with pytest.raises(SystemExit) as exited:
        generate_main([str(tmp_path), *CLI_SMALL])
    assert exited.value.code == 2
    err = capsys.readouterr().err
    assert f"path {str(tmp_path)!r} is a folder" in err and "Traceback" not in err


def _sigterm_disposition() -> str:
    return repr(signal.getsignal(signal.SIGTERM))


def test_a_pool_worker_leaves_sigterm_to_its_parent():
    # workers forked while the generator turns SIGTERM into KeyboardInterrupt used to
    # inherit that handler: a SIGTERM to the process group then printed a traceback from
    # a pymunk finaliser in a worker (2 runs of 10); a worker that died of it broke the
    # pool under the parent's cancelled futures (another traceback)
    with chunks._sigterm_as_interrupt(), executors.open_executor("process:1") as pool:
        assert pool.submit(_sigterm_disposition).result() == repr(signal.SIG_IGN)


@pytest.mark.slow
def test_sigterm_to_the_generator_s_process_group_ends_it_in_one_line(tmp_path):
    # as `timeout` or a terminal's hang-up sends it: the parent and every pool worker
    for trial in range(6):
        path = tmp_path / f"d{trial}.npz"
        proc = subprocess.Popen(
            [sys.executable, "-m", "sim2d.generate", str(path), "--executor", "process:2",
             "--quiet", "--chunk-size", "50", "--configs", str(BOTTOM_ROW), "0", "1023"],
            cwd=Path(__file__).resolve().parents[2], stderr=subprocess.PIPE, text=True,
            start_new_session=True,
        )  # fmt: skip
        parts = path.with_name(path.name + ".parts")
        deadline = time.monotonic() + 120
        while len(list(parts.glob("chunk-*.npz"))) < 2 + trial and time.monotonic() < deadline:
            time.sleep(0.02)
        os.killpg(proc.pid, signal.SIGTERM)
        err = proc.communicate(timeout=60)[1]
        assert proc.returncode == 130, err
        assert err.strip().splitlines() == [
            "python -m effect_networks.sim2d.generate: interrupted; run it again to resume"
        ], err


@pytest.mark.parametrize("port", ["0", "65536", "99999"])
def test_a_port_out_of_range_is_refused_naming_it(port):
    with pytest.raises(ValueError, match=rf"executor='dask://h:{port}' names port {port}; "):
        executors.parse_spec(f"dask://h:{port}")


def test_random_damage_to_a_chunk_is_named_or_harmless(tmp_path):
    """Bytes overwritten anywhere in a chunk: the chunk check names the file, or the
    arrays read are those saved (the damage hit no field that matters)."""
    rows = np.array([[BOTTOM_ROW, field, 0, 0] for field in range(10)])
    arrays = can_dataset._simulate_chunk(rows, 0.003, 0)
    file = tmp_path / "chunk-000000.npz"
    save_npz(file, arrays | {"protocol": np.array("key")})
    good = file.read_bytes()
    rng = np.random.default_rng(0)
    named = 0
    for _ in range(400):
        data = bytearray(good)
        for i in rng.integers(len(data), size=rng.choice([1, 2, 5])):
            data[i] = rng.integers(256)
        file.write_bytes(bytes(data))
        problem = chunks._problem(file, "key", lambda k, a: can_dataset._chunk_problem(rows, a), 0)
        if problem is None:
            read = read_npz(file)
            assert all(np.array_equal(read[n], arrays[n]) for n in arrays)
            assert all(read[n].dtype == arrays[n].dtype for n in arrays)
        else:
            assert str(file) in problem
            named += 1
    assert named > 200
