"""The documentation site's sources: every Markdown page of docs/ and every tutorial script
(a page of its own, executed by the build) is reached from the index's table of contents
(no orphan page), and (slow) the site builds strictly, as ``bin/build-docs`` builds it,
every tutorial rendered with its outputs and figures."""

import json
import re
import runpy
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
SKIP = {"_build", "_generated", "api"}  # build output and the generated API pages


def pages(root: Path = DOCS) -> set[str]:
    """Every Markdown page and tutorial script under ``root``, as a toctree names it
    (relative, no suffix)."""
    return {
        path.relative_to(root).with_suffix("").as_posix()
        for path in [*root.rglob("*.md"), *(root / "tutorials").glob("*.py")]
        if not SKIP & set(path.relative_to(root).parts)
    }


def tutorials() -> list[Path]:
    return sorted((DOCS / "tutorials").glob("*.py"))


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


def test_every_tutorial_is_a_page_of_percent_cells():
    entries = reached()
    assert len(tutorials()) >= 5
    for script in tutorials():
        name = script.relative_to(DOCS).with_suffix("").as_posix()
        assert name in entries, f"{script.name} is in no toctree"
        assert not script.with_suffix(".md").exists(), f"{script.name} and its .md: one page"
        text = script.read_text()
        # a title cell, then code and Markdown cells as jupytext's percent format has them
        assert text.startswith("# %% [markdown]\n# # "), script.name
        assert text.count("\n# %%\n") >= 2 and text.count("# %% [markdown]") >= 2, script.name
        assert "EFFECT_NETWORKS_TUTORIALS" in text, f"{script.name} reads no tiny scale"


@pytest.mark.parametrize("script", tutorials(), ids=lambda p: p.stem)
def test_every_tutorial_runs_at_a_tiny_scale_and_draws(script, tmp_path, monkeypatch):
    """As the site's build runs it: at the tiny scale, in a folder of its own; each figure
    it leaves open (a script's ``plt.show()`` does not close it under Agg) renders."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.close("all")
    monkeypatch.setenv("EFFECT_NETWORKS_TUTORIALS", "tiny")
    monkeypatch.setattr(sys, "argv", [str(script)])
    monkeypatch.chdir(tmp_path)
    runpy.run_path(str(script), run_name="__main__")
    figures = [plt.figure(n) for n in plt.get_fignums()]
    assert figures, f"{script.name} drew no figure"
    for i, figure in enumerate(figures):
        figure.savefig(tmp_path / f"{i}.png")
        assert any(ax.has_data() or ax.patches or ax.texts for ax in figure.axes)
        assert (tmp_path / f"{i}.png").stat().st_size > 5_000
    plt.close("all")


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
    # one page per function and class of the faces, listed on the reference's index
    api = out / "api"
    fit = (api / "function" / "effect_networks.inference.fit.html").read_text()
    assert 'id="effect_networks.inference.fit"' in fit
    plan = (api / "class" / "effect_networks.inference.Plan.html").read_text()
    assert 'id="effect_networks.inference.Plan"' in plan
    index = (api / "index.html").read_text()
    assert 'href="function/effect_networks.inference.infer_action.html' in index
    assert index.index("Declaring a network") < index.index("Result types")
    # the modules behind the faces are out of the search (their text and their objects),
    # the guides and the reference's pages in it
    search = (out / "searchindex.js").read_text()
    frozen = json.loads(search[search.index("(") + 1 : search.rindex(")")])
    titles = dict(zip(frozen["docnames"], frozen["titles"], strict=True))
    assert titles["planning"] and titles["api/function/effect_networks.inference.plan"]
    assert titles["api/effect_networks.inference.sequences.planner"] == ""
    assert "effect_networks.inference.sequences.planner" not in frozen["objects"]
    assert "plan" in {entry[4] for entry in frozen["objects"]["effect_networks.inference"]}
    # formulas render offline: MathJax is served from the site itself
    formulas = (out / "structure.html").read_text()
    assert re.search(r'<script [^>]*src="_static/mathjax/tex-chtml\.js"', formulas)
    assert "cdn.jsdelivr" not in formulas
    assert (out / "_static" / "mathjax" / "tex-chtml.js").stat().st_size > 100_000
    for script in tutorials():
        page = (out / "tutorials" / script.with_suffix(".html").name).read_text()
        # executed: each tutorial's page holds its cells' outputs and at least one figure
        assert "cell_output" in page, script.name
        images = re.findall(r'<img [^>]*src="\.\./_images/([^"]+\.png)"', page)
        assert images, f"{script.name} rendered no figure"
        assert all((out / "_images" / image).stat().st_size > 5_000 for image in images)


def test_the_compiled_page_names_every_method():
    from effect_networks.inference.compiled import CompiledQueries

    methods = {n for n in vars(CompiledQueries) if not n.startswith("_")}
    assert len(methods) >= 9, methods
    text = (DOCS / "compiled.md").read_text()
    missing = {n for n in methods if f"`{n}`" not in text}
    assert not missing, f"docs/compiled.md does not name {sorted(missing)}"


#: A measured figure: a decimal, a percentage, or a number with a unit of time, length,
#: memory or speed-up.
MEASURED = re.compile(
    r"\d+\.\d+|\d\s?%|\d\s?(?:cm|mm|ms|us|s|MB|GB|MiB|GiB|x|throws/s)\b", re.IGNORECASE
)
#: The settings docs/results.md names (the table heights a command takes), not measured.
SETTINGS = {"0.75", "0.35"}


def measured_figures(text: str) -> list[str]:
    """The measured-looking figures of a Markdown text, outside its ``{include}`` blocks and
    outside the generated results table (between its markers)."""
    from effect_networks.experiments.harness.summary import BEGIN, END

    text = re.sub(r"^```\{include\}.*?^```", "", text, flags=re.S | re.M)
    text = re.sub(re.escape(BEGIN) + ".*?" + re.escape(END), "", text, flags=re.S)
    return [m.group(0) for m in MEASURED.finditer(text) if m.group(0) not in SETTINGS]


def test_the_results_page_holds_the_generated_table_and_copies_no_figure():
    from effect_networks.experiments.harness.summary import BEGIN, END

    text = (DOCS / "results.md").read_text()
    assert text.count(BEGIN) == 1 and text.count(END) == 1
    assert text.index(BEGIN) < text.index(END)
    assert "Generated by `./reproduce`" in text.split(BEGIN)[1].split(END)[0]
    assert BEGIN not in (ROOT / "README.md").read_text()
    assert measured_figures(text) == [], "docs/results.md: cite the generated block"


def test_the_figure_check_sees_a_copied_figure():
    from effect_networks.experiments.harness.summary import BEGIN, END

    page = f"A.\n\n{BEGIN}\n| 1.36 | 95.7 % |\n{END}\n\nthe 400-cluster fit"
    assert measured_figures(page) == []
    for copied in ("fit in 1.36 s", "re-throws at 0.0078 cm", "95.73 %", "12 ms", "3x faster"):
        assert measured_figures(f"{page} {copied}."), copied


def test_the_benchmarks_page_names_every_script_and_logs_no_measurement():
    text = (DOCS / "benchmarks.md").read_text()
    for script in sorted((ROOT / "benchmarks").glob("*.py")):
        assert f"`{script.name}`" in text, f"docs/benchmarks.md does not name {script.name}"
        takes_out = "add_out(parser)" in script.read_text()
        assert takes_out or script.stem in {"sim", "timing"}, f"{script.name} takes no --out"
    assert not re.findall(r"\b20\d\d-\d\d-\d\d\b", text), "a dated measurement"
    assert not re.findall(r"\b[0-9a-f]{7,40}\b", text), "a measurement keyed by commit"
    assert measured_figures(text) == [], "figures go to the scripts' output (--out)"


def test_the_limits_page_names_each_limit_with_its_value():
    """Each constant docs/limits.md names exists, with the value the page gives it."""
    import importlib

    text = (DOCS / "limits.md").read_text()
    rows = re.findall(r"^\| `([\w.]+)\.([A-Z_]+)` \(([^)]*)\)", text, re.M)
    assert len(rows) >= 6, rows
    for module, name, shown in rows:
        value = getattr(importlib.import_module(f"effect_networks.{module}"), name)
        number = shown.split(" numbers")[0].split(" entries")[0].replace(",", "")
        number = number.replace("10^", "10**").replace("2^", "2**").replace(" MiB", " * 2**20")
        assert eval(number) == value, (module, name, shown, value)  # noqa: S307


def conf_faces() -> tuple[str, ...]:
    """docs/conf.py's FACES (the faces the reference documents one page a name), read from
    its source: importing conf.py would write the reference's pages."""
    import ast

    tree = ast.parse((DOCS / "conf.py").read_text())
    (assign,) = [
        n for n in tree.body if isinstance(n, ast.Assign) and ast.unparse(n.targets[0]) == "FACES"
    ]
    (loop,) = [c for c in ast.walk(assign.value) if isinstance(c, ast.comprehension)]
    names = [ast.literal_eval(element) for element in loop.iter.elts]  # for p in (...)
    assert names, "docs/conf.py's FACES lists no face"
    return tuple(f"effect_networks.{name}" for name in names)


def numpy_sections(docstring: str) -> set[str]:
    """The numpy-style section headings of a docstring (a title over a dashed line)."""
    import inspect

    text = inspect.cleandoc(docstring or "")
    return set(re.findall(r"^(\w[\w ]*)\n-+$", text, re.M))


def test_every_face_function_documents_its_parameters_and_what_it_returns():
    import importlib
    import inspect

    missing = []
    faces = conf_faces()
    assert "effect_networks.inference" in faces and len(faces) >= 5
    for face in faces:
        module = importlib.import_module(face)
        for name in [*module.__all__, *getattr(module, "NOT_STARRED", ())]:
            value = getattr(module, name)
            if inspect.isfunction(value):
                lacks = {"Parameters", "Returns"} - numpy_sections(value.__doc__)
                if lacks:
                    missing.append(f"{face}.{name}: {sorted(lacks)}")
    assert not missing, "\n".join(missing)


def test_the_section_reader_sees_a_missing_returns():
    documented = "Do.\n\n    Parameters\n    ----------\n    x\n        A.\n\n    Returns\n    -------\n    int\n"
    assert numpy_sections(documented) == {"Parameters", "Returns"}
    assert numpy_sections("Do.\n\n    Parameters\n    ----------\n    x\n") == {"Parameters"}
