"""The league: two teams of agents, matched, rated and improved against each other (seed §3)."""

from alignrl.league.matchmaking import (
    PFSP_WEIGHTINGS,
    STRATEGIES,
    TEAMS,
    Matchmaker,
    MatchmakingConfig,
    OpponentPool,
    Pairing,
    Snapshot,
)
from alignrl.league.ratings import PayoffTable, Rating, RatingConfig, Ratings, anchor_scores

__all__ = [
    "PFSP_WEIGHTINGS",
    "STRATEGIES",
    "TEAMS",
    "Matchmaker",
    "MatchmakingConfig",
    "OpponentPool",
    "Pairing",
    "PayoffTable",
    "Rating",
    "RatingConfig",
    "Ratings",
    "Snapshot",
    "anchor_scores",
]
