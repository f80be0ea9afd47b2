"""The shape of models/: its imports form no circle, point to nothing above it, and no
room grows past 600 lines.

The import graph is read from the source (an ast walk), so it counts every import: at the
top, inside functions, and under ``if TYPE_CHECKING``, where a type-only circle hides.
"""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
MODELS = ROOT / "models"
#: The packages models/ sits below (its imports point down only).
ABOVE = ("inference", "experiments", "examples", "sim2d", "benchmarks")
MAX_LINES = 600


def module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imported(tree: ast.Module, name: str, is_package: bool) -> list[str]:
    """Every module an ast imports from (absolute names), a ``from X import y`` counting
    ``X`` and, when it names a module, ``X.y``."""
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.extend(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: from the package holding the module
                base = name.split(".")
                base = base[: len(base) - node.level + (1 if is_package else 0)]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module
            out.append(module)
            out.extend(f"{module}.{alias.name}" for alias in node.names)
    return out


def import_graph(package: Path) -> dict[str, set[str]]:
    """``{module: the modules of the package it imports}`` for every module under
    ``package`` (a folder of the repository root's)."""
    root = package.parent
    files = {module_name(p, root): p for p in sorted(package.rglob("*.py"))}
    graph = {}
    for name, path in files.items():
        tree = ast.parse(path.read_text(), filename=str(path))
        targets = imported(tree, name, path.name == "__init__.py")
        graph[name] = {t for t in targets if t in files and t != name}
    return graph


def all_imports(package: Path) -> dict[str, list[str]]:
    """``{module: every module name it imports}``, inside the package or not."""
    root = package.parent
    return {
        module_name(p, root): imported(
            ast.parse(p.read_text()), module_name(p, root), p.name == "__init__.py"
        )
        for p in sorted(package.rglob("*.py"))
    }


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One circle of the graph, as the modules along it (first = last), or ``None``."""
    state: dict[str, str] = {}
    for start in graph:
        if start in state:
            continue
        state[start] = "open"
        stack = [(start, iter(sorted(graph[start])))]
        path = [start]
        while stack:
            node, children = stack[-1]
            child = next(children, None)
            if child is None:
                state[node] = "done"
                stack.pop()
                path.pop()
            elif state.get(child) == "open":
                return path[path.index(child) :] + [child]
            elif child not in state:
                state[child] = "open"
                stack.append((child, iter(sorted(graph[child]))))
                path.append(child)
    return None


def test_find_cycle_finds_a_type_only_circle(tmp_path):
    """The walk sees an import under ``if TYPE_CHECKING`` (the circle models/ had)."""
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from pkg.b import B\n")
    (pkg / "b.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg.c import C\n"
    )
    (pkg / "c.py").write_text("def f():\n    from pkg import a\n")
    cycle = find_cycle(import_graph(pkg))
    assert cycle is not None and set(cycle) == {"pkg.a", "pkg.b", "pkg.c"}
    (pkg / "c.py").write_text("X = 1\n")
    assert find_cycle(import_graph(pkg)) is None


def test_models_has_no_import_circle():
    graph = import_graph(MODELS)
    assert "models.declaration" in graph and "models.cpds.mixture" in graph
    cycle = find_cycle(graph)
    assert cycle is None, f"models/ imports in a circle: {' -> '.join(cycle)}"


@pytest.mark.parametrize(
    "leaf", ["models.dtype", "models.sites", "models.features", "models.gaussian"]
)
def test_the_leaves_import_nothing_of_models_but_the_dtype(leaf):
    assert import_graph(MODELS)[leaf] <= {"models.dtype"}


@pytest.mark.parametrize("above", ABOVE)
def test_models_imports_nothing_above_it(above):
    wrong = {
        module: sorted(t for t in targets if t == above or t.startswith(f"{above}."))
        for module, targets in all_imports(MODELS).items()
    }
    wrong = {m: t for m, t in wrong.items() if t}
    assert not wrong, f"models/ imports from {above}/: {wrong}"


def test_no_room_in_models_is_above_600_lines():
    long = {
        str(p.relative_to(ROOT)): n
        for p in MODELS.rglob("*.py")
        if (n := len(p.read_text().splitlines())) > MAX_LINES
    }
    assert not long, f"modules above {MAX_LINES} lines: {long}"
