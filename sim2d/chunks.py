"""Long simulations saved chunk by chunk: resumable, locked, verified, atomic.

:func:`run_chunks` runs one task per chunk on an executor (:mod:`sim2d.executors`),
collects the arrays as the tasks finish and writes each chunk to its own ``.npz`` in a
parts folder. A later call with the same protocol resumes: chunks already saved and
intact are kept, missing ones are computed. What can go wrong on the way is handled:

- a chunk file that is truncated, corrupt (in any field of its zip or array headers), of
  another protocol or of the wrong shape is named in a warning and computed again (only
  that chunk); every chunk carries its protocol's key itself, so a manifest that is
  corrupt, or edited into other JSON while the chunks carry this protocol's key, is
  named and rewritten, and a folder is refused only when its chunks belong to another
  protocol (the message says which fields of the manifest differ);
- :func:`locked` keeps two processes from writing one output (an OS file lock, released
  when its holder ends, however it ends);
- files are written to a temporary file, flushed and renamed (:func:`save_npz`), so a
  crash or a full disk leaves no half file; a failed write removes its temporary file,
  and the temporary files a killed writer left are removed by the next run (which holds
  the lock); files are created with the permissions of an ordinary file (0666 less the
  umask, 0644 usually);
- an executor that cannot be opened (a Dask scheduler that does not answer) fails before
  anything is written;
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
from effect_networks.sim2d.clock import simulating
from effect_networks.sim2d.executors import as_finished, open_executor

__all__ = [
    "WRITE_ERRNOS",
    "ChunkWarning",
    "locked",
    "protocol_key",
    "read_npz",
    "remove_temporaries",
    "run_chunks",
    "save_npz",
    "write_failure",
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
    """A temporary file in ``path``'s folder, renamed to ``path`` once fully written.

    An ``OSError`` that does not say which file it is about (a full disk) is raised
    again naming ``path``.
    """
    tmp = None
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        os.fchmod(fd, _file_mode())
        with os.fdopen(fd, mode) as file:
            yield file
            file.flush()
            os.fsync(file.fileno())
        os.replace(tmp, path)
    except BaseException as error:
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
        if isinstance(error, OSError) and (error.filename is None or tmp is None):
            raise OSError(error.errno, error.strerror or str(error), str(path)) from error
        raise


#: Errors of a path that cannot be a folder or a file to write: a file where a folder is
#: needed (``mkdir`` gives EEXIST, a path through it ENOTDIR), a folder where the file
#: goes, a name too long.
_PATH_ERRNOS = frozenset({errno.EEXIST, errno.ENOTDIR, errno.EISDIR, errno.ENAMETOOLONG})
#: The errors of a write that the user can remedy: a full disk or quota, a read-only or
#: forbidden folder, a file-size limit, a path that cannot be written (see above).
WRITE_ERRNOS = (
    frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EFBIG})
    | _PATH_ERRNOS
)


_READ_ONLY_ERRNOS = frozenset({errno.EROFS, errno.EACCES, errno.EPERM})


def write_failure(error: BaseException) -> str | None:
    """One line saying which write failed and why, for an ``OSError`` of :data:`WRITE_ERRNOS`.

    None for any other error.
    """
    if not isinstance(error, OSError) or error.errno not in WRITE_ERRNOS:
        return None
    name = error.filename2 if error.errno == errno.EISDIR and error.filename2 else error.filename
    where = f" {name}" if name else " a file"
    why = error.strerror or str(error)
    if error.errno in (errno.EEXIST, errno.ENOTDIR):
        why += " (a file stands where a folder is needed)"
    elif error.errno == errno.EISDIR:
        why += " (a folder stands where the file goes)"
    return f"could not write{where}: {why}"


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
    except Exception as error:
        # Damage can reach any field zipfile or numpy reads: a changed compression method
        # or flag raises NotImplementedError, an encryption bit RuntimeError, a changed
        # header ValueError or EOFError; each means the same: this file is unusable.
        raise ValueError(
            f"{path} is truncated or corrupt ({type(error).__name__}: {error})"
        ) from None


@contextlib.contextmanager
def locked(path, *, or_read_only: bool = False) -> Iterator[Path | None]:
    """Hold ``<path>.lock`` exclusively while writing ``path``.

    With ``or_read_only``, a lock file that cannot be created because its folder cannot
    be written to (a read-only file system, no permission) is not taken and None is
    yielded: what is finished there can still be read (every file is renamed into place
    whole), and any write fails naming its file.

    Raises
    ------
    RuntimeError
        When another process holds the lock (naming the lock file and that process).
    """
    import fcntl

    lock = Path(f"{path}.lock")
    lock.parent.mkdir(parents=True, exist_ok=True)
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, _file_mode())
        except OSError as error:
            if not (or_read_only and error.errno in _READ_ONLY_ERRNOS):
                raise
            yield None
            return
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


def _manifest_is_current(folder: Path, protocol: dict, key: str) -> bool:
    """Whether ``folder``'s manifest describes ``protocol`` (False: write it).

    Reads only. A manifest that is unreadable or describes another protocol is judged by
    the chunks, which carry their protocol's key: when some carry this protocol's (or
    none is readable) it is named in a warning and is to be rewritten, and no chunk is
    lost; when they all belong to another protocol the folder is refused.
    """
    manifest = folder / "manifest.json"
    if not manifest.exists():
        return False
    try:
        saved = json.loads(manifest.read_text())
    except (ValueError, OSError, RecursionError) as error:
        what = f"is truncated or corrupt ({type(error).__name__})"
    else:
        if saved == protocol:
            return True
        what = f"does not describe this data set ({_difference(saved, protocol)})"
    keys = [_chunk_key(file) for file in sorted(folder.glob("chunk-*.npz"))]
    ours = keys.count(key)
    others = len(keys) - ours - keys.count(None)
    if ours or not others:
        chunks = f"{ours} of its chunks do" if ours else "no chunk belongs to another"
        warnings.warn(
            f"{manifest} {what}; rewritten ({chunks}: the chunks carry their protocol's "
            "key and are checked one by one)",
            ChunkWarning,
            stacklevel=3,
        )
        return False
    raise ValueError(
        f"{folder} holds {others} chunk(s) of a different data set (its manifest.json "
        f"{what}); none was computed for these constants and arguments. Delete that "
        "folder or choose another path"
    )


def _chunk_key(file: Path) -> str | None:
    """The protocol key a chunk file carries, or None if it cannot be read."""
    try:
        with np.load(file, allow_pickle=False) as data:
            return str(data["protocol"])
    except Exception:  # damaged: checked (and recomputed) with the other chunks
        return None


def _difference(saved, protocol: dict) -> str:
    """How a manifest's JSON differs from ``protocol``, field by field, briefly."""
    if not isinstance(saved, dict):
        return f"holds a JSON {type(saved).__name__}, not an object"

    def brief(value) -> str:
        text = json.dumps(value)
        return text if len(text) <= 40 else text[:37] + "..."

    changed = [
        f"{name}: {brief(saved[name])} there, {brief(protocol[name])} here"
        for name in sorted(set(saved) & set(protocol))
        if saved[name] != protocol[name]
    ]
    changed += [f"{name}: missing there" for name in sorted(set(protocol) - set(saved))]
    changed += [f"{name}: not expected" for name in sorted(set(saved) - set(protocol))]
    shown = "; ".join(changed[:4]) + ("; ..." if len(changed) > 4 else "")
    return f"differs in {shown}"


def remove_temporaries(path) -> None:
    """Remove the temporary files that killed writers of ``path`` left.

    ``path``'s name may be a glob pattern (``folder / "*"``: every file of the folder).
    Call it holding the lock on the output (:func:`locked`), when no writer is at work.
    """
    path = Path(path)
    for stale in path.parent.glob(f".{path.name}.*.tmp"):
        with contextlib.suppress(OSError):
            stale.unlink()


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
        The caller holds a lock (:func:`locked`) on the output the folder is for: the
        temporary files found in the folder are a killed writer's and are removed.
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
    key = protocol_key(protocol)
    current = _manifest_is_current(folder, protocol, key)
    remove_temporaries(folder / "*")
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

    def save(k: int, arrays: dict[str, np.ndarray]) -> None:
        save_npz(files[k], {**arrays, "protocol": np.array(key)})

    with contextlib.ExitStack() as stack:
        # The executor opens before anything is written: an unreachable cluster leaves
        # no folder or manifest behind.
        if todo and (executor is None or isinstance(executor, str)):
            executor = stack.enter_context(open_executor(executor))
        folder.mkdir(parents=True, exist_ok=True)
        if not current:
            write_text(folder / "manifest.json", json.dumps(protocol))
        bar = None
        if progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=sum(sizes), unit="throw", desc=desc, smoothing=0.05)
            bar.update(sum(sizes) - sum(sizes[k] for k in todo))
        stack.enter_context(_sigterm_as_interrupt())
        if bar is not None:
            stack.callback(bar.close)
        futures: dict = {}
        try:
            if todo:  # the chunks' simulations, here or on workers
                stack.enter_context(simulating())
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
