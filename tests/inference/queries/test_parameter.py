"""The parameter posterior: the traced query and the compiled one
(``inference.compile(net, params).infer_parameter``) on the same cases, equal answers;
evidence the compiled query does not read goes to the traced query."""

import re

import pytest
import torch
from effect_networks.inference import infer_parameter
from effect_networks.models import Continuous, EffectNetwork, Parameter, Partial
from effect_networks.models.declaration import DTYPE

from effect_networks import inference
from tests.helpers import random_params
from tests.networks import NET, sliding, throwing
from tests.questions import TracedCalls, assert_same_answer

pytestmark = pytest.mark.filterwarnings(
    "ignore::effect_networks.inference.queries.implausibility.OutsideTrainingData"
)

PARAMS = random_params(NET, 11, unseen=0.3)
THROWING, THROWING_PARAMS = throwing()


def pushes(n, seed=0, **extra):
    """``n`` rows of NET: the initial state, tap or push, and where the object ended."""
    g = torch.Generator().manual_seed(seed)
    return {
        "initial.visible": torch.randint(0, 2, (n,), generator=g).bool().tolist(),
        "initial.pos": torch.randn(n, 2, generator=g, dtype=DTYPE),
        "action": ["tap", "push"] * (n // 2) + ["tap"] * (n % 2),
        "end.pos": 3 * torch.randn(n, 2, generator=g, dtype=DTYPE),
    } | extra


def throws(n, seed=0, ends=("end.land", "end.roll")):
    g = torch.Generator().manual_seed(seed)
    evidence = {
        "initial.land": torch.randn(n, 2, generator=g, dtype=DTYPE),
        "initial.roll": torch.randn(n, 1, generator=g, dtype=DTYPE),
        "action": ["throw"] * n,
    }
    sizes = {"end.land": 2, "end.roll": 1}
    return evidence | {s: 2 * torch.randn(n, sizes[s], generator=g, dtype=DTYPE) for s in ends}


# One action uses the parameter: the queries fill it in when the evidence leaves it out.
GOING = EffectNetwork(
    (Continuous("y", 2, initial=False),),
    ("go", "stay"),
    (Parameter("p", (0.0,), (1.0,), (4,), ("go",), "y"),),
)
GOING_PARAMS = random_params(GOING, 8, unseen=0.3)
GOES = torch.randn(7, 2, generator=torch.Generator().manual_seed(8), dtype=DTYPE)

# (network, parameters, parameter, evidence)
CASES = {
    "the action left out": (GOING, GOING_PARAMS, "p", {"end.y": GOES}),
    "the action left out, one row": (GOING, GOING_PARAMS, "p", {"end.y": GOES[0]}),
    "the action left out, two features": (
        THROWING,
        THROWING_PARAMS,
        "aim",
        {k: v for k, v in throws(5, 2).items() if k != "action"},
    ),
    "one feature": (NET, PARAMS, "force", pushes(10)),
    "one feature, one row": (NET, PARAMS, "force", pushes(1, 1)),
    "one feature, far from the data": (
        NET,
        PARAMS,
        "force",
        pushes(4, 2) | {"end.pos": 1e3 * torch.ones(4, 2, dtype=DTYPE)},
    ),
    "one feature, in part": (
        NET,
        PARAMS,
        "force",
        pushes(6, 3) | {"end.pos": Partial(torch.ones(6, 2, dtype=DTYPE), [True, False])},
    ),
    "one feature, empty batch": (NET, PARAMS, "force", pushes(0)),
    "two features": (THROWING, THROWING_PARAMS, "aim", throws(8)),
    "two features, one observed": (THROWING, THROWING_PARAMS, "aim", throws(8, 1, ("end.roll",))),
    "two features, empty batch": (THROWING, THROWING_PARAMS, "aim", throws(0)),
}


@pytest.mark.parametrize("mixture", [False, True])
@pytest.mark.parametrize("case", sorted(CASES))
def test_compiled_equals_traced(case, mixture, monkeypatch):
    net, params, parameter, evidence = CASES[case]
    traced_calls = TracedCalls(monkeypatch, "infer_parameter")
    compiled = inference.compile(net, params).infer_parameter(parameter, evidence, mixture=mixture)
    assert traced_calls.calls == 0  # answered by the compiled query
    traced = infer_parameter(net, params, parameter, evidence, mixture=mixture)
    assert_same_answer(compiled, traced)


def test_the_cases_reach_unseen_clusters_and_the_implausible_flag():
    *_, evidence = CASES["one feature, far from the data"]
    assert bool(infer_parameter(NET, PARAMS, "force", evidence).implausible.all())
    *_, evidence = CASES["one feature"]
    answer = infer_parameter(NET, PARAMS, "force", evidence)
    assert not bool(answer.implausible.all()) and bool((answer.unseen > 0).any())


# (network, parameters, parameter, evidence): evidence the compiled query does not read
FALLBACKS = {
    "initial state unknown": (
        NET,
        PARAMS,
        "force",
        {k: v for k, v in pushes(6, 4).items() if k != "initial.visible"},
    ),
    "an end feature the parameter does not act on": (
        NET,
        PARAMS,
        "force",
        pushes(6, 5, **{"end.visible": [True, False, True, True, False, True]}),
    ),
    "the parameter given": (NET, PARAMS, "force", pushes(2, 6) | {"param.force": [[1.0], [2.0]]}),
    "a feature two parameters act on": (
        *sliding(),
        "force",
        {
            "initial.pos": [[0.1], [0.4]],
            "action": ["push", "push"],
            "param.angle": [[0.2], [-0.5]],
            "end.pos": [[0.5], [0.9]],
        },
    ),
}


@pytest.mark.parametrize("case", sorted(FALLBACKS))
def test_other_evidence_falls_back_to_the_traced_query(case, monkeypatch):
    net, params, parameter, evidence = FALLBACKS[case]
    traced_calls = TracedCalls(monkeypatch, "infer_parameter")
    compiled = inference.compile(net, params)
    try:
        expected = infer_parameter(net, params, parameter, evidence, mixture=True)
    except ValueError as error:  # the traced query refuses it: so does the surface
        with pytest.raises(ValueError, match=re.escape(str(error))):
            compiled.infer_parameter(parameter, evidence, mixture=True)
    else:
        assert_same_answer(compiled.infer_parameter(parameter, evidence, mixture=True), expected)
    assert traced_calls.calls == 1


def test_a_feature_two_parameters_act_on_has_no_compiled_query():
    net, params, *_ = FALLBACKS["a feature two parameters act on"]
    assert inference.compile(net, params).parameter_query("force") is None
