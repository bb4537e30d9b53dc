"""League ratings (openskill, with fixed-rating anchors), payoff table, opponent pool and
matchmaking, checked against numbers worked out by hand and against seeded sampling."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from alignrl.league import (
    Matchmaker,
    MatchmakingConfig,
    OpponentPool,
    Pairing,
    PayoffTable,
    Rating,
    RatingConfig,
    Ratings,
    anchor_scores,
)
from alignrl.league.matchmaking import PFSP_WEIGHTINGS, pfsp_probabilities


def through_json(state: dict) -> dict:
    """What a run directory gives back: plain data only, or json.dumps fails."""
    return json.loads(json.dumps(state))


# --- ratings -----------------------------------------------------------------------------------

SIGMA, BETA = 25 / 3, 25 / 6  # openskill's defaults


def test_one_win_between_new_players_moves_them_as_worked_out_by_hand():
    # Plackett-Luce, two new players, tau 0: c^2 = 2 sigma^2 + 2 beta^2, p = 1/2.
    # mu +- sigma^2 / c * (1 - p); sigma * sqrt(1 - (sigma / c) * sigma^2 / c^2 * p (1 - p)).
    ratings = Ratings(RatingConfig(tau=0.0))
    c = math.sqrt(2 * SIGMA**2 + 2 * BETA**2)
    step = SIGMA**2 / c * 0.5
    sigma = SIGMA * math.sqrt(1 - SIGMA / c * SIGMA**2 / c**2 * 0.25)
    winner, loser = ratings.update("aligner-0", "misaligner-0", [1.0])
    assert winner == pytest.approx((25 + step, sigma)) and step == pytest.approx(2.6352, abs=1e-4)
    assert loser == pytest.approx((25 - step, sigma))
    # A draw between equals moves no mean, and narrows both spreads alike.
    even = Ratings(RatingConfig(tau=0.0)).update("a", "b", [0.5])
    assert even == (pytest.approx((25.0, sigma)), pytest.approx((25.0, sigma)))


def test_a_loss_is_a_win_seen_from_the_other_side():
    first = Ratings().update("a", "m", [0.0, 1.0, 0.0])
    second = Ratings().update("m", "a", [1.0, 0.0, 1.0])
    assert first[0] == pytest.approx(second[1]) and first[1] == pytest.approx(second[0])


def test_sigma_shrinks_with_games_and_wins_raise_mu_by_shrinking_steps():
    ratings = Ratings()
    trajectory = [ratings.update("winner", "loser", [1.0])[0] for _ in range(20)]
    mus = np.array([25.0, *(rating.mu for rating in trajectory)])
    sigmas = np.array([SIGMA, *(rating.sigma for rating in trajectory)])
    assert np.all(np.diff(sigmas) < 0) and sigmas[-1] > 0
    assert np.all(np.diff(mus) > 0) and np.all(np.diff(mus, 2) < 0)
    # Draws narrow the spread too: each is news about the skill.
    ratings = Ratings()
    drawn = [ratings.update("a", "b", [0.5])[0] for _ in range(20)]
    assert all(rating.mu == pytest.approx(25.0) for rating in drawn)
    assert np.all(np.diff([SIGMA, *(rating.sigma for rating in drawn)]) < 0)


def test_tau_keeps_a_rating_able_to_move():
    still, moving = Ratings(RatingConfig(tau=0.0)), Ratings(RatingConfig(tau=1.0))
    for ratings in (still, moving):
        ratings.update("a", "b", [0.5] * 200)
    assert moving.rating("a").sigma > still.rating("a").sigma
    assert moving.update("a", "b", [1.0])[0].mu - 25 > still.update("a", "b", [1.0])[0].mu - 25


def test_an_anchor_never_moves_whoever_wins():
    ratings = Ratings()
    assert ratings.pin("hyperbola", 25.0) == Rating(25.0, 0.0)
    before = ratings.rating("aligner-0")
    aligner, anchor = ratings.update("aligner-0", "hyperbola", [1.0, 0.0, 0.5, 0.0, 0.0])
    assert anchor == Rating(25.0, 0.0) == ratings.rating("hyperbola")
    assert aligner.mu < before.mu and aligner.sigma < before.sigma  # lost more than it won
    anchor, aligner = ratings.update("hyperbola", "aligner-1", [0.0] * 5)  # either side
    assert anchor == Rating(25.0, 0.0) and aligner.mu > 25.0
    assert ratings.anchors == ["hyperbola"] and ratings.is_anchor("hyperbola")
    ratings.pin("golden-section", 20.0)
    with pytest.raises(ValueError, match="both anchors"):
        ratings.update("hyperbola", "golden-section", [1.0])


def _against_the_anchor(aligner_meets_spec: bool, seed: int = 0) -> Rating:
    """An aligner rated on 200 starts against a hyperbola fit that meets the spec on 90 % of
    them (and ends at 2.5 px there, at 4 px elsewhere)."""
    rng = np.random.default_rng(seed)
    anchor_success = rng.random(200) < 0.9
    anchor_px = np.where(anchor_success, 2.5, 4.0)
    mine = np.full(200, aligner_meets_spec)
    mine_px = np.where(mine, 2.6, 6.0)
    ratings = Ratings()
    ratings.pin("hyperbola", 25.0)
    scores = anchor_scores(mine, mine_px, anchor_success, anchor_px)
    return ratings.update("aligner", "hyperbola", scores.tolist())[0]


def test_always_meeting_the_spec_rates_above_the_hyperbola_anchor_never_below():
    always, never = _against_the_anchor(True), _against_the_anchor(False)
    assert always.mu > 25.0 > never.mu
    # Many matches: both are sure of it, not just ahead by chance.
    assert always.ordinal > 25.0 - 3 * always.sigma and never.mu + 3 * never.sigma < 25.0


def test_anchor_scores_as_worked_out_by_hand():
    #          aligner: met,  width | anchor: met, width | score
    cases = [
        (True, 2.6, False, 3.5, 1.0),  # only the aligner met the spec
        (False, 3.5, True, 2.6, 0.0),  # only the anchor
        (True, 2.6, True, 2.2, 0.5),  # both: a draw, however narrow either ended
        (False, 4.0, False, 5.0, 1.0),  # neither: the aligner 20 % narrower
        (False, 5.0, False, 4.0, 0.0),
        (False, 4.1, False, 4.0, 0.5),  # neither, within 5 %: alike
        (False, np.nan, False, 9.0, 0.0),  # no image is wider than any
        (False, 9.0, False, np.nan, 1.0),
        (False, np.nan, False, np.nan, 0.5),
    ]
    mine, mine_px, theirs, theirs_px, expected = (
        np.array(column) for column in zip(*cases, strict=True)
    )
    np.testing.assert_array_equal(
        anchor_scores(mine.astype(bool), mine_px, theirs.astype(bool), theirs_px), expected
    )


@pytest.mark.parametrize("score", [0.3, -0.1, 1.5, math.nan])
def test_invalid_score_names_the_pair_and_the_value(score):
    ratings = Ratings()
    with pytest.raises(ValueError, match=r"'aligner-0'.*'misaligner-1'.*" + str(score)):
        ratings.update("aligner-0", "misaligner-1", [1.0, score])
    assert len(ratings) == 0  # nothing rated by a rejected update


def test_unknown_ids_start_at_the_initial_rating_and_add_refuses_a_duplicate():
    ratings = Ratings(RatingConfig(mu=10.0, sigma=2.0))
    assert "aligner-0" not in ratings and ratings.rating("aligner-0") == Rating(10.0, 2.0)
    won = ratings.update("aligner-0", "misaligner-0", [1.0])[0]
    assert ratings.add("aligner-2", won) == won  # a PBT copy of aligner-0
    assert ratings.add("aligner-3") == Rating(10.0, 2.0)
    with pytest.raises(ValueError, match="already rated"):
        ratings.add("aligner-0")
    with pytest.raises(ValueError, match="itself"):
        ratings.update("aligner-0", "aligner-0", [1.0])
    with pytest.raises(ValueError, match="sigma\n  Input should be greater than 0"):
        RatingConfig(sigma=0.0)


def test_ranking_is_by_ordinal_best_first_with_ties_by_id():
    ratings = Ratings()
    ratings.add("sure", Rating(30.0, 1.0))  # ordinal 27
    ratings.add("unsure", Rating(32.0, 3.0))  # higher mean, but ordinal 23
    ratings.add("b", Rating(26.0, 1.0))
    ratings.add("a", Rating(26.0, 1.0))
    assert [player for player, _ in ratings.ranking()] == ["sure", "a", "b", "unsure"]
    assert ratings.ranking(["unsure", "new"]) == [
        ("unsure", Rating(32.0, 3.0)),
        ("new", Rating(25.0, SIGMA)),
    ]
    assert Rating(30.0, 1.0).ordinal == 27.0 and Rating(30.0, 1.0).text() == "30.0 ± 1.0"


def test_win_probabilities_are_symmetric():
    ratings = Ratings()
    ratings.add("strong", Rating(30.0, 1.0))
    assert ratings.win_probability("a", "b") == pytest.approx(0.5)
    assert ratings.win_probability("strong", "a") > 0.5
    assert ratings.win_probability("strong", "a") + ratings.win_probability(
        "a", "strong"
    ) == pytest.approx(1.0)


def test_history_records_every_rated_player_per_iteration():
    ratings = Ratings()
    ratings.update("a", "m", [1.0])
    ratings.record(0)
    ratings.update("a", "m", [1.0])
    ratings.record(1)
    assert [row[:2] for row in ratings.history] == [(0, "a"), (0, "m"), (1, "a"), (1, "m")]
    assert ratings.history[2][2:] == tuple(ratings.rating("a"))  # (mu, sigma)
    assert ratings.history[0][2] < ratings.history[2][2]
    with pytest.raises(ValueError, match="increasing order"):
        ratings.record(1)


def test_ratings_state_round_trips_through_json():
    rng = np.random.default_rng(3)
    pairs = [("a0", "m0"), ("a1", "m0"), ("a0", "m0@2"), ("a1", "hyperbola")]
    original = Ratings()
    original.pin("hyperbola", 25.0)
    for iteration in range(8):
        scores = rng.choice([0.0, 0.5, 1.0], 4).tolist()
        original.update(*pairs[iteration % 4], scores)
        original.record(iteration)
    restored = Ratings()
    restored.load_state_dict(through_json(original.state_dict()))
    assert restored.history == original.history and restored.anchors == ["hyperbola"]
    for ratings in (original, restored):
        ratings.update("a1", "m0@2", [0.0, 1.0])
        ratings.update("a0", "hyperbola", [1.0])
        ratings.record(8)
    assert restored.ranking() == original.ranking()
    assert restored.rating("hyperbola") == Rating(25.0, 0.0)  # still an anchor
    assert restored.history == original.history
    with pytest.raises(ValueError, match="increasing order"):
        restored.record(8)


def test_elo_ratings_of_an_older_league_are_refused_with_what_to_do():
    with pytest.raises(ValueError, match=r"Elo.*start it again"):
        Ratings().load_state_dict(
            {"ratings": {"a0": 1208.0}, "anchors": [], "history": [], "last_recorded": None}
        )


# --- payoff table ------------------------------------------------------------------------------


def test_payoff_win_rates_and_never_played_cells():
    payoff = PayoffTable()
    payoff.add("a0", "m0", matches=8, aligner_score_sum=6.0)
    payoff.add("a0", "m0", matches=2, aligner_score_sum=0.0)
    payoff.add("a1", "m1@4", matches=5, aligner_score_sum=5.0)
    assert payoff.matches("a0", "m0") == 10
    assert payoff.win_rate("a0", "m0") == pytest.approx(0.6)
    assert payoff.win_rate("m0", "a0") is None  # pairs are ordered (aligner, misaligner)
    assert payoff.win_rate("a1", "m0") is None
    matrix = payoff.matrix(["a0", "a1"], ["m0", "m1@4"])
    np.testing.assert_array_equal(np.isnan(matrix), [[False, True], [True, False]])
    assert matrix[0, 0] == pytest.approx(0.6) and matrix[1, 1] == 1.0


@pytest.mark.parametrize(
    ("matches", "score_sum", "message"),
    [
        (0, 0.0, "whole number"),
        (2.5, 1.0, "whole number"),
        (4, 5.0, r"\[0, matches=4\]"),
        (4, -1.0, r"\[0, matches=4\]"),
        (4, math.nan, "nan"),
    ],
)
def test_payoff_rejects_impossible_batches(matches, score_sum, message):
    payoff = PayoffTable()
    with pytest.raises(ValueError, match=message):
        payoff.add("a0", "m0", matches, score_sum)
    assert payoff.win_rate("a0", "m0") is None


def test_payoff_history_keeps_only_changed_pairs_and_replays():
    payoff = PayoffTable()
    payoff.add("a0", "m0", 4, 1.0)
    payoff.add("a1", "m0", 4, 3.0)
    payoff.record(1)
    payoff.record(2)  # nothing changed: no rows
    payoff.add("a0", "m0", 4, 3.0)
    payoff.record(3)
    assert payoff.history == [
        (1, "a0", "m0", 4, 1.0),
        (1, "a1", "m0", 4, 3.0),
        (3, "a0", "m0", 8, 4.0),
    ]
    rows, columns = ["a0", "a1"], ["m0"]
    assert np.isnan(payoff.matrix_at(0, rows, columns)).all()
    np.testing.assert_array_equal(payoff.matrix_at(2, rows, columns), [[0.25], [0.75]])
    np.testing.assert_array_equal(payoff.matrix_at(3, rows, columns), payoff.matrix(rows, columns))


def test_payoff_state_round_trips_through_json():
    original = PayoffTable()
    original.add("a0", "m0", 4, 1.0)
    original.add("a1", "m0@2", 3, 2.5)
    original.record(0)
    original.add("a1", "m0@2", 3, 0.5)
    restored = PayoffTable()
    restored.load_state_dict(through_json(original.state_dict()))
    for payoff in (original, restored):
        payoff.add("a0", "m1", 2, 2.0)
        payoff.record(1)  # must see a1 and a0/m1 as changed, a0/m0 as not
    assert restored.history == original.history
    assert [row[:3] for row in restored.history[2:]] == [(1, "a1", "m0@2"), (1, "a0", "m1")]
    np.testing.assert_array_equal(
        restored.matrix(["a0", "a1"], ["m0", "m0@2", "m1"]),
        original.matrix(["a0", "a1"], ["m0", "m0@2", "m1"]),
    )


# --- opponent pool -----------------------------------------------------------------------------


def make_pool(max_snapshots: int = 10) -> OpponentPool:
    pool = OpponentPool(max_snapshots=max_snapshots)
    for member, team in [
        ("a0", "aligner"),
        ("a1", "aligner"),
        ("m0", "misaligner"),
        ("m1", "misaligner"),
    ]:
        pool.add_member(member, team)
    return pool


def test_freeze_adds_a_snapshot_opponent():
    pool = make_pool()
    assert pool.freeze("m0", 3) == "m0@3"
    assert pool.candidates("misaligner") == ["m0", "m1", "m0@3"]
    assert pool.candidates("aligner") == ["a0", "a1"]
    assert pool.is_snapshot("m0@3") and not pool.is_snapshot("m0")
    assert pool.team_of("m0@3") == "misaligner"
    assert pool.snapshots("misaligner")[0].member == "m0"
    with pytest.raises(ValueError, match="already frozen"):
        pool.freeze("m0", 3)
    with pytest.raises(KeyError, match="not an active member"):
        pool.freeze("m0@3", 4)  # a snapshot is not frozen again


def test_snapshot_cap_drops_the_oldest_snapshot_never_an_active_member():
    pool = make_pool(max_snapshots=2)
    for iteration in (1, 2, 3):
        pool.freeze("m0", iteration)
    pool.freeze("a0", 3)
    assert pool.candidates("misaligner") == ["m0", "m1", "m0@2", "m0@3"]
    pool.freeze("m1", 4)
    assert pool.candidates("misaligner") == ["m0", "m1", "m0@3", "m1@4"]
    assert pool.candidates("aligner") == ["a0", "a1", "a0@3"]  # the cap is per team


def test_removed_member_keeps_its_snapshots_and_ids_are_checked():
    pool = make_pool()
    pool.freeze("a1", 2)
    pool.remove_member("a1")
    assert pool.candidates("aligner") == ["a0", "a1@2"]
    with pytest.raises(ValueError, match="already in the opponent pool"):
        pool.add_member("a0", "misaligner")
    with pytest.raises(ValueError, match="marks snapshots"):
        pool.add_member("a2@1", "aligner")
    with pytest.raises(ValueError, match="team 'referee'"):
        pool.add_member("r0", "referee")
    with pytest.raises(ValueError, match="at least 1 snapshot"):
        OpponentPool(max_snapshots=0)


def test_pool_state_round_trips_through_json():
    original = make_pool(max_snapshots=2)
    original.freeze("m0", 1)
    original.freeze("a0", 1)
    original.freeze("m1", 2)
    restored = OpponentPool(max_snapshots=2)
    restored.load_state_dict(through_json(original.state_dict()))
    for pool in (original, restored):
        pool.freeze("m0", 5)
    for team in ("aligner", "misaligner"):
        assert restored.candidates(team) == original.candidates(team)
        assert restored.snapshots(team) == original.snapshots(team)
    with pytest.raises(ValueError, match="max_snapshots=1"):
        OpponentPool(max_snapshots=1).load_state_dict(original.state_dict())


# --- matchmaking -------------------------------------------------------------------------------


def league_with_history() -> tuple[OpponentPool, PayoffTable]:
    """a0's win rates: 0.2 against m0, never met m1 (0.5), 0.9 against m0@3, 0.5 against m0@5."""
    pool = make_pool()
    pool.freeze("m0", 3)
    pool.freeze("m0", 5)
    payoff = PayoffTable()
    payoff.add("a0", "m0", 10, 2.0)
    payoff.add("a0", "m0@3", 10, 9.0)
    payoff.add("a0", "m0@5", 4, 2.0)
    return pool, payoff


def only(strategy: str, weighting: str = "hard") -> Matchmaker:
    weights = {"pfsp": 0.0, "uniform": 0.0, "latest": 0.0, strategy: 1.0}
    return Matchmaker(MatchmakingConfig(**weights, weighting=weighting))


@pytest.mark.parametrize(
    ("weighting", "weights"),
    [
        ("hard", [0.8**2, 0.5**2, 0.1**2, 0.5**2]),
        ("variance", [0.2 * 0.8, 0.25, 0.9 * 0.1, 0.25]),
        ("linear", [0.8, 0.5, 0.1, 0.5]),
    ],
)
def test_pfsp_probabilities_follow_the_formula(weighting, weights):
    pool, payoff = league_with_history()
    probabilities = only("pfsp", weighting).opponent_probabilities("a0", payoff, pool)
    assert list(probabilities) == ["m0", "m1", "m0@3", "m0@5"]
    expected = np.array(weights) / sum(weights)
    np.testing.assert_allclose(list(probabilities.values()), expected, rtol=1e-12)


def test_pfsp_sees_the_misaligner_side_of_the_payoff():
    pool, payoff = league_with_history()
    # m0 wins 0.8 of its matches against a0 and never met a1: weights 0.2^2 and 0.5^2.
    probabilities = only("pfsp").opponent_probabilities("m0", payoff, pool)
    assert probabilities == pytest.approx({"a0": 0.04 / 0.29, "a1": 0.25 / 0.29})


def test_pfsp_falls_back_to_uniform_when_the_learner_beats_everyone():
    weighting = PFSP_WEIGHTINGS["hard"]
    probabilities = pfsp_probabilities(np.ones(4), np.ones(4, bool), weighting=weighting)
    np.testing.assert_array_equal(probabilities, np.full(4, 0.25))


def test_uniform_and_latest_strategies():
    pool, payoff = league_with_history()
    assert only("uniform").opponent_probabilities("a0", payoff, pool) == pytest.approx(
        {"m0": 0.25, "m1": 0.25, "m0@3": 0.25, "m0@5": 0.25}
    )
    assert only("latest").opponent_probabilities("a0", payoff, pool) == pytest.approx(
        {"m0": 0.5, "m1": 0.5, "m0@3": 0.0, "m0@5": 0.0}
    )


def test_mixture_is_the_weighted_sum_of_strategies():
    pool, payoff = league_with_history()
    hard = np.array([0.64, 0.25, 0.01, 0.25]) / 1.15
    uniform = np.full(4, 0.25)
    latest = np.array([0.5, 0.5, 0.0, 0.0])
    expected = 0.5 * hard + 0.3 * uniform + 0.2 * latest  # the default mixture
    probabilities = Matchmaker().opponent_probabilities("a0", payoff, pool)
    np.testing.assert_allclose(list(probabilities.values()), expected, rtol=1e-12)
    # Weights need not sum to 1.
    doubled = Matchmaker(MatchmakingConfig(pfsp=1.0, uniform=0.6, latest=0.4))
    assert doubled.opponent_probabilities("a0", payoff, pool) == pytest.approx(probabilities)


def test_sampled_opponents_match_the_mixture():
    pool, payoff = league_with_history()
    matchmaker = Matchmaker()
    rng = np.random.default_rng(2024)
    draws = 20_000
    counts = dict.fromkeys(pool.candidates("misaligner"), 0)
    for _ in range(draws):
        counts[matchmaker.choose_opponent(rng, "a0", payoff, pool)] += 1
    probabilities = matchmaker.opponent_probabilities("a0", payoff, pool)
    for opponent, count in counts.items():
        assert count / draws == pytest.approx(probabilities[opponent], abs=0.015)


def test_learners_rotate_over_teams_and_active_members_only():
    pool, payoff = league_with_history()
    matchmaker = Matchmaker()
    learners = [matchmaker.learner_for(iteration, pool) for iteration in range(8)]
    assert learners == ["a0", "m0", "a1", "m1", "a0", "m0", "a1", "m1"]
    pairing = matchmaker.select_pair(np.random.default_rng(0), payoff, pool, iteration=1)
    assert pairing.learner_team == "misaligner" and pairing.learner == "m0"
    assert pairing.misaligner == "m0"
    assert pairing.aligner == pairing.opponent
    assert pairing.opponent in ("a0", "a1")
    with pytest.raises(ValueError, match="only active members learn"):
        matchmaker.opponent_probabilities("m0@3", payoff, pool)


def play(seed: int, iterations: int = 30) -> list[Pairing]:
    """A miniature league: pairs chosen, results recorded, snapshots frozen."""
    pool, payoff = make_pool(max_snapshots=3), PayoffTable()
    matchmaker, rng = Matchmaker(), np.random.default_rng(seed)
    pairings = []
    for iteration in range(iterations):
        pairing = matchmaker.select_pair(rng, payoff, pool, iteration)
        payoff.add(pairing.aligner, pairing.misaligner, 8, float(rng.integers(0, 9)))
        if iteration % 5 == 4:
            pool.freeze(pairing.learner, iteration)
        pairings.append(pairing)
    return pairings


def test_same_seed_same_pairs():
    assert play(seed=7) == play(seed=7)
    assert play(seed=7) != play(seed=8)
    assert any("@" in pairing.opponent for pairing in play(seed=7))


@pytest.mark.parametrize(
    ("config", "message"),
    [
        ({"fictitious": 0.5}, "fictitious\n  Extra inputs are not permitted"),
        ({"uniform": -0.1}, "uniform\n  Input should be greater than or equal to 0"),
        ({"latest": math.nan}, "latest\n  Input should be a finite number"),
        ({"pfsp": 0.0, "uniform": 0.0, "latest": 0.0}, "cannot all be 0"),
        ({"weighting": "squared"}, "weighting\n  Input should be 'hard', 'variance' or 'linear'"),
    ],
)
def test_invalid_matchmaking_config(config, message):
    with pytest.raises(ValueError, match=message):
        MatchmakingConfig(**config)
