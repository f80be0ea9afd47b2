"""Long simulations saved chunk by chunk: resumable, locked, verified, atomic.

:func:`run_chunks` runs one task per chunk on an executor (:mod:`sim2d.executors`),
collects the arrays as the tasks finish and writes each chunk to its own ``.npz`` in a
parts folder. A later call with the same protocol resumes: chunks already saved and
intact are kept, missing ones are computed. What can go wrong on the way is handled:

- a chunk file that is truncated, corrupt, of another protocol or of the wrong shape is
  named in a warning and computed again (only that chunk); a corrupt manifest is named
  and rewritten, since every chunk carries its protocol's key itself;
- :func:`locked` keeps two processes from writing one output (an OS file lock, released
  when its holder ends, however it ends);
- files are written to a temporary file, flushed and renamed (:func:`save_npz`), so a
  crash or a full disk leaves no half file and no stray temporary file; they are created
  with the permissions of an ordinary file (0666 less the umask, 0644 usually);
- an interrupt (SIGINT, or SIGTERM while running) saves the chunks already finished and
  cancels the rest.

:func:`save_npz` writes the zip entries with a fixed timestamp, so equal arrays give
equal bytes whichever executor computed them.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import signal
import tempfile
import threading
import warnings
import zipfile
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import numpy as np

from sim2d.executors import as_finished, open_executor

__all__ = [
    "ChunkWarning",
    "locked",
    "protocol_key",
    "read_npz",
    "run_chunks",
    "save_npz",
    "write_text",
]

_ZIP_TIME = (1980, 1, 1, 0, 0, 0)  # zip's earliest date: equal arrays, equal bytes


class ChunkWarning(UserWarning):
    """A saved chunk or manifest was unusable and is being replaced."""


def protocol_key(protocol: dict) -> str:
    """A short hash of a JSON-serialisable protocol (what a chunk was computed for)."""
    text = json.dumps(protocol, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def _file_mode() -> int:
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


@contextlib.contextmanager
def _atomic_file(path: Path, mode: str = "wb") -> Iterator:
    """A temporary file in ``path``'s folder, renamed to ``path`` once fully written."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, _file_mode())
        with os.fdopen(fd, mode) as file:
            yield file
            file.flush()
            os.fsync(file.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def save_npz(path, arrays: dict[str, np.ndarray]) -> Path:
    """Write ``arrays`` as an uncompressed ``.npz`` atomically, byte for byte reproducibly."""
    path = Path(path)
    with _atomic_file(path) as file, zipfile.ZipFile(file, "w", zipfile.ZIP_STORED) as archive:
        for name, value in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=_ZIP_TIME)
            info.external_attr = 0o644 << 16
            with archive.open(info, "w", force_zip64=True) as member:
                np.lib.format.write_array(member, np.asanyarray(value), allow_pickle=False)
    return path


def write_text(path, text: str) -> Path:
    """Write a text file atomically (see :func:`save_npz`)."""
    path = Path(path)
    with _atomic_file(path, "w") as file:
        file.write(text)
    return path


def read_npz(path) -> dict[str, np.ndarray]:
    """Every array of an ``.npz`` (no pickles); ``ValueError`` naming the file if unreadable."""
    try:
        with np.load(path, allow_pickle=False) as data:
            return {name: data[name] for name in data.files}
    except (OSError, EOFError, ValueError, KeyError, zipfile.BadZipFile) as error:
        raise ValueError(
            f"{path} is truncated or corrupt ({type(error).__name__}: {error})"
        ) from None


@contextlib.contextmanager
def locked(path) -> Iterator[Path]:
    """Hold ``<path>.lock`` exclusively while writing ``path``.

    Raises
    ------
    RuntimeError
        When another process holds the lock (naming the lock file and that process).
    """
    import fcntl

    lock = Path(f"{path}.lock")
    lock.parent.mkdir(parents=True, exist_ok=True)
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, _file_mode())
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 100, 0).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise RuntimeError(
                f"{lock} is held by another generator (pid {holder}) writing {path}; "
                "wait for it to finish or choose another path"
            ) from None
        # The holder before us may have removed the file between our open and our lock.
        try:
            same = os.stat(lock).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, str(os.getpid()).encode(), 0)
        yield lock
    finally:
        with contextlib.suppress(OSError):
            os.unlink(lock)
        os.close(fd)


@contextlib.contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    """While running, SIGTERM raises KeyboardInterrupt (so finished work gets saved)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum, frame):
        raise KeyboardInterrupt(f"signal {signum}")

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _manifest(folder: Path, protocol: dict) -> None:
    manifest = folder / "manifest.json"
    if manifest.exists():
        try:
            saved = json.loads(manifest.read_text())
        except (ValueError, OSError) as error:
            warnings.warn(
                f"{manifest} is truncated or corrupt ({type(error).__name__}); rewritten "
                "(the chunks carry their protocol's key and are checked one by one)",
                ChunkWarning,
                stacklevel=3,
            )
        else:
            if saved != protocol:
                raise ValueError(
                    f"{folder} holds chunks of a different data set (other constants or "
                    "arguments); delete that folder or choose another path"
                )
            return
    write_text(manifest, json.dumps(protocol))


def _problem(file: Path, key: str, check, k: int) -> str | None:
    try:
        arrays = read_npz(file)
    except ValueError as error:
        return str(error)
    if str(arrays.pop("protocol", "")) != key:
        return f"{file} belongs to another protocol"
    problem = check(k, arrays) if check is not None else None
    return None if problem is None else f"{file} {problem}"


def run_chunks(
    folder,
    protocol: dict,
    fn: Callable[..., dict[str, np.ndarray]],
    chunk_args: Sequence[tuple],
    *,
    executor=None,
    check: Callable[[int, dict[str, np.ndarray]], str | None] | None = None,
    sizes: Sequence[int] | None = None,
    progress: bool = True,
    desc: str = "chunks",
) -> list[Path]:
    """Compute ``fn(*chunk_args[k])`` for every chunk not yet saved in ``folder``.

    Parameters
    ----------
    folder : path-like
        The parts folder (created); ``chunk-<k>.npz`` per chunk and ``manifest.json``.
    protocol : dict
        JSON-serialisable description of what is computed; chunks of another protocol
        are never reused (the folder is refused, or a stray chunk recomputed).
    fn : callable
        Module-level function (workers import it) returning a dict of arrays.
    chunk_args : sequence of tuples
        The arguments of each chunk's task.
    executor : str or object with ``submit``, optional
        A specification for :func:`sim2d.executors.open_executor` (opened and closed
        here), or an open executor; default: a process pool on every core.
    check : callable, optional
        ``check(k, arrays)`` returns what is wrong with chunk k's arrays, or None.
    sizes : sequence of int, optional
        Units of work per chunk, for the progress bar (default 1 each).
    progress : bool
        Show a tqdm progress bar.
    desc : str
        The progress bar's label.

    Returns
    -------
    list of Path
        The chunk files, in chunk order, all intact.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    _manifest(folder, protocol)
    key = protocol_key(protocol)
    files = [folder / f"chunk-{k:06d}.npz" for k in range(len(chunk_args))]
    sizes = list(sizes) if sizes is not None else [1] * len(files)
    todo = []
    for k, file in enumerate(files):
        if not file.exists():
            todo.append(k)
            continue
        problem = _problem(file, key, check, k)
        if problem is not None:
            warnings.warn(f"{problem}; this chunk is computed again", ChunkWarning, stacklevel=2)
            file.unlink()
            todo.append(k)

    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=sum(sizes), unit="throw", desc=desc, smoothing=0.05)
        bar.update(sum(sizes) - sum(sizes[k] for k in todo))

    def save(k: int, arrays: dict[str, np.ndarray]) -> None:
        save_npz(files[k], {**arrays, "protocol": np.array(key)})

    with contextlib.ExitStack() as stack:
        if not todo:
            pass
        elif executor is None or isinstance(executor, str):
            executor = stack.enter_context(open_executor(executor))
        stack.enter_context(_sigterm_as_interrupt())
        if bar is not None:
            stack.callback(bar.close)
        futures: dict = {}
        try:
            futures = {executor.submit(fn, *chunk_args[k]): k for k in todo}
            for future in as_finished(futures):
                k = futures[future]
                arrays = future.result()
                problem = check(k, arrays) if check is not None else None
                assert problem is None, f"chunk {k} computed wrong: {problem}"
                save(k, arrays)
                if bar is not None:
                    bar.update(sizes[k])
        except BaseException as error:
            # Interrupted, a task failed or the disk is full: keep what finished (unless
            # writing is what failed), drop the rest.
            disk_full = isinstance(error, OSError) and error.errno == errno.ENOSPC
            for future, k in futures.items():
                if not disk_full and not files[k].exists() and _succeeded(future):
                    with contextlib.suppress(OSError):
                        save(k, future.result())
                future.cancel()
            raise
    return files


def _succeeded(future) -> bool:
    if not future.done() or future.cancelled():
        return False
    try:
        future.result()
    except BaseException:
        return False
    return True
