"""The inference package's place in the layers: imports point down (experiments ->
inference -> models), so no inference module imports the experiments, except the
deprecated re-export of the scoring that moved there."""

import ast
from pathlib import Path

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
