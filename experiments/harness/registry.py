"""Every experiment, declared once in its own module.

An experiment module ends with ``EXPERIMENTS = (Experiment(...),)``: its settings
dataclass, its run function, its result type (whose ``experiment_name`` names the experiment, its
files and its script ``examples/<name>.py``), the settings of a run in seconds for the
tests (``tiny``) and of ``./reproduce --quick`` (``quick``), where its files go below
the results folder, and its place in the paper's order. :func:`experiments` finds every
declaration in the package; ``./reproduce``, the results table
(:mod:`experiments.harness.summary`), the scripts' command lines (:mod:`experiments.harness.cli`) and
the tests iterate over it, so a new experiment is its module, its script and its test.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
import pkgutil
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

from effect_networks.experiments.harness.config import Result, write_result

__all__ = ["Experiment", "experiment", "experiments"]


@dataclass(frozen=True)
class Experiment:
    """One experiment's declaration.

    Attributes
    ----------
    config : type
        Its settings: a frozen dataclass that checks every field on construction (a
        ``progress`` field is the scripts' ``--quiet``).
    run : callable
        ``run(config)`` returns the result; with ``draws``, ``run(config, out)`` draws
        into the folder ``out`` while it runs.
    result : type
        Its :class:`experiments.harness.config.Result` subclass; its ``experiment_name`` is the
        experiment's name.
    order : int
        Its place in ``./reproduce`` and in the results table (the paper's order; a step
        runs after the steps whose simulations it reuses).
    tiny, quick : mapping
        Settings (field -> value) of a run in seconds (the tests), and of
        ``./reproduce --quick`` and a script's ``--quick``.
    folder : str
        Its files' folder below the results folder ("": the results folder itself).
    draws : bool
        ``run`` takes the output folder.
    markdown, figures, summary_rows : callable or None
        The report as functions of a result, for an experiment whose report is a module
        of its own: ``markdown(result)``, ``figures(result, out)`` and
        ``summary_rows(result, results)``; None: the result's own methods.
    """

    config: type
    run: Callable[..., Result]
    result: type[Result]
    order: int
    tiny: Mapping[str, Any] = field(default_factory=dict)
    quick: Mapping[str, Any] = field(default_factory=dict)
    folder: str = ""
    draws: bool = False
    markdown: Callable[[Result], str] | None = None
    figures: Callable[[Result, Path], list[Path]] | None = None
    summary_rows: Callable[[Result, Mapping[str, Result]], list[str]] | None = None

    def __post_init__(self):
        assert dataclasses.is_dataclass(self.config), self.config
        assert issubclass(self.result, Result) and self.result.experiment_name, self.result
        for settings in (self.tiny, self.quick):
            unknown = set(settings) - self.fields
            assert not unknown, f"{self.name}: {sorted(unknown)} are not settings"
        object.__setattr__(self, "tiny", MappingProxyType(dict(self.tiny)))
        object.__setattr__(self, "quick", MappingProxyType(dict(self.quick)))

    @property
    def name(self) -> str:
        """The experiment's name: its result's ``experiment_name``."""
        return self.result.experiment_name

    @property
    def fields(self) -> set[str]:
        """The names of its settings."""
        return {f.name for f in dataclasses.fields(self.config)}

    def out(self, results) -> Path:
        """Its files' folder below the results folder ``results``."""
        return Path(results) / self.folder if self.folder else Path(results)

    def result_file(self, results) -> Path:
        """Its JSON file below the results folder ``results``."""
        return self.out(results) / f"{self.name}.json"

    def report(self, result: Result) -> str:
        """The report of its result ``result``, in Markdown."""
        return self.markdown(result) if self.markdown else result.to_markdown()

    def draw(self, result: Result, out: Path) -> list[Path]:
        """Draw the figures of ``result`` into the folder ``out``; their paths."""
        return self.figures(result, out) if self.figures else result.figures(out)

    def rows(self, result: Result, results: Mapping[str, Result]) -> list[str]:
        """The rows of ``result`` in the results table, given every result by name."""
        if self.summary_rows:
            return self.summary_rows(result, results)
        return result.summary_rows(results)

    def save(self, result: Result, out) -> list[Path]:
        """Write the JSON, the report and the figures of ``result`` to the folder ``out``."""
        return write_result(result, out, self.report(result), lambda at: self.draw(result, at))

    def perform(self, config, out) -> Result:
        """Run it with the settings ``config`` and save its files to the folder ``out``."""
        result = self.run(config, out) if self.draws else self.run(config)
        self.save(result, out)
        return result


@functools.cache
def _registry() -> Mapping[str, Experiment]:
    from effect_networks import experiments as package

    found: list[Experiment] = []
    for module in pkgutil.iter_modules(package.__path__):
        found += getattr(
            importlib.import_module(f"effect_networks.experiments.{module.name}"), "EXPERIMENTS", ()
        )
    found.sort(key=lambda e: e.order)
    names = [e.name for e in found]
    assert len(set(names)) == len(names), f"experiments declared twice: {names}"
    return MappingProxyType({e.name: e for e in found})


def experiments() -> Mapping[str, Experiment]:
    """Every declared experiment by name, in order."""
    return _registry()


def experiment(name: str) -> Experiment:
    """The experiment ``name``; a ``ValueError`` lists the names when there is none."""
    try:
        return _registry()[name]
    except KeyError:
        raise ValueError(
            f"no experiment {name!r}; the experiments are {', '.join(_registry())}"
        ) from None
