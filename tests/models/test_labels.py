"""Labels are matched as declared: a value is one of a feature's states by equality and
type (``1`` is not ``"1"``), whatever container holds the rows and whatever other labels
stand beside it; a value that is none is named with its row."""

import numpy as np
import pytest
from effect_networks.inference import fit, predict
from effect_networks.models import Discrete, EffectNetwork
from hypothesis import given, settings
from hypothesis import strategies as st

#: Labels of every kind a state may have; Python counts 1, 1.0 and True as one value, so
#: a declaration holds at most one of each such group.
LABELS = st.one_of(
    st.booleans(),
    st.integers(-3, 3),
    st.sampled_from([0.5, 2.5, -1.5]),
    st.sampled_from(["0", "1", "2", "True", "many", "1.0", ""]),
)


def distinct(labels: list) -> tuple:
    out: list = []
    for label in labels:
        if all(label != other for other in out):
            out.append(label)
    return tuple(out)


def same_label(a, b) -> bool:
    return a == b and isinstance(a, str) == isinstance(b, str)


@settings(max_examples=200, deadline=None)
@given(
    states=st.lists(LABELS, min_size=2, max_size=5).map(distinct).filter(lambda s: len(s) >= 2),
    data=st.data(),
)
def test_every_row_reads_as_the_state_it_is(states, data):
    net = EffectNetwork((Discrete("x", states),), ("a",))
    rows = data.draw(st.lists(st.sampled_from(states), min_size=1, max_size=12))
    container = data.draw(st.sampled_from([list, tuple, lambda r: np.array(r, dtype=object)]))
    index = net.encode({"initial.x": container(rows)})["initial.x"].tolist()
    assert index == [next(i for i, s in enumerate(states) if same_label(s, r)) for r in rows]


@settings(max_examples=200, deadline=None)
@given(
    states=st.lists(LABELS, min_size=2, max_size=5).map(distinct).filter(lambda s: len(s) >= 2),
    data=st.data(),
)
def test_a_value_that_is_no_state_is_named_with_its_row(states, data):
    strangers = [v for v in (str(s) for s in states) if all(not same_label(v, s) for s in states)]
    strangers += ["maybe"]
    good = data.draw(st.lists(st.sampled_from(states), max_size=6))
    bad = data.draw(st.sampled_from(strangers))
    at = data.draw(st.integers(0, len(good)))
    rows = [*good[:at], bad, *good[at:]]
    net = EffectNetwork((Discrete("x", states),), ("a",))
    with pytest.raises(ValueError, match=rf"value {bad!r} is not one of its states .*\(row {at}\)"):
        net.encode({"initial.x": rows})


def test_a_fit_on_rows_half_text_half_number_counts_each():
    """States ("1", 1): rows "1" and 1 alternate, so each state has half the rows."""
    net = EffectNetwork((Discrete("x", ("1", 1)),), ("a", "b"), parents={"end.x": ("initial.x",)})
    rows = ["1", 1] * 200
    params = fit(net, {"initial.x": rows, "action": ["a"] * 400, "end.x": rows}).params
    np.testing.assert_allclose(params.cpds["initial.x"].probs.numpy(), [0.5, 0.5], atol=1e-3)
    staying = predict(net, params, {"initial.x": [1, "1"], "action": ["a", "a"]})
    assert staying.prob("x", 1)[0] > 0.99 and staying.prob("x", "1")[1] > 0.99


def test_labels_of_several_types_beside_each_other_in_evidence():
    net = EffectNetwork((Discrete("y", (0, 1, "many")),), ("a",))
    assert net.encode({"initial.y": [0, "many"]})["initial.y"].tolist() == [0, 2]
    with pytest.raises(ValueError, match=r"value 'maybe' is not one of its states.*\(row 0\)"):
        EffectNetwork((Discrete("z", (False, True)),), ("a",)).encode(
            {"initial.z": ["maybe", False, True]}
        )
