"""One evidence convention for every container; states that save; declarations that say why."""

import warnings

import numpy as np
import pytest
import torch
from effect_networks.inference import predict
from effect_networks.models import (
    Continuous,
    Discrete,
    EffectNetwork,
    Evidence,
    Parameter,
    Partial,
    load,
    random_params,
    save,
)
from effect_networks.models.evidence import MAX_MAGNITUDE
from hypothesis import given, settings
from hypothesis import strategies as st

NET = EffectNetwork((Discrete("level", (1, 2, 3)), Discrete("mood", ("calm", "wild"))), ("a", "b"))


@pytest.mark.parametrize(
    "value",
    [
        [1],
        (1,),
        1,
        np.array([1]),
        np.array([1], dtype=np.int32),
        torch.tensor([1]),
        torch.tensor([1], dtype=torch.int16),
        np.int64(1),
        torch.tensor(1),
        [np.int64(1)],
    ],
)
def test_every_container_means_the_label(value):
    # state 1 (index 0), whatever holds it
    assert NET.encode({"initial.level": value})["initial.level"].tolist() == [0]


def test_labels_for_every_site_kind():
    enc = NET.encode(
        {
            "initial.mood": np.array(["wild", "calm", "wild"]),
            "action": ["b", "a", "b"],
            "end.level": torch.tensor([3, 1, 2]),
        }
    )
    assert enc["initial.mood"].tolist() == [1, 0, 1]
    assert enc["action"].tolist() == [1, 0, 1]
    assert enc["end.level"].tolist() == [2, 0, 1]
    with pytest.raises(
        ValueError, match=r"value 0 is not one of its states \['a', 'b'\].*encode_indices"
    ):
        NET.encode({"action": torch.tensor([0])})


@pytest.mark.parametrize("gap", [None, float("nan"), "pandas NA"])
def test_a_missing_label_in_query_evidence_is_named_as_missing(gap):
    if gap == "pandas NA":
        gap = pytest.importorskip("pandas").NA
    values = np.array(["calm", gap], dtype=object)
    with pytest.raises(ValueError, match=r"site 'initial.mood'.*\(row 1\) \(a missing value"):
        NET.encode({"initial.mood": values})
    # None as a declared state is a label, not a gap
    with_none = EffectNetwork((Discrete("lid", (None, "on")),), ("a", "b"))
    assert with_none.encode({"initial.lid": [None, "on"]})["initial.lid"].tolist() == [0, 1]


def test_indices_only_through_the_named_path():
    enc = NET.encode_indices({"initial.level": torch.tensor([1]), "action": np.array([1])})
    assert isinstance(enc, Evidence)
    assert enc["initial.level"].tolist() == [1] and enc["action"].tolist() == [1]
    assert NET.decode("initial.level", enc["initial.level"]) == [2]
    with pytest.raises(ValueError, match="state indices must be integers"):
        NET.encode_indices({"action": ["a"]})
    # encoded evidence passes through every query unchanged, and merges with labels
    merged = enc | {"initial.mood": ["calm"]}
    assert merged["initial.level"].tolist() == [1] and merged["initial.mood"].tolist() == [0]
    params = random_params(NET, 0)
    by_index = predict(NET, params, merged).discrete["level"]
    by_label = predict(
        NET, params, {"initial.level": [2], "action": ["b"], "initial.mood": ["calm"]}
    ).discrete["level"]
    torch.testing.assert_close(by_index, by_label)
    with pytest.raises(ValueError, match="rows disagree"):
        enc | {"initial.mood": ["calm", "wild"]}


def test_states_are_normalised_and_checked():
    d = Discrete("x", tuple(np.unique(np.array([3, 1, 2]))))
    assert d.states == (1, 2, 3) and all(type(s) is int for s in d.states)
    assert Discrete("b", (np.bool_(False), np.bool_(True))).states == (False, True)
    with pytest.raises(ValueError, match="is a tuple; states must be str, int, float, bool"):
        Discrete("pair", (("a", 1), ("b", 2)))
    with pytest.raises(ValueError, match="not a finite number"):
        Discrete("x", (1.0, float("nan")))
    with pytest.raises(ValueError, match="repeated states.*1, 1.0 and True"):
        Discrete("x", (1, True))
    with pytest.raises(ValueError, match="sequence of labels"):
        Discrete("x", "ab")


def test_parameter_takes_numpy_numbers():
    p = Parameter("f", np.float32(0.0), np.float64(2.0), np.int64(5), "a", "pos")
    assert p.low == (0.0,) and p.bins == (5,) and type(p.bins[0]) is int
    q = Parameter(
        "g", np.array([0.0, 1.0]), torch.tensor([1.0, 2.0]), np.array([2, 3]), ["a"], "pos"
    )
    assert q.n_clusters == 6
    with pytest.raises(ValueError, match="bins must be a number or a sequence of positive ints"):
        Parameter("f", 0.0, 1.0, 2.5, "a", "pos")
    with pytest.raises(ValueError, match="low and high must be finite"):
        Parameter("f", 0.0, float("inf"), 2, "a", "pos")


labels = st.one_of(
    st.integers(-5, 1000),
    st.text(min_size=1, max_size=4),
    st.floats(allow_nan=False, allow_infinity=False, width=32),
)


@st.composite
def networks(draw):
    features = []
    for i in range(draw(st.integers(1, 3))):
        if draw(st.booleans()):
            states = draw(
                st.lists(labels, min_size=2, max_size=4, unique_by=lambda s: (type(s) is str, s))
            )
            if len(set(states)) != len(states):  # 1 == 1.0: not two states
                states = [f"s{j}" for j in range(len(states))]
            as_numpy = draw(st.booleans()) and all(isinstance(s, int) for s in states)
            features.append(Discrete(f"d{i}", np.array(states) if as_numpy else tuple(states)))
        else:
            features.append(Continuous(f"c{i}", draw(st.integers(1, 2))))
    actions = tuple(f"act{j}" for j in range(draw(st.integers(1, 3))))
    continuous = [f for f in features if isinstance(f, Continuous)]
    parameters = ()
    if continuous and draw(st.booleans()):
        parameters = (
            Parameter(
                "p", 0.0, 1.0, np.int64(draw(st.integers(1, 3))), actions[:1], continuous[0].name
            ),
        )
    return EffectNetwork(tuple(features), actions, parameters)


@settings(max_examples=25, deadline=None)
@given(net=networks(), seed=st.integers(0, 100))
def test_save_load_round_trips_any_network(tmp_path_factory, net, seed):
    params = random_params(net, seed)
    path = tmp_path_factory.mktemp("nets") / "net.pt"
    net2, params2 = load(save(path, net, params))
    assert net2 == net
    for f, g in zip(net.features, net2.features, strict=True):
        if isinstance(f, Discrete):
            assert [type(s) for s in f.states] == [type(s) for s in g.states]
    for site, cpd in params.cpds.items():
        for name, value in vars(cpd).items():
            assert torch.equal(value, getattr(params2[site], name))


MIXED = EffectNetwork(
    (Discrete("level", (1, 2, 3)), Continuous("pos", 2)),
    ("a", "b"),
    (Parameter("force", 0.0, 1.0, 2, ("b",), "pos"),),
)


@pytest.mark.parametrize(
    ("site", "value"),
    [
        ("initial.pos", 5j),
        ("initial.pos", [[5j, 1.0]]),
        ("initial.pos", np.array([[1.0, 2 + 5j]])),
        ("end.pos", torch.tensor([[0.0, 5j]])),
        ("end.pos", Partial(np.array([[1.0 + 0j, 0.0]]), observed=[True, False])),
        ("param.force", [[5j]]),
        ("initial.level", [1 + 0j]),  # equal to the state 1, but not a label
        ("initial.level", np.array([2 + 0j])),
        ("initial.level", torch.tensor([3 + 0j])),
    ],
)
def test_complex_evidence_is_refused_by_name(site, value):
    """A complex number is refused, naming the site; none is read as its real part."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "discards the imaginary part" on the way
        with pytest.raises(ValueError, match=rf"site '{site}': complex numbers"):
            MIXED.encode({site: value})


@settings(max_examples=40, deadline=None)
@given(
    site=st.sampled_from(["initial.pos", "end.pos", "param.force"]),
    magnitude=st.floats(1.0, 300.0).map(lambda e: 10.0**e),
    sign=st.sampled_from([1.0, -1.0]),
)
def test_one_magnitude_rule_for_every_continuous_site(site, magnitude, sign):
    """Values up to +-MAX_MAGNITUDE are evidence; beyond it, a ValueError names the site:
    the limit training has, at the boundary queries read too."""
    dim = 1 if site == "param.force" else 2
    value = np.zeros((3, dim))
    value[1, -1] = sign * magnitude
    if magnitude <= MAX_MAGNITUDE:
        assert MIXED.encode({site: value})[site][1, -1] == sign * magnitude
    else:
        with pytest.raises(ValueError, match=rf"site '{site}': row 1 .* beyond \+-1e\+150"):
            MIXED.encode({site: value})
