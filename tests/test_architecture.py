"""The floor plan, read from the code: one installed package, imports that point down and
never close a circle (function-local imports included), rooms of at most 600 lines, and
tests that import the package by its installed name, never one another."""

from __future__ import annotations

import ast
import builtins
import importlib
import tomllib
from pathlib import Path

import pytest

import effect_networks

ROOT = Path(__file__).resolve().parents[1]
TOP = "effect_networks"
#: The installed subpackages and the folders that hold them.
FOLDERS = {
    "models": "models",
    "sim2d": "sim2d",
    "inference": "inference",
    "experiments": "experiments",
}
#: What each subpackage may import of the others (its own modules always).
MAY_IMPORT = {
    "sim2d": set(),
    "models": set(),
    "inference": {"models"},
    "experiments": {"models", "inference", "sim2d"},
}
#: Within inference, a floor imports only the floors listed (and models).
INFERENCE_FLOORS = {
    "exact": set(),
    "fitting": {"exact"},
    "queries": {"exact"},
    "sequences": {"exact", "queries"},
}
LARGEST_ROOM = 600


def library_modules(root: Path = ROOT) -> dict[str, Path]:
    """Every module of the installed package, by its dotted name, and its file."""
    found = {TOP: root / TOP / "__init__.py"}
    for sub, folder in FOLDERS.items():
        for path in sorted((root / folder).rglob("*.py")):
            parts = list(path.relative_to(root / folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            found[".".join([TOP, sub, *parts])] = path
    return found


def imported_names(tree: ast.AST, name: str, is_package: bool) -> set[str]:
    """Every module name an import in ``tree`` reaches for, at any depth (inside functions,
    classes and ``if TYPE_CHECKING`` blocks too), relative imports resolved."""
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".") if is_package else name.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            out.add(module)
            out |= {f"{module}.{alias.name}" for alias in node.names}
    return out


def import_graph(modules: dict[str, Path]) -> dict[str, set[str]]:
    """Module -> the project's modules it imports (a name resolved to its longest module)."""
    graph = {}
    for name, path in modules.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        targets = set()
        for imported in imported_names(tree, name, path.name == "__init__.py"):
            while imported and imported not in modules:
                imported = imported.rpartition(".")[0]
            if imported and imported != name:
                targets.add(imported)
        graph[name] = targets
    return graph


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import circles: strongly connected components of more than one module, less
    those made only by a package importing its own submodules (its re-exports)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan's algorithm
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            inner = [m for m in component if not any(o.startswith(m + ".") for o in component)]
            if len(inner) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def subpackage(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else None


def inference_floor(module: str, modules: dict[str, Path]) -> str | None:
    """The inference floor a module belongs to (``exact``, ``fitting``, ...), or None."""
    parts = module.split(".")
    if len(parts) > 3 and parts[1] == "inference":
        return parts[2]
    if len(parts) == 3 and parts[1] == "inference" and modules[module].name == "__init__.py":
        return parts[2]
    return None


# -- the checker, on a made-up tree: it finds what it must ----------------------------------


def fake_tree(tmp_path: Path, files: dict[str, str]) -> dict[str, Path]:
    for relative, text in {"effect_networks/__init__.py": "", **files}.items():
        path = tmp_path / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    for folder in FOLDERS.values():
        (tmp_path / folder).mkdir(exist_ok=True)
    return library_modules(tmp_path)


def test_a_circle_closed_by_a_function_local_import_is_found(tmp_path):
    modules = fake_tree(
        tmp_path,
        {
            "inference/__init__.py": "",
            "inference/a.py": "from effect_networks.inference.b import g\n",
            "inference/b.py": "def g():\n    from effect_networks.inference import a\n",
            "inference/c.py": "from . import a\n",
        },
    )
    graph = import_graph(modules)
    assert graph["effect_networks.inference.c"] == {
        "effect_networks.inference",
        "effect_networks.inference.a",
    }
    assert circles(graph) == [["effect_networks.inference.a", "effect_networks.inference.b"]]


def test_a_package_reexporting_its_submodules_is_not_a_circle(tmp_path):
    modules = fake_tree(
        tmp_path,
        {
            "models/__init__.py": "from effect_networks.models.x import X\n",
            "models/x.py": "from effect_networks.models import y\nX = 1\n",
            "models/y.py": "Y = 2\n",
        },
    )
    assert circles(import_graph(modules)) == []
    (tmp_path / "models/y.py").write_text("def f():\n    from effect_networks.models import x\n")
    assert circles(import_graph(modules)) == [
        ["effect_networks.models", "effect_networks.models.x", "effect_networks.models.y"]
    ]


# -- the project ---------------------------------------------------------------------------

MODULES = library_modules()
GRAPH = import_graph(MODULES)


def test_the_walk_found_the_package():
    assert len(MODULES) > 100
    assert {f"{TOP}.{sub}" for sub in FOLDERS} <= set(MODULES)


def test_no_import_circle_anywhere():
    assert circles(GRAPH) == []


def test_imports_point_down():
    upward = sorted(
        f"{module} -> {target}"
        for module, targets in GRAPH.items()
        if (home := subpackage(module)) is not None
        for target in targets
        if (there := subpackage(target)) not in (home, None) and there not in MAY_IMPORT[home]
    )
    assert upward == []


def test_no_subpackage_imports_a_name_from_the_package_face():
    """The face loads its names on first use; a subpackage taking one from it would load
    them all (a subpackage, ``from effect_networks import models``, is fine)."""
    offenders = []
    for module, path in MODULES.items():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.module == TOP and not node.level:
                offenders += [f"{module}: {a.name}" for a in node.names if a.name not in FOLDERS]
    assert offenders == []


def test_inference_floors():
    """The exact sums sit below fitting and the questions, which never reach into each
    other; the sequence questions sit above the one-step ones."""
    present = {f for m in MODULES if (f := inference_floor(m, MODULES)) is not None}
    wrong = sorted(
        f"{module} -> {target}"
        for module, targets in GRAPH.items()
        if (floor := inference_floor(module, MODULES)) in INFERENCE_FLOORS
        for target in targets
        if (other := inference_floor(target, MODULES)) is not None
        and other != floor
        and other in INFERENCE_FLOORS
        and other not in INFERENCE_FLOORS[floor]
    )
    assert present >= {"fitting", "queries"}
    assert wrong == []


#: The leaves of models/, which every other room of it reads: they import nothing of the
#: project but the dtype.
MODELS_LEAVES = ("dtype", "sites", "features", "gaussian")


@pytest.mark.parametrize("leaf", MODELS_LEAVES)
def test_the_leaves_of_models_import_nothing_of_it_but_the_dtype(leaf):
    name = f"{TOP}.models.{leaf}"
    assert name in GRAPH
    assert GRAPH[name] <= {f"{TOP}.models.dtype"}, GRAPH[name]


@pytest.mark.parametrize("module", sorted(MODULES))
def test_every_room_is_at_most_600_lines(module):
    assert len(MODULES[module].read_text(encoding="utf-8").splitlines()) <= LARGEST_ROOM


def test_no_module_is_named_after_a_function_or_class_it_defines():
    """``inference.transitions`` the function and a module of that name would confuse every
    reader: a module says what it holds (``transition_tables``), its functions what they do."""
    clashes = []
    for module, path in MODULES.items():
        if path.name == "__init__.py":
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"))
        defined = {n.name for n in tree.body if isinstance(n, ast.FunctionDef | ast.ClassDef)}
        if module.rsplit(".", 1)[1] in defined:
            clashes.append(module)
    assert clashes == []


def python_files() -> list[Path]:
    """Every Python file of the repository: the library, tests, examples, benchmarks, docs."""
    skip = {".venv", "build", "results", "data", ".git", "_build"}
    return sorted(
        p
        for p in ROOT.rglob("*.py")
        if not skip & set(p.relative_to(ROOT).parts) and not p.name.startswith(".")
    )


def test_every_import_names_the_installed_package():
    """``from effect_networks.models import ...``, never the bare folder names, which a
    user's own ``models/`` package would shadow."""
    bare = []
    for path in python_files():
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        for name in imported_names(tree, "", False):
            if name.split(".")[0] in FOLDERS:
                bare.append(f"{path.relative_to(ROOT)}: {name}")
    assert bare == []


def test_no_test_module_imports_another():
    """Shared networks and builders live in helper modules, not in other tests."""
    offenders = []
    for path in sorted((ROOT / "tests").rglob("test_*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        for name in imported_names(tree, "", False):
            if name.startswith("tests.") and any(
                part.startswith("test_") for part in name.split(".")[1:]
            ):
                offenders.append(f"{path.relative_to(ROOT)}: {name}")
    assert sorted(set(offenders)) == []


def test_pyproject_lists_every_package_and_maps_the_folders():
    tool = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    packages = {m for m, p in MODULES.items() if p.name == "__init__.py"}
    assert set(tool["packages"]) == packages
    assert tool["package-dir"] == {f"{TOP}.{sub}": folder for sub, folder in FOLDERS.items()}


def test_the_face_gives_every_name_of_models_and_inference():
    models = importlib.import_module(f"{TOP}.models")
    inference = importlib.import_module(f"{TOP}.inference")
    for face in (models, inference):
        for name in face.__all__:
            assert getattr(effect_networks, name) is getattr(face, name), name
    assert set(effect_networks.__all__) == (
        set(models.__all__) | set(inference.__all__) | {"__version__"}
    ) - {"compile"}
    assert effect_networks.compile is inference.compile  # on the face, not in __all__
    assert "compile" not in inference.__all__ and "compile" in inference.NOT_STARRED
    assert isinstance(effect_networks.__version__, str) and effect_networks.__version__
    with pytest.raises(AttributeError, match="no attribute 'fitt'"):
        effect_networks.fitt  # noqa: B018


@pytest.mark.parametrize("face", [TOP, f"{TOP}.models", f"{TOP}.inference"])
def test_a_star_import_of_a_face_hides_no_builtin(face):
    namespace: dict = {}
    exec(f"from {face} import *", namespace)  # noqa: S102
    assert not set(namespace) & set(dir(builtins)) - {"__builtins__"}
    assert "EffectNetwork" in namespace or "fit" in namespace


def test_help_names_the_version_and_the_documentation():
    text = effect_networks.__doc__
    assert f"effect-networks {effect_networks.__version__}" in text
    assert "README.md" in text and "docs/guide.md" in text
