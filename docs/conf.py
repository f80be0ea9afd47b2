"""Sphinx configuration: the site is built from docs/ by ``bin/build-docs``, offline and
strict (a warning or a broken cross-reference fails the build).

The tutorials (docs/tutorials/*.py, percent-format scripts) are pages of their own: MyST-NB
reads each through jupytext, runs it in a Jupyter kernel at a tiny scale (the environment
variable ``EFFECT_NETWORKS_TUTORIALS=tiny``, which every tutorial reads; set it to ``full``
for a reader's scale) and renders its cells with their printed output and figures; a
tutorial that raises fails the build."""

import os
from pathlib import Path

DOCS = Path(__file__).resolve().parent
ROOT = DOCS.parent

project = "effect-networks"
author = "The effect-networks authors"
copyright = "The effect-networks authors"  # noqa: A001

extensions = [
    "myst_nb",  # MyST Markdown pages, and the tutorials executed
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",  # the reference's tables of names (no stub pages: conf.py)
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    # MathJax served from the built site (_static/mathjax), so formulas render offline
    "sphinx-mathjax-offline",
    "sphinx.ext.viewcode",
]

exclude_patterns = ["_build", "conf.py", "guide_setup.py"]  # a module the guide imports
root_doc = "index"

myst_enable_extensions = ["dollarmath"]
myst_heading_anchors = 3

# -- the tutorials: percent-format scripts, executed on every build -------------------
nb_custom_formats = {".py": ["jupytext.reads", {"fmt": "py:percent"}]}
nb_execution_mode = "force"  # never a cached output: the pages show what the code does now
# a cell that raises is a warning with its traceback (the strict build fails on it, and
# --keep-going still reports every tutorial's)
nb_execution_raise_on_error = False
nb_execution_show_tb = True
nb_execution_timeout = 300
nb_merge_streams = True
# a warning a tutorial prints is a defect of the page: the strict build fails on it
nb_output_stderr = "warn"
# the kernel inherits this process's environment: the tutorials' scale (the package is the
# installed effect_networks), and matplotlib's inline backend (not a file-only one set for
# the tests), so that each figure a cell makes is rendered below it
os.environ.setdefault("EFFECT_NETWORKS_TUTORIALS", "tiny")  # "full": as a reader runs them
os.environ.pop("MPLBACKEND", None)
# tqdm.auto, in a kernel without ipywidgets, falls back to the text bar with a warning
os.environ["PYTHONWARNINGS"] = ",".join(
    filter(None, [os.environ.get("PYTHONWARNINGS"), "ignore:IProgress not found"])
)

autodoc_member_order = "bysource"
autodoc_default_options = {"members": True, "show-inheritance": False}
# The signatures would name the classes by the module that defines them, which the
# reference documents under its public face; the numpy docstrings' Parameters sections
# carry the types.
autodoc_typehints = "none"

napoleon_google_docstring = False
napoleon_numpy_docstring = True
napoleon_use_rtype = False
# an Attributes section reads like a Parameters one: its types stay text too
napoleon_custom_sections = [("Attributes", "params_style")]
# types stay text ("(n, 2) float, optional"), not cross-references
napoleon_use_param = False
napoleon_use_keyword = False

# third-party types only; every name of this project's must resolve
nitpick_ignore_regex = [
    (r"py:.*", r"(torch|pyro|numpy|np|matplotlib|pgmpy|pandas|dask|ray|pymunk)(\..*)?"),
    # the standard library's (no intersphinx: the build is offline)
    (r"py:class", r"(collections\.abc|pathlib|typing)\..*"),
]

autosummary_generate = False  # the pages the tables link to are written below

# furo: a sidebar with the table of contents, code blocks and cell outputs that scroll
# sideways instead of being cut (docs/_static/site.css), a light and a dark scheme
html_theme = "furo"
html_title = "effect-networks"
html_static_path = ["_static"]
html_css_files = ["site.css"]
html_theme_options = {"navigation_with_keys": True}


# -- the API reference: one page per module, generated here ---------------------------
TOP = "effect_networks"
PACKAGES = tuple(f"{TOP}.{p}" for p in ("models", "inference", "experiments", "sim2d"))
# the faces whose names README and the guides import; a name is documented once, under
# the first face here that exports it (its defining module's name still resolves: autodoc
# records it as the canonical name)
FACES = tuple(
    f"{TOP}.{p}"
    for p in (
        "models",
        "inference",
        "inference.fitting",
        "inference.queries",
        "inference.sequences",
        "inference.plots",
    )
)
GROUPS = {
    f"{TOP}.models": "declaring a network, its parameters and distributions",
    f"{TOP}.inference": "fitting, exact questions, active exploration, pictures",
    f"{TOP}.experiments": "the paper's experiments as a library",
    f"{TOP}.sim2d": "the simulated can world and the robot's throw",
}
# The libraries without a face: their module pages are their reference, and stay in the
# search. Every other module page (the modules behind the faces) is left out of it.
SEARCHED = (f"{TOP}.experiments", f"{TOP}.sim2d")

#: The reference index, by purpose: (heading, what the group is for, the names of the
#: faces' functions and classes in it). Every function and class a face documents is in
#: exactly one group (the build fails otherwise); result types come last.
REFERENCE = (
    (
        "Declaring a network",
        "Features, actions and parameters; evidence; the network as a Pyro model.",
        "EffectNetwork Discrete Continuous Parameter Evidence Partial effect_model "
        "initial_site end_site param_site cluster_site",
    ),
    (
        "Parameters, kinds and files",
        "Fitted numbers, the conditional distributions' kinds, saving and loading, other formats.",
        "NetworkParams random_params save load CPD TableCPD TableParams LinearGaussianCPD "
        "LinearGaussianParams SoftmaxCPD SoftmaxParams ParameterMixture to_frame from_frame "
        "to_pgmpy from_pgmpy read_bif write_bif read_xmlbif write_xmlbif read_uai write_uai"
        " save_npz load_npz to_networkx PgmpyNetwork DroppedSites",
    ),
    (
        "Fitting",
        "Maximum likelihood, EM over gaps, priors, clusters, structure and scores.",
        "fit fit_em fit_gradient fit_pooled grid_kernel fit_update fit_statistics "
        "params_from_statistics Statistics BDeu K2 NormalInverseWishart select_clusters "
        "learn_structure family_scores log_likelihood aic bic n_parameters cross_validate",
    ),
    (
        "One-step questions",
        "What an action will do, which action did this, with which parameter, and what to "
        "try next.",
        "predict predict_joint infer_action infer_parameter parameter_for_effect "
        "imitation_check simulate compile explore",
    ),
    (
        "Sequences",
        "Transitions between states, plans, chained steps and demonstrations read back.",
        "transitions step_model plan chain link_probabilities explain StateSpace ProjectedSpace "
        "StepModel StepFactor BoxPartition FunctionLink",
    ),
    (
        "Pictures",
        "Matplotlib figures of a network, its tables, clusters, posteriors and plans.",
        "plot_network plot_table plot_clusters plot_action_posterior plot_demonstration "
        "plot_plan site_parents state_labels",
    ),
    (
        "Result types",
        "What the functions above return, and the warnings they give.",
        "Prediction JointPrediction ActionPosterior ParameterPosterior ParameterForEffect "
        "GaussianMixture ImitationCheck CompiledQueries FitResult EMResult ClusterSelection "
        "LogLikelihood CrossValidation Transitions Plan Certificate LinkProbabilities "
        "Explanation ConvergenceWarning OutsideTrainingData RestsOnUnseen",
    ),
)


def _modules() -> list[str]:
    import importlib
    import pkgutil

    names = [TOP]
    for package in PACKAGES:
        module = importlib.import_module(package)
        names.append(package)
        for info in pkgutil.walk_packages(module.__path__, package + "."):
            if not info.name.rsplit(".", 1)[-1].startswith("_"):
                names.append(info.name)
    return sorted(names)


def _public(module) -> dict[str, object]:
    """The names autodoc documents for ``module``: a face's ``__all__``, else what the
    module defines (its helpers too, which other docstrings name)."""
    if module.__name__ in FACES:
        names = [*module.__all__, *getattr(module, "NOT_STARRED", ())]
        return {name: getattr(module, name) for name in names}
    return {
        name: value
        for name, value in vars(module).items()
        if not name.startswith("_") and getattr(value, "__module__", None) == module.__name__
    }


#: id of an object documented under a face -> (the face, its documented name)
HOME: dict[int, tuple[str, str]] = {}


def _object_page(name: str, value) -> str:
    """The page (relative to docs/api) of a face's function or class: one folder per kind,
    so that ``plan`` and ``Plan`` are two files on a case-blind file system too."""
    return f"{'class' if isinstance(value, type) else 'function'}/{name}"


def _write(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if not path.exists() or path.read_text() != text:
        path.write_text(text)  # unchanged pages keep their time: no rebuild


def _heading(text: str, underline: str = "=") -> list[str]:
    return [text, underline * len(text), ""]


def _write_api_pages() -> None:
    import importlib

    modules = _modules()
    for face in FACES:
        for member, value in _public(importlib.import_module(face)).items():
            HOME.setdefault(id(value), (face, f"{face}.{member}"))
    # every function and class of a face: its page, and its group on the index
    objects: dict[str, tuple[str, object]] = {}  # short name -> (documented name, object)
    for face in FACES:
        for member, value in _public(importlib.import_module(face)).items():
            if callable(value) and HOME[id(value)][1] == f"{face}.{member}":
                if member in objects:
                    raise ValueError(f"two faces document a {member}: name its page apart")
                objects[member] = (f"{face}.{member}", value)
    grouped = [name for _, _, names in REFERENCE for name in names.split()]
    ungrouped = set(objects) - set(grouped)
    unknown = [name for name in grouped if name not in objects or grouped.count(name) > 1]
    if ungrouped or unknown:
        raise ValueError(
            f"docs/conf.py REFERENCE: put {sorted(ungrouped)} in a group; "
            f"{sorted(set(unknown))} are in none of the faces, or in two groups"
        )
    pages = {_object_page(full, value): (full, value) for full, value in objects.values()}
    if len({page.lower() for page in pages}) != len(pages):
        raise ValueError("two reference pages differ only in case")

    out = DOCS / "api"
    keep = {out / f"{m}.rst" for m in [*modules, "index", "modules"]} | {
        out / f"{p}.rst" for p in pages
    }
    for stale in set(out.rglob("*.rst")) - keep:
        stale.unlink()  # a module or a name renamed or removed since the last build
    for page, (full, value) in pages.items():
        short = full.rsplit(".", 1)[1]
        directive = "autoclass" if isinstance(value, type) else "autofunction"
        lines = [*_heading(f"``{short}``"), f".. {directive}:: {full}"]
        _write(out / f"{page}.rst", "\n".join(lines) + "\n")

    for name in modules:
        module = importlib.import_module(name)
        lines = []
        if name not in FACES and not name.startswith(SEARCHED) and name != TOP:
            lines += [":nosearch:", ""]  # file-wide metadata: the page is left out of search
        lines += [*_heading(f"``{name}``"), f".. automodule:: {name}"]
        if name in FACES:  # the face: its names, each on its own page, in a table
            names = [*module.__all__, *getattr(module, "NOT_STARRED", ())]
            callables = [n for n in names if callable(getattr(module, n))]
            lines += ["   :no-members:", "", ".. currentmodule:: None", ""]  # full names
            lines += [".. autosummary::", "   :nosignatures:", ""]
            lines += [f"   ~{HOME[id(getattr(module, n))][1]}" for n in callables]
            lines += [""]
            lines += [f".. autodata:: {name}.{n}" for n in names if n not in callables]
        else:
            lines.append("   :ignore-module-all:")
            skip = sorted(
                member
                for member, value in _public(module).items()
                if HOME.get(id(value), (name,))[0] != name and callable(value)
            )
            if skip:
                lines.append(f"   :exclude-members: {', '.join(skip)}")
        _write(out / f"{name}.rst", "\n".join(lines) + "\n")

    index = _heading("API reference")
    index += [
        "One page per function and class that the faces export (``import effect_networks as",
        "en``: ``en.fit``, ``en.plan``, ...), grouped by purpose. Every module has a page of",
        "its own too (:doc:`modules`); the module that defines a name links to its page here.",
        "",
    ]
    for heading, blurb, names in REFERENCE:
        index += [*_heading(heading, "-"), blurb, "", ".. autosummary::", "   :nosignatures:", ""]
        index += [f"   ~{objects[n][0]}" for n in names.split()]
        index += ["", ".. toctree::", "   :hidden:", ""]
        index += [f"   {_object_page(*objects[n])}" for n in names.split()]
        index.append("")
    index += [".. toctree::", "   :hidden:", "", "   modules", ""]
    _write(out / "index.rst", "\n".join(index))

    listing = _heading("Every module")
    listing += [
        "One page per module. The names README and the guides import are documented under",
        "the face that exports them (:mod:`effect_networks.models`,",
        ":mod:`effect_networks.inference` and its subpackages), one page each; the pages of",
        "the modules behind the faces are left out of the site's search.",
        "",
        *_heading(f"``{TOP}``: the package and its face", "-"),
        ".. toctree::",
        "   :maxdepth: 1",
        "",
        f"   {TOP}",
        "",
    ]
    for package in PACKAGES:
        listing += [*_heading(f"``{package}``: {GROUPS[package]}", "-")]
        listing += [".. toctree::", "   :maxdepth: 1", ""]
        listing += [f"   {m}" for m in modules if m == package or m.startswith(package + ".")]
        listing.append("")
    _write(out / "modules.rst", "\n".join(listing))


_write_api_pages()


def _lookup(target: str):
    """The object a dotted name imports to, or None."""
    import importlib

    parts = target.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            value = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        try:
            for part in parts[cut:]:
                value = getattr(value, part)
        except AttributeError:
            return None
        return value
    return None


def _face_name(target: str) -> str | None:
    """``target`` (a defining module's path, or a package's re-export) spelled by the face
    that documents it: ``inference.queries.forward.predict`` ->
    ``effect_networks.inference.predict`` (a docstring may leave out the package's name)."""
    if f"{TOP}.{target.split('.')[0]}" in PACKAGES:
        target = f"{TOP}.{target}"
    parts = target.split(".")
    for cut in range(len(parts), 1, -1):
        value = _lookup(".".join(parts[:cut]))
        if value is not None and id(value) in HOME:
            name = ".".join([HOME[id(value)][1], *parts[cut:]])
            return name if name != target else None
    return None


_PROSE: dict[str, list[str]] = {}


def _keep_prose(app, what, name, obj, options, lines):
    """A constant's ``#:`` comment is prose: napoleon would read a colon in its first line
    as "type: description" and make the words before it a cross-reference. Its lines are
    kept before napoleon runs (priority 400) and put back after it (priority 600)."""
    if what in ("data", "attribute", "property"):
        _PROSE[name] = list(lines)


def _restore_prose(app, what, name, obj, options, lines):
    if what in ("data", "attribute", "property") and name in _PROSE:
        lines[:] = _PROSE.pop(name)


def _foreign_docstring(app, what, name, obj, options, lines):
    """A method that overrides torch's or pyro's without a docstring of its own would show
    theirs (written for their site); it shows none."""
    if what != "method" or getattr(obj, "__doc__", "") is not None:
        return
    owner = _lookup(name.rsplit(".", 1)[0])
    for cls in getattr(owner, "__mro__", ())[1:]:
        method = vars(cls).get(name.rsplit(".", 1)[1])
        if method is not None and getattr(method, "__doc__", None):
            if not cls.__module__.startswith(PACKAGES):
                lines[:] = []
            return


def _short_name(app, env, node, contnode):
    """Resolve a name by the face that documents it, or a short Python name (``fit``, ``EffectNetwork.encode``) that names exactly one
    documented object, as a reference written ``~.name`` would; an ambiguous or unknown
    name stays unresolved, and the strict build fails on it."""
    if node.get("refdomain") != "py" or node.get("refspecific"):
        return None
    domain = env.get_domain("py")
    target = _face_name(node["reftarget"]) or node["reftarget"]
    node["refspecific"] = True
    try:
        return domain.resolve_xref(
            env, node["refdoc"], app.builder, node["reftype"], target, node, contnode
        )
    finally:
        node["refspecific"] = False


def _readme_links(app, docname, source):
    """The guides link README as ``../README.md`` (right on a repository's web page); in the
    site README is the page ``readme``, which includes it."""
    source[0] = source[0].replace("](../README.md", "](readme.md")


def _python_domain_hiding_unsearched_pages():
    """The Python domain, whose objects documented on a page left out of the search
    (``:nosearch:``: the modules behind the faces) are left out of it too: Sphinx's search
    index skips an object of negative priority, while cross-references and objects.inv
    still find it."""
    from sphinx.domains.python import PythonDomain

    class Domain(PythonDomain):
        def get_objects(self):
            for name, shown, kind, docname, anchor, priority in super().get_objects():
                if "nosearch" in self.env.metadata.get(docname, {}):
                    priority = -1
                yield name, shown, kind, docname, anchor, priority

    return Domain


def setup(app):
    app.add_domain(_python_domain_hiding_unsearched_pages(), override=True)
    app.connect("source-read", _readme_links)
    app.connect("missing-reference", _short_name)
    app.connect("autodoc-process-docstring", _keep_prose, priority=400)
    app.connect("autodoc-process-docstring", _restore_prose, priority=600)
    app.connect("autodoc-process-docstring", _foreign_docstring, priority=300)
