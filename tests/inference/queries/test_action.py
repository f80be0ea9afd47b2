"""Which action was executed: the traced query and the compiled one
(``inference.compile(net, params).infer_action``) on the same cases, equal answers."""

import pytest
import torch
from effect_networks.inference import infer_action
from effect_networks.models.declaration import DTYPE

from effect_networks import inference
from tests.helpers import discrete_network, random_params
from tests.networks import NET
from tests.questions import TracedCalls, assert_same_answer

DISCRETE = discrete_network([3, 2], 4)
PARAMS = random_params(DISCRETE, 4, unseen=0.3)  # some configurations never seen


def rows(sites, n, seed=0):
    g = torch.Generator().manual_seed(seed)
    sizes = {s: DISCRETE.site(s).size for s in sites}
    return DISCRETE.encode_indices(
        {s: torch.randint(0, k, (n,), generator=g) for s, k in sizes.items()}
    )


EVERY_SITE = ("initial.f0", "initial.f1", "end.f0", "end.f1")
CASES = {
    "initial and end observed": (rows(EVERY_SITE, 9), {}),
    "initial state unknown": (rows(("initial.f0", "end.f0", "end.f1"), 9, 1), {}),
    "end state in part": (rows(("initial.f0", "initial.f1", "end.f1"), 9, 2), {}),
    "no end state": (rows(("initial.f0", "initial.f1"), 5, 3), {}),
    "one row": (rows(EVERY_SITE, 1, 4), {}),
    "one row, labels": ({"initial.f0": [2], "initial.f1": [0], "end.f0": [1]}, {}),
    "allowed by name": (rows(EVERY_SITE, 9, 5), {"allowed": ["a1", "a3"]}),
    "allowed per row": (
        rows(("initial.f0", "end.f1"), 4, 6),
        {
            "allowed": torch.tensor(
                [[True, False, True, False]] * 2 + [[False, True, True, True]] * 2
            )
        },
    ),
    "unseen actions not avoided": (rows(EVERY_SITE, 9, 7), {"avoid_unseen": False}),
    "a strict threshold": (rows(EVERY_SITE, 9, 8), {"implausible_below": 0.2}),
    "empty batch": (rows(EVERY_SITE, 0), {}),
    "empty batch, initial state unknown": (rows(("end.f0",), 0), {}),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_compiled_equals_traced(case, monkeypatch):
    evidence, options = CASES[case]
    traced_calls = TracedCalls(monkeypatch, "infer_action")
    compiled = inference.compile(DISCRETE, PARAMS).infer_action(evidence, **options)
    assert traced_calls.calls == 0  # answered from the tables
    assert_same_answer(compiled, infer_action(DISCRETE, PARAMS, evidence, **options))


def test_the_cases_reach_unseen_configurations_and_the_implausible_flag():
    """The cases are not all easy: some answer rests on an unseen configuration, and the
    strict threshold flags some row and passes another."""
    evidence, options = CASES["a strict threshold"]
    answer = infer_action(DISCRETE, PARAMS, evidence, **options)
    assert 0 < int(answer.implausible.sum()) < len(answer.implausible)
    evidence, _ = CASES["initial and end observed"]
    assert bool((infer_action(DISCRETE, PARAMS, evidence).unseen > 0.5).any())


@pytest.mark.parametrize("n", [3, 0])
def test_a_continuous_network_falls_back_to_the_traced_query(n, monkeypatch):
    params = random_params(NET, 2)
    evidence = {
        "initial.visible": [True, False, True][:n],
        "initial.pos": torch.tensor([[0.1, 0.2], [0.0, -0.3], [1.0, 0.5]], dtype=DTYPE)[:n],
        "end.pos": torch.tensor([[0.4, 0.2], [0.0, 0.1], [2.0, 0.4]], dtype=DTYPE)[:n],
    }
    traced_calls = TracedCalls(monkeypatch, "infer_action")
    compiled = inference.compile(NET, params)
    assert compiled.action_tables is None
    answer = compiled.infer_action(evidence, allowed=["tap", "push"])
    assert traced_calls.calls == 1
    assert_same_answer(answer, infer_action(NET, params, evidence, allowed=["tap", "push"]))


def test_the_tables_refuse_what_the_traced_query_refuses_in_the_same_words():
    compiled = inference.compile(DISCRETE, PARAMS)
    for evidence, match in (
        ({"initial.f0": [0], "action": ["a1"]}, "infers it \\(use predict or imitation_check\\)"),
        ({}, "evidence is empty"),
        ({"initial.f0": [5]}, "'initial.f0': value 5 is not one of its states"),
    ):
        with pytest.raises(ValueError, match=match) as traced:
            infer_action(DISCRETE, PARAMS, evidence)
        with pytest.raises(ValueError, match=match) as tables:
            compiled.infer_action(evidence)
        assert str(tables.value) == str(traced.value)


@pytest.mark.parametrize("name", sorted(CASES))
def test_patterns_summed_per_row_answer_bit_for_bit_as_the_summed_table(name, monkeypatch):
    """With the plan budget at 0 every pattern with an observed end site keeps its factors
    and sums them per queried row: the same bits as the table summed once."""
    from effect_networks.inference.queries import action_tables

    evidence, kwargs = CASES[name]
    whole = inference.compile(DISCRETE, PARAMS).infer_action(evidence, **kwargs)
    monkeypatch.setattr(action_tables, "PLAN_BUDGET", 0)
    per_row = inference.compile(DISCRETE, PARAMS)
    rows_ = per_row.infer_action(evidence, **kwargs)
    for field in ("probs", "best", "log_evidence", "unseen", "implausible"):
        assert torch.equal(getattr(rows_, field), getattr(whole, field)), field
    if any(s.startswith("end.") for s in DISCRETE.encode(evidence)):
        assert all(
            isinstance(p.log_table, action_tables._RowSums)
            for p in per_row.action_tables.plans.values()
            if any(s.startswith("end.") for s in p.observed)
        )


def test_a_pattern_whose_table_exceeds_the_budget_is_never_built():
    """Every site observed but the action on two 30-state features and 50 actions: the
    summed table would hold 30**4 * 50 = 40.5 million values (324 MB); the plan holds no
    tensor above the budget and answers as the traced query."""
    from effect_networks.inference.queries import action_tables

    net = discrete_network([30, 30], 50)
    params = random_params(net, 7, unseen=0.3)
    g = torch.Generator().manual_seed(0)
    ev = net.encode_indices(
        {s.name: torch.randint(0, 30, (5,), generator=g) for s in net.sites if s.name != "action"}
    )
    compiled = inference.compile(net, params)
    fast = compiled.infer_action(ev)
    slow = infer_action(net, params, ev)
    torch.testing.assert_close(fast.probs, slow.probs, atol=1e-12, rtol=0)
    torch.testing.assert_close(fast.log_evidence, slow.log_evidence, atol=1e-9, rtol=0)
    torch.testing.assert_close(fast.unseen, slow.unseen, atol=1e-12, rtol=0)
    assert torch.equal(fast.best, slow.best)
    for plan in compiled.action_tables.plans.values():
        for table in (plan.log_table, plan.unseen):
            tensors = table.parts if isinstance(table, action_tables._RowSums) else [table]
            assert all(t is None or t.numel() <= action_tables.PLAN_BUDGET for t in tensors)


@pytest.mark.parametrize("k", [8, 16, 40])
def test_sparse_networks_compiled_by_elimination_equal_traced_and_closed_form(k, monkeypatch):
    """``k`` binary features whose end values depend on their own initial value and the
    action, the initial state unknown: the compiled tables answer as the traced query
    and the closed form (to 1e-12), one row or many, and above a few features never
    build a table over the joint of the initial state (2^40 values at k = 40)."""
    from effect_networks.inference.exact.factored import FactoredPlan

    from tests.networks import closed_form, sparse_network

    net = sparse_network(k)
    params = random_params(net, 3, unseen=0.2)
    observed = k - 2  # two end features unobserved: summed out
    y = torch.randint(0, 2, (6, observed), generator=torch.Generator().manual_seed(k))
    evidence = net.encode_indices({f"end.f{i}": y[:, i] for i in range(observed)})
    post, unseen, _, _ = closed_form(params, k, y, observed)
    compiled = inference.compile(net, params)
    traced_calls = TracedCalls(monkeypatch, "infer_action")
    for rows_ in (slice(0, 6), slice(2, 3)):
        for options in ({}, {"allowed": ["lift", "wait"]}, {"implausible_below": 1e-3 ** (k / 8)}):
            fast = compiled.infer_action(evidence.rows(rows_), **options)
            assert_same_answer(fast, infer_action(net, params, evidence.rows(rows_), **options))
            torch.testing.assert_close(fast.probs, post[rows_], atol=1e-12, rtol=0)
            torch.testing.assert_close(fast.unseen, unseen[rows_], atol=1e-12, rtol=0)
            if "implausible_below" in options and rows_.stop == 6:  # some flagged, not all
                assert 0 < int(fast.implausible.sum()) < 6
    assert traced_calls.calls == 0
    assert bool((unseen > 0.01).any())  # the unseen configurations take part
    plan = compiled.action_tables.plans[frozenset(evidence)]
    if k >= 16:
        assert isinstance(plan, FactoredPlan)
        assert all(t.table.numel() <= 64 for t in plan.parts)


def test_a_query_skips_pyro_s_per_site_checks_and_leaves_validation_as_it_was(monkeypatch):
    """The evidence's encoding and the parameters' check validate a query's inputs once;
    Pyro's checks of every traced site's log-probability would repeat them per call.
    The global validation setting is left as it was."""
    import pyro
    from pyro.poutine import trace_struct

    checked = []
    monkeypatch.setattr(trace_struct, "warn_if_nan", lambda *a, **k: checked.append(a))
    evidence, _ = CASES["initial state unknown"]
    with pyro.validation_enabled(True):
        answer = infer_action(DISCRETE, PARAMS, evidence)
        assert pyro.poutine.util.is_validation_enabled()
        trace = pyro.poutine.trace(lambda: pyro.sample("x", pyro.distributions.Normal(0, 1)))
        trace.get_trace().compute_log_prob()  # validation still on outside the query
    assert len(checked) == 1
    assert bool(torch.isfinite(answer.log_evidence).all())


@pytest.mark.parametrize("n", [1, 9])
def test_a_table_pattern_whose_prior_is_summed_by_elimination(n, monkeypatch):
    """With the thresholds at 0, the end state's pattern (each end feature depends on
    every initial one: its joint does not split) keeps its summed table and answers,
    while the prior of the implausible flag (the initial features and the action,
    independent) is summed per row by elimination: the same answers as traced."""
    from effect_networks.inference.exact import elimination, factored

    monkeypatch.setattr(factored, "SUMMED_TABLE", 0)
    monkeypatch.setattr(elimination, "DENSE_CONFIGURATIONS", 0)
    params = random_params(DISCRETE, 4)  # every configuration seen: one row is read whole
    evidence = rows(("end.f0", "end.f1"), n, 9)
    compiled = inference.compile(DISCRETE, params)
    flags = []
    for below in (0.01, 0.2):
        fast = compiled.infer_action(evidence, implausible_below=below)
        assert_same_answer(fast, infer_action(DISCRETE, params, evidence, implausible_below=below))
        flags += fast.implausible.tolist()
    assert any(flags) and not all(flags)
    plans = compiled.action_tables.plans
    assert plans[frozenset(evidence)].answers is not None
    assert isinstance(plans[frozenset()], factored.FactoredPlan)
