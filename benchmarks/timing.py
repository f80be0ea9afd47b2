"""Timing and output shared by the benchmark scripts."""

from __future__ import annotations

import atexit
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TextIO


def median_seconds(fn: Callable[[], object], repeats: int) -> float:
    """Median wall time of ``fn()`` over ``repeats`` calls, after one warm-up call."""
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


class _Both:
    """A text stream writing to two others."""

    def __init__(self, first: TextIO, second: TextIO) -> None:
        self.first, self.second = first, second

    def write(self, text: str) -> int:
        self.second.write(text)
        return self.first.write(text)

    def flush(self) -> None:
        self.first.flush()
        self.second.flush()

    def __getattr__(self, name: str):
        return getattr(self.first, name)


def print_also_to(out: Path | str | None, script: str) -> Path | None:
    """From now on, what this process prints also goes to ``out/<script's name>.md``.

    ``out`` ``None``: nothing changes. The folder is made where missing; the file is
    written afresh and closed when the process exits. Returns its path.
    """
    if out is None:
        return None
    path = Path(out) / f"{Path(script).stem}.md"
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, printed = path.open("w"), sys.stdout
    sys.stdout = _Both(printed, handle)

    def close() -> None:
        sys.stdout = printed
        handle.close()

    atexit.register(close)
    return path


def add_out(parser) -> None:
    """The ``--out DIR`` option of a benchmark script (see :func:`print_also_to`)."""
    parser.add_argument(
        "--out", default=None, help="also write the printed figures to OUT/<script>.md"
    )
