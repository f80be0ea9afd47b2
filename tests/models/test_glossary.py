"""The glossary in docs/design.md names things that exist."""

import importlib
import re
from pathlib import Path

import pytest

DESIGN = Path(__file__).resolve().parents[2] / "docs" / "design.md"
PACKAGES = ("models", "inference", "sim2d", "experiments")
#: Names the glossary gives for a surface another part of the toolkit provides; each is
#: checked where it exists.
PROVIDED_ELSEWHERE = {"inference.compile"}


def glossary() -> str:
    text = DESIGN.read_text()
    start = text.index("## Glossary")
    return text[start : text.index("\n## ", start + 1)]


def dotted_names() -> list[str]:
    """Every ``package.name...`` the glossary writes in backticks (calls' arguments cut)."""
    names = set()
    for quoted in re.findall(r"`([^`]+)`", glossary()):
        name = quoted.split("(")[0]
        if re.fullmatch(r"[a-z_][\w.]*", name) and name.split(".")[0] in PACKAGES:
            names.add(name)
    return sorted(names)


def resolve(name: str) -> object:
    parts = name.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            value = importlib.import_module(".".join(parts[:cut]))
        except ModuleNotFoundError:
            continue
        for attr in parts[cut:]:
            value = getattr(value, attr)
        return value
    raise ModuleNotFoundError(name)


def test_the_glossary_names_dotted_paths():
    names = dotted_names()
    assert "sim2d.world.run_ball" in names and "models.can_pyramid.n_cans" in names


@pytest.mark.parametrize("name", dotted_names())
def test_a_name_in_the_glossary_exists(name):
    if name in PROVIDED_ELSEWHERE and not hasattr(
        importlib.import_module(name.rsplit(".", 1)[0]), name.rsplit(".", 1)[1]
    ):
        pytest.skip(f"{name} is not part of this tree yet")
    resolve(name)


@pytest.mark.parametrize(
    "word", ["TableParams", "SoftmaxParams", "LinearGaussianParams", "ParameterMixture"]
)
def test_the_glossary_uses_the_current_names(word):
    from effect_networks.models import cpds

    assert f"`{word}`" in glossary() and hasattr(cpds, word)
