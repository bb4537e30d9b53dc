"""What a training run's files say: the members' shapes (`team_spec`, `member_spec`: from the task
and the history alone, no apparatus is opened) and the trained aligner of a run directory or
checkpoint file (`load_policy`: checkpoints/best.pt, a training checkpoint, or a league member
file).
"""

from __future__ import annotations

from pathlib import Path

from alignrl.agents.agent import Agent, MemberSpec
from alignrl.checkpoints import load_checkpoint
from alignrl.config.experiment import ExperimentConfig, parse_experiment
from alignrl.config.learner import LearnerConfig
from alignrl.config.run import RunConfig
from alignrl.envs.alignment import aligner_spaces
from alignrl.runs.state import config_of_checkpoint

__all__ = ["load_policy", "member_spec", "team_spec"]


def team_spec(member_id: str, team: str, learner: LearnerConfig, config: RunConfig) -> MemberSpec:
    """A member of either team, its shapes from the task and the history alone (no apparatus
    is opened): an aligner reads the history (aligner_spaces); a misaligner reads one row
    [1, aligned settings (k), complexity] and answers with a start in the window per knob, or
    designs the instrument as well (RunConfig.misaligner_shape). The one place a member's
    shapes are decided: the trainer, the league and the league's warm starts all build their
    members here."""
    task = config.resolved_task()
    knobs = len(task.knobs)
    if team == "aligner":
        observation_space, action_space = aligner_spaces(knobs, config.history, task.extra_features)
        shape, actions = observation_space.shape, action_space.shape[0]
    else:
        shape, actions = config.misaligner_shape()
    return MemberSpec(
        id=member_id,
        team=team,
        algorithm=learner.algorithm,
        observation_shape=shape,
        action_dim=actions,
        secret_dim=knobs,
        hyperparameters=learner.hyperparameters(),
    )


def member_spec(config: ExperimentConfig, member_id: str | None = None) -> MemberSpec:
    """The aligner an experiment trains."""
    return team_spec(member_id or config.name, "aligner", config.learner, config)


def load_policy(path: str | Path, device: str = "cpu") -> tuple[Agent, ExperimentConfig]:
    """A trained aligner from a run directory (its best.pt) or a checkpoint file."""
    path = Path(path)
    checkpoint = path / "checkpoints" / "best.pt" if path.is_dir() else path
    state = load_checkpoint(checkpoint, device)
    if state.get("format") == "alignrl-member-1":  # a league member (runs/<league>/best/...)
        agent = Agent.load(checkpoint, device=device)
        if agent.spec.team != "aligner":
            raise ValueError(f"{checkpoint} holds a {agent.spec.team}, not an aligner")
        return agent, parse_experiment(
            {"name": agent.id, "history": agent.spec.observation_shape[0]}, str(checkpoint)
        )
    config = config_of_checkpoint(state, checkpoint)
    spec = member_spec(config)
    agent = Agent(spec, device=device)
    saved = state["agent"]
    if saved.get("format") is None and "actor" in saved:  # alignrl-train-1: a bare SAC state
        saved = {
            "format": "alignrl-member-1",
            "spec": spec.to_dict(),
            "learner": saved,
            "steps_seen": 0,
            "update_debt": 0.0,
        }
    agent.load_state_dict(saved)
    return agent, config
