"""Two runs' results compared: every JSON value equal, timings and paths aside.

``python -m effect_networks.experiments.harness.compare BEFORE AFTER`` walks both results folders (as
``./reproduce --out`` or an example's ``--out`` leave them), pairs their ``*.json`` files
by relative path and reports every value that differs, every file or key found on one
side only, and the count. What legitimately changes between two runs of the same code is
left out: the commit, date and machine, every field that holds a time (a key ending in
``_s`` or containing ``time`` or ``seconds``), peak memory, and paths (``out``,
``data_dir``, ``files``). Floats compare exactly (NaN equals NaN): the question is
whether a change kept the results, not whether they are close.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

__all__ = ["compare_folders", "compare_values", "ignored", "main"]

_IGNORED = {
    "commit", "date", "machine", "args", "argv", "command", "out", "data_dir", "files",
    "python", "torch", "peak_bytes",
}  # fmt: skip


def ignored(key: str) -> bool:
    """Whether a JSON key holds what differs between runs of the same code.

    Parameters
    ----------
    key
        A JSON object's key.

    Returns
    -------
    bool
        True for run metadata, paths, memory and every time.
    """
    low = key.lower()
    return key in _IGNORED or key.endswith("_s") or "time" in low or "seconds" in low


def compare_values(before: object, after: object, path: str) -> list[str]:
    """Every difference between two JSON values, one line each, named by its path.

    Parameters
    ----------
    before, after
        Decoded JSON values.
    path
        Where they stand (the file and the keys above them).

    Returns
    -------
    list of str
        ``"path: before vs after"``, ``"path/key: only in before|after"`` or
        ``"path: length m vs n"``; empty where equal.
    """
    out: list[str] = []
    if isinstance(before, dict) and isinstance(after, dict):
        for key in sorted(set(before) | set(after)):
            if ignored(key):
                continue
            if key not in before or key not in after:
                out.append(f"{path}/{key}: only in {'after' if key in after else 'before'}")
            else:
                out += compare_values(before[key], after[key], f"{path}/{key}")
    elif isinstance(before, list) and isinstance(after, list):
        if len(before) != len(after):
            out.append(f"{path}: length {len(before)} vs {len(after)}")
        for i, (x, y) in enumerate(zip(before, after, strict=False)):
            out += compare_values(x, y, f"{path}[{i}]")
    elif isinstance(before, float) and isinstance(after, float):
        if not (before == after or (math.isnan(before) and math.isnan(after))):
            out.append(f"{path}: {before!r} vs {after!r}")
    elif before != after or type(before) is not type(after):
        out.append(f"{path}: {str(before)[:80]!r} vs {str(after)[:80]!r}")
    return out


def compare_folders(before: Path | str, after: Path | str) -> list[str]:
    """Every difference between two results folders' JSON files.

    Parameters
    ----------
    before, after
        Results folders.

    Returns
    -------
    list of str
        One line per difference (see :func:`compare_values`), files found on one side
        only included; empty where every result is equal.

    Raises
    ------
    ValueError
        Where a folder does not exist.
    """
    before, after = Path(before), Path(after)
    for folder in (before, after):
        if not folder.is_dir():
            raise ValueError(f"{folder} is not a folder of results")
    out: list[str] = []
    for file in sorted(before.rglob("*.json")):
        rel = file.relative_to(before)
        twin = after / rel
        if not twin.exists():
            out.append(f"{rel}: only in before")
            continue
        out += compare_values(json.loads(file.read_text()), json.loads(twin.read_text()), str(rel))
    out += [
        f"{file.relative_to(after)}: only in after"
        for file in sorted(after.rglob("*.json"))
        if not (before / file.relative_to(after)).exists()
    ]
    return out


def main(argv: list[str] | None = None) -> int:
    """Print the differences and their count; exit status 1 where there are any.

    Parameters
    ----------
    argv
        ``BEFORE AFTER``; the command line by default.

    Returns
    -------
    int
        0 where every result is equal, 1 otherwise.
    """
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("before", type=Path)
    parser.add_argument("after", type=Path)
    args = parser.parse_args(argv)
    try:
        differences = compare_folders(args.before, args.after)
    except ValueError as error:
        parser.error(str(error))
    print("\n".join(differences) or "equal")
    print(f"{len(differences)} differences")
    return 1 if differences else 0


if __name__ == "__main__":
    raise SystemExit(main())
