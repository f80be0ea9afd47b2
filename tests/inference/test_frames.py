"""DataFrames through fit, every query and simulate: the same answers as from the
mapping the frame holds, exactly; and the results' frames, column by column against the
results' own fields."""

import runpy
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from effect_networks.inference import (
    compile,
    fit,
    fit_em,
    fit_pooled,
    fit_statistics,
    imitation_check,
    infer_action,
    infer_parameter,
    parameter_for_effect,
    predict,
    simulate,
)
from effect_networks.models import Continuous, Discrete, EffectNetwork, Parameter, random_params
from effect_networks.models.frames import from_frame, to_frame

from tests.questions import TracedCalls, assert_same_answer

ROOT = Path(__file__).resolve().parents[2]

NET = EffectNetwork(
    features=(
        Discrete("visible", (False, True)),
        Discrete("colour", ("red", "blue")),
        Continuous("position", 2),
        Continuous("displacement", 1, initial=False),
    ),
    actions=("look", "remove", "tap"),
    parameters=(
        Parameter("force", low=0.0, high=20.0, bins=3, actions=("tap",), affects="displacement"),
    ),
)
DISCRETE = EffectNetwork(
    features=(Discrete("visible", (False, True)), Discrete("count", (1, 2, 3))),
    actions=("look", "remove"),
)


def exactly(a, b, path="answer"):
    """Two results equal field by field, bit for bit (NaN where the other has NaN)."""
    assert type(a) is type(b), path
    if isinstance(a, torch.Tensor):
        torch.testing.assert_close(a, b, rtol=0, atol=0, equal_nan=True, msg=path)
    elif hasattr(a, "__dataclass_fields__"):
        for name in a.__dataclass_fields__:
            exactly(getattr(a, name), getattr(b, name), f"{path}.{name}")
    elif isinstance(a, dict):
        assert a.keys() == b.keys(), path
        for k in a:
            exactly(a[k], b[k], f"{path}[{k!r}]")
    else:
        assert a == b, (path, a, b)


def tensors(params):
    out = []
    params.map(lambda t: out.append(t) or t)
    return out


@pytest.fixture(scope="module")
def fitted():
    truth = random_params(NET, seed=4)
    rows = simulate(NET, truth, 300, seed=5)
    return rows, to_frame(NET, rows), fit(NET, rows).params


def test_fit_from_a_frame_equals_fit_from_its_mapping(fitted):
    rows, frame, params = fitted
    from_csv_like = frame.sample(frac=1.0, axis=1, random_state=0)  # columns in any order
    got = fit(NET, from_csv_like).params
    assert all(torch.equal(a, b) for a, b in zip(tensors(params), tensors(got), strict=True))
    # the clusters left out: each row filed under its value's cell, as from the mapping
    no_clusters = {k: v for k, v in rows.items() if k != "cluster.force"}
    a = fit(NET, no_clusters).params
    b = fit(NET, frame.drop(columns="cluster.force")).params
    assert all(torch.equal(x, y) for x, y in zip(tensors(a), tensors(b), strict=True))


def test_frame_chunks_sum_to_the_statistics_of_the_whole():
    rows = simulate(DISCRETE, random_params(DISCRETE, seed=1), 200, seed=2)
    frame = to_frame(DISCRETE, rows)
    got = fit(DISCRETE, iter([frame.iloc[:120], frame.iloc[120:]])).params
    whole = fit(DISCRETE, rows).params
    for a, b in zip(tensors(whole), tensors(got), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    assert fit_statistics(DISCRETE, [frame]).rows == 200


def test_the_pooled_and_em_fits_take_a_frame():
    rows = simulate(DISCRETE, random_params(DISCRETE, seed=1), 200, seed=2)
    kernel = torch.ones(2, 2)
    a = fit_pooled(DISCRETE, rows, kernel).params
    b = fit_pooled(DISCRETE, to_frame(DISCRETE, rows), kernel).params
    assert all(torch.equal(x, y) for x, y in zip(tensors(a), tensors(b), strict=True))
    net = EffectNetwork(
        (Discrete("visible", (0, 1)), Continuous("pos", 1, initial=False)),
        ("remove", "tap"),
        (Parameter("force", (0.0,), (10.0,), (2,), ("tap",), "pos", layout="adaptive"),),
    )
    rows = simulate(net, random_params(net, seed=3), 100, seed=4)
    rows = {k: v for k, v in rows.items() if k != "cluster.force"}  # latent: EM fills it
    a, b = fit_em(net, rows, steps=3), fit_em(net, to_frame(net, rows), steps=3)
    assert all(torch.equal(x, y) for x, y in zip(tensors(a.params), tensors(b.params), strict=True))


def test_fit_names_a_site_the_frame_lacks(fitted):
    _, frame, _ = fitted
    with pytest.raises(ValueError, match=r"missing \['end.position'\]"):
        fit(NET, frame.drop(columns=["end.position[0]", "end.position[1]"]))
    with pytest.raises(ValueError, match=r"lacks the columns \['end.position\[1\]'\]"):
        fit(NET, frame.drop(columns=["end.position[1]"]))
    with pytest.raises(ValueError, match=r"\['trial'\] name no site"):
        fit(NET, frame.assign(trial=1))


def test_fit_takes_missing_labels_from_a_frame_with_masks():
    truth = random_params(DISCRETE, seed=1)
    rows = simulate(DISCRETE, truth, 200, seed=2)
    frame = to_frame(DISCRETE, rows)
    frame["end.count"] = frame["end.count"].astype(object)
    frame.loc[::7, "end.count"] = np.nan
    masks = {"end.count": frame["end.count"].notna()}  # a Series: read-only underneath
    mapping = dict(rows) | {"end.count": [None if m is np.nan else m for m in frame["end.count"]]}
    a = fit(DISCRETE, frame, masks=masks)
    b = fit(DISCRETE, mapping, masks=masks)
    assert all(torch.equal(x, y) for x, y in zip(tensors(a.params), tensors(b.params), strict=True))
    assert a.losses == b.losses


# ------------------------------------------------------------------------- queries
QUERY_COLUMNS = [
    "initial.visible", "initial.colour", "initial.position[0]", "initial.position[1]",
    "end.visible", "end.colour", "end.position[0]", "end.position[1]", "end.displacement",
]  # fmt: skip


@pytest.fixture(scope="module")
def evidence(fitted):
    """A few observed rows as a frame and as the mapping it holds (tap rows first)."""
    _, frame, _ = fitted
    rows = pd.concat([frame[frame["action"] == "tap"].iloc[:3], frame.iloc[:3]])
    return rows.reset_index(drop=True)


def both(frame, columns):
    part = frame[columns]
    return part, from_frame(NET, part)


@pytest.mark.parametrize("compiled", [False, True])
def test_every_query_from_a_frame_equals_its_mapping(fitted, evidence, compiled):
    _, _, params = fitted
    queries = compile(NET, params) if compiled else None

    def ask(name, *args, **kwargs):
        fn = getattr(queries, name) if compiled else globals()[name]
        return fn(*args, **kwargs) if compiled else fn(NET, params, *args, **kwargs)

    initial = QUERY_COLUMNS[:4]
    frame, mapping = both(evidence, [*initial, "action"])
    exactly(ask("predict", frame), ask("predict", mapping))
    frame, mapping = both(evidence, QUERY_COLUMNS)
    exactly(ask("infer_action", frame), ask("infer_action", mapping))
    frame, mapping = both(evidence, [*QUERY_COLUMNS, "action"])
    exactly(ask("imitation_check", frame), ask("imitation_check", mapping))
    frame, mapping = both(evidence.iloc[:3], [*QUERY_COLUMNS, "action"])
    exactly(ask("infer_parameter", "force", frame), ask("infer_parameter", "force", mapping))
    exactly(
        ask("parameter_for_effect", "force", frame), ask("parameter_for_effect", "force", mapping)
    )


def test_the_compiled_parameter_query_serves_a_frame(fitted, evidence, monkeypatch):
    _, _, params = fitted
    queries = compile(NET, params)
    traced = TracedCalls(monkeypatch, "infer_parameter")
    frame = evidence.iloc[:3][[*QUERY_COLUMNS[:4], "action", "end.displacement"]]
    got = queries.infer_parameter("force", frame)
    assert traced.calls == 0  # answered from the compiled query, not the traced model
    exactly(got, queries.infer_parameter("force", from_frame(NET, frame)))


def test_compiled_action_tables_take_a_frame():
    params = random_params(DISCRETE, seed=3)
    frame = pd.DataFrame({"initial.visible": ["True", "False"], "end.count": [3.0, 1.0]})
    mapping = {"initial.visible": [True, False], "end.count": [3, 1]}
    queries = compile(DISCRETE, params)
    assert queries.action_tables is not None
    exactly(queries.infer_action(frame), queries.infer_action(mapping))
    # and as the traced model answers (compiled and traced agree to rounding)
    assert_same_answer(queries.infer_action(frame), infer_action(DISCRETE, params, frame))


def test_simulate_takes_a_frame_and_gives_one(fitted):
    _, _, params = fitted
    frame = pd.DataFrame({"initial.visible": [True, False], "action": ["tap", "look"]})
    mapping = {"initial.visible": [True, False], "action": ["tap", "look"]}
    a = simulate(NET, params, 2, frame, seed=3)
    b = simulate(NET, params, 2, mapping, seed=3)
    exactly({k: torch.as_tensor(np.asarray(v, float)) for k, v in _numeric(a).items()},
            {k: torch.as_tensor(np.asarray(v, float)) for k, v in _numeric(b).items()})  # fmt: skip
    assert a["end.colour"] == b["end.colour"]
    drawn = simulate(NET, params, 5, seed=7, as_frame=True)
    pd.testing.assert_frame_equal(drawn, to_frame(NET, simulate(NET, params, 5, seed=7)))
    assert drawn.loc[drawn["action"] != "tap", "param.force"].isna().all()


def _numeric(rows):
    return {k: v for k, v in rows.items() if isinstance(v, torch.Tensor)}


# ------------------------------------------------------------------------- result frames
def test_a_prediction_frame_holds_labels_probabilities_and_means(fitted, evidence):
    _, _, params = fitted
    frame = evidence[["initial.visible", "initial.colour", "initial.position[0]",
                      "initial.position[1]", "action"]]  # fmt: skip
    result = predict(NET, params, frame)
    table = result.to_frame(index=frame.index)
    assert list(table.index) == list(frame.index)
    assert table["end.visible"].tolist() == list(result.most_likely("visible"))
    for state in (False, True):
        np.testing.assert_array_equal(table[f"end.visible={state}"], result.prob("visible", state))
    np.testing.assert_allclose(
        table[["end.colour=red", "end.colour=blue"]].sum(axis=1), 1, atol=1e-12
    )
    mean = result.continuous["position"].mean.numpy()
    np.testing.assert_array_equal(table[["end.position[0]", "end.position[1]"]], mean)
    np.testing.assert_array_equal(
        table["end.displacement"], result.continuous["displacement"].mean[:, 0]
    )
    assert table["unseen"].tolist() == result.unseen.tolist()
    assert table["implausible"].dtype == bool


def test_an_action_posterior_frame_names_the_actions(fitted, evidence):
    _, _, params = fitted
    result = infer_action(NET, params, evidence[QUERY_COLUMNS])
    table = result.to_frame()
    assert table["action"].tolist() == list(result.best_names)
    probs = table[[f"action={a}" for a in NET.actions]].to_numpy()
    np.testing.assert_array_equal(probs, result.probs)
    assert [NET.actions[i] for i in probs.argmax(1)] == table["action"].tolist()
    np.testing.assert_array_equal(table["unseen|action=tap"], result.unseen[:, 2])
    np.testing.assert_array_equal(table["log_evidence"], result.log_evidence)


def test_parameter_frames(fitted, evidence):
    _, _, params = fitted
    frame = evidence.iloc[:3][[*QUERY_COLUMNS, "action"]]
    post = infer_parameter(NET, params, "force", frame)
    table = post.to_frame()
    assert table["cluster"].tolist() == post.best_cluster.tolist()
    np.testing.assert_array_equal(
        table[["cluster=0", "cluster=1", "cluster=2"]], post.cluster_probs
    )
    np.testing.assert_array_equal(table["mean"], post.mean[:, 0])
    np.testing.assert_allclose(table["sd"] ** 2, post.cov[:, 0, 0], rtol=1e-14)
    inverse = parameter_for_effect(NET, params, "force", frame)
    table = inverse.to_frame()
    assert list(table.columns) == ["value", "cluster", "log_density", "miss", "outside"]
    np.testing.assert_array_equal(table["value"], inverse.value[:, 0])
    check = imitation_check(NET, params, frame).to_frame()
    assert list(check.columns) == ["log_likelihood", "surprise", "unseen", "implausible"]
    assert ((check["surprise"] >= 0) & (check["surprise"] <= 1)).all()


# ------------------------------------------------------------------------- the tutorial
def test_the_csv_tutorial_runs_at_a_tiny_scale(tmp_path, monkeypatch, capsys):
    script = ROOT / "docs" / "tutorials" / "csv_round_trip.py"
    out = tmp_path / "rows.csv"
    monkeypatch.setattr(sys, "argv", [str(script), "--out", str(out), "--rows", "200"])
    runpy.run_path(str(script), run_name="__main__")
    read = pd.read_csv(out)
    assert len(read) == 200 and "end.displacement" in read.columns
    assert "action=tap" in capsys.readouterr().out
