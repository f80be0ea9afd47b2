"""The tables the free queries keep per (network, parameters): never a stale answer."""

from __future__ import annotations

import torch
from effect_networks.inference import infer_action
from effect_networks.inference.queries import action, kept_tables
from effect_networks.models import Discrete, EffectNetwork, random_params


def _net(k: int = 4) -> EffectNetwork:
    return EffectNetwork(
        tuple(Discrete(f"f{i}", (0, 1)) for i in range(k)),
        ("push", "lift", "wait"),
        parents={f"end.f{i}": (f"initial.f{i}", "action") for i in range(k)},
    )


def _rows(net: EffectNetwork, n: int, seed: int, *, initial: bool = False):
    g = torch.Generator().manual_seed(seed)
    sites = [f"end.f{i}" for i in range(len(net.features))]
    sites += [f"initial.f{i}" for i in range(len(net.features))] if initial else []
    return net.encode_indices({s: torch.randint(0, 2, (n,), generator=g) for s in sites})


def _fields(a):
    return (a.probs, a.log_evidence, a.unseen, a.best, a.implausible)


def _traced_each(net, params, evidence, monkeypatch):
    with monkeypatch.context() as m:
        m.setattr(action, "tables_for", lambda *_: None)
        return [
            infer_action(net, params, evidence.rows(slice(i, i + 1)))
            for i in range(evidence.n_rows)
        ]


def _same_answers(a, b):
    """Equal to rounding in the probabilities, exactly in what is chosen from them."""
    for x, y in zip(_fields(a)[:3], _fields(b)[:3], strict=True):
        torch.testing.assert_close(x, y, atol=1e-12, rtol=0)
    assert torch.equal(a.best, b.best) and a.best_names == b.best_names
    assert torch.equal(a.implausible, b.implausible)


def test_one_row_loop_equals_the_traced_rows(monkeypatch):
    for initial in (False, True):
        net = _net()
        params = random_params(net, 3)
        evidence = _rows(net, 24, 1, initial=initial)
        kept = [infer_action(net, params, evidence.rows(slice(i, i + 1))) for i in range(24)]
        assert kept_tables.tables_for(net, params).plans  # the tables answered
        for a, b in zip(kept, _traced_each(net, params, evidence, monkeypatch), strict=True):
            _same_answers(a, b)


def test_a_larger_batch_is_traced_bit_for_bit(monkeypatch):
    net = _net()
    params = random_params(net, 8)
    evidence = _rows(net, kept_tables.FEW_ROWS + 1, 5, initial=True)
    got = infer_action(net, params, evidence)
    assert id(params) not in kept_tables._KEPT  # no tables were built for it
    with monkeypatch.context() as m:
        m.setattr(action, "tables_for", lambda *_: None)
        traced = infer_action(net, params, evidence)
    for x, y in zip(_fields(got), _fields(traced), strict=True):
        assert torch.equal(x, y)


def test_one_row_loop_equals_the_batch():
    net = _net()
    params = random_params(net, 4)
    evidence = _rows(net, 30, 2)
    batch = infer_action(net, params, evidence)
    for i in range(30):
        one = infer_action(net, params, evidence.rows(slice(i, i + 1)))
        for x, y in zip(_fields(one), _fields(batch), strict=True):
            torch.testing.assert_close(x, y[i : i + 1], atol=1e-12, rtol=0)
        assert one.best_names == batch.best_names[i : i + 1]


def test_edited_or_new_parameters_give_fresh_answers(monkeypatch):
    net = _net()
    params = random_params(net, 5)
    evidence = _rows(net, 8, 3)
    one = evidence.rows(slice(0, 1))
    before = infer_action(net, params, one)
    infer_action(net, params, one)  # from the kept tables
    table = params["end.f0"].probs
    with torch.no_grad():
        table.copy_(table.flip(-1))  # edited in place
    after = infer_action(net, params, one)
    (fresh,) = _traced_each(net, params, one, monkeypatch)
    assert not torch.equal(before.probs, after.probs)
    _same_answers(after, fresh)
    other = random_params(net, 6)  # new parameters
    (expected,) = _traced_each(net, other, one, monkeypatch)
    _same_answers(infer_action(net, other, one), expected)


def test_tables_are_dropped_with_their_parameters():
    import gc

    net = _net()
    params = random_params(net, 7)
    infer_action(net, params, _rows(net, 1, 4))
    key = id(params)
    assert key in kept_tables._KEPT
    del params
    gc.collect()
    assert key not in kept_tables._KEPT
