"""The shared checks of training rows, settings and masks (inference.fitting.rows)."""

import re

import numpy as np
import pytest
import torch
from effect_networks.inference.fitting.rows import (
    check_settings,
    ignore_missing,
    mask_values,
    missing_masks,
    refuse_adaptive,
    row_masks,
    training_rows,
)
from effect_networks.models import Continuous, Discrete, EffectNetwork, Parameter

TAP = EffectNetwork(
    (Discrete("visible", (0, 1)), Continuous("pos", 1)),
    ("remove", "tap"),
    (Parameter("force", 0.0, 10.0, 2, ("tap",), "pos"),),
)


def tap_rows():
    force = [[float("nan")], [1.0], [7.5], [float("nan")], [4.9]]
    return {
        "initial.visible": [0, 1, 1, 0, 1],
        "initial.pos": [[0.0], [0.1], [0.2], [0.3], [0.4]],
        "action": ["remove", "tap", "tap", "remove", "tap"],
        "param.force": force,
        "end.visible": [0, 1, 0, 0, 1],
        "end.pos": [[0.0], [0.4], [2.4], [0.3], [1.9]],
    }


def test_training_rows_file_each_row_under_its_values_cell():
    enc = training_rows(TAP, tap_rows())
    # two equidistant cells on [0, 10]: [0, 5) and [5, 10]; 0 where tap is not played
    assert enc["cluster.force"].tolist() == [0, 0, 1, 0, 0]


@pytest.mark.parametrize(
    "edit, match",
    [
        ({"param.force": [[1.0]] * 5}, "row 0 has action 'remove', which does not use"),
        ({"param.force": [[float("nan")]] * 5}, "row 1 has action 'tap', which uses"),
        ({"end.pos": [[0.0], [np.nan], [0.0], [0.0], [0.0]]}, "end.pos"),
    ],
)
def test_training_rows_refuse_a_row_against_the_rules(edit, match):
    with pytest.raises(ValueError, match=match):
        training_rows(TAP, tap_rows() | edit)


def test_training_rows_name_a_missing_site():
    rows = tap_rows()
    del rows["end.pos"]
    with pytest.raises(ValueError, match=r"missing \['end.pos'\]"):
        training_rows(TAP, rows)


@pytest.mark.parametrize(
    "setting",
    [
        {"steps": 0},
        {"steps": 2.0},
        {"steps": True},
        {"tol": 0.0},
        {"lr": float("inf")},
        {"pseudo_count": -1e-3},
        {"l2": np.float32(0.1)},
        {"min_variance": float("nan")},
    ],
)
def test_check_settings_names_a_bad_setting(setting):
    ((name, value),) = setting.items()
    with pytest.raises(ValueError, match=rf"^{name} must be .*got {re.escape(repr(value))}$"):
        check_settings(**setting)


def test_check_settings_accepts_python_and_numpy_counts():
    check_settings(steps=np.int64(3), tol=1e-9, lr=1, pseudo_count=0, l2=0.0)


def test_refuse_adaptive_names_the_parameter():
    adaptive = EffectNetwork(
        (Continuous("pos", 1),),
        ("tap",),
        (Parameter("force", 0.0, 10.0, 2, ("tap",), "pos", layout="adaptive"),),
    )
    refuse_adaptive(TAP, "fit")
    with pytest.raises(ValueError, match=r"fit_x files .* \['force'\] are adaptive"):
        refuse_adaptive(adaptive, "fit_x")


def test_mask_values_take_bools_or_0_and_1_only():
    assert mask_values("action", [1, 0, 1]).tolist() == [True, False, True]
    assert mask_values("action", torch.tensor([1.0, 0.0])).dtype == torch.bool
    for bad, match in (([0.5, 1], "other than 0 and 1"), (["no"], "dtype"), ([[1, 0]], "shape")):
        with pytest.raises(ValueError, match=rf"masks\['action'\].*{match}"):
            mask_values("action", bad)


def test_row_masks_check_the_site_and_the_length():
    assert row_masks(TAP, None, 5) == {}
    with pytest.raises(ValueError, match="'initial.pos' is continuous"):
        row_masks(TAP, {"initial.pos": [True] * 5}, 5)
    with pytest.raises(ValueError, match=r"masks\['action'\] has 4 rows, the data 5"):
        row_masks(TAP, {"action": [True] * 4}, 5)
    with pytest.raises(ValueError, match="no such site"):
        row_masks(TAP, {"nothing": [True] * 5}, 5)


def test_missing_masks_keep_the_gaps_and_refuse_a_cluster():
    full = {"action": [True] * 5, "end.visible": [True, False, True, True, True]}
    assert list(missing_masks(TAP, full, 5)) == ["end.visible"]
    with pytest.raises(ValueError, match="never missing on its own"):
        missing_masks(TAP, {"cluster.force": [False] * 5}, None)


def test_ignore_missing_puts_a_declared_state_where_a_value_is_missing():
    rows = tap_rows() | {"action": [None, "tap", "tap", "remove", "??"]}
    mask = [False, True, True, True, False]
    out = ignore_missing(TAP, rows, {"action": mask})
    assert list(out["action"]) == ["remove", "tap", "tap", "remove", "remove"]
    assert rows["action"][0] is None  # the caller's rows are not changed
    training_rows(TAP, out, unknown_action=~mask_values("action", mask))
