"""The inference package's own rules, beside the repository-wide architecture test: its
face, no private names across modules, every floor importing at the top, and each
question's traced answer beside its compiled one."""

import ast
from pathlib import Path

import pytest

from effect_networks import inference

PACKAGE = Path(inference.__file__).parent


def test_the_package_face_keeps_its_functions():
    """``inference.fit`` and ``inference.simulate`` are the functions, not modules."""
    assert (
        callable(inference.fit)
        and inference.fit.__module__ == "effect_networks.inference.fitting.maximum_likelihood"
    )
    assert inference.simulate.__module__ == "effect_networks.inference.queries.sampling"


#: Folders whose modules may still import another module's private name: none.
PRIVATE_IMPORTS_ALLOWED: set[Path] = set()


def private_imports(tree: ast.AST) -> list[str]:
    """Every ``from inference... import _name`` in ``tree``, as ``module._name``."""
    return [
        f"{node.module}.{alias.name}"
        for node in ast.walk(tree)
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module
        if node.module.startswith("effect_networks.inference")
        for alias in node.names
        if alias.name.startswith("_")
    ]


def test_private_imports_are_found():
    tree = ast.parse(
        "def f():\n    from effect_networks.inference.fitting.maximum_likelihood import _x, y\n"
    )
    assert private_imports(tree) == ["effect_networks.inference.fitting.maximum_likelihood._x"]
    source = "from effect_networks.models.params import _x\nfrom effect_networks import inference"
    assert private_imports(ast.parse(source)) == []


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


#: The floors of the inference package, the engine's first.
FLOORS = ["exact", "fitting", "queries", "sequences", "design"]


@pytest.mark.parametrize("folder", FLOORS)
def test_every_floor_imports_at_the_top(folder):
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


def test_every_name_of_the_face_resolves_without_a_warning():
    import warnings

    assert len(inference.__all__) == len(set(inference.__all__))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for name in inference.__all__:
            assert getattr(inference, name) is not None, name
    assert (
        callable(inference.compile)
        and inference.compile.__module__ == "effect_networks.inference.compiled"
    )


def test_the_face_exports_what_the_readme_and_the_guide_teach():
    """Every name imported from ``effect_networks`` or ``effect_networks.inference`` in the
    README and the guide's pages, and every ``inference.<name>`` they write that is not a
    module, is on a face (the package's own or the inference face)."""
    import re

    import effect_networks
    from tests.snippets import guide_text

    text = guide_text()
    imported = set()
    lists = re.findall(r"from effect_networks(?:\.inference)? import \(([^)]*)\)", text)
    lists += re.findall(r"from effect_networks(?:\.inference)? import ([\w, ]+)$", text, re.M)
    for names in lists:
        imported |= {n.strip() for n in names.split(",") if n.strip()}
    written = set(re.findall(r"\binference\.(\w+)\b(?!\.)", text))
    submodules = {p.stem for p in PACKAGE.iterdir() if p.suffix == ".py" or p.is_dir()}
    taught = imported | (written - submodules)
    assert {"compile", "fit", "predict", "simulate"} <= taught  # the parse found them
    faces = set(inference.__all__) | set(effect_networks.__all__) | set(effect_networks.SUBPACKAGES)
    faces |= set(inference.NOT_STARRED)
    assert taught <= faces, taught - faces


QUESTIONS = [PACKAGE / "queries", PACKAGE / "sequences"]


def test_no_query_module_imports_another_modules_private_names():
    offenders = []
    for path in sorted(p for folder in QUESTIONS for p in folder.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("inference"):
                private = [a.name for a in node.names if a.name.startswith("_")]
                offenders += [f"{path.name}: {node.module}.{name}" for name in private]
    assert offenders == []


def test_each_question_keeps_its_traced_and_compiled_answers_side_by_side():
    """The action query beside its discrete tables (one folder), the parameter posterior
    beside its compiled query; the package face offers the questions and the compiled surface."""
    from effect_networks.inference.queries import action, action_tables, parameter

    assert "infer_action" in vars(action)
    assert {"CompiledNetwork", "compile_discrete"} <= set(vars(action_tables))
    assert {"infer_parameter", "compile_parameter_query"} <= set(vars(parameter))
    import effect_networks.inference.queries as queries

    assert set(queries.__all__) >= {"infer_action", "infer_parameter", "predict"}
