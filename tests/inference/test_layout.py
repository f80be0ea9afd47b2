"""The inference package's place in the layers: imports point down (experiments ->
inference -> models), so no inference module imports the experiments, except the
deprecated re-export of the scoring that moved there."""

import ast
from pathlib import Path

import pytest

import inference

PACKAGE = Path(inference.__file__).parent
DEPRECATED_REEXPORTS = {PACKAGE / "evaluation.py"}


def imported_packages(tree: ast.Module) -> set[str]:
    """The top-level package of every absolute import in ``tree``."""
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module.split(".")[0])
        elif isinstance(node, ast.Import):
            out |= {a.name.split(".")[0] for a in node.names}
    return out


def test_no_inference_module_imports_experiments():
    modules = sorted(PACKAGE.rglob("*.py"))
    assert len(modules) > 10, modules  # the walk found the package
    offenders = [
        str(p.relative_to(PACKAGE))
        for p in modules
        if p not in DEPRECATED_REEXPORTS
        and "experiments" in imported_packages(ast.parse(p.read_text()))
    ]
    assert offenders == []


def test_the_deprecated_reexport_is_the_only_upward_import():
    (shim,) = DEPRECATED_REEXPORTS
    assert imported_packages(ast.parse(shim.read_text())) == {"experiments", "warnings"}


#: Old flat module -> where it lives now (the old path forwards there with a warning).
MOVED = {
    "em": "inference.fitting.em",
    "pooling": "inference.fitting.pooling",
    "statistics": "inference.fitting.statistics",
    "compiled": "inference.queries.compiled",
    "enumeration": "inference.queries.enumeration",
    "plausibility": "inference.queries.plausibility",
    "surprise": "inference.queries.surprise",
    "planning": "inference.queries.planning",
    "active": "inference.design.active",
    "active_gaussian": "inference.design.active_gaussian",
}


@pytest.mark.parametrize("old", sorted(MOVED))
def test_old_flat_paths_forward_with_a_warning(old):
    import importlib
    import sys

    sys.modules.pop(f"inference.{old}", None)
    with pytest.warns(DeprecationWarning, match=MOVED[old]):
        shim = importlib.import_module(f"inference.{old}")
    new = importlib.import_module(MOVED[old])
    public = [n for n in dir(new) if not n.startswith("_") and not n.startswith("__")]
    assert public, MOVED[old]
    for name in public:
        assert getattr(shim, name) is getattr(new, name)


def test_the_package_face_keeps_its_functions():
    """``inference.fit`` and ``inference.simulate`` are the functions, not modules."""
    assert callable(inference.fit) and inference.fit.__module__ == "inference.fitting.fit"
    assert inference.simulate.__module__ == "inference.queries.simulate"


#: Folders whose modules may still import another module's private name. The queries
#: are being split into one module per question; remove the entry when that is done.
PRIVATE_IMPORTS_ALLOWED = {PACKAGE / "queries"}


def private_imports(tree: ast.AST) -> list[str]:
    """Every ``from inference... import _name`` in ``tree``, as ``module._name``."""
    return [
        f"{node.module}.{alias.name}"
        for node in ast.walk(tree)
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module
        if node.module.split(".")[0] == "inference"
        for alias in node.names
        if alias.name.startswith("_")
    ]


def test_private_imports_are_found():
    tree = ast.parse("def f():\n    from inference.fitting.fit import _x, y\n")
    assert private_imports(tree) == ["inference.fitting.fit._x"]
    assert private_imports(ast.parse("from models.params import _x\nimport inference")) == []


def test_no_inference_module_imports_another_modules_private_name():
    modules = sorted(PACKAGE.rglob("*.py"))
    assert any(p.parent.name == "fitting" for p in modules), modules
    offenders = {
        str(p.relative_to(PACKAGE)): found
        for p in modules
        if not any(folder in p.parents for folder in PRIVATE_IMPORTS_ALLOWED)
        if (found := private_imports(ast.parse(p.read_text())))
    }
    assert offenders == {}


@pytest.mark.parametrize("folder", ["fitting", "design"])
def test_fitting_and_design_import_at_the_top(folder):
    """An import inside a function hides a circle; the shared pieces live below."""
    offenders = []
    for path in sorted((PACKAGE / folder).glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                offenders += [
                    f"{path.name}:{inner.lineno}"
                    for inner in ast.walk(node)
                    if isinstance(inner, ast.Import | ast.ImportFrom)
                ]
    assert offenders == []


@pytest.mark.parametrize("folder", ["fitting", "design"])
def test_fitting_and_design_rooms_stay_small(folder):
    """One concept per module: none above 600 lines."""
    sizes = {p.name: len(p.read_text().splitlines()) for p in (PACKAGE / folder).glob("*.py")}
    assert sizes and max(sizes.values()) <= 600, sizes
