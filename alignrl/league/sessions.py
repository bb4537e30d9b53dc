"""A league's evaluation sessions on its eval_apparatus (seed sections 6.2-6.3): validation
sessions choose, the test session reports.

* Validation sessions (scenarios and starts of `sessions.validation_seed`) judge the best
  rated aligners every `schedule.evaluate_every` iterations. By their successes (then their
  median acquisitions) the league keeps its best members in best/, and the first of
  best/best.json is its champion.
* The test session (scenarios and starts of `sessions.test_seed`, never the validation
  seed) runs once the league has finished: the champion, the same member as it started
  (untrained) and the task's classical controllers align the same scenarios from the same
  starts. Nothing is chosen by it: it only reports, in runs/<name>/test.json
  (`write_test`, `read_test`), which the leaderboard and the report show.

Every success figure goes with its 95 % Wilson interval (alignrl.intervals), as
`session_figures` gives it.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

from alignrl.checkpoints import atomic_write_text
from alignrl.intervals import CONFIDENCE, success_text, wilson

if TYPE_CHECKING:
    from alignrl.agents.agent import Agent
    from alignrl.evaluation.session import SessionResult
    from alignrl.league.config import LeagueConfig

__all__ = [
    "TEST",
    "TEST_FILE",
    "VALIDATION",
    "champion_test_session",
    "interval",
    "lines_of_test",
    "policy_session",
    "read_test",
    "session_figures",
    "write_test",
]

VALIDATION, TEST = "validation", "test"  # which kind of session a figure comes from
TEST_FILE = "test.json"
TEST_FORMAT = "alignrl-league-test-1"


def interval(successes: int, scenarios: int) -> list[float]:
    """The 95 % Wilson interval of successes/scenarios, as rates rounded for JSON."""
    low, high = wilson(successes, scenarios)
    return [round(low, 4), round(high, 4)]


def session_figures(result: SessionResult) -> dict[str, Any]:
    """What a leaderboard, a report and `--json` give of one session."""
    return {
        "successes": result.successes,
        "scenarios": result.scenarios,
        "interval": interval(result.successes, result.scenarios),
        "median_acquisitions": result.median_acquisitions,
        "p90_acquisitions": round(result.p90_acquisitions, 2),
    }


def policy_session(
    agent: Agent, config: LeagueConfig, seed: int, scenarios: int, name: str
) -> SessionResult:
    """A session of `agent` (its mean actions) on the league's eval_apparatus, judged at the
    task's spec; training's random streams are untouched."""
    import torch

    from alignrl.training import evaluate_policy

    with torch.random.fork_rng(devices=[]):
        return evaluate_policy(
            lambda observation: agent.act(observation, deterministic=True),
            config.eval_apparatus,
            config.eval_apparatus_args,
            config.resolved_task(),
            config.history,
            scenarios,
            seed=seed,
            name=name,
        )


def _classical_session(name: str, config: LeagueConfig, seed: int, scenarios: int) -> Any:
    from alignrl.apparatus.registry import make_apparatus
    from alignrl.evaluation.baselines import get_baseline
    from alignrl.evaluation.session import run_session

    unit = make_apparatus(config.eval_apparatus, config.eval_apparatus_args)
    return run_session(get_baseline(name), unit, config.resolved_task(), scenarios, seed)


def champion_test_session(
    config: LeagueConfig,
    champion: Agent,
    untrained: Agent,
    chosen: dict[str, Any],
    iteration: int,
) -> dict[str, Any]:
    """The test session: the champion (chosen by the validation sessions, `chosen` its row
    of best/best.json), the same member untrained and the classical controllers, on the same
    scenarios of the test seed."""
    sessions = config.sessions
    scenarios = sessions.test_scenarios or config.schedule.eval_scenarios
    rows = []
    for label, agent in (("champion", champion), ("untrained", untrained)):
        result = policy_session(agent, config, sessions.test_seed, scenarios, label)
        rows.append({"label": label, "member": agent.id, **session_figures(result)})
    for name in config.test_classical():
        result = _classical_session(name, config, sessions.test_seed, scenarios)
        rows.append({"label": name, "member": None, **session_figures(result)})
    return {
        "format": TEST_FORMAT,
        "session": TEST,
        "seed": sessions.test_seed,
        "scenarios": scenarios,
        "iteration": iteration,
        "confidence": CONFIDENCE,
        "chosen_by": {
            "session": VALIDATION,
            "seed": sessions.validation_seed,
            "member": chosen["member"],
            "iteration": chosen["iteration"],
            "successes": chosen["successes"],
            "scenarios": chosen["scenarios"],
            "interval": interval(chosen["successes"], chosen["scenarios"]),
        },
        "rows": rows,
    }


def write_test(run_dir: Path, data: dict[str, Any]) -> Path:
    path = run_dir / TEST_FILE
    atomic_write_text(path, json.dumps(data, indent=2) + "\n")
    return path


def read_test(run_dir: Path) -> dict[str, Any] | None:
    """runs/<name>/test.json; None before the league has finished. ValueError naming the
    file where it is not one."""
    path = run_dir / TEST_FILE
    if not path.exists():
        return None
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise ValueError(f"{path}: not valid JSON ({error})") from None
    if not isinstance(data, dict) or data.get("format") != TEST_FORMAT:
        raise ValueError(f"{path}: not a league test session ({TEST_FORMAT})")
    return data


def lines_of_test(data: dict[str, Any]) -> list[str]:
    """The test session as the terminal shows it: where it comes from, then one line per
    aligner or controller."""
    chosen = data["chosen_by"]
    width = max(len(row["label"]) for row in data["rows"])
    lines = [
        f"test session: {data['scenarios']} held-out scenarios of seed {data['seed']}, "
        "never used for a choice",
        f"(the champion was chosen by validation sessions of seed {chosen['seed']}: "
        f"{chosen['member']} {success_text(chosen['successes'], chosen['scenarios'])} "
        f"at iteration {chosen['iteration']})",
    ]
    for row in data["rows"]:
        who = f"{row['member']} aligned" if row["member"] else "aligned"
        lines.append(
            f"{row['label']:{width}}: {who} {success_text(row['successes'], row['scenarios'])}, "
            f"median {row['median_acquisitions']:g} acquisitions"
        )
    return lines
