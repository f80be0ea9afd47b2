"""The paper's round planner: the paper's arithmetic, a hand-made world with a known plan."""

import pytest
from effect_networks.experiments.round_planner import (
    INTERMEDIATE,
    NO_HIT,
    SUCCESS,
    TOO_MANY,
    Round,
    classify,
    paper_planner,
    success_rates,
)


def test_table_ii_arithmetic_gives_the_papers_rate():
    """Paper Table II: its rows give its 57.13 % (2a and 2b: 5 of 7 each, 71.42 %)."""
    s1, s2a, s2b = frozenset("abc"), frozenset("a"), frozenset("b")
    r1 = Round(
        "1",
        s1,
        3,
        actions=list(range(6)),
        outcomes={SUCCESS: 2, TOO_MANY: 1, NO_HIT: 1},
        intermediate={s2a: 1, s2b: 1},
    )
    r2a = Round("2a", s2a, 1, actions=list(range(7)), outcomes={SUCCESS: 5, TOO_MANY: 2, NO_HIT: 0})
    r2b = Round("2b", s2b, 1, actions=list(range(7)), outcomes={SUCCESS: 5, TOO_MANY: 0, NO_HIT: 2})
    rates = success_rates([r1, r2a, r2b])
    assert rates[1] == pytest.approx(0.7142, abs=1e-4) and rates[2] == pytest.approx(
        0.7142, abs=1e-4
    )
    assert rates[0] == pytest.approx(0.5713, abs=2e-4)


def test_rates_with_a_cycle_solve_the_linear_system():
    a, b = frozenset("xy"), frozenset("xyz")
    ra = Round(
        "a",
        a,
        1,
        actions=[0, 1],
        outcomes={SUCCESS: 1, TOO_MANY: 0, NO_HIT: 0},
        intermediate={b: 1},
    )
    rb = Round(
        "b",
        b,
        2,
        actions=[0, 1],
        outcomes={SUCCESS: 0, TOO_MANY: 1, NO_HIT: 0},
        intermediate={a: 1},
    )
    r_a, r_b = success_rates([ra, rb])
    # r_a = 1/2 + r_b/2, r_b = r_a/2  ->  r_a = 2/3, r_b = 1/3
    assert r_a == pytest.approx(2 / 3) and r_b == pytest.approx(1 / 3)


def test_classify():
    start, goal = frozenset("abcd"), frozenset("ab")
    assert classify(start, goal, frozenset("ab")) == SUCCESS
    assert classify(start, goal, frozenset("a")) == TOO_MANY
    assert classify(start, goal, start) == NO_HIT
    assert classify(start, goal, frozenset("abc")) == INTERMEDIATE


def test_paper_planner_on_a_hand_made_world():
    """Objects a, b, c; goal: only a. Action k removes object k; "bc" removes both but
    misfires from the full state, taking a too. The model proposes what its table says."""
    world = {
        ("abc", "b"): "ac",
        ("abc", "c"): "ab",
        ("abc", "bc"): "",  # misfire: too many
        ("abc", "miss"): "abc",
        ("ab", "b"): "a",
        ("ac", "c"): "a",
    }
    model = {
        ("abc", "a"): ["bc", "miss"],
        ("abc", "ab"): ["c"],
        ("ab", "a"): ["b"],
        ("ac", "a"): ["c"],
    }

    def propose(state, goal):
        return model.get(("".join(sorted(state)), "".join(sorted(goal))), [])

    def play(state, action):
        return frozenset(world[("".join(sorted(state)), action)])

    rounds, rate = paper_planner(frozenset("abc"), frozenset("a"), propose, play)
    first = rounds[0]
    assert first.outcomes == {SUCCESS: 0, TOO_MANY: 1, NO_HIT: 1}
    assert len(rounds) == 1 and rate == 0.0
    # with only the intermediate goal available, the plan goes through "ab"
    model[("abc", "a")] = []
    rounds, rate = paper_planner(frozenset("abc"), frozenset("a"), propose, play)
    assert [sorted(r.state) for r in rounds] == [["a", "b", "c"], ["a", "b"]]
    assert rounds[0].intermediate == {frozenset("ab"): 1} and rate == 1.0


def test_paper_planner_rejects_a_goal_that_is_not_a_subset():
    with pytest.raises(ValueError, match="subset"):
        paper_planner(frozenset("a"), frozenset("b"), lambda s, g: [], lambda s, a: s)
