"""What a training run's files say: the aligner its config trains (`member_spec`, from the task
and the history alone: no apparatus is opened) and the trained aligner of a run directory or
checkpoint file (`load_policy`: checkpoints/best.pt, a training checkpoint, or a league member
file).
"""

from __future__ import annotations

from pathlib import Path

from alignrl.agents.agent import Agent, MemberSpec
from alignrl.checkpoints import load_checkpoint
from alignrl.config import ExperimentConfig, parse_experiment
from alignrl.envs.alignment import aligner_spaces

__all__ = ["load_policy", "member_spec"]


def member_spec(config: ExperimentConfig, member_id: str | None = None) -> MemberSpec:
    """The aligner an experiment trains. Its shapes follow from the task and the history
    alone, so no apparatus needs to be opened to build or load it."""
    task = config.resolved_task()
    knobs = len(task.knobs)
    observation_space, action_space = aligner_spaces(knobs, config.history, task.extra_features)
    return MemberSpec(
        id=member_id or config.name,
        team="aligner",
        algorithm=config.learner.algorithm,
        observation_shape=observation_space.shape,
        action_dim=action_space.shape[0],
        secret_dim=knobs,
        hyperparameters=config.learner.hyperparameters(),
    )


def load_policy(path: str | Path, device: str = "cpu") -> tuple[Agent, ExperimentConfig]:
    """A trained aligner from a run directory (its best.pt) or a checkpoint file."""
    from alignrl.yaml_io import parse_yaml

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
    source = f"{checkpoint} (config)"
    config = parse_experiment(parse_yaml(state["config"], source), source)
    spec = member_spec(config)
    agent = Agent(spec, device=device)
    saved = state["agent"]
    if saved.get("format") is None and "actor" in saved:  # alignrl-train-1: a bare SAC state
        saved = {"format": "alignrl-member-1", "spec": spec.to_dict(), "learner": saved,
                 "steps_seen": 0, "update_debt": 0.0}  # fmt: skip
    agent.load_state_dict(saved)
    return agent, config
