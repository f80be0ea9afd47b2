"""The can-tossing data set: every stable configuration x 195 fields x angles x repeats.

Protocol (paper §IV-A): each physically possible configuration is hit at
every field with every angle, ``repeats`` times, each repeat with its own seeded aim
jitter (``jitter`` metres, normal per axis; the seed of throw (config, field, angle,
repeat) is :func:`sim2d.field_throws.aim_seed` of the data set's ``seed``). Rows are ordered
by configuration (ascending mask), field, angle, repeat.

Unthrowable actions (:func:`sim2d.field_throws.is_throwable` False) are not simulated: their
rows carry ``throwable = False``, ``end_config = start_config``, ``thrown_off = 0``,
``hit_any_can = False`` and ``sim_time = 0``. Use ``throwable`` to drop them.

File format (``.npz``, ``np.load(path)`` without pickles), one row per throw:

=============  =======  ============================================================
array          dtype    meaning
=============  =======  ============================================================
start_config   int16    configuration mask before the throw
field          int16    field index, ``row * 15 + column``
angle          int8     index into ``sim2d.geometry.ANGLES``
repeat         int8     repeat number
seed           uint32   seed of the aim jitter
end_config     int16    cans not thrown off
thrown_off     int16    cans thrown off
count_before   int8     number of cans before
count_after    int8     number of cans after
hit_any_can    bool     the ball touched a can
touched        int16    mask of the cans the ball touched
throwable      bool     the action can be thrown (else not simulated)
timed_out      bool     the simulation hit the time cap
sim_time       float32  simulated seconds
metadata       str      0-d array, JSON: format version, constants, geometry, protocol
=============  =======  ============================================================

Generation is written in chunks to ``<path>.parts/`` (:func:`sim2d.chunks.run_chunks`:
one ``.npz`` per chunk, written atomically, checked when reused), so an interrupted run
resumes where it stopped and a damaged chunk is computed again; the chunks are merged
into ``path`` at the end and then removed. ``<path>.lock`` keeps a second generator off
the same path; a finished data set is recognised without it (so it is usable in a
read-only folder), and the temporary file of a merge that was killed is removed by the
next run. The chunks run on any executor (:mod:`sim2d.executors`); workers return
arrays and this process writes the files, byte for byte the same on every executor.

Format versions: 2 runs every throw under :data:`sim2d.materials.STOPPING` and steps the
world as :data:`sim2d.materials.STEPPING` says (both recorded under ``constants``); 1 ran
them under :data:`sim2d.materials.STOPPING_FORMAT_1`, which removed bodies leaving the
scene only 50 cm past the pyramid instead of 10 cm. A file of another version is refused.
"""

from __future__ import annotations

import importlib.metadata
import json
import shutil
import warnings
from dataclasses import dataclass
from dataclasses import field as dataclass_field
from pathlib import Path

import numpy as np
from effect_networks.sim2d import geometry, materials
from effect_networks.sim2d.chunks import (
    ChunkWarning,
    locked,
    read_npz,
    remove_temporaries,
    run_chunks,
    save_npz,
)
from effect_networks.sim2d.configurations import (
    SETTLE_TIME,
    STABLE_TOLERANCE,
    stable_configurations,
)
from effect_networks.sim2d.executors import parse_spec
from effect_networks.sim2d.field_throws import (
    aim_offset,
    aim_seed,
    is_throwable,
    launch_state,
    outcome_of,
)
from effect_networks.sim2d.validation import as_int, check_index
from effect_networks.sim2d.world import run_ball

__all__ = ["FORMAT_VERSION", "CanDataset", "generate_dataset", "load_dataset"]

FORMAT_VERSION = 2
_DTYPES = {
    "start_config": np.int16,
    "field": np.int16,
    "angle": np.int8,
    "repeat": np.int8,
    "seed": np.uint32,
    "end_config": np.int16,
    "thrown_off": np.int16,
    "count_before": np.int8,
    "count_after": np.int8,
    "hit_any_can": np.bool_,
    "touched": np.int16,
    "throwable": np.bool_,
    "timed_out": np.bool_,
    "sim_time": np.float32,
}


@dataclass(frozen=True)
class CanDataset:
    """The can-tossing data set as arrays of shape ``(n,)``, one entry per throw.

    See the module docstring for each array's meaning; ``metadata`` is the decoded JSON.
    """

    start_config: np.ndarray
    field: np.ndarray
    angle: np.ndarray
    repeat: np.ndarray
    seed: np.ndarray
    end_config: np.ndarray
    thrown_off: np.ndarray
    count_before: np.ndarray
    count_after: np.ndarray
    hit_any_can: np.ndarray
    touched: np.ndarray
    throwable: np.ndarray
    timed_out: np.ndarray
    sim_time: np.ndarray
    metadata: dict = dataclass_field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.start_config)


def _simulate_chunk(rows: np.ndarray, jitter: float, seed: int) -> dict[str, np.ndarray]:
    """Simulate the throws ``rows`` (``(n, 4)`` int: config, field, angle, repeat).

    Runs in a worker; the configurations were validated by the caller.
    """
    n = len(rows)
    out = {name: np.zeros(n, dtype=dtype) for name, dtype in _DTYPES.items()}
    throwable = {(f, a): is_throwable(f, a) for f, a in {(r[1], r[2]) for r in rows.tolist()}}
    for k, (config, fld, angle, repeat) in enumerate(rows.tolist()):
        row_seed = aim_seed(seed, config, fld, angle, repeat)
        out["start_config"][k] = config
        out["field"][k] = fld
        out["angle"][k] = angle
        out["repeat"][k] = repeat
        out["seed"][k] = row_seed
        out["count_before"][k] = config.bit_count()
        if not throwable[fld, angle]:
            out["end_config"][k] = config
            out["count_after"][k] = config.bit_count()
            continue
        out["throwable"][k] = True
        position, velocity = launch_state(fld, angle, offset=aim_offset(jitter, row_seed))
        outcome = outcome_of(config, run_ball(config, position, velocity))
        out["end_config"][k] = outcome.end_config
        out["thrown_off"][k] = outcome.thrown_off
        out["count_after"][k] = outcome.count_after
        out["hit_any_can"][k] = outcome.hit_any_can
        out["touched"][k] = outcome.touched
        out["timed_out"][k] = outcome.timed_out
        out["sim_time"][k] = outcome.sim_time
    return out


def _rows(configs, angles, repeats) -> np.ndarray:
    grid = np.meshgrid(
        configs, np.arange(geometry.N_FIELDS), angles, np.arange(repeats), indexing="ij"
    )
    return np.stack([g.ravel() for g in grid], axis=1).astype(np.int64)


def _package_version() -> str:
    try:
        return importlib.metadata.version("effect-networks")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def _metadata(configs, angles, repeats, jitter, seed, chunk_size) -> dict:
    return {
        "format_version": FORMAT_VERSION,
        "producer": "sim2d.can_dataset.generate_dataset",
        "package_version": _package_version(),
        "constants": materials.physical_constants(),
        "settle_time": SETTLE_TIME,
        "stable_tolerance": STABLE_TOLERANCE,
        "geometry": {
            "can_positions": geometry.can_positions().tolist(),
            "field_centres": geometry.field_centres().tolist(),
            "supporters": [list(s) if s else None for s in geometry.SUPPORTERS],
            "top_three": list(geometry.TOP_THREE),
            "near_flank": list(geometry.NEAR_FLANK),
            "far_flank": list(geometry.FAR_FLANK),
            "field_index": "row * 15 + column; row 0 bottom, column 0 near side",
        },
        "configs": [int(c) for c in configs],
        "angles": [int(a) for a in angles],
        "repeats": int(repeats),
        "jitter": float(jitter),
        "jitter_rule": "normal(0, jitter) per axis added to the field centre, clipped at 3 sd",
        "seed": int(seed),
        "seed_rule": "aim seed = sim2d.field_throws.aim_seed(seed, config, field, angle, repeat)",
        "unthrowable_rule": "not simulated; end_config = start_config, throwable = False",
        "thrown_off_rule": "at rest moved > 1 cm vertically or > 10 cm horizontally, or left",
        "row_order": "config (ascending), field, angle, repeat",
        "chunk_size": int(chunk_size),
    }


def _check_args(configs, angles, repeats, jitter, chunk_size):
    stable = stable_configurations()
    if configs is None:
        configs = stable
    configs = sorted({as_int(c, "configs") for c in configs})
    bad = [c for c in configs if c not in stable]
    if bad:
        raise ValueError(
            f"configs contains {bad[:5]}{'...' if len(bad) > 5 else ''}, not physically "
            "possible; expected a subset of sim2d.configurations.stable_configurations()"
        )
    angles = sorted({check_index(a, "angles", len(geometry.ANGLES), "an angle") for a in angles})
    if not angles:
        raise ValueError("angles=() is empty; expected a subset of (0, 1, 2)")
    repeats = as_int(repeats, "repeats")
    if not 1 <= repeats <= 127:
        raise ValueError(f"repeats={repeats} is out of range; expected 1..127")
    if not (np.isfinite(jitter) and 0 <= jitter <= materials.TABLE_CLEARANCE / 3):
        raise ValueError(
            f"jitter={jitter!r} is invalid; expected metres in [0, {materials.TABLE_CLEARANCE / 3:.4f}]"
            " (larger aim errors could start a throwable parabola inside the table)"
        )
    chunk_size = as_int(chunk_size, "chunk_size")
    if chunk_size < 1:
        raise ValueError(f"chunk_size={chunk_size} is invalid; expected >= 1")
    return configs, angles, repeats, float(jitter), chunk_size


def generate_dataset(
    path,
    *,
    configs=None,
    angles=(0, 1, 2),
    repeats: int = 3,
    jitter: float = 0.003,
    seed: int = 0,
    executor=None,
    chunk_size: int = 1000,
    progress: bool = True,
) -> Path:
    """Simulate the data set and save it as one ``.npz`` (format: module docstring).

    Parameters
    ----------
    path : path-like
        Output file. If it exists with the same protocol, nothing is recomputed.
    configs : iterable of int, optional
        Start configurations; default every stable configuration.
    angles : iterable of int
        Angle indices to throw with.
    repeats : int
        Throws per (configuration, field, angle), each with its own aim jitter.
    jitter : float, metres
        Standard deviation of the aim error per axis (at most 3.3 mm).
    seed : int
        Seed of the data set; the throws' seeds derive from it.
    executor : str or object with ``submit``, optional
        Where the chunks run: ``process:N``, ``dask-local:N``, ``dask://HOST:PORT`` or
        ``ray`` (:mod:`sim2d.executors`; opened and closed here), or an open executor
        whose ``submit(fn, *args)`` returns a future with ``result()``. Default: a
        process pool on every core. The file is the same, byte for byte, on any of them.
    chunk_size : int
        Throws per chunk (the unit of work and of resumption).
    progress : bool
        Show a tqdm progress bar of throws.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    ValueError
        For invalid arguments, or when ``<path>.parts/`` holds chunks of a different
        protocol (delete it or choose another path).
    RuntimeError
        When another generator is writing ``path`` (``<path>.lock`` is held).
    """
    configs, angles, repeats, jitter, chunk_size = _check_args(
        configs, angles, repeats, jitter, chunk_size
    )
    seed = as_int(seed, "seed")
    if seed < 0:
        raise ValueError(f"seed={seed} is negative; expected an int >= 0")
    if executor is not None and isinstance(executor, str):
        parse_spec(executor)  # a bad specification fails before any work
    path = Path(path)
    if path.is_dir():  # refused before any throw is computed: the rename would fail last
        raise ValueError(f"path {str(path)!r} is a folder; expected the data set's file (.npz)")
    metadata = _metadata(configs, angles, repeats, jitter, seed, chunk_size)
    if _finished(path, metadata):  # read only: usable in a read-only folder, without the lock
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    with locked(path):
        remove_temporaries(path)  # a merge that was killed
        if _finished(path, metadata, warn=True):  # another generator finished it meanwhile
            return path
        rows = _rows(configs, angles, repeats)
        chunks = [rows[i : i + chunk_size] for i in range(0, len(rows), chunk_size)]

        def check(k: int, arrays: dict[str, np.ndarray]) -> str | None:
            return _chunk_problem(chunks[k], arrays)

        files = run_chunks(
            path.with_name(path.name + ".parts"),
            metadata,
            _simulate_chunk,
            [(chunk, jitter, seed) for chunk in chunks],
            executor=executor,
            check=check,
            sizes=[len(c) for c in chunks],
            progress=progress,
            desc="can data set",
        )
        pieces = [read_npz(f) for f in files]
        merged = {
            name: np.concatenate([p[name] for p in pieces]).astype(dtype, copy=False)
            for name, dtype in _DTYPES.items()
        }
        assert np.array_equal(merged["start_config"], rows[:, 0])
        merged["metadata"] = np.array(json.dumps(metadata))
        save_npz(path, merged)
        shutil.rmtree(files[0].parent if files else path.with_name(path.name + ".parts"))
    return path


def _finished(path: Path, metadata: dict, *, warn: bool = False) -> bool:
    """Whether ``path`` holds the data set ``metadata`` describes (read only).

    The file is replaced in one rename, so it can be read without the lock. With
    ``warn``, a damaged file is named in a warning (it is generated again).
    """
    if not path.exists():
        return False
    try:
        return load_dataset(path).metadata == metadata
    except ValueError as error:
        if warn:
            warnings.warn(f"{error}; generating it again", ChunkWarning, stacklevel=3)
        return False


def _chunk_problem(rows: np.ndarray, arrays: dict[str, np.ndarray]) -> str | None:
    """What is wrong with a chunk's arrays for the throws ``rows``, or None."""
    for name, dtype in _DTYPES.items():
        if name not in arrays:
            return f"lacks the array {name!r}"
        if arrays[name].dtype != dtype or arrays[name].shape != (len(rows),):
            return (
                f"has {name} of {arrays[name].dtype} {arrays[name].shape}; "
                f"expected {np.dtype(dtype)} ({len(rows)},)"
            )
    for j, name in enumerate(("start_config", "field", "angle", "repeat")):
        if not np.array_equal(arrays[name], rows[:, j]):
            return f"holds other throws than expected ({name} differs)"
    return None


def load_dataset(path) -> CanDataset:
    """Load a data set written by :func:`generate_dataset`.

    Raises
    ------
    ValueError
        If the file is truncated or corrupt, or not a can data set of this format
        version (the message names the file).
    """
    path = Path(path)
    data = read_npz(path)
    missing = [name for name in (*_DTYPES, "metadata") if name not in data]
    if missing:
        raise ValueError(f"path={str(path)!r} lacks arrays {missing}; expected a can data set")
    try:
        metadata = json.loads(str(data["metadata"]))
    except (ValueError, RecursionError):
        raise ValueError(f"path={str(path)!r} has unreadable metadata; expected JSON") from None
    if not isinstance(metadata, dict):
        raise ValueError(
            f"path={str(path)!r} has metadata of JSON type {type(metadata).__name__}; "
            "expected an object"
        )
    if metadata.get("format_version") != FORMAT_VERSION:
        raise ValueError(
            f"path={str(path)!r} has format version {metadata.get('format_version')}; "
            f"expected {FORMAT_VERSION} (generate it again)"
        )
    n = len(data["start_config"])
    for name, dtype in _DTYPES.items():
        if data[name].dtype != dtype or data[name].shape != (n,):
            raise ValueError(
                f"path={str(path)!r} has {name} of {data[name].dtype} {data[name].shape}; "
                f"expected {np.dtype(dtype)} ({n},)"
            )
    return CanDataset(**{name: data[name] for name in _DTYPES}, metadata=metadata)
