"""The deprecated ``inference.evaluation`` path: it warns and hands out the very objects of
:mod:`experiments.evaluation`, where the scoring and its tests live."""

import importlib
import sys

import pytest

import experiments.evaluation


def test_old_path_warns_and_reexports_the_public_names():
    sys.modules.pop("inference.evaluation", None)
    with pytest.warns(DeprecationWarning, match="experiments.evaluation"):
        old = importlib.import_module("inference.evaluation")
    assert old.__all__ == experiments.evaluation.__all__
    for name in experiments.evaluation.__all__:
        assert getattr(old, name) is getattr(experiments.evaluation, name), name
