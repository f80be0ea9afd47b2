"""Declarations, evidence validation, and save/load."""

import importlib
import warnings

import numpy as np
import pytest
import torch
from effect_networks.inference import fit, infer_action
from effect_networks.models import (
    Continuous,
    Discrete,
    EffectNetwork,
    Parameter,
    load,
    load_npz,
    save,
    save_npz,
)
from effect_networks.models.params import FORMAT_VERSION, _checksum

from tests.helpers import random_params

NET = EffectNetwork(
    (
        Discrete("visible", (False, True), kind="object"),
        Continuous("pos", 2),
        Discrete("light", ("dark", "lit"), kind="world"),
    ),
    ("remove", "tap"),
    (Parameter("force", (0.0,), (10.0,), (4,), ("tap",), "pos"),),
)


def test_fig1_structure():
    for f in ("visible", "pos", "light"):
        assert NET.discrete_parents(f)[:2] == ("initial.visible", "initial.light")
        assert "action" in NET.discrete_parents(f)
        assert NET.continuous_parents(f)[0] == "initial.pos"
    assert NET.discrete_parents("pos")[-1] == "cluster.force"
    assert NET.continuous_parents("pos")[-1] == "param.force"
    assert "param.force" not in NET.continuous_parents("visible")


def test_cluster_grid():
    p = Parameter("t", (0.0, -1.0), (2.0, 1.0), (2, 4), ("a",), "x")
    assert p.n_clusters == 8
    x = torch.tensor([[0.1, -0.9], [1.9, 0.9], [5.0, -5.0]])
    assert p.cluster_of(x).tolist() == [0, 7, 4]
    assert p.cluster_centres().shape == (8, 2)
    assert p.cluster_of(p.cluster_centres()).tolist() == list(range(8))


@pytest.mark.parametrize(
    ("evidence", "match"),
    [
        ({"initial.visible": ["maybe"]}, r"initial.visible.*'maybe' is not one of its states"),
        ({"initial.pos": [[0.0, 1.0, 2.0]]}, r"initial.pos.*expected shape \(n, 2\)"),
        ({"initial.pos": [[0.0, float("nan")]]}, r"initial.pos.*NaN or inf in row 0"),
        ({"end.pos": [[0.0, float("inf")]]}, r"end.pos.*NaN or inf"),
        ({"action": ["kick"]}, r"action.*'kick' is not one of its states"),
        ({"initial.colour": [1]}, r"site 'initial.colour', which does not exist"),
        ({"initial.visible": [True, False], "initial.light": ["lit"]}, "rows disagree"),
        ({"initial.visible": torch.tensor([2])}, "value 2 is not one of its states"),
    ],
)
def test_bad_evidence_is_named(evidence, match):
    with pytest.raises(ValueError, match=match):
        NET.encode(evidence)


def test_bad_indices_are_named():
    with pytest.raises(ValueError, match="state index 2 outside 0..1"):
        NET.encode_indices({"initial.visible": torch.tensor([2])})


def test_bad_declarations():
    with pytest.raises(ValueError, match="at least two states"):
        Discrete("x", (1,))
    with pytest.raises(ValueError, match="kind"):
        Continuous("x", 1, kind="thing")
    with pytest.raises(ValueError, match=r"affects \['w'\], which are not features"):
        EffectNetwork((Discrete("v", (0, 1)),), ("a",), (Parameter("f", 0.0, 1.0, 2, ("a",), "w"),))
    with pytest.raises(ValueError, match="unknown actions"):
        EffectNetwork((Continuous("x"),), ("a",), (Parameter("f", 0.0, 1.0, 2, ("b",), "x"),))
    with pytest.raises(ValueError, match="low < high"):
        Parameter("f", 1.0, 0.0, 2, ("a",), "x")
    with pytest.raises(ValueError, match="distinct"):
        EffectNetwork((Continuous("x"), Continuous("x")), ("a",))


def test_query_errors():
    params = random_params(NET, 0)
    with pytest.raises(ValueError, match="evidence names the action"):
        infer_action(NET, params, {"initial.pos": [[0.0, 0.0]], "action": ["tap"]})
    # end.visible is a softmax of initial.pos: an unknown pos has no closed form there
    with pytest.raises(ValueError, match=r"initial state of \['initial.pos'\].*end.visible"):
        infer_action(NET, params, {"initial.visible": [True]})


def test_save_load_round_trip(tmp_path):
    params = random_params(NET, 1)
    path = save(tmp_path / "net.pt", NET, params)
    net2, params2 = load(path)
    assert net2 == NET
    for site, cpd in params.cpds.items():
        for name in cpd.__dataclass_fields__:
            torch.testing.assert_close(getattr(params2[site], name), getattr(cpd, name))


def test_load_refuses_corrupt_and_incompatible_files(tmp_path):
    params = random_params(NET, 1)
    path = save(tmp_path / "net.pt", NET, params)
    bad = tmp_path / "bad.pt"
    bad.write_bytes(path.read_bytes()[:200])
    with pytest.raises(ValueError, match="not a readable effect-network file"):
        load(bad)
    payload = torch.load(path, weights_only=True)
    payload["version"] = 99
    torch.save(payload, tmp_path / "v99.pt")
    with pytest.raises(ValueError, match="format version 99"):
        load(tmp_path / "v99.pt")
    payload["version"] = FORMAT_VERSION
    payload["cpds"]["end.pos"]["bias"] = torch.zeros(3)
    payload["sha256"] = _checksum(payload)  # resealed: the shape check is what refuses it
    torch.save(payload, tmp_path / "shape.pt")
    with pytest.raises(ValueError, match="end.pos"):
        load(tmp_path / "shape.pt")
    torch.save({"hello": 1}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="not an effect-network file"):
        load(tmp_path / "other.pt")


def test_fitted_network_round_trips(tmp_path):
    g = torch.Generator().manual_seed(0)
    n = 100
    data = NET.encode_indices(
        {
            "initial.visible": torch.randint(0, 2, (n,), generator=g),
            "initial.pos": torch.randn(n, 2, generator=g),
            "initial.light": torch.randint(0, 2, (n,), generator=g),
            "action": torch.zeros(n, dtype=torch.long),
            "param.force": torch.full((n, 1), float("nan")),
            "end.visible": torch.randint(0, 2, (n,), generator=g),
            "end.pos": torch.randn(n, 2, generator=g),
            "end.light": torch.randint(0, 2, (n,), generator=g),
        }
    )
    params = fit(NET, data).params
    net2, params2 = load(save(tmp_path / "fitted.pt", NET, params))
    assert net2 == NET and set(params2.cpds) == set(params.cpds)


@pytest.mark.parametrize("actions", ["tap", b"tap", 3])
def test_actions_given_as_one_string_are_refused(actions):
    # iterating "tap" would declare the three actions 't', 'a', 'p'
    with pytest.raises(ValueError, match="actions must be a sequence of action names"):
        EffectNetwork((Continuous("x"),), actions)
    assert EffectNetwork((Continuous("x"),), ("tap",)).actions == ("tap",)


def test_networks_beyond_the_size_limit_are_refused_at_declaration():
    from effect_networks.models.declaration import MAX_CPD_ENTRIES

    # 10**9 cells: the cluster table alone is 2 x 10**9 numbers (it used to be allocated)
    with pytest.raises(ValueError, match=r"site 'cluster.f' would hold 2e\+09 numbers"):
        EffectNetwork((Continuous("x"),), ("a", "b"), (Parameter("f", 0.0, 1.0, 10**9, "a", "x"),))
    # 27 binary features, each end site's table spans 2**27 parent configurations x 2 states
    many = tuple(Discrete(f"f{i}", (False, True)) for i in range(27))
    assert 2**28 > MAX_CPD_ENTRIES
    with pytest.raises(ValueError, match=r"site 'end.f0' .*134217728 configurations"):
        EffectNetwork(many, ("a",))
    # the same features with one parent each are small
    parents = {f"end.f{i}": (f"initial.f{i}", "action") for i in range(27)}
    assert EffectNetwork(many, ("a",), parents=parents).cpd("end.f0").card == (2, 1)


#: Names callers import from models.declaration and models.evidence, and the leaf
#: modules that hold them now.
MOVED = {
    "effect_networks.models.declaration": {
        "ACTION": "effect_networks.models.sites",
        "SiteSpec": "effect_networks.models.sites",
        "cluster_site": "effect_networks.models.sites",
        "end_site": "effect_networks.models.sites",
        "initial_site": "effect_networks.models.sites",
        "param_site": "effect_networks.models.sites",
        "Continuous": "effect_networks.models.features",
        "Discrete": "effect_networks.models.features",
        "Feature": "effect_networks.models.features",
        "FeatureKind": "effect_networks.models.features",
        "LAYOUTS": "effect_networks.models.features",
        "Parameter": "effect_networks.models.features",
        "DTYPE": "effect_networks.models.dtype",
        "MAX_CPD_ENTRIES": "effect_networks.models.structure",
    },
    "effect_networks.models.evidence": {
        "DTYPE": "effect_networks.models.dtype",
        "MAX_MAGNITUDE": "effect_networks.models.dtype",
    },
}


@pytest.mark.parametrize(
    "module, name", [(m, n) for m, names in MOVED.items() for n in names], ids=str
)
def test_names_keep_their_old_import_path_without_a_warning(module, name):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        value = getattr(importlib.import_module(module), name)
    assert value is getattr(importlib.import_module(MOVED[module][name]), name)


def test_action_names_are_normalised_and_saved_like_states(tmp_path):
    """numpy action names become Python ones, so save writes them; composite ones are refused."""
    lift = Parameter("height", 0.0, 1.0, 2, actions=(np.int64(1),), affects="arm")
    net = EffectNetwork(
        (Discrete("lid", (0, 1)), Continuous("arm", 1)),
        tuple(np.arange(2)) + (np.str_("lift"),),
        (lift,),
    )
    assert net.actions == (0, 1, "lift") and [type(a) for a in net.actions] == [int, int, str]
    assert type(net.parameters[0].actions[0]) is int
    params = random_params(net, seed=0)
    for back, _ in (
        load(save(tmp_path / "n.pt", net, params)),
        load_npz(save_npz(tmp_path / "n.npz", net, params)),
    ):
        assert back.identity() == net.identity()
    with pytest.raises(ValueError, match=r"action \('a', 'b'\) is a tuple; action names must be"):
        EffectNetwork((Discrete("lid", (0, 1)),), (("a", "b"), "c"))
    with pytest.raises(ValueError, match="action nan is not a finite number"):
        EffectNetwork((Discrete("lid", (0, 1)),), (float("nan"), "c"))
