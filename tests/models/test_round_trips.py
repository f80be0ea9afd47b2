"""Round trips through pgmpy and BIF on random discrete networks, against pgmpy's own
variable elimination to 1e-12: the numbers a file or a pgmpy network holds are the ones
our queries use."""

from __future__ import annotations

import itertools

import pytest
import torch
from effect_networks.inference import infer_action, predict
from effect_networks.models import (
    Discrete,
    EffectNetwork,
    from_pgmpy,
    random_params,
    read_bif,
    to_pgmpy,
    write_bif,
)
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.networks import counts_of, declared_networks, pgmpy_marginal

pytest.importorskip("pgmpy")
from pgmpy.inference import VariableElimination  # noqa: E402
from pgmpy.readwrite import BIFReader  # noqa: E402

TOL = 1e-12


def assert_answers_as_pgmpy(net, params, model, text: bool = False) -> None:
    """Every end feature's marginal given every initial state and action, and the action
    posterior given the initial state and one end feature, against pgmpy on ``model``."""
    ve = VariableElimination(model)
    show = str if text else (lambda v: v)  # a model read from BIF names its states in text
    initial = [f for f in net.features if f.initial]
    for states in itertools.product(*(f.states for f in initial)):
        given_initial = {f"initial.{f.name}": show(s) for f, s in zip(initial, states, strict=True)}
        rows = {f"initial.{f.name}": [s] for f, s in zip(initial, states, strict=True)}
        for action in net.actions:
            ours = predict(net, params, rows | {"action": [action]})
            for f in net.features:
                names, theirs = pgmpy_marginal(
                    ve, f"end.{f.name}", given_initial | {"action": action}
                )
                order = [f.states.index(_label(f, n)) for n in names]
                torch.testing.assert_close(
                    ours.discrete[f.name][0][order], theirs, atol=TOL, rtol=0
                )
        f = net.features[-1]
        for end in f.states:
            post = infer_action(net, params, rows | {f"end.{f.name}": [end]})
            names, theirs = pgmpy_marginal(
                ve, "action", given_initial | {f"end.{f.name}": show(end)}
            )
            order = [net.actions.index(n) for n in names]
            torch.testing.assert_close(post.probs[0][order], theirs, atol=TOL, rtol=0)


def _label(feature, name):
    """pgmpy's state name of ``feature`` as its declared label (BIF gives text)."""
    return next(s for s in feature.states if s == name or str(s) == str(name))


@settings(max_examples=8, deadline=None, derandomize=True)
@given(net=declared_networks(), seed=st.integers(0, 10_000))
def test_to_and_from_pgmpy_answer_as_pgmpy_to_1e12(net, seed):
    params = random_params(net, seed)
    model, _ = to_pgmpy(net, params)
    assert_answers_as_pgmpy(net, params, model)
    net2, params2 = from_pgmpy(model, n=counts_of(params))
    assert net2.identity() == net.identity()
    for site, cpd in params.cpds.items():
        torch.testing.assert_close(params2[site].probs, cpd.probs, atol=TOL, rtol=0)
    assert_answers_as_pgmpy(net2, params2, model)


def test_read_bif_answers_as_pgmpy_on_the_same_file_to_1e12(tmp_path):
    net = EffectNetwork(
        (Discrete("lid", ("on", "off")), Discrete("count", (0, 1, 2), initial=False)),
        ("fill", "drink"),
        parents={"end.count": ("initial.lid", "action"), "end.lid": ("initial.lid", "end.count")},
    )
    path = write_bif(tmp_path / "net.bif", net, random_params(net, 5))
    states = {f.name: f.states for f in net.features}
    net2, params2 = read_bif(path, n=1, states=states, order=["lid", "count"])
    assert net2.identity() == net.identity()
    assert_answers_as_pgmpy(net2, params2, BIFReader(path=str(path)).get_model(), text=True)
