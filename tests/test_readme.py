"""Every Python snippet in README.md and then in the user guide's pages, which continue
its quick start, runs in order and says what its comments say; so does the runnable
snippet of the experiments page.

The order is the guide's own (docs/guide.md lists the pages in it): each page's snippets
may use the names that README's and the earlier pages' snippets define."""

import math
import os
import re
import warnings
from pathlib import Path

import pytest
import torch

README = Path(__file__).resolve().parents[1] / "README.md"
DOCS = README.parent / "docs"
#: the user guide's pages, in the order docs/guide.md gives and the snippets run
GUIDE_PAGES = tuple(
    DOCS / f"{name}.md"
    for name in (
        "network",
        "evidence",
        "parameters",
        "fitting",
        "queries",
        "compiled",
        "pyro",
        "interop",
        "pictures",
    )
)
#: a page whose ```python blocks run on their own (its outlines use ```{code-block})
EXPERIMENTS = DOCS / "experiments.md"


def blocks(text: str) -> list[str]:
    """The bodies of the ```python blocks of a Markdown text, in order, de-indented."""
    found = re.findall(r"^( *)```python\n(.*?)^\1```", text, re.S | re.M)
    out = []
    for indent, body in found:
        lines = [
            line[len(indent) :] if line.startswith(indent) else line for line in body.splitlines()
        ]
        out.append("\n".join(lines))
    return out


def snippets() -> list[tuple[Path, str]]:
    """README's snippets, then each guide page's, as (file, code) in running order."""
    return [(path, code) for path in (README, *GUIDE_PAGES) for code in blocks(path.read_text())]


def guide_text() -> str:
    """README and the user guide's pages, as one text (the names they teach)."""
    return "\n".join(path.read_text() for path in (README, *GUIDE_PAGES))


def test_the_guide_lists_its_pages_in_the_running_order():
    linked = re.findall(r"^\d+\. \[[^]]+\]\(([\w/]+)\.md\)", (DOCS / "guide.md").read_text(), re.M)
    assert tuple(DOCS / f"{name}.md" for name in linked) == GUIDE_PAGES


def test_readme_and_the_guide_have_snippets():
    files = [path for path, _ in snippets()]
    assert files.count(README) >= 3
    for page in ("network", "evidence", "parameters", "fitting", "compiled", "pyro", "interop"):
        assert DOCS / f"{page}.md" in files, page


@pytest.mark.timeout(600)
@pytest.mark.filterwarnings(
    "ignore::effect_networks.inference.OutsideTrainingData"
)  # network.md says so
def test_readme_snippets_run(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the snippets write nothing into the current folder
    namespace: dict = {}
    with torch.random.fork_rng():
        torch.manual_seed(0)
        for path, code in snippets():
            exec(compile(code, str(path), "exec"), namespace)  # noqa: S102
    assert namespace["path"].exists() and not tmp_path.joinpath("net.pt").exists()
    assert abs(float(namespace["where"][0, 0]) - 0.35) < 0.02
    assert namespace["best"] == ("remove",)
    assert namespace["kind"] == "table"
    assert float(namespace["still"][0]) > 0.99
    assert float(namespace["diagonal"]) == 0.0
    assert namespace["plane"].cpd("end.xy").name == "diagonal_gaussian"
    assert abs(float(namespace["which"].sum()) - 1) < 1e-12
    assert float(namespace["rest"].cov[0, 0, 0]) == 0.0
    assert float(namespace["rest"].mean[0, 0]) == 0.4 and torch.isfinite(namespace["y_given_x"])
    assert float(namespace["gone"][0]) > 0.99
    assert float(namespace["surprise"][0]) > 0.99
    assert abs(float(namespace["force_needed"][0, 0]) - 10.0) < 0.5
    assert abs(float(namespace["force_to_use"][0, 0]) - 10.0) < 0.5
    assert namespace["p_gone"] > 0.99
    assert namespace["first"] == "remove" and namespace["chance"] > 0.99
    assert namespace["story"] == (("tap", "remove"),)
    curve = namespace["fitted"].log_likelihoods
    assert all(b >= a for a, b in zip(curve, curve[1:], strict=False))
    assert math.isfinite(namespace["score"])
    assert namespace["parents"] == ("initial.visible", "action")
    assert namespace["better"]
    assert namespace["drift"] < 0.05  # simulate's clusters, fitted back
    curve = namespace["em"].log_likelihoods
    assert namespace["em"].converged and namespace["gain"] > 0
    assert all(b >= a for a, b in zip(curve, curve[1:], strict=False))  # pseudo_count=0
    assert namespace["gap"] < 1e-12  # the compiled parameter posterior, the traced one's
    assert namespace["draws"]["param.force"].shape == (100, 5, 1)
    assert set(namespace["draws"]) == {site.name for site in namespace["net"].sites}
    assert math.isfinite(namespace["loss"])
    assert_loss_is_exact(namespace)
    # 10 N lies on the edge of cells 3 and 4 (of 8 over 0..20 N): a handler conditions the
    # model itself, where the cluster's posterior is the mixture's responsibility
    assert int(namespace["cluster"]) in (3, 4)
    assert '"param.force" -> "end.position"' in namespace["graph"].source
    assert len(namespace["rows"]["action"]) == 500
    assert os.path.getsize("pictures.png") > 0  # the guide's plots


def test_the_experiments_page_snippet_runs(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the snippet saves into tap/
    runnable = blocks(EXPERIMENTS.read_text())
    assert len(runnable) == 1  # the outlines of a new experiment use ```{code-block}
    namespace: dict = {}
    exec(compile(runnable[0], str(EXPERIMENTS), "exec"), namespace)  # noqa: S102
    no_parameter, _, clusters = namespace["rms"].values()
    assert clusters < no_parameter and namespace["same"]
    assert os.path.exists("tap/tap_and_remove.png")


def assert_loss_is_exact(namespace):
    """The README's ``TraceEnum_ELBO`` idiom is -log p(evidence), against the model summed
    by enumeration, also where a continuous end site is left out of the evidence."""
    from effect_networks.inference.exact.enumeration import enumerate_model
    from pyro.infer import TraceEnum_ELBO

    net, params, pushed = namespace["net"], namespace["params"], namespace["pushed"]
    given = {"param.force": [[10.0]]}
    bins = net.mixture("force").parameter.n_clusters
    for evidence in (namespace["tap"], net.encode(namespace["ev"] | {"action": ["tap"]})):
        # a handler conditions the model itself, where the cluster stays latent: the
        # evidence given each cluster in turn, summed over the clusters
        exact = float(
            torch.stack(
                [
                    enumerate_model(
                        net, params, evidence | net.encode(given | {"cluster.force": [c]})
                    ).log_evidence[0]
                    for c in range(bins)
                ]
            ).logsumexp(0)
        )
        for _ in range(3):  # an unobserved end.position is integrated out
            with warnings.catch_warnings():  # Pyro's note that end.position is drawn
                warnings.filterwarnings("ignore", "Found vars in model but not guide")
                loss = TraceEnum_ELBO(max_plate_nesting=1).loss(
                    lambda evidence=evidence: pushed(net, params, evidence, collapse=True),
                    lambda: None,
                )
            assert abs(loss + exact) < 1e-9


def test_the_links_of_readme_and_the_guide_lead_to_files():
    # the site's strict build checks the pages' links; README's own (LICENSE, the figure,
    # docs/*.md as GitHub shows them) are checked here, with the guide's
    for path in (README, DOCS / "guide.md", *GUIDE_PAGES, EXPERIMENTS):
        for target in re.findall(r"\]\(([^)\s]+)\)", path.read_text()):
            if re.match(r"[a-z]+:", target) or target.startswith("#"):
                continue  # a web address or an anchor on the page itself
            assert (path.parent / target.split("#")[0]).exists(), f"{path.name}: {target}"
