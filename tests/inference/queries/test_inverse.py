"""The inverse model (``parameter_for_effect``): the compiled surface answers with the
traced query (its candidates scored in closed form where it can), on the same cases."""

import pytest
import torch
from effect_networks.inference import parameter_for_effect
from effect_networks.models.declaration import DTYPE

from effect_networks import inference
from tests.helpers import random_params
from tests.networks import NET, throwing
from tests.questions import TracedCalls, assert_same_answer

PARAMS = random_params(NET, 11)
THROWING, THROWING_PARAMS = throwing()


def pushes(n):
    g = torch.Generator().manual_seed(n)
    return {
        "initial.visible": [True, False] * (n // 2) + [True] * (n % 2),
        "initial.pos": torch.randn(n, 2, generator=g, dtype=DTYPE),
        "action": ["push"] * n,
        "end.pos": torch.randn(n, 2, generator=g, dtype=DTYPE),
    }


CASES = {
    "one feature": (NET, PARAMS, "force", pushes(5)),
    "one feature, empty batch": (NET, PARAMS, "force", pushes(0)),
    "two features": (
        THROWING,
        THROWING_PARAMS,
        "aim",
        {
            "initial.land": [[0.1, -0.2], [0.3, 0.0]],
            "initial.roll": [[0.3], [-0.1]],
            "action": ["throw", "throw"],
            "end.land": [[0.5, 1.0], [0.2, 0.4]],
            "end.roll": [[0.2], [0.7]],
        },
    ),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_the_inverse_model_through_the_surface_is_the_traced_query(case, monkeypatch):
    net, params, parameter, evidence = CASES[case]
    traced_calls = TracedCalls(monkeypatch, "parameter_for_effect")
    answer = inference.compile(net, params).parameter_for_effect(parameter, evidence)
    assert traced_calls.calls == 1
    assert_same_answer(answer, parameter_for_effect(net, params, parameter, evidence))
