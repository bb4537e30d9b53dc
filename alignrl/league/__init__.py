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
from alignrl.league.ratings import EloConfig, PayoffTable, Ratings, expected_score

__all__ = [
    "PFSP_WEIGHTINGS",
    "STRATEGIES",
    "TEAMS",
    "EloConfig",
    "Matchmaker",
    "MatchmakingConfig",
    "OpponentPool",
    "Pairing",
    "PayoffTable",
    "Ratings",
    "Snapshot",
    "expected_score",
]
