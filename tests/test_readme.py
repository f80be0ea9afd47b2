"""README.md's Python snippets run in order, as its reader runs them, and say what their
comments say; each page of the user guide runs alone, in a fresh namespace and folder
(its first snippet imports what it uses, the quick start's objects from
docs/guide_setup.py), and says what its comments say; so does the runnable snippet of
the experiments page."""

import math
import os
import re
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.snippets import DOCS, EXPERIMENTS, GUIDE_PAGES, README, blocks, snippets


def test_the_guide_lists_its_pages():
    linked = re.findall(r"^\d+\. \[[^]]+\]\(([\w/]+)\.md\)", (DOCS / "guide.md").read_text(), re.M)
    assert tuple(DOCS / f"{name}.md" for name in linked) == GUIDE_PAGES


def test_readme_and_the_guide_have_snippets():
    assert len(snippets(README)) >= 3
    for page in ("network", "evidence", "parameters", "fitting", "compiled", "pyro", "interop"):
        assert snippets(DOCS / f"{page}.md"), page


def run_snippets(path: Path) -> dict:
    """Run a Markdown file's snippets in order in one fresh namespace; return it."""
    namespace: dict = {}
    with torch.random.fork_rng():
        torch.manual_seed(0)
        for code in snippets(path):
            exec(compile(code, str(path), "exec"), namespace)  # noqa: S102
    return namespace


@pytest.mark.timeout(300)
def test_readme_snippets_run_in_sequence(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the snippets write nothing into the current folder
    namespace = run_snippets(README)
    assert namespace["path"].exists() and not tmp_path.joinpath("net.pt").exists()
    assert abs(float(namespace["where"][0, 0]) - 0.35) < 0.02
    assert namespace["best"] == ("remove",)
    assert float(namespace["gone"][0]) > 0.99
    assert float(namespace["surprise"][0]) > 0.99
    assert abs(float(namespace["force_needed"][0, 0]) - 10.0) < 0.5
    assert abs(float(namespace["force_to_use"][0, 0]) - 10.0) < 0.5
    assert namespace["p_gone"] > 0.99
    assert namespace["first"] == "remove" and namespace["chance"] > 0.99
    assert namespace["story"] == (("tap", "remove"),)
    route = namespace["route"]
    assert route.route == "dense" and 0.0 <= route.unseen <= 1.0 and route.features == ("visible",)
    curve = namespace["fitted"].log_likelihoods
    assert all(b >= a for a, b in zip(curve, curve[1:], strict=False))
    assert math.isfinite(namespace["score"])
    assert namespace["parents"] == ("initial.visible", "action")
    assert namespace["better"]
    # the guide's shared set-up builds what the quick start builds
    monkeypatch.syspath_prepend(str(DOCS))
    monkeypatch.delitem(sys.modules, "guide_setup", raising=False)
    import guide_setup

    assert guide_setup.net == namespace["net"] and guide_setup.ev == namespace["ev"]
    assert set(guide_setup.data) == set(namespace["data"])
    for site, values in namespace["data"].items():
        same = np.array_equal(guide_setup.data[site], values, equal_nan=values.dtype.kind == "f")
        assert same, site
    # the same rows fitted the same: the same parameter posterior, to the bit
    assert torch.equal(guide_setup.aim.mean, namespace["aim"].mean)


def check_network(ns):
    assert ns["kind"] == "table"
    assert float(ns["still"][0]) > 0.99
    assert float(ns["diagonal"]) == 0.0
    assert ns["plane"].cpd("end.xy").name == "diagonal_gaussian"


def check_evidence(ns):
    assert abs(float(ns["which"].sum()) - 1) < 1e-12
    assert float(ns["rest"].cov[0, 0, 0]) == 0.0
    assert float(ns["rest"].mean[0, 0]) == 0.4 and torch.isfinite(ns["y_given_x"])


def check_parameters(ns):
    assert ns["drift"] < 0.05  # simulate's clusters, fitted back
    curve = ns["em"].log_likelihoods
    assert ns["em"].converged and ns["gain"] > 0
    assert all(b >= a for a, b in zip(curve, curve[1:], strict=False))  # pseudo_count=0


def check_compiled(ns):
    assert ns["gap"] < 1e-12  # the compiled parameter posterior, the traced one's


def check_pyro(ns):
    assert ns["draws"]["param.force"].shape == (100, 5, 1)
    assert set(ns["draws"]) == {site.name for site in ns["net"].sites}
    assert math.isfinite(ns["loss"])
    assert_loss_is_exact(ns)
    # 10 N lies on the edge of cells 3 and 4 (of 8 over 0..20 N): a handler conditions the
    # model itself, where the cluster's posterior is the mixture's responsibility
    assert int(ns["cluster"]) in (3, 4)
    assert '"param.force" -> "end.position"' in ns["graph"].source
    assert len(ns["rows"]["action"]) == 500


def check_pictures(ns):
    assert os.path.getsize("pictures.png") > 0


def check_interop(ns):
    net = ns["net"]
    left = ("initial.position", "cluster.force", "param.force", "end.visible", "end.position")
    assert ns["left_out"] == left and str(list(left)) in ns["refusal"]
    assert len(ns["dropped"]) == 1 and "end.visible" in str(ns["dropped"][0].message)
    assert list(ns["bn"].nodes()) == ["initial.visible", "action"]
    door = ns["door"]
    assert ns["from_bif"].feature("door") == door.feature("door")
    assert ns["from_xml"] == door and ns["from_uai"] is door
    for site, cpd in ns["door_params"].cpds.items():
        assert torch.equal(ns["uai_params"][site].probs, cpd.probs)
        assert torch.allclose(ns["xml_params"][site].probs, cpd.probs, atol=1e-12, rtol=0)
    assert ns["same_net"] == net
    for site, cpd in ns["params"].cpds.items():
        assert torch.equal(ns["same_params"][site].n, cpd.n)
    assert ns["end_visible"]["type"] == "Softmax"
    assert np.array_equal(ns["weight"], ns["params"]["end.visible"].weight.numpy())
    cpd = net.cpd("end.position")
    assert ns["parents"] == sorted({*cpd.parents, *cpd.inputs})
    assert ns["order"].index("param.force") < ns["order"].index("end.position")


#: What each guide page's comments promise, checked after the page runs alone.
CHECKS = {
    "network": check_network,
    "evidence": check_evidence,
    "parameters": check_parameters,
    "compiled": check_compiled,
    "pyro": check_pyro,
    "pictures": check_pictures,
    "interop": check_interop,
}


@pytest.mark.timeout(300)
@pytest.mark.filterwarnings(
    "ignore::effect_networks.inference.OutsideTrainingData"
)  # network.md says so
@pytest.mark.parametrize("page", GUIDE_PAGES, ids=lambda p: p.stem)
def test_each_guide_page_runs_alone(page, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # a page writes only into its reader's folder
    monkeypatch.syspath_prepend(str(DOCS))  # where guide_setup lives
    monkeypatch.delitem(sys.modules, "guide_setup", raising=False)  # a fresh set-up
    namespace = run_snippets(page)
    CHECKS.get(page.stem, lambda ns: None)(namespace)


def test_every_check_names_a_guide_page():
    assert set(CHECKS) <= {page.stem for page in GUIDE_PAGES}


def test_the_experiments_page_snippet_runs(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the snippet saves into tap/
    runnable = blocks(EXPERIMENTS.read_text())
    assert len(runnable) == 1  # the outlines of a new experiment use ```{code-block}
    namespace: dict = {}
    exec(compile(runnable[0], str(EXPERIMENTS), "exec"), namespace)  # noqa: S102
    no_parameter, _, clusters = namespace["rms"].values()
    assert clusters < no_parameter and namespace["same"]
    assert os.path.exists("tap/tap_and_remove.png")


def test_the_front_page_snippet_runs(tmp_path, monkeypatch):
    # the site's front page (docs/index.md): declare, fit, ask, as its comments say
    monkeypatch.chdir(tmp_path)
    page = DOCS / "index.md"
    assert len(snippets(page)) == 1 and "import effect_networks as en" in snippets(page)[0]
    namespace = run_snippets(page)
    assert abs(float(namespace["where"][0, 0]) - 0.35) < 0.02
    assert namespace["best"] == ("remove",)


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
