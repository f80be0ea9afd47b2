"""Every Python snippet in README.md and then in its guide (docs/guide.md, which continues
the quick start) runs, in order, and says what its comments say."""

import math
import os
import re
import warnings
from pathlib import Path

import pytest
import torch

README = Path(__file__).resolve().parents[1] / "README.md"
GUIDE = README.parent / "docs" / "guide.md"


def snippets() -> list[str]:
    text = README.read_text() + "\n" + GUIDE.read_text()
    blocks = re.findall(r"^( *)```python\n(.*?)^\1```", text, re.S | re.M)
    out = []
    for indent, body in blocks:
        lines = [
            line[len(indent) :] if line.startswith(indent) else line for line in body.splitlines()
        ]
        out.append("\n".join(lines))
    return out


def test_readme_has_snippets():
    assert len(snippets()) >= 2


@pytest.mark.timeout(600)
def test_readme_snippets_run(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the snippet saves net.pt
    namespace: dict = {}
    with torch.random.fork_rng():
        torch.manual_seed(0)
        for code in snippets():
            exec(compile(code, str(README), "exec"), namespace)  # noqa: S102
    assert os.path.exists("net.pt")
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
    no_parameter, _, clusters = namespace["rms"].values()
    assert clusters < no_parameter and namespace["same"]
    assert os.path.exists("tap/tap_and_remove.png")
    assert os.path.getsize("pictures.png") > 0  # the guide's plots


def assert_loss_is_exact(namespace):
    """The README's ``TraceEnum_ELBO`` idiom is -log p(evidence), against the model summed
    by enumeration, also where a continuous end site is left out of the evidence."""
    from pyro.infer import TraceEnum_ELBO

    from inference.queries.enumeration import enumerate_model

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
