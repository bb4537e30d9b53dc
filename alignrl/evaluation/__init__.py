"""Evaluation sessions (seed sections 6.2-6.3), classical autofocus baselines, and their
reports: successes out of N, acquisitions per alignment, final edge widths, trajectories."""

from alignrl.evaluation.baselines import (
    BASELINES,
    GoldenSection,
    HillClimb,
    HyperbolaFit,
    get_baseline,
)
from alignrl.evaluation.controllers import BudgetExhausted, Controller, CountingApparatus
from alignrl.evaluation.session import DEFAULT_BUDGET, ScenarioResult, SessionResult, run_session

__all__ = [
    "BASELINES",
    "DEFAULT_BUDGET",
    "BudgetExhausted",
    "Controller",
    "CountingApparatus",
    "GoldenSection",
    "HillClimb",
    "HyperbolaFit",
    "ScenarioResult",
    "SessionResult",
    "get_baseline",
    "run_session",
]
