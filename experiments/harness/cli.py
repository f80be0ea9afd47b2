"""An experiment's command line, derived from its settings dataclass.

Each field of the experiment's Config is a flag: ``n_train`` is ``--n-train``, typed
by the field's annotation (``int``, ``float``, ``str``, ``Path``, ``bool`` a switch, a
``tuple[int, ...]`` one or more values, ``X | None`` an ``X``), its help the field's
entry in the class docstring's ``Attributes`` section (or ``field(metadata={"help":
...})``), its default the field's. The values are checked by the Config itself
(:func:`experiments.harness.config.config_or_exit`: a bad value is a usage error naming the
flag). Every script also takes:

``--out``      the folder for its files;
``--quick``    the experiment's quick settings (a flag given as well wins);
``--quiet``    no progress bars (the Config's ``progress`` field);
``--threads``  torch threads (small tensors: 1 is fastest, and timings use 1).

A script ``examples/<name>.py`` is its docstring and ``main("<name>", __doc__)``.
"""

from __future__ import annotations

import argparse
import dataclasses
import re
import types
import typing
from pathlib import Path

from effect_networks.experiments.harness.config import check_threads, config_or_exit, run_script
from effect_networks.experiments.harness.registry import Experiment, experiment

__all__ = ["field_help", "main", "make_parser", "parse_args"]

SHARED = ("out", "quick", "quiet", "threads")
#: Fields set by a shared flag rather than one of their own.
NOT_FLAGS = ("progress",)


def _plain(text: str) -> str:
    """Docstring markup as plain text: roles and double backquotes dropped."""
    text = re.sub(r":\w+:`~?([^`]+)`", r"\1", text)
    return " ".join(text.replace("``", "").split())


def field_help(config: type) -> dict[str, str]:
    """Each field's description.

    ``field(metadata={"help": ...})``, else its entry in the docstring's numpydoc ``Attributes``
    section (``a, b : type`` then indented lines).
    """
    entries: dict[str, str] = {}
    for cls in reversed(config.__mro__):  # a subclass's entry wins over its base's
        if dataclasses.is_dataclass(cls):
            entries |= _attributes(cls.__doc__ or "")
    helps = {n: _plain(text) for n, text in entries.items()}
    for f in dataclasses.fields(config):
        if "help" in f.metadata:
            helps[f.name] = _plain(f.metadata["help"])
    return helps


def _attributes(doc: str) -> dict[str, str]:
    """The entries of a numpydoc ``Attributes`` section by name."""
    lines = doc.expandtabs().splitlines()
    entries: dict[str, str] = {}
    try:
        start = next(i for i, line in enumerate(lines) if line.strip() == "Attributes") + 2
    except StopIteration:
        start = len(lines)
    names: list[str] = []
    indent = None
    for line in lines[start:]:
        if not line.strip():
            continue
        depth = len(line) - len(line.lstrip())
        if indent is None:
            indent = depth
        if depth <= indent:
            if depth < indent:
                break
            names = [n.strip() for n in line.split(":")[0].split(",")]
            for n in names:
                entries[n] = ""
        else:
            for n in names:
                entries[n] = (entries[n] + " " + line.strip()).strip()
    return entries


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def _add_field(parser: argparse.ArgumentParser, f: dataclasses.Field, hint, help_text: str):
    """One field's flag.

    Its default is left out of the namespace (``SUPPRESS``) so that only the flags given override
    the Config's defaults and the quick settings.
    """
    default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):  # X | None
        (hint,) = [a for a in args if a is not type(None)]
        origin, args = typing.get_origin(hint), typing.get_args(hint)
    shown = list(default) if isinstance(default, tuple) else default
    if "default" not in help_text:
        help_text = f"{help_text} (default: {shown})"
    kw: dict = {"default": argparse.SUPPRESS, "help": help_text.replace("%", "%%")}
    if hint is bool:
        action = "store_true" if not default else argparse.BooleanOptionalAction
        parser.add_argument(_flag(f.name), action=action, **kw)
        return
    if origin is tuple:
        kw["nargs"] = "+"
        hint = args[0]
    if hint not in (int, float, str, Path):
        raise TypeError(
            f"{f.name}: a {hint} setting has no command-line flag; use int, "
            "float, str, Path or bool, a tuple of one of them, or X | None"
        )
    kw["type"] = {int: int, float: float}.get(hint, str)  # a Path: its Config converts it
    parser.add_argument(_flag(f.name), **kw)


def make_parser(exp: Experiment, description: str | None = None) -> argparse.ArgumentParser:
    """The experiment's command line: one flag per setting, and the shared ones."""
    parser = argparse.ArgumentParser(
        prog=f"{exp.name}.py",
        description=description,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    helps = field_help(exp.config)
    hints = typing.get_type_hints(exp.config)
    for f in dataclasses.fields(exp.config):
        if f.name not in NOT_FLAGS:
            _add_field(parser, f, hints[f.name], helps.get(f.name, ""))
    shared = parser.add_argument_group("every experiment's")
    shared.add_argument(
        "--out", default=str(exp.out("results")), help="folder for the files (default: %(default)s)"
    )
    quick = ", ".join(f"{k}={v}" for k, v in exp.quick.items())
    shared.add_argument(
        "--quick",
        action="store_true",
        help=f"a first look: {quick}" if quick else "the defaults (they are quick already)",
    )
    shared.add_argument("--quiet", action="store_true", help="no progress bars")
    shared.add_argument(
        "--threads", type=int, default=1, help="torch threads (small tensors: 1 is fastest)"
    )
    return parser


def parse_args(
    name: str | Experiment, argv=None, description: str | None = None
) -> argparse.Namespace:
    """The command line of experiment ``name`` (or of the declaration itself).

    ``experiment``, ``config`` (its checked settings), ``out``, ``threads``; a bad value exits with
    a usage error naming the flag.
    """
    exp = name if isinstance(name, Experiment) else experiment(name)
    parser = make_parser(exp, description)
    args = parser.parse_args(argv)
    config_or_exit(parser, lambda: check_threads("threads", args.threads))
    given = {k: v for k, v in vars(args).items() if k not in SHARED}
    settings = (dict(exp.quick) if args.quick else {}) | given
    settings = {k: tuple(v) if isinstance(v, list) else v for k, v in settings.items()}
    if "progress" in exp.fields:
        settings["progress"] = not args.quiet
    config = config_or_exit(parser, lambda: exp.config(**settings))
    return argparse.Namespace(
        experiment=exp, config=config, out=Path(args.out), threads=args.threads
    )


def _perform(args: argparse.Namespace):
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(args.threads)
    try:
        result = args.experiment.perform(args.config, args.out)
    finally:
        torch.set_num_threads(threads)
    print(args.experiment.report(result))
    return result


def main(name: str | Experiment, description: str | None = None, argv=None):
    """Run experiment ``name`` from the command line and exit.

    ``argv`` defaults to ``sys.argv`` (:func:`experiments.harness.config.run_script`).
    """
    run_script(_perform, parse_args(name, argv, description))
