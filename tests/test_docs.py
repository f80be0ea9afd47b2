"""The documentation site's sources: every Markdown page of docs/ is reached from the
index's table of contents (no orphan page), every tutorial script has its page, and (slow)
the site builds strictly, as ``bin/build-docs`` builds it."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
SKIP = {"_build", "_generated", "api"}  # build output and the generated API pages


def pages(root: Path = DOCS) -> set[str]:
    """Every Markdown page under ``root``, as a toctree names it (relative, no suffix)."""
    return {
        path.relative_to(root).with_suffix("").as_posix()
        for path in root.rglob("*.md")
        if not SKIP & set(path.relative_to(root).parts)
    }


def toctree_entries(page: Path, root: Path = DOCS) -> set[str]:
    """The entries of a MyST page's ``{toctree}`` blocks, relative to ``root``."""
    entries = set()
    for block in re.findall(r"^```\{toctree\}\n(.*?)^```", page.read_text(), re.S | re.M):
        for line in block.splitlines():
            line = line.strip()
            if line and not line.startswith(":"):
                entries.add((page.parent / line).relative_to(root).as_posix())
    return entries


def reached(root: Path = DOCS) -> set[str]:
    """The pages reached from ``root``'s index through toctrees, the index included."""
    seen, todo = set(), ["index"]
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        path = root / f"{name}.md"
        if path.exists():
            todo.extend(toctree_entries(path, root))
    return seen


def test_every_page_is_in_the_table_of_contents():
    entries = reached()
    assert {"guide", "data", "experiments", "results", "benchmarks", "design"} <= pages()
    orphans = pages() - entries
    assert not orphans, f"pages of docs/ in no toctree: {sorted(orphans)}"
    assert "api/index" in entries  # the generated API reference
    missing = {e for e in entries if e not in pages() and e != "api/index"}
    assert not missing, f"toctree entries with no page: {sorted(missing)}"


def test_every_tutorial_script_has_its_page():
    for script in (DOCS / "tutorials").glob("*.py"):
        page = script.with_suffix(".md")
        assert page.exists(), f"{script.name} has no page {page.name}"
        assert re.search(rf"```{{literalinclude}} {re.escape(script.name)}\n", page.read_text())


def test_the_check_sees_an_orphan_and_a_nested_page(tmp_path):
    # the reader the checks above rely on: a nested toctree is followed, an unlisted page
    # is left out
    (tmp_path / "sub").mkdir()
    (tmp_path / "index.md").write_text("# x\n\n```{toctree}\n:maxdepth: 1\n\nsub/a\n```\n")
    (tmp_path / "sub" / "a.md").write_text("# a\n\n```{toctree}\nb\n```\n")
    (tmp_path / "sub" / "b.md").write_text("# b\n")
    (tmp_path / "orphan.md").write_text("# orphan\n")
    assert pages(tmp_path) - reached(tmp_path) == {"orphan"}


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_site_builds_strictly(tmp_path):
    out = tmp_path / "html"
    command = [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-n", "-q", "-b", "html"]
    result = subprocess.run(
        [*command, str(DOCS), str(out)], cwd=ROOT, capture_output=True, text=True
    )
    assert result.returncode == 0, result.stderr[-4000:]
    assert (out / "index.html").exists() and (out / "search.html").exists()
    api = (out / "api" / "inference.html").read_text()
    assert 'id="inference.fit"' in api and 'id="inference.infer_action"' in api
    assert (out / "_images" / "plots.png").stat().st_size > 10_000
