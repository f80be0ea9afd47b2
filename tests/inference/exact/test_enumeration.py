"""The traced sums' engine: small queries on one torch thread, the caller's setting kept."""

from __future__ import annotations

import effect_networks.inference.exact.enumeration as enumeration
import torch
from effect_networks.inference import infer_action
from effect_networks.models import random_params

from tests.networks import sparse_network


def test_a_small_query_runs_on_one_thread_and_gives_the_caller_s_setting_back(monkeypatch):
    net = sparse_network(6)
    params = random_params(net, 0)
    ev = net.encode_indices({f"end.f{i}": torch.zeros(50, dtype=torch.long) for i in range(6)})
    before = torch.get_num_threads()
    seen = []
    real = torch.set_num_threads
    monkeypatch.setattr(torch, "set_num_threads", lambda n: (seen.append(n), real(n))[1])
    try:
        real(2)
        got = infer_action(net, params, ev)
        assert torch.get_num_threads() == 2 and 1 in seen and seen[-1] == 2
        with enumeration.one_thread_below(enumeration.SMALL_WORK + 1):
            assert torch.get_num_threads() == 2  # a large query keeps the caller's threads
        real(1)
        assert torch.equal(infer_action(net, params, ev).probs, got.probs)
    finally:
        real(before)
