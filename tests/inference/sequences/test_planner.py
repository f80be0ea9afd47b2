"""plan: exact finite-horizon planning over a network's states, against brute force over
every action sequence (open loop) and every policy (closed loop), and against a
dynamic programme written out by hand on a door world."""

from __future__ import annotations

import itertools

import pytest
import torch
from effect_networks.inference import fit
from effect_networks.inference.sequences.dynamic_programming import policy_value
from effect_networks.inference.sequences.planner import plan, plan_on
from effect_networks.inference.sequences.transition_tables import transitions
from effect_networks.models import Discrete, EffectNetwork, random_params
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st


def forward(probs, goal, start, choose, horizon):
    """P(goal reached within ``horizon``) playing ``choose(t, s)`` from ``start``, by
    pushing the state distribution forward (the goal absorbing)."""
    p = start.clone()
    for t in range(horizon):
        nxt = torch.where(goal, p, 0.0)
        for s in range(len(p)):
            if not goal[s] and p[s] > 0:
                a = choose(t, s)
                if a >= 0:
                    nxt = nxt + p[s] * probs[s, a]
        p = nxt
    return float(p[goal].sum())


@st.composite
def small_worlds(draw):
    k = draw(st.integers(2, 3))
    two = draw(st.booleans()) and k == 2
    features = (Discrete("f", tuple(f"s{i}" for i in range(k))),)
    if two:
        features += (Discrete("g", ("a", "b")),)
    n_actions = draw(st.integers(2, 3))
    net = EffectNetwork(features=features, actions=tuple(f"a{i}" for i in range(n_actions)))
    params = random_params(net, draw(st.integers(0, 2**16)))
    model = transitions(net, params)
    s = len(model.space)
    goal = torch.tensor(draw(st.lists(st.booleans(), min_size=s, max_size=s)))
    if not bool(goal.any()) or bool(goal.all()):
        goal = torch.arange(s) == draw(st.integers(0, s - 1))
    free = int((~goal).sum())
    h_max = max(h for h in (1, 2, 3) if n_actions ** (free * h) <= 4096 or h == 1)
    horizon = draw(st.integers(1, h_max))
    start = draw(st.integers(0, s - 1))
    return model, goal, start, horizon


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(small_worlds())
def test_plan_is_the_best_policy_and_beats_every_action_sequence(world):
    model, goal, start, horizon = world
    s, a = len(model.space), len(model.actions)
    result = plan_on(model, start, lambda labels: bool(goal[model.space.index_of(labels)]), horizon)
    start_dist = torch.zeros(s, dtype=torch.float64)
    start_dist[start] = 1
    # closed loop: every deterministic policy (state, steps left) -> action
    free = [i for i in range(s) if not goal[i]]
    best = 0.0
    for choice in itertools.product(range(a), repeat=len(free) * horizon):
        table = {
            (t, f): choice[t * len(free) + j] for t in range(horizon) for j, f in enumerate(free)
        }
        best = max(
            best,
            forward(
                model.probs, goal, start_dist, lambda t, x, table=table: table[(t, x)], horizon
            ),
        )
    assert result.success == pytest.approx(best, abs=1e-12)
    own = forward(
        model.probs, goal, start_dist, lambda t, x: int(result.policy[horizon - t, x]), horizon
    )
    assert own == pytest.approx(best, abs=1e-12)
    # open loop: every action sequence; the closed loop can only do better
    open_best = max(
        forward(model.probs, goal, start_dist, lambda t, x, seq=seq: seq[t], horizon)
        for seq in itertools.product(range(a), repeat=horizon)
    )
    assert result.success >= open_best - 1e-12
    if horizon == 1:
        assert result.success == pytest.approx(open_best, abs=1e-12)
    # the most likely path: every state sequence under the policy, brute force
    top = 0.0
    for k in range(horizon + 1):
        for seq in itertools.product(range(s), repeat=k):
            states = (start, *seq)
            if not goal[states[-1]] or any(goal[x] for x in states[:-1]):
                continue
            p = 1.0
            for t in range(k):
                act = int(result.policy[horizon - t, states[t]])
                p *= float(model.probs[states[t], act, states[t + 1]]) if act >= 0 else 0.0
            top = max(top, p)
    assert result.path_probability == pytest.approx(top, abs=1e-12)
    if top > 0:
        labels = result.path
        p = 1.0
        for i in range(0, len(labels) - 1, 2):
            p *= model.prob(labels[i], labels[i + 1], labels[i + 2])
        assert p == pytest.approx(top, rel=1e-9)
        assert goal[model.space.index_of(labels[-1])]


# ---------------------------------------------------------------- the door world
DOOR = ("closed", "open")
LOCK = ("locked", "unlocked")
ACTIONS = ("unlock", "push", "wait")


def door_world():
    """Unlock works 9 times in 10; push opens an unlocked closed door 4 times in 5 and a
    locked one never; wait changes nothing. Rows in exactly those proportions."""
    net = EffectNetwork(features=(Discrete("door", DOOR), Discrete("lock", LOCK)), actions=ACTIONS)
    rows = {k: [] for k in ("initial.door", "initial.lock", "action", "end.door", "end.lock")}

    def add(door, lock, action, end_door, end_lock, times):
        for key, v in zip(rows, (door, lock, action, end_door, end_lock), strict=True):
            rows[key] += [v] * times

    for door in DOOR:
        for lock in LOCK:
            add(door, lock, "wait", door, lock, 10)
            add(door, lock, "unlock", door, "unlocked", 9 if lock == "locked" else 10)
            if lock == "locked":
                add(door, lock, "unlock", door, "locked", 1)
            if door == "closed" and lock == "unlocked":
                add(door, lock, "push", "open", lock, 8)
                add(door, lock, "push", "closed", lock, 2)
            else:
                add(door, lock, "push", door, lock, 10)
    return net, fit(net, rows).params


def hand_dp(t, horizon):
    """The dynamic programme written out over labels: V_h(s) = max_a sum P(s'|s,a) V(s')."""
    states = [(d, lk) for d in DOOR for lk in LOCK]
    value = {s: float(s[0] == "open") for s in states}
    policy = {}
    for h in range(1, horizon + 1):
        new = {}
        for s in states:
            if s[0] == "open":
                new[s] = 1.0
                continue
            q = {a: sum(t.prob(s, a, n) * value[n] for n in states) for a in ACTIONS}
            policy[(s, h)] = max(ACTIONS, key=lambda a: (q[a], -ACTIONS.index(a)))
            new[s] = q[policy[(s, h)]]
        value = new
    return value, policy


@pytest.fixture(scope="module")
def door():
    return door_world()


@pytest.mark.parametrize("horizon", [1, 2, 3])
def test_the_door_world_against_a_hand_written_dynamic_programme(door, horizon):
    net, params = door
    result = plan(net, params, ("closed", "locked"), {"door": "open"}, horizon)
    value, policy = hand_dp(result.model, horizon)
    for s, v in value.items():
        assert result.probability(s) == pytest.approx(v, abs=1e-12)
    assert result.to_dict() == policy
    # and beside the world's nominal numbers (the fitted tables' pseudo-counts aside)
    nominal = {1: 0.0, 2: 0.9 * 0.8, 3: 0.9 * 0.8 + 0.9 * 0.2 * 0.8 + 0.1 * 0.9 * 0.8}
    assert result.success == pytest.approx(nominal[horizon], abs=0.01)
    if horizon >= 2:
        assert result.path == (
            ("closed", "locked"),
            "unlock",
            ("closed", "unlocked"),
            "push",
            ("open", "unlocked"),
        )
        assert result.action(("closed", "unlocked"), 1) == "push"
        assert result.action(("open", "locked")) is None


def test_a_start_in_the_goal_has_succeeded(door):
    net, params = door
    result = plan(net, params, ("open", "locked"), {"door": "open"}, 2)
    assert result.success == 1.0 and result.path == (("open", "locked"),)
    assert result.path_probability == 1.0


def test_a_partial_start_weighs_the_states_it_allows_by_the_initial_tables(door):
    net, params = door
    result = plan(net, params, {"door": "closed"}, {"door": "open"}, 2)
    prior = result.model.prior
    closed = result.model.space.mask({"door": "closed"})
    expected = (prior * closed * result.value[2]).sum() / (prior * closed).sum()
    assert result.success == pytest.approx(float(expected), abs=1e-12)
    assert result.start.sum() == pytest.approx(1.0)


def test_allowed_restricts_the_actions(door):
    net, params = door
    no_unlock = plan(
        net, params, ("closed", "locked"), {"door": "open"}, 3, allowed=["push", "wait"]
    )
    assert set(no_unlock.to_dict().values()) <= {"push", "wait"}
    assert no_unlock.success < 0.01
    mask = torch.tensor([True, False, False])
    only = plan(net, params, ("closed", "unlocked"), {"door": "open"}, 2, allowed=mask)
    assert only.success < 0.01 and set(only.to_dict().values()) == {"unlock"}
    per_state = torch.ones(4, 3, dtype=torch.bool)
    per_state[0] = False  # ('closed', 'locked') may do nothing
    stuck = plan(net, params, ("closed", "locked"), {"door": "open"}, 2, allowed=per_state)
    assert stuck.action(("closed", "locked")) is None and stuck.success == 0.0
    assert stuck.path == ()
    with pytest.raises(ValueError, match="unknown action 'kick'"):
        plan(net, params, ("closed", "locked"), {"door": "open"}, 2, allowed=["kick"])
    with pytest.raises(ValueError, match="horizon"):
        plan(net, params, ("closed", "locked"), {"door": "open"}, 0)
    with pytest.raises(ValueError, match="picks no state"):
        plan(net, params, ("closed", "locked"), lambda s: False, 2)


def test_a_plan_scored_under_another_model_with_policy_value(door):
    """Plan on one model, score on another: policy_value with the plan's policy equals the
    forward push of the state distribution under the other model."""
    net, params = door
    result = plan(net, params, ("closed", "locked"), {"door": "open"}, 3)
    other = transitions(net, random_params(net, 3))
    value = policy_value(other.probs, result.policy, result.goal, 3)
    for s in range(4):
        start = torch.zeros(4, dtype=torch.float64)
        start[s] = 1
        pushed = forward(
            other.probs, result.goal, start, lambda t, x: int(result.policy[3 - t, x]), 3
        )
        assert float(value[3, s]) == pytest.approx(pushed, abs=1e-12)


def test_avoid_unseen_keeps_to_configurations_seen_in_training():
    net = EffectNetwork(features=(Discrete("door", DOOR),), actions=("push", "kick"))
    rows = {
        "initial.door": ["closed"] * 4,
        "action": ["push"] * 4,
        "end.door": ["open", "closed", "closed", "closed"],
    }
    params = fit(net, rows).params
    # "kick" was never tried: its table is the uniform prior, which a plan may prefer
    loose = plan(net, params, ("closed",), {"door": "open"}, 1)
    assert loose.action(("closed",)) == "kick"
    careful = plan(net, params, ("closed",), {"door": "open"}, 1, avoid_unseen=True)
    assert careful.action(("closed",)) == "push"


def test_the_planning_page_runs_and_says_what_its_comments_say():
    """docs/planning.md's snippets run in order; their numbers are what the page says."""
    import re
    from pathlib import Path

    page = Path(__file__).resolve().parents[3] / "docs" / "planning.md"
    namespace: dict = {}
    for code in re.findall(r"^```python\n(.*?)^```", page.read_text(), re.S | re.M):
        exec(compile(code, str(page), "exec"), namespace)  # noqa: S102
    assert namespace["opens"] == pytest.approx(0.8, abs=0.01)
    assert list(namespace["after_push"])[:2] == [("open", "unlocked"), ("closed", "unlocked")]
    assert namespace["chance"] == pytest.approx(
        0.9 * 0.8 + 0.9 * 0.2 * 0.8 + 0.1 * 0.9 * 0.8, abs=0.01
    )
    assert namespace["first"] == "unlock"
    assert namespace["path"] == (
        ("closed", "locked"),
        "unlock",
        ("closed", "unlocked"),
        "push",
        ("open", "unlocked"),
    )
    assert namespace["no_key"].success < 0.9  # without unlock only an unlocked start opens
    assert len(namespace["space"]) == 4
    big = namespace["big"]
    assert (big.route, big.features) == ("projected", ("f0", "f1", "f2", "f3"))


def test_planning_on_the_readme_network():
    """The quick start's network (visible, position; look, remove, tap with a force on the
    position): its one state feature is visible, the position is the given context."""
    import numpy as np
    from effect_networks.models import Continuous, Parameter

    net = EffectNetwork(
        features=(Discrete("visible", (False, True)), Continuous("position", 1)),
        actions=("look", "remove", "tap"),
        parameters=(
            Parameter("force", low=0.0, high=20.0, bins=8, actions=("tap",), affects="position"),
        ),
    )
    rng = np.random.default_rng(0)
    n = 2000
    action = rng.choice(net.actions, n)
    visible = rng.random(n) < 0.7
    position = rng.uniform(-1.0, 1.0, (n, 1))
    force = np.where(action[:, None] == "tap", rng.uniform(0.0, 20.0, (n, 1)), np.nan)
    data = {
        "initial.visible": visible,
        "initial.position": position,
        "action": action,
        "param.force": force,
        "end.visible": visible & (action != "remove"),
        "end.position": position + 0.02 * np.nan_to_num(force) + rng.normal(0.0, 0.01, (n, 1)),
    }
    params = fit(net, data).params
    at = {"position": [0.0]}
    steps = transitions(net, params, given=at)
    assert steps.prob((True,), "remove", (False,)) > 0.99
    route = plan(net, params, {"visible": True}, {"visible": False}, 2, given=at)
    assert route.action((True,)) == "remove" and route.success > 0.99
    assert route.path == ((True,), "remove", (False,))
    per_cluster = transitions(net, params, given=at, parameter_values="clusters")
    assert (
        per_cluster.actions[:3] == ("look", "remove", "tap[force=0]")
        and len(per_cluster.actions) == 10
    )
