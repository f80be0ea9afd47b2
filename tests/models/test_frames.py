"""models.frames: the column convention read and written, labels matched to the declared
states, missing values kept missing, every column error named, and a CSV round trip."""

import io
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from effect_networks.inference import simulate
from effect_networks.models import (
    Continuous,
    Discrete,
    EffectNetwork,
    Parameter,
    Partial,
    random_params,
)
from effect_networks.models.frames import as_data, columns, from_frame, is_frame, to_frame
from hypothesis import given, settings
from hypothesis import strategies as st

ROOT = Path(__file__).resolve().parents[2]


def mixed_network() -> EffectNetwork:
    """Bool, string and int states, a 2-d feature, a 1-d outcome and a parameter."""
    return EffectNetwork(
        features=(
            Discrete("visible", (False, True)),
            Discrete("colour", ("red", "blue", "7")),
            Discrete("count", (1, 2, 3)),
            Continuous("position", 2),
            Continuous("displacement", 1, initial=False),
        ),
        actions=("look", "remove", "tap"),
        parameters=(
            Parameter(
                "force", low=0.0, high=20.0, bins=3, actions=("tap",), affects="displacement"
            ),
        ),
    )


NET = mixed_network()


def same_evidence(a, b) -> None:
    """Two encodings equal site by site, exactly (NaN where the other has NaN)."""
    a, b = NET.encode(a), NET.encode(b)
    assert sorted(a) == sorted(b) and a.n_rows == b.n_rows
    for site in a:
        torch.testing.assert_close(a[site], b[site], rtol=0, atol=0, equal_nan=True, msg=site)


@pytest.fixture(scope="module")
def rows():
    return simulate(NET, random_params(NET, seed=1), 60, seed=2)


# ------------------------------------------------------------------------- the convention
def test_columns_are_the_site_or_one_per_dimension():
    assert columns(NET, "initial.visible") == ("initial.visible",)
    assert columns(NET, "action") == ("action",)
    assert columns(NET, "end.position") == ("end.position[0]", "end.position[1]")
    assert columns(NET, "end.displacement") == ("end.displacement",)
    assert columns(NET, "param.force") == ("param.force",)


def test_to_frame_writes_the_convention_with_labels(rows):
    frame = to_frame(NET, rows)
    assert list(frame.columns) == [
        "initial.visible", "initial.colour", "initial.count", "initial.position[0]",
        "initial.position[1]", "action", "cluster.force", "param.force", "end.visible",
        "end.colour", "end.count", "end.position[0]", "end.position[1]", "end.displacement",
    ]  # fmt: skip
    assert frame["initial.visible"].dtype == bool and frame["end.count"].dtype == np.int64
    assert frame["action"].tolist() == list(rows["action"])
    assert frame["end.colour"].tolist() == list(rows["end.colour"])
    np.testing.assert_array_equal(frame["end.position[1]"], rows["end.position"][:, 1].numpy())
    tap = frame["action"] == "tap"
    assert (
        frame.loc[~tap, "param.force"].isna().all() and frame.loc[tap, "param.force"].notna().all()
    )


def test_to_frame_then_from_frame_gives_the_rows(rows):
    same_evidence(from_frame(NET, to_frame(NET, rows)), rows)


def test_a_hand_written_frame_reads_as_its_mapping():
    # columns in any order, a 1-d value as name[0], labels of other types than declared
    frame = pd.DataFrame(
        {
            "end.position[1]": [0.5, 1.5],
            "initial.visible": ["True", "False"],  # text, as a CSV file holds it
            "initial.count": [2.0, 3.0],  # whole floats, as a column with a gap reads
            "initial.colour": pd.Categorical(["blue", "7"]),
            "end.position[0]": [-1, 2],  # ints are numbers too
            "end.displacement[0]": [0.25, 0.0],
            "action": ["tap", "look"],
        },
        index=[10, 20],  # the index is ignored
    )
    same_evidence(
        from_frame(NET, frame),
        {
            "initial.visible": [True, False],
            "initial.count": [2, 3],
            "initial.colour": ["blue", "7"],
            "action": ["tap", "look"],
            "end.position": [[-1.0, 0.5], [2.0, 1.5]],
            "end.displacement": [[0.25], [0.0]],
        },
    )
    converted = from_frame(NET, frame)
    assert converted["initial.count"].tolist() == [2, 3]
    assert all(type(v) is int for v in converted["initial.count"])
    assert converted["initial.visible"].tolist() == [True, False]


def test_a_number_read_from_text_matches_a_string_state():
    frame = pd.DataFrame({"initial.colour": [7, 7]})  # a column of "7" reads as ints
    assert from_frame(NET, frame)["initial.colour"].tolist() == ["7", "7"]


def test_a_value_of_no_state_is_refused_where_it_is_encoded():
    frame = pd.DataFrame({"initial.colour": ["red", "green"]})
    with pytest.raises(ValueError, match=r"'initial.colour'.*'green' is not one of its states"):
        NET.encode(frame)


def test_is_frame_and_as_data():
    frame = pd.DataFrame({"action": ["tap"]})
    mapping = {"action": ["tap"]}
    assert is_frame(frame) and not is_frame(mapping) and not is_frame(None)
    assert as_data(NET, mapping) is mapping
    assert as_data(NET, frame)["action"].tolist() == ["tap"]


# ------------------------------------------------------------------------- missing values
def test_missing_values_stay_missing():
    frame = pd.DataFrame(
        {
            "initial.visible": pd.Series([True, None, False], dtype=object),
            "initial.colour": pd.Series(["red", pd.NA, "blue"], dtype="string"),
            "initial.count": [1.0, np.nan, 3.0],
            "initial.position[0]": [0.0, 1.0, 2.0],
            "initial.position[1]": [0.0, 1.0, 2.0],
            "action": pd.Categorical(["tap", "look", None]),
            "param.force": [3.0, np.nan, np.nan],
            "end.position[0]": [1.0, np.nan, np.nan],
            "end.position[1]": [2.0, 3.0, np.nan],
        }
    )
    data = from_frame(NET, frame)
    assert data["initial.visible"].tolist() == [True, None, False]
    assert data["initial.colour"].tolist() == ["red", None, "blue"]
    assert data["initial.count"].tolist() == [1, None, 3]
    assert data["action"].tolist() == ["tap", "look", None]
    assert data["initial.visible"].dtype == object
    np.testing.assert_array_equal(data["param.force"], [[3.0], [np.nan], [np.nan]])
    end = data["end.position"]  # an end feature with gaps: observed where not NaN
    assert isinstance(end, Partial)
    np.testing.assert_array_equal(end.observed, [[True, True], [False, True], [False, False]])
    enc = NET.encode({"end.position": end, "param.force": data["param.force"]})
    assert torch.isnan(enc["end.position"]).tolist() == [
        [False, False],
        [True, False],
        [True, True],
    ]


def test_a_complete_end_feature_is_a_plain_array(rows):
    assert isinstance(from_frame(NET, to_frame(NET, rows))["end.position"], np.ndarray)


# ------------------------------------------------------------------------- column errors
@pytest.mark.parametrize(
    ("columns_", "match"),
    [
        (["initial.visible", "initial.shape"], r"columns \['initial.shape'\] name no site"),
        (["end.position[0]"], r"site 'end.position' lacks the columns \['end.position\[1\]'\]"),
        (["end.position"], r"column 'end.position': site 'end.position' has 2 dimensions"),
        (["end.position[0]", "end.position[1]", "end.position[2]"], r"'end.position\[2\]'.*0\.\.1"),
        (["action[0]"], r"\['action\[0\]'\]: site 'action' is discrete"),
        (["end.displacement", "end.displacement[0]"], r"both give site 'end.displacement'"),
        (["initial.count", "initial.count"], r"columns \['initial.count'\] appear more than once"),
    ],
)
def test_a_column_that_does_not_fit_is_named(columns_, match):
    frame = pd.DataFrame([[1.0] * len(columns_)], columns=columns_)
    with pytest.raises(ValueError, match=match):
        from_frame(NET, frame)


def test_an_unknown_column_is_left_out_on_request():
    frame = pd.DataFrame({"action": ["tap"], "trial_id": [7], 3: [1]})
    with pytest.raises(ValueError, match=r"\['trial_id', 3\] name no site.*extra='ignore'"):
        from_frame(NET, frame)
    assert list(from_frame(NET, frame, extra="ignore")) == ["action"]
    with pytest.raises(ValueError, match="extra must be 'raise' or 'ignore'"):
        from_frame(NET, frame, extra="drop")


def test_a_continuous_column_must_hold_numbers():
    with pytest.raises(ValueError, match=r"column 'param.force'.*not numbers"):
        from_frame(NET, pd.DataFrame({"param.force": ["strong"]}))
    with pytest.raises(ValueError, match=r"column 'param.force': bools are not numbers"):
        from_frame(NET, pd.DataFrame({"param.force": [True]}))


def test_from_frame_wants_a_frame():
    with pytest.raises(ValueError, match="expected a pandas DataFrame, got dict"):
        from_frame(NET, {"action": ["tap"]})


# ------------------------------------------------------------------------- CSV
def test_a_csv_round_trip_gives_the_rows_again(rows, tmp_path):
    path = tmp_path / "rows.csv"
    to_frame(NET, rows).to_csv(path, index=False)
    same_evidence(pd.read_csv(path), rows)  # labels matched, floats exact (pandas >= 3)


def test_a_csv_with_gaps_reads_its_labels_back():
    frame = pd.DataFrame(
        {
            "initial.visible": pd.Series([True, None, False], dtype=object),
            "initial.count": pd.Series([1, None, 3], dtype=object),
            "initial.colour": ["7", None, "red"],
        }
    )
    text = io.StringIO()
    frame.to_csv(text, index=False)
    text.seek(0)
    data = from_frame(NET, pd.read_csv(text))
    assert data["initial.visible"].tolist() == [True, None, False]
    assert data["initial.count"].tolist() == [1, None, 3]
    assert data["initial.colour"].tolist() == ["7", None, "red"]


# ------------------------------------------------------------------------- hypothesis
@settings(max_examples=30, deadline=None)
@given(
    dim=st.integers(1, 4),
    n=st.integers(0, 5),
    bare=st.booleans(),
    order=st.randoms(use_true_random=False),
    seed=st.integers(0, 2**16),
)
def test_any_column_order_reads_to_the_same_vector(dim, n, bare, order, seed):
    net = EffectNetwork(features=(Continuous("xy", dim),), actions=("a", "b"))
    value = np.random.default_rng(seed).normal(size=(n, dim))
    names = ["end.xy"] if dim == 1 and bare else [f"end.xy[{i}]" for i in range(dim)]
    frame = pd.DataFrame({c: value[:, i] for i, c in enumerate(names)})
    shuffled = list(frame.columns)
    order.shuffle(shuffled)
    got = from_frame(net, frame[shuffled])["end.xy"]
    np.testing.assert_array_equal(got, value)
    back = to_frame(net, {"end.xy": value})
    assert list(back.columns) == (["end.xy"] if dim == 1 else names)
    np.testing.assert_array_equal(back.to_numpy(), value)


# ------------------------------------------------------------------------- pandas optional
def test_the_data_extra_holds_pandas_and_dev_installs_it():
    import tomllib

    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"][
        "optional-dependencies"
    ]
    assert [r.split(">")[0] for r in extras["data"]] == ["pandas"]
    assert any(r.startswith("pandas") for r in extras["dev"])


def test_without_pandas_a_frame_call_names_the_extra(monkeypatch):
    from effect_networks.inference.queries.results import ImitationCheck

    monkeypatch.setitem(sys.modules, "pandas", None)  # import pandas now raises ImportError
    check = ImitationCheck(torch.zeros(1), torch.zeros(1), torch.zeros(1))
    calls = [
        lambda: to_frame(NET, {"action": ["tap"]}),
        lambda: from_frame(NET, {"action": ["tap"]}),
        check.to_frame,
    ]
    for call in calls:
        with pytest.raises(ImportError, match=r"effect-networks\[data\]"):
            call()
    assert not is_frame({"action": ["tap"]})
    assert as_data(NET, {"action": ["tap"]}) == {"action": ["tap"]}  # mappings need no pandas


@pytest.mark.slow
def test_without_pandas_the_toolkit_imports_and_a_frame_call_names_the_extra():
    code = (
        "import sys; sys.modules['pandas'] = None\n"
        "import models, inference\n"
        "from models.frames import to_frame, is_frame\n"
        "assert not is_frame({})\n"
        "net = models.EffectNetwork(features=(models.Discrete('v', (0, 1)),), actions=('a',))\n"
        "try:\n"
        "    to_frame(net, {'action': ['a']})\n"
        "except ImportError as exc:\n"
        "    print(exc)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert "effect-networks[data]" in done.stdout
