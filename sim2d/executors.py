"""Where simulations run: a process pool, a Dask cluster or Ray, chosen by one string.

The can world's long jobs (:func:`sim2d.can_dataset.generate_dataset`,
:func:`sim2d.configurations.stable_configurations`, :func:`sim2d.chunks.run_chunks`) take
an ``executor``: either an object with ``submit(fn, *args)`` returning a future with
``result()`` (nothing else is used), or one of these specifications, opened and closed
by :func:`open_executor`:

====================  ================================================================
``process:N``         N worker processes on this machine (``concurrent.futures``); the
                      workers end when the process that started them ends
``dask-local:N``      a Dask ``LocalCluster`` of N single-threaded worker processes
``dask://HOST:PORT``  the Dask scheduler at HOST:PORT (any cluster: ``dask scheduler``
                      plus ``dask worker tcp://HOST:PORT`` on each machine)
``ray``               Ray: the cluster named by ``RAY_ADDRESS`` if set, else a local one
====================  ================================================================

An executor that cannot be opened raises :class:`ExecutorUnavailable` naming the
specification (a Dask scheduler that does not answer within ``DASK_CONNECT_TIMEOUT``
seconds, for instance). Workers need this package importable (installed in the same version on every machine)
but no shared disk: they return arrays and the calling process writes the files. Every
executor opened here returns ``concurrent.futures.Future`` objects, so results can be
collected as they finish (:func:`as_finished`).
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import importlib
import os
import re
import socket
import threading
from collections.abc import Iterator

__all__ = [
    "DASK_CONNECT_TIMEOUT",
    "ExecutorUnavailable",
    "RayExecutor",
    "as_finished",
    "available_cores",
    "default_spec",
    "open_executor",
    "parse_spec",
]

_SPEC = re.compile(r"^(?:(process|dask-local):(\d+)|dask://([^\s:/]+):(\d+)|(ray))$")
_EXPECTED = "process:N, dask-local:N, dask://HOST:PORT or ray"

#: Seconds to wait for a Dask scheduler to answer (a refused connection is retried until
#: then): long enough for a scheduler across a network, short enough to tell a user soon.
DASK_CONNECT_TIMEOUT = 10


class ExecutorUnavailable(RuntimeError):
    """An executor specification names a cluster that cannot be reached."""


def available_cores() -> int:
    """The number of CPU cores this process may use."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def default_spec() -> str:
    """``process:N`` with N the number of CPU cores this process may use."""
    return f"process:{available_cores()}"


def parse_spec(spec: str) -> tuple[str, int | str | None]:
    """``(kind, argument)`` of an executor specification (see the module docstring).

    Raises
    ------
    ValueError
        Naming the specification and the forms expected.
    """
    match = _SPEC.match(spec) if isinstance(spec, str) else None
    if match is None:
        raise ValueError(f"executor={spec!r} is not an executor; expected {_EXPECTED}")
    kind, n, host, port, ray = match.groups()
    if kind is not None:
        if int(n) < 1:
            raise ValueError(f"executor={spec!r} asks for {n} workers; expected at least 1")
        return kind, int(n)
    if host is not None:
        if not 1 <= int(port) <= 65535:
            raise ValueError(f"executor={spec!r} names port {port}; expected a port in 1..65535")
        return "dask", f"tcp://{host}:{int(port)}"
    return "ray", None


def _end_with_parent(parent: int) -> None:
    """Pool-worker initializer: exit as soon as the process that started the pool is gone.

    The worker also ignores SIGINT and SIGTERM: a Ctrl-C or a SIGTERM to the process
    group reaches every worker too, and the parent saves what finished and shuts the
    pool down (a worker that died of the signal instead would break the pool under the
    parent's cancelled futures, whose bookkeeping thread then fails with a traceback). A
    pool worker blocks on its task queue, whose other end the forked workers keep open
    themselves, so a parent killed by a signal would leave them waiting forever: the
    kernel kills the worker then (SIGKILL, which cannot be ignored), or the watch below.
    """
    import ctypes
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    # ... and so is SIGTERM. A worker forked while the parent turns SIGTERM into
    # KeyboardInterrupt (so that it saves what finished) would otherwise inherit that
    # handler, whose interrupt can land in a pymunk finaliser and print a traceback.
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    with contextlib.suppress(OSError, AttributeError):  # Linux: the kernel tells us
        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG

    def watch() -> None:  # everywhere else (and for a parent that died before prctl)
        while os.getppid() == parent:
            threading.Event().wait(0.2)
        os._exit(1)

    threading.Thread(target=watch, daemon=True, name="end-with-parent").start()


class RayExecutor:
    """``submit(fn, *args)`` as a Ray task; returns its ``ObjectRef.future()``."""

    def __init__(self) -> None:
        self._ray = _optional("ray", "Ray")
        self._remote: dict = {}

    def submit(self, fn, *args) -> concurrent.futures.Future:
        """Run ``fn(*args)`` as a Ray task; its future."""
        if fn not in self._remote:
            self._remote[fn] = self._ray.remote(fn)
        return self._remote[fn].remote(*args).future()


@contextlib.contextmanager
def open_executor(spec: str | None = None) -> Iterator:
    """Open the executor named by ``spec`` (default :func:`default_spec`) and close it after.

    Yields an object with ``submit(fn, *args)`` returning ``concurrent.futures.Future``.
    A process pool is shut down with its queued tasks cancelled; a Dask client and its
    local cluster are closed; Ray is shut down if it was started here.
    """
    kind, arg = parse_spec(default_spec() if spec is None else spec)
    if kind == "process":
        pool = concurrent.futures.ProcessPoolExecutor(
            max_workers=arg, initializer=_end_with_parent, initargs=(os.getpid(),)
        )
        try:
            yield pool
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
    elif kind in ("dask-local", "dask"):
        distributed = _optional("distributed", "Dask")
        Client, LocalCluster = distributed.Client, distributed.LocalCluster

        with contextlib.ExitStack() as stack:
            if kind == "dask-local":
                cluster = stack.enter_context(
                    LocalCluster(
                        n_workers=arg,
                        threads_per_worker=1,
                        processes=True,
                        dashboard_address=None,
                    )
                )
                client = stack.enter_context(Client(cluster))
            else:
                try:
                    # A plain connection first: distributed retries a refused one until
                    # its timeout, where nothing listening is known at once.
                    host, port = arg.removeprefix("tcp://").rsplit(":", 1)
                    socket.create_connection((host, int(port)), DASK_CONNECT_TIMEOUT).close()
                    client = stack.enter_context(Client(arg, timeout=DASK_CONNECT_TIMEOUT))
                except OSError as error:  # distributed's connection timeout is an OSError
                    raise ExecutorUnavailable(
                        f"executor={spec!r}: no Dask scheduler answers at {arg} "
                        f"({error}); expected a running scheduler there "
                        f"(`dask scheduler --port {port}`)"
                    ) from None
            yield client.get_executor(pure=False)
    else:
        ray = _optional("ray", "Ray")
        started = not ray.is_initialized()
        if started:
            ray.init(address=os.environ.get("RAY_ADDRESS"), log_to_driver=False)
        try:
            yield RayExecutor()
        finally:
            if started:
                ray.shutdown()


def as_finished(futures) -> Iterator:
    """The futures in the order they finish (``concurrent.futures`` ones), else as given."""
    futures = list(futures)
    if all(isinstance(f, concurrent.futures.Future) for f in futures):
        return concurrent.futures.as_completed(futures)
    return iter(futures)


def _optional(module: str, name: str):
    """``module`` imported, or an ImportError naming the extra that installs it."""
    try:
        return importlib.import_module(module)
    except ImportError as error:
        raise ImportError(
            f"this executor needs {name} ({module}), the `cluster` extra of effect-networks: "
            "install it with `pip install 'effect-networks[cluster]'`"
        ) from error
