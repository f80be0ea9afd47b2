"""XMLBIF and UAI files (models.pgmpy_files): drawn discrete networks written and read
back answer as pgmpy answers on the original network to 1e-12; labels come back as the
module says; a hand-written UAI file in the format's own layout reads as its numbers
say; what a file cannot hold, or a file that is not the declaration's, is refused."""

import numpy as np
import pytest
import torch
from effect_networks.inference import predict
from effect_networks.models import (
    Continuous,
    Discrete,
    EffectNetwork,
    random_params,
    read_uai,
    read_xmlbif,
    to_pgmpy,
    write_uai,
    write_xmlbif,
)
from effect_networks.models.pgmpy_files import uai_sites, xmlbif_text
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from tests.networks import (
    counts_of,
    declared_networks,
    discrete_networks,
    pgmpy_marginal,
    same_bits,
)

pytest.importorskip("pgmpy")
from pgmpy.inference import VariableElimination  # noqa: E402
from pgmpy.readwrite import XMLBIFReader, XMLBIFWriter  # noqa: E402

FILES = settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def assert_answers_as_pgmpy(ve, net, net2, params2, data):
    """Our answers on the read network equal pgmpy's on ``ve`` (the original) to 1e-12."""
    initial = {
        f"initial.{f.name}": data.draw(st.sampled_from(f.states))
        for f in net.features
        if f.initial and data.draw(st.booleans())
    }
    action = data.draw(st.sampled_from(net.actions))
    ev = initial | {"action": action}
    ours = predict(net2, params2, {k: [v] for k, v in ev.items()})
    for f in net.features:
        states, theirs = pgmpy_marginal(ve, f"end.{f.name}", ev)
        assert tuple(states) == f.states
        torch.testing.assert_close(ours.discrete[f.name][0], theirs, atol=1e-12, rtol=0)


@FILES
@given(net=st.one_of(discrete_networks(), declared_networks()), seed=st.integers(0, 10_000))
def test_xmlbif_round_trips_and_answers_as_pgmpy(tmp_path_factory, net, seed):
    params = random_params(net, seed, unseen=0.3)
    path = write_xmlbif(tmp_path_factory.mktemp("xmlbif") / "net.xml", net, params)
    states = {f.name: f.states for f in net.features}
    order = [f.name for f in net.features]
    net2, params2 = read_xmlbif(path, n=counts_of(params), states=states, order=order)
    assert net2 == net
    for site, cpd in params.cpds.items():
        torch.testing.assert_close(params2[site].probs, cpd.probs, atol=1e-12, rtol=0)
        assert same_bits(params2[site].n, cpd.n)
    # pgmpy's own reading of the same file answers as the original network
    theirs = VariableElimination(XMLBIFReader(path=str(path)).get_model())
    original = VariableElimination(to_pgmpy(net, params).model)
    for f in net.features:
        site = f"end.{f.name}"
        a, b = (
            original.query([site], show_progress=False),
            theirs.query([site], show_progress=False),
        )
        np.testing.assert_allclose(a.values, b.values, atol=1e-12, rtol=0)


@FILES
@given(
    net=st.one_of(discrete_networks(), declared_networks()),
    seed=st.integers(0, 10_000),
    data=st.data(),
)
def test_uai_round_trips_bit_for_bit_and_answers_as_pgmpy(tmp_path_factory, net, seed, data):
    params = random_params(net, seed, unseen=0.3)
    path = write_uai(tmp_path_factory.mktemp("uai") / "net.uai", net, params)
    net2, params2 = read_uai(path, net, n=counts_of(params))
    assert net2 is net
    for site, cpd in params.cpds.items():
        assert same_bits(params2[site].probs, cpd.probs), site  # repr of each float
        assert same_bits(params2[site].n, cpd.n), site
    assert_answers_as_pgmpy(
        VariableElimination(to_pgmpy(net, params).model), net, net, params2, data
    )


def test_xmlbif_labels_are_their_text_unless_states_restore_them(tmp_path):
    net = EffectNetwork(
        (Discrete("n", (7, -1, 2)), Discrete("flag", (False, True)), Discrete("s", ("a-b", "c"))),
        ("push-hard", "wait"),
    )
    path = write_xmlbif(tmp_path / "net.xml", net, random_params(net, 0))
    plain, _ = read_xmlbif(path, n=1, order=["n", "flag", "s"])
    assert plain.feature("n").states == ("7", "_1", "2")
    assert plain.feature("flag").states == ("False", "True")
    assert plain.feature("s").states == ("a_b", "c")
    assert plain.actions == ("push_hard", "wait")
    states = {"n": (7, -1, 2), "flag": (False, True), "s": ("a-b", "c")}
    restored, _ = read_xmlbif(path, n=1, states=states, order=["n", "flag", "s"])
    assert restored.features == net.features


@settings(max_examples=200, deadline=None)
@given(
    text=st.text(
        st.characters(blacklist_categories=("Zs", "Cc", "Zl", "Zp")), min_size=1, max_size=8
    )
)
def test_xmlbif_text_is_what_pgmpy_writes(text):
    assume(not any(c.isspace() for c in text))  # refused: pgmpy keeps some, replaces others
    writer = XMLBIFWriter.__new__(XMLBIFWriter)  # the state-name rule only, no model
    assert xmlbif_text(text) == writer._make_valid_state_name(text)


def test_labels_xmlbif_cannot_tell_apart_are_refused(tmp_path):
    net = EffectNetwork((Discrete("n", (-1, "_1")),), ("push", "wait"))
    with pytest.raises(ValueError, match=r"site 'initial.n': labels -1 and '_1' are both '_1'"):
        write_xmlbif(tmp_path / "net.xml", net, random_params(net, 0))
    net = EffectNetwork((Discrete("s", ("a b", "c")),), ("push", "wait"))
    with pytest.raises(ValueError, match=r"site 'initial.s': label 'a b' .*without white space"):
        write_xmlbif(tmp_path / "net.xml", net, random_params(net, 0))


def door():
    return EffectNetwork((Discrete("door", ("shut", "open")),), ("wait", "push", "pull"))


def test_a_hand_written_uai_file_reads_as_the_format_says(tmp_path):
    """UAI's layout: the child last in a scope, the last scope variable fastest. Here the
    end table's scope lists the action before the initial door (ours: door, action)."""
    net = door()
    assert uai_sites(net) == ["initial.door", "action", "end.door"]
    # p(end.door = open | action, initial.door), rows (action, initial) with end fastest
    open_given = {("wait", "shut"): 0.0, ("wait", "open"): 1.0, ("push", "shut"): 0.9}
    open_given |= {("push", "open"): 1.0, ("pull", "shut"): 0.2, ("pull", "open"): 0.5}
    values = []
    for a in net.actions:
        for d in ("shut", "open"):
            values += [1 - open_given[a, d], open_given[a, d]]
    text = "\n".join(
        [
            "BAYES",
            "3",
            "2 3 2",
            "3",
            "1 0",
            "1 1",
            "3 1 0 2",
            "2 0.25 0.75",
            "3 0.5 0.25 0.25",
            f"12 {' '.join(map(repr, values))}",
        ]
    )
    (tmp_path / "door.uai").write_text(text)
    _, params = read_uai(tmp_path / "door.uai", net, n=4)
    assert params["initial.door"].probs.tolist() == [0.25, 0.75]
    assert params["action"].probs.tolist() == [0.5, 0.25, 0.25]
    for (a, d), p in open_given.items():
        i, j = ("shut", "open").index(d), net.actions.index(a)
        assert params["end.door"].probs[i, j].tolist() == [1 - p, p]
    assert float(params["end.door"].n[0, 0]) == 4.0


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("MARKOV 3 2 3 2 0", "'MARKOV' network; expected 'BAYES'"),
        ("BAYES 3 2 3", "ends before its cardinalities"),
        ("BAYES 2 2 3 2 1 0 1 1 2 0.5 0.5 3 0.2 0.3 0.5", "variables of \\[2, 3\\] states"),
        ("BAYES 3 2 3 2 3 1 0 1 1 2 0 2 2 0.5 0.5 3 1 0 0 4 1 0 0 1", "site 'end.door'"),
        ("BAYES 3 2 3 2 3 1 0 1 1 1 9 2 0.5 0.5", "names no variable"),
        ("BAYES 3 2 3 2 1 1 0 3 0.5 0.5", "table 0 has 3 values"),
        ("BAYES 3 2 3 2 1 1 0 2 0.5 x", "not a number"),
        ("BAYES 3 2 3 2 1 1 0 2 0.5 0.5 7", "no table for the sites|words after"),
    ],
)
def test_a_uai_file_that_is_not_the_declarations_is_refused(tmp_path, text, message):
    (tmp_path / "bad.uai").write_text(text)
    with pytest.raises(ValueError, match=message):
        read_uai(tmp_path / "bad.uai", door(), n=1)


def test_a_uai_column_that_is_no_distribution_is_refused_as_from_pgmpy_refuses(tmp_path):
    net = door()
    path = write_uai(tmp_path / "door.uai", net, random_params(net, 0))
    lines = path.read_text().splitlines()
    count = max(i for i, line in enumerate(lines) if line == "3")  # the action's 3 values
    lines[count + 1] = "0.5 0.25 0.5"  # sum to 1.25
    path.write_text("\n".join(lines))
    with pytest.raises(ValueError, match="check_model refuses.*node action"):
        read_uai(path, net, n=1)


def test_networks_the_files_cannot_hold_are_refused_naming_the_sites(tmp_path):
    net = EffectNetwork((Discrete("visible", (False, True)), Continuous("pos", 1)), ("a", "b"))
    params = random_params(net, 0)
    for write, holder in ((write_xmlbif, "XMLBIF"), (write_uai, "UAI")):
        with pytest.raises(
            ValueError, match=rf"^{holder} holds .* sites \['initial.pos', 'end.visible'"
        ):
            write(tmp_path / "net", net, params)
    with pytest.raises(ValueError, match=r"UAI holds .*initial.pos: a continuous feature"):
        read_uai(tmp_path / "net", net, n=1)
    assert list(tmp_path.iterdir()) == []
