"""Forward questions (``predict``, ``imitation_check``): the compiled surface has no
tables for them yet and answers with the traced query, on the same cases."""

import pytest
import torch
from effect_networks.inference import imitation_check, predict
from effect_networks.models.declaration import DTYPE
from effect_networks.models.evidence import Evidence

from effect_networks import inference
from tests.helpers import discrete_network, random_params
from tests.networks import NET
from tests.questions import TracedCalls, assert_same_answer

pytestmark = pytest.mark.filterwarnings(
    "ignore::effect_networks.inference.queries.implausibility.OutsideTrainingData"
)

DISCRETE = discrete_network([3, 2], 4)
DISCRETE_PARAMS = random_params(DISCRETE, 4, unseen=0.3)
MIXED_PARAMS = random_params(NET, 11)


def discrete_rows(n, sites=("initial.f0", "initial.f1", "action", "end.f0")):
    g = torch.Generator().manual_seed(n)
    return DISCRETE.encode_indices(
        {s: torch.randint(0, DISCRETE.site(s).size, (n,), generator=g) for s in sites}
    )


def mixed_rows(n, **extra):
    g = torch.Generator().manual_seed(n)
    return {
        "initial.visible": [True, False] * (n // 2) + [True] * (n % 2),
        "initial.pos": torch.randn(n, 2, generator=g, dtype=DTYPE),
        "action": ["tap"] * n,
        "end.pos": torch.randn(n, 2, generator=g, dtype=DTYPE),
    } | extra


# (network, parameters, evidence)
CASES = {
    "discrete": (DISCRETE, DISCRETE_PARAMS, discrete_rows(6)),
    "discrete, initial state unknown": (
        DISCRETE,
        DISCRETE_PARAMS,
        discrete_rows(6, ("initial.f1", "action", "end.f0")),
    ),
    "discrete, empty batch": (DISCRETE, DISCRETE_PARAMS, discrete_rows(0)),
    "mixed, parameter unknown": (NET, MIXED_PARAMS, mixed_rows(4)),
    "mixed, parameter given": (
        NET,
        MIXED_PARAMS,
        mixed_rows(4, **{"param.force": [[1.0], [4.0], [9.0], [2.5]]}),
    ),
    "mixed, empty batch": (NET, MIXED_PARAMS, mixed_rows(0)),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_predict_through_the_surface_is_the_traced_query(case, monkeypatch):
    net, params, evidence = CASES[case]
    ends = [site for site in evidence if site.startswith("end.")]
    if isinstance(evidence, Evidence):
        evidence = evidence.without(*ends)
    else:
        evidence = {k: v for k, v in evidence.items() if k not in ends}
    traced_calls = TracedCalls(monkeypatch, "predict")
    answer = inference.compile(net, params).predict(evidence, implausible_below=1e-3)
    assert traced_calls.calls == 1
    assert_same_answer(answer, predict(net, params, evidence, implausible_below=1e-3))


@pytest.mark.parametrize("case", sorted(CASES))
def test_imitation_check_through_the_surface_is_the_traced_query(case, monkeypatch):
    net, params, evidence = CASES[case]
    traced_calls = TracedCalls(monkeypatch, "imitation_check")
    answer = inference.compile(net, params).imitation_check(evidence, n_samples=64, seed=3)
    assert traced_calls.calls == 1
    assert_same_answer(answer, imitation_check(net, params, evidence, n_samples=64, seed=3))
