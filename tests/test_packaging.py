"""The project as a user installs it: the built wheel, not the checkout."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_wheel_installs_and_runs_the_readme_snippet():
    # .ci/wheel-check builds the wheel, installs it into a fresh environment and runs
    # README's first snippet from outside the repository; it fails if any package the
    # snippet needs (models.cpds among them) is missing from the wheel.
    env = os.environ | {"PY": sys.executable}
    done = subprocess.run(
        [str(ROOT / ".ci" / "wheel-check")], env=env, capture_output=True, text=True
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert "installs and runs README's snippets" in done.stdout


def project() -> dict:
    import tomllib

    return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]


def requirement_names(requirements) -> set[str]:
    import re

    return {re.split(r"[\[<>=!~; ]", r, maxsplit=1)[0].lower() for r in requirements}


def test_extras_by_purpose_and_dev_installs_them_all():
    extras = project()["optional-dependencies"]
    assert requirement_names(extras["interop"]) == {"pgmpy"}
    assert requirement_names(extras["cluster"]) == {"dask", "ray"}
    dev = requirement_names(extras["dev"])
    assert {"pytest", "hypothesis", "ruff"} <= dev
    assert requirement_names(extras["render"]) == {"graphviz"}
    assert requirement_names(extras["graph"]) == {"networkx"}
    assert "graphviz" not in requirement_names(project()["dependencies"])  # no module needs it
    # the site's build: Sphinx and MyST-NB, the furo theme, MathJax served offline
    docs = requirement_names(extras["docs"])
    assert {"sphinx", "myst-nb", "jupytext", "furo", "sphinx-mathjax-offline"} <= docs
    assert (
        requirement_names(extras["interop"])
        | requirement_names(extras["cluster"])
        | requirement_names(extras["render"])
        | requirement_names(extras["graph"])
        <= dev
    )
    # the setup script installs the dev extra, so the two README commands get everything
    import re

    installs = re.search(r'-e "\.\[([\w,]+)\]"', (ROOT / "bin" / "setup-venv").read_text())
    assert installs and {"dev", "docs"} <= set(installs.group(1).split(","))


def test_a_missing_pgmpy_names_the_interop_extra(monkeypatch):
    from effect_networks.models import pgmpy_files

    monkeypatch.setitem(sys.modules, "pgmpy", None)  # import pgmpy now raises ImportError
    monkeypatch.setitem(sys.modules, "pgmpy.models", None)
    monkeypatch.setitem(sys.modules, "pgmpy.factors.discrete", None)
    monkeypatch.setitem(sys.modules, "pgmpy.readwrite", None)
    with pytest.raises(ImportError, match=r"effect-networks\[interop\]"):
        pgmpy_files.read_bif("nowhere.bif", n=1)
    with pytest.raises(ImportError, match=r"effect-networks\[interop\]"):
        pgmpy_files.write_bif("nowhere.bif", None, None)
    with pytest.raises(ImportError, match=r"effect-networks\[interop\]"):
        pgmpy_files.write_xmlbif("nowhere.xml", None, None)
    with pytest.raises(ImportError, match=r"effect-networks\[interop\]"):
        pgmpy_files.read_xmlbif("nowhere.xml", n=1)
    with pytest.raises(ImportError, match=r"effect-networks\[interop\]"):
        pgmpy_files.read_uai("nowhere.uai", None, n=1)


def test_a_missing_networkx_names_the_graph_extra(monkeypatch):
    from effect_networks.models import Discrete, EffectNetwork, to_networkx

    monkeypatch.setitem(sys.modules, "networkx", None)
    net = EffectNetwork((Discrete("f", (0, 1)),), ("x", "y"))
    with pytest.raises(ImportError, match=r"effect-networks\[graph\]"):
        to_networkx(net)


@pytest.mark.parametrize(("spec", "module"), [("dask-local:1", "distributed"), ("ray", "ray")])
def test_a_missing_cluster_library_names_the_cluster_extra(monkeypatch, spec, module):
    from effect_networks.sim2d.executors import open_executor

    monkeypatch.setitem(sys.modules, module, None)
    with pytest.raises(ImportError, match=r"effect-networks\[cluster\]"):
        with open_executor(spec):
            pass


def test_license_citation_and_changelog():
    assert (ROOT / "LICENSE").read_text().startswith("MIT License")
    assert project()["license"] == {"text": "MIT"}
    citation = (ROOT / "CITATION.cff").read_text()
    assert citation.startswith("cff-version: 1.2.0")
    assert "Learning the Consequences of Actions" in citation  # the paper it implements
    assert "\nversion:" not in citation  # the version lives in pyproject.toml only
    changelog = (ROOT / "CHANGELOG.md").read_text()
    assert f"## {project()['version']}" in changelog
