"""The exact planner: dynamic programming against every policy enumerated, policy values."""

import itertools

import pytest
import torch
from effect_networks.inference.sequences.dynamic_programming import exact_plan, policy_value


def test_exact_plan_equals_best_enumerated_policy():
    g = torch.Generator().manual_seed(0)
    s, a, horizon, goal = 3, 2, 2, 0
    t = torch.rand(s, a, s, generator=g, dtype=torch.float64)
    t = t / t.sum(-1, keepdim=True)
    plan = exact_plan(t, goal, horizon)
    best = torch.zeros(s, dtype=torch.float64)
    for choice in itertools.product(range(a), repeat=s * horizon):
        pol = torch.tensor(choice).reshape(horizon, s)  # pol[k, s]: action with k+1 steps left
        for start in range(s):
            dist = torch.zeros(s, dtype=torch.float64)
            dist[start] = 1
            reached = float(dist[goal])
            dist[goal] = 0
            for k in reversed(range(horizon)):
                dist = torch.einsum("s,st->t", dist, t[torch.arange(s), pol[k]])
                reached += float(dist[goal])
                dist[goal] = 0
            best[start] = max(best[start], reached)
    torch.testing.assert_close(plan.value[horizon], best)


def test_exact_plan_rejects_bad_input():
    with pytest.raises(ValueError, match="shape"):
        exact_plan(torch.ones(2, 2), 0, 1)
    with pytest.raises(ValueError, match="goal index"):
        exact_plan(torch.ones(2, 1, 2) / 2, 5, 1)


def test_policy_value_of_the_optimal_policy_is_the_optimum():
    g = torch.Generator().manual_seed(1)
    t = torch.rand(4, 3, 4, generator=g, dtype=torch.float64)
    t = t / t.sum(-1, keepdim=True)
    plan = exact_plan(t, 2, 3)
    torch.testing.assert_close(policy_value(t, plan.policy, 2, 3), plan.value)


def test_policy_value_on_a_hand_made_chain():
    # 0 -a0-> 1 with 0.5 (else stays); 1 -a0-> 2 (goal) surely; a1 never moves
    t = torch.zeros(3, 2, 3, dtype=torch.float64)
    t[0, 0, 0] = t[0, 0, 1] = 0.5
    t[1, 0, 2] = 1.0
    t[:, 1] = torch.eye(3, dtype=torch.float64)
    t[2, 0, 2] = 1.0
    policy = torch.tensor([[-1, -1, -1], [0, 0, 0], [0, 0, 0], [0, 0, 0]])
    value = policy_value(t, policy, 2, 3)
    # from 0: reach 1 by step k then 2 at k+1: within 2 steps 0.5, within 3 steps 0.75
    assert value[2, 0].item() == 0.5 and value[3, 0].item() == 0.75
    no_action = policy.clone()
    no_action[1:, 1] = -1  # state 1 has no action: 0 can never get through
    assert policy_value(t, no_action, 2, 3)[3, 0].item() == 0.0
    with pytest.raises(ValueError, match="policy must have shape"):
        policy_value(t, policy[:2], 2, 3)


def test_a_goal_mask_of_one_state_is_that_state_and_of_two_reaches_either():
    g = torch.Generator().manual_seed(1)
    t = torch.rand(4, 3, 4, generator=g, dtype=torch.float64)
    t = t / t.sum(-1, keepdim=True)
    one = torch.tensor([False, False, True, False])
    by_index, by_mask = exact_plan(t, 2, 3), exact_plan(t, one, 3)
    torch.testing.assert_close(by_mask.value, by_index.value)
    assert torch.equal(by_mask.policy, by_index.policy)
    torch.testing.assert_close(policy_value(t, by_index.policy, one, 3), by_index.value)
    # two goal states: one step from s reaches either with P(s' in goal | s, a)
    two = torch.tensor([False, True, True, False])
    step = exact_plan(t, two, 1)
    torch.testing.assert_close(step.value[1, ~two], t[~two][:, :, two].sum(-1).amax(-1))
    with pytest.raises(ValueError, match="goal mask"):
        exact_plan(t, torch.tensor([True, False]), 1)
