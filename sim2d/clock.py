"""The wall time this process spends simulating.

So that a run can say what share of it is the physics and what share everything else.

Every entry point that simulates (generating a data set, playing throws, settling
configurations) runs under :func:`simulating`, directly or through the :func:`simulation`
decorator; so does a caller that waits on simulations running elsewhere (an executor's
workers). Nested entry points count once: only the outermost interval is added to the
process's total, :func:`simulation_seconds`.
"""

from __future__ import annotations

import functools
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TypeVar

__all__ = ["simulating", "simulation", "simulation_seconds"]

F = TypeVar("F", bound=Callable)

_lock = threading.Lock()
_depth = 0
_started = 0.0
_total = 0.0


@contextmanager
def simulating() -> Iterator[None]:
    """Count the wall time of the ``with`` block as simulation (once, however nested)."""
    global _depth, _started, _total
    with _lock:
        if _depth == 0:
            _started = time.perf_counter()
        _depth += 1
    try:
        yield
    finally:
        with _lock:
            _depth -= 1
            if _depth == 0:
                _total += time.perf_counter() - _started


def simulation(fn: F) -> F:
    """``fn`` with its calls counted as simulation (:func:`simulating`)."""

    @functools.wraps(fn)
    def timed(*args, **kwargs):
        with simulating():
            return fn(*args, **kwargs)

    return timed  # type: ignore[return-value]


def simulation_seconds() -> float:
    """Seconds of wall time this process has spent simulating so far.

    An interval still open counts up to now.
    """
    with _lock:
        running = time.perf_counter() - _started if _depth else 0.0
        return _total + running
