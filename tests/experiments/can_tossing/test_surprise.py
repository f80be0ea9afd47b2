"""experiments.can_tossing.surprise: the imitation surprise's physics bound on hand-made replays
whose outcome distributions, and so whose AUCs, are known by hand; the operating point."""

import numpy as np
import pytest
import torch
from effect_networks.experiments.can_tossing import surprise as cs
from effect_networks.experiments.cans import Replays
from effect_networks.experiments.evaluation import roc_auc
from effect_networks.sim2d import field_throws, geometry

START, A, B, C = 7, 7, 3, 1  # a start mask and three end configurations, A the start itself
THROWABLE = torch.tensor([field_throws.is_throwable(f, 0) for f in range(geometry.N_FIELDS)])
FIELD = int(np.flatnonzero(THROWABLE.numpy())[len(np.flatnonzero(THROWABLE.numpy())) // 2])


def hand_replays(at_field, elsewhere, beside=None) -> Replays:
    """One start; ``at_field`` replays of ``FIELD``, ``beside`` of the next field in its row,
    ``elsewhere`` of every other field."""
    ends = np.tile(np.array(elsewhere, np.int64), (1, geometry.N_FIELDS, 1))
    ends[0, FIELD] = at_field
    if beside is not None:
        assert THROWABLE[FIELD + 1] and (FIELD + 1) % geometry.N_COLUMNS
        ends[0, FIELD + 1] = beside
    return Replays((START,), ends, np.vectorize(lambda m: bin(m).count("1"))(ends))


def hand_throws(observed, failed, failed_ordinary) -> dict:
    n = len(observed)
    return {
        "start": np.full(n, START),
        "field": np.full(n, FIELD),
        "observed": np.array(observed),
        "failed": np.array(failed),
        "failed_ordinary": np.array(failed_ordinary),
    }


def test_bound_of_two_known_outcome_distributions_by_hand():
    # The world's outcome at the aim: A 3/4, B 1/4, estimated from four replays; surprise A 0,
    # B 3/4 (A is more likely), C 1 (never seen). Successes observe A, A, B; failures C, B.
    sims = hand_replays([A, A, A, B], [A, A, A, B])
    throws = hand_throws([A, A, B, C, B], [0, 0, 0, 1, 1], [0, 0, 0, 1, 0])
    bound = cs.surprise_bound(sims, throws, throws, THROWABLE)
    assert bound["surprise"] == [0.0, 0.0, 0.75, 1.0, 0.75]
    # failed: C beats A, A, B (3); B beats A, A and ties B (2.5) -> 5.5 of 6 pairs
    assert bound["auc"] == pytest.approx(5.5 / 6)
    assert bound["auc_ordinary"] == 1.0  # C above A, A, B, B
    # every field has the same replays: pooling changes nothing, the smallest aim error wins
    assert bound["aim_sigma"] == 0.0 and bound["auc_pooled"] == bound["auc"]
    # from the first two replays (A, A) B was never seen: surprise 1 like C
    half = bound["half_repeats"]
    assert half["repeats"] == 2 and half["auc"] == pytest.approx(5 / 6)
    assert bound["repeats"] == 4


def test_the_pooled_bound_finds_an_outcome_the_neighbours_produce():
    # The aimed field always gives A in its replays, the one beside it C: an observed C is
    # impossible at the aim (surprise 1) but not once the aim error is pooled in.
    sims = hand_replays([A] * 4, [A] * 4, beside=[C] * 4)
    throws = hand_throws([A, C, B], [0, 0, 1], [0, 0, 1])
    table_of = cs.replay_tables(sims)
    exact = cs.surprise_under(table_of, throws, 0.0, THROWABLE)
    pooled = cs.surprise_under(table_of, throws, 1.0, THROWABLE)
    assert exact.tolist() == [0.0, 1.0, 1.0]
    assert pooled[0] == 0.0 and 0.0 < pooled[1] < 1.0 and pooled[2] == 1.0
    bound = cs.surprise_bound(sims, throws, throws, THROWABLE)
    assert bound["auc"] == 0.75 and bound["auc_pooled"] == 1.0 and bound["aim_sigma"] > 0


def test_operating_points_are_chosen_on_the_held_out_draw():
    held = {"failed": np.array([0, 0, 1, 1], bool), "failed_ordinary": np.array([0, 0, 0, 1], bool)}
    scored = {"failed": np.array([0, 1, 1], bool), "failed_ordinary": np.array([0, 0, 0], bool)}
    points = cs.operating_points([0.1, 0.4, 0.5, 0.8], held, [0.2, 0.5, 0.9], scored)
    assert points["failed"] == {"threshold": 0.5, "fpr": 0.0, "tpr": 1.0}
    # one class on the scored draw: the threshold without its rates
    assert points["failed_ordinary"] == {"threshold": 0.8, "fpr": None, "tpr": None}
    assert roc_auc([0.2, 0.5, 0.9], scored["failed"]) == 1.0


def test_own_replay_surprise_by_hand_and_against_the_tail_surprise():
    # row 0: replays A A A B, observed B -> A is more frequent: 3/4; row 1: observed C never
    # replayed -> 1; row 2: observed A, the most frequent -> 0; row 3: A B tie -> 0
    ends = np.array([[A, A, A, B], [A, A, B, B], [A, B, A, A], [A, B, A, B]])
    surprise = cs.own_replay_surprise(ends, np.array([B, C, A, B]))
    assert surprise.tolist() == [0.75, 1.0, 0.0, 0.0]
    # the same as the bound's tables where each row is its own aim
    sims = hand_replays([A, A, A, B], [A, A, A, B])
    throws = hand_throws([A, B, C], [0, 1, 1], [0, 0, 1])
    by_table = cs.surprise_under(cs.replay_tables(sims), throws, 0.0, THROWABLE)
    own = cs.own_replay_surprise(np.tile([A, A, A, B], (3, 1)), throws["observed"])
    assert own.tolist() == by_table.tolist()
    with pytest.raises(ValueError, match="ends must be"):
        cs.own_replay_surprise(np.array([A, B]), np.array([A, B]))


def test_bound_curve_doubles_its_replays_and_scores_both_labels():
    assert cs.curve_counts(2) == [2]
    assert cs.curve_counts(16) == [2, 4, 8, 16]
    assert cs.curve_counts(24) == [2, 4, 8, 16, 24]
    with pytest.raises(ValueError, match="at least 2"):
        cs.curve_counts(1)
    # four throws, replays A A B B C C C C for each: from 2 replays (A A) a B or a C is never
    # seen (surprise 1); from 4, B ties A (0) and C is unseen; from 8, C is the most
    # frequent: A and B both 1/2
    ends = np.tile([A, A, B, B, C, C, C, C], (4, 1))
    throws = hand_throws([A, B, C, B], [0, 0, 1, 1], [0, 0, 1, 0])
    curve = cs.bound_curve(ends, throws)
    assert [c["repeats"] for c in curve] == [2, 4, 8]
    # failed = (C, B) against (A, B): from 2, both failures score 1 above A's 0 and tie B's 1
    assert curve[0]["auc"] == pytest.approx((1 + 0.5 + 1 + 0.5) / 4)
    assert curve[1]["auc"] == pytest.approx((1 + 1 + 0.5 + 0.5) / 4)  # C 1; B 0 ties A, B
    assert curve[2]["auc"] == pytest.approx((0 + 0 + 0.5 + 0.5) / 4)  # C 0 below A, B (1/2)
    assert curve[1]["auc_ordinary"] == 1.0  # C alone above A, B, B (all 0)
