"""What every experiment shares: checks of its settings and its result files.

An experiment is a function of one frozen settings dataclass (``...Config``) that
returns a result dataclass. A settings dataclass checks every field in
``__post_init__`` with the functions here, which raise :class:`ConfigError` (a
``ValueError``) naming the field, the value and what was expected; a script turns it
into a command-line error with :func:`config_or_exit`, and runs its ``main`` with
:func:`run_script` (what a user can remedy ends it with a short message, not a
traceback). A result dataclass derives from
:class:`Result`: ``to_json`` / ``from_json`` / ``load`` round-trip its fields (plain
JSON values: numbers, strings, lists, dicts with string keys), ``to_markdown`` is its
report, ``figures(out)`` draws its figures, ``summary_rows`` are its rows of the results
table (:mod:`experiments.harness.summary`), and ``save(out)`` writes them all as
``<experiment_name>.json``, ``.md`` and the figures' files.
"""

from __future__ import annotations

import argparse
import json
import math
import numbers
import operator
import sys
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, ClassVar, TypeVar

from effect_networks.experiments.harness.steps import write_step_record
from effect_networks.sim2d.chunks import write_failure, write_text
from effect_networks.sim2d.executors import ExecutorUnavailable, available_cores, parse_spec

__all__ = [
    "ConfigError",
    "Result",
    "check_choice",
    "check_executor",
    "check_float",
    "check_int",
    "check_threads",
    "config_or_exit",
    "percent",
    "run_script",
    "write_result",
]

T = TypeVar("T")


class ConfigError(ValueError):
    """An experiment setting out of range; ``field`` names it."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field


def check_int(field: str, value, low: int, high: int | None = None) -> int:
    """``value`` as an int in ``[low, high]`` (``high`` None: no upper limit)."""
    expected = f"an integer >= {low}" if high is None else f"an integer in {low}..{high}"
    if isinstance(value, bool):
        raise ConfigError(field, f"{value!r} is a bool; expected {expected}")
    try:
        number = operator.index(value)
    except TypeError:
        raise ConfigError(field, f"{value!r} is not an integer; expected {expected}") from None
    if number < low or (high is not None and number > high):
        raise ConfigError(field, f"{value!r} is out of range; expected {expected}")
    return number


def check_float(
    field: str, value, low: float, high: float, *, low_open: bool = False, unit: str = ""
) -> float:
    """``value`` as a finite float in ``[low, high]`` (``(low, high]`` with ``low_open``)."""
    bracket = "(" if low_open else "["
    expected = f"a number in {bracket}{low:g}, {high:g}]" + (f" {unit}" if unit else "")
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ConfigError(field, f"{value!r} is not a number; expected {expected}")
    number = float(value)
    below = number <= low if low_open else number < low
    if not math.isfinite(number) or below or number > high:
        raise ConfigError(field, f"{value!r} is out of range; expected {expected}")
    return number


def check_threads(field: str, value) -> int:
    """A number of torch threads: an int from 1 to the CPU cores this process may use."""
    return check_int(field, value, 1, available_cores())


def check_choice(field: str, value: T, choices: Iterable[T]) -> T:
    """``value`` if it is one of ``choices``."""
    choices = tuple(choices)
    if value not in choices:
        raise ConfigError(field, f"{value!r} is not one of {', '.join(map(repr, choices))}")
    return value


def check_executor(field: str, value: str | None) -> str | None:
    """An executor specification (:mod:`sim2d.executors`), or None for every core here."""
    if value is not None:
        try:
            parse_spec(value)
        except ValueError as error:
            raise ConfigError(field, str(error)) from None
    return value


def config_or_exit(parser: argparse.ArgumentParser, make: Callable[[], T]) -> T:
    """``make()``, or the parser's usage error (exit status 2) naming the option at fault.

    A :class:`ConfigError` on field ``n_train`` is reported as ``--n-train: ...``.
    """
    try:
        return make()
    except ConfigError as error:
        flag = "--" + error.field.replace("_", "-")
        parser.error(f"{flag}{str(error)[len(error.field) :]}")
    raise AssertionError("parser.error returns only by raising")  # pragma: no cover


def run_script(main: Callable[[argparse.Namespace], object], args: argparse.Namespace):
    """Run a script's ``main(args)`` and exit: status 0, or the int ``main`` returns.

    What a user can remedy ends the script with a line or two on stderr instead of a
    traceback: a write that failed (a full disk, a read-only or forbidden folder; status
    1), an executor that cannot be reached (2), an interrupt (Ctrl-C, or SIGTERM while a
    data set is generated; 130). A data set being generated keeps its finished chunks,
    so running the script again resumes it. Run as a step of ``./reproduce``, it writes its
    simulation time and peak memory as it exits (:mod:`experiments.harness.steps`).
    """
    try:
        _run(main, args)
    finally:
        write_step_record()


def _run(main: Callable[[argparse.Namespace], object], args: argparse.Namespace):
    prog = Path(sys.argv[0]).name
    try:
        result = main(args)
    except KeyboardInterrupt:
        sys.stderr.write(f"{prog}: interrupted; run it again to resume\n")
        sys.exit(130)
    except ExecutorUnavailable as error:
        sys.stderr.write(f"{prog}: error: {error}\n")
        sys.exit(2)
    except OSError as error:
        failure = write_failure(error)
        if failure is None:
            raise
        sys.stderr.write(
            f"{prog}: error: {failure}\n{prog}: free some space or choose a writable "
            "folder, then run it again (a data set being generated resumes where it stopped)\n"
        )
        sys.exit(1)
    sys.exit(result if isinstance(result, int) and not isinstance(result, bool) else 0)


def percent(x: float | None, digits: int = 2) -> str:
    """The fraction ``x`` in per cent with ``digits`` decimals, or ``n/a`` for None."""
    return "n/a" if x is None else f"{100 * x:.{digits}f} %"


def write_result(
    result: Result, out, markdown: str, figures: Callable[[Path], Iterable[Path]]
) -> list[Path]:
    """Write ``<name>.json``, ``<name>.md`` (``markdown``) and ``figures(out)`` to the folder ``out``.

    The folder is made if absent; returns the paths written.
    """
    name = result.experiment_name
    assert name, f"{type(result).__name__} names no experiment"
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = [
        write_text(out / f"{name}.json", result.to_json()),
        write_text(out / f"{name}.md", markdown),
    ]
    return files + list(figures(out))


@dataclass
class Result:
    """Base of the experiments' results: JSON round trip of the dataclass's fields, and their files.

    A subclass names its experiment in the class variable ``experiment_name`` (its files
    are ``<experiment_name>.json`` and ``.md``), writes its report in :meth:`to_markdown`, and may
    draw figures (:meth:`figures`) and give rows of the results table
    (:meth:`summary_rows`). An experiment whose report is a module of its own (a layer above
    its run) leaves these out and declares the report's functions instead
    (:class:`experiments.harness.registry.Experiment`).
    """

    experiment_name: ClassVar[str] = ""

    def to_markdown(self) -> str:
        """The report, in Markdown."""
        raise NotImplementedError(f"{type(self).__name__} has no report")

    def figures(self, out: Path) -> list[Path]:
        """Draw the figures into the folder ``out``; their paths (none by default)."""
        return []

    def summary_rows(self, results: Mapping[str, Result]) -> list[str]:
        """Rows of the results table (``| experiment | paper | ours | bound |``).

        Given every result of the run by experiment name; none by default.
        """
        return []

    def save(self, out) -> list[Path]:
        """Write ``<name>.json``, ``<name>.md`` and the figures to the folder ``out``.

        The folder is made if absent; returns the paths written.
        """
        return write_result(self, out, self.to_markdown(), self.figures)

    def to_dict(self) -> dict[str, Any]:
        """The fields by name (values are shared, not copied)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def to_json(self) -> str:
        """The fields as one JSON object (what :meth:`from_json` reads back)."""
        return json.dumps(self.to_dict(), indent=1) + "\n"

    @classmethod
    def from_json(cls: type[T], text: str) -> T:
        """The result :meth:`to_json` wrote.

        ``ValueError`` for a file of another experiment, or one that is not JSON (truncated, nested
        too deep) or not an object.
        """
        try:
            data = json.loads(text)
        except (ValueError, RecursionError) as error:
            raise ValueError(
                f"not a {cls.__name__}: unreadable JSON ({type(error).__name__})"
            ) from None
        if not isinstance(data, dict):
            raise ValueError(
                f"not a {cls.__name__}: the JSON is a {type(data).__name__}, not an object"
            )
        names = [f.name for f in fields(cls)]
        missing = [n for n in names if n not in data]
        if missing:
            raise ValueError(f"not a {cls.__name__}: the JSON lacks {missing}")
        return cls(**{n: data[n] for n in names})

    @classmethod
    def load(cls: type[T], path) -> T:
        """:meth:`from_json` of a file; its ``ValueError`` names the file."""
        try:
            return cls.from_json(Path(path).read_text())
        except ValueError as error:
            raise ValueError(f"{path}: {error}") from None
