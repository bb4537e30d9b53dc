"""Evaluation sessions (seed sections 6.2-6.3), the classical baselines (autofocus; stigmation,
aperture centring and the whole column), and their reports: successes out of N, acquisitions
per alignment, final edge widths, directional widths and wobble shifts, trajectories."""

from alignrl.evaluation.baselines import (
    BASELINES,
    CLASSICAL,
    TASK_BASELINES,
    ColumnSequence,
    GoldenSection,
    HillClimb,
    HyperbolaFit,
    StigmatorSearch,
    WobbleCenter,
    get_baseline,
    task_baselines,
)
from alignrl.evaluation.controllers import (
    BudgetExhausted,
    Controller,
    CountingApparatus,
    TaskController,
)
from alignrl.evaluation.session import (
    DEFAULT_BUDGET,
    ScenarioResult,
    SessionResult,
    default_budget,
    run_session,
)

__all__ = [
    "BASELINES",
    "CLASSICAL",
    "DEFAULT_BUDGET",
    "TASK_BASELINES",
    "BudgetExhausted",
    "ColumnSequence",
    "Controller",
    "CountingApparatus",
    "GoldenSection",
    "HillClimb",
    "HyperbolaFit",
    "ScenarioResult",
    "SessionResult",
    "StigmatorSearch",
    "TaskController",
    "WobbleCenter",
    "default_budget",
    "get_baseline",
    "run_session",
    "task_baselines",
]
