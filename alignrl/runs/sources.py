"""The aligner a run names, and where it came from: `resolve_source` reads a league run
(its champion, first of best/best.json, or a member by id), a training run (its
checkpoints/best.pt), or a member/checkpoint .pt file, into a `PolicySource` that export,
align and adapt share.

A source is checked before it is handed out: only aligners (a misaligner's actions mean
nothing to an instrument), and a member whose history and knobs fit its run's config.
`ExportError` is the error of a run or a policy that cannot be used; alignrl.deploy raises
it too.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from alignrl.agents.agent import MEMBER_FORMAT, Agent, MemberSpec
from alignrl.envs.task import Task

__all__ = ["ExportError", "PolicySource", "resolve_source"]


class ExportError(ValueError):
    """A run that names no usable aligner, an export that cannot be done, or an exported
    policy that cannot be used."""


@dataclass(frozen=True)
class PolicySource:
    """The aligner a run names (to export, align or adapt) and where it came from.

    kind: "league" (a league run), "training" (an `alignrl train` run) or "member" (a
    checkpoint file outside any run); chosen_as: how RUN named it ("champion", "--member",
    "best checkpoint", "file"). `config` is the run's RunConfig (alignrl.config), or the
    defaults where no run config was found (config_file None).
    """

    agent: Agent
    member_file: Path
    kind: str
    chosen_as: str
    run_dir: Path | None
    config: Any
    config_file: Path | None
    env_steps: int | None = None  # training: env steps when the best checkpoint was saved
    best: dict[str, Any] | None = None  # league: the member's row of best/best.json

    @property
    def task(self) -> Task:
        return self.config.resolved_task()


def _member_ids(run_dir: Path) -> list[str]:
    """Members with a file in best/ or in the newest checkpoint."""
    ids = {path.stem for path in (run_dir / "best").glob("*.pt")}
    latest = run_dir / "checkpoints" / "LATEST"
    if latest.exists():
        folder = run_dir / "checkpoints" / latest.read_text().strip() / "members"
        ids |= {path.stem for path in folder.glob("*.pt")}
    return sorted(ids)


def _league_config(run_dir: Path) -> tuple[Any, Path]:
    from alignrl.league.config import parse_league
    from alignrl.yaml_io import read_yaml_file

    path = run_dir / "config.yaml"
    if not path.exists():
        raise ExportError(f"{run_dir} is not a league run: it has no config.yaml")
    return parse_league(read_yaml_file(path), str(path)), path


def _league_root(member_file: Path) -> Path | None:
    """The league run a member file lies in (best/, initial/, snapshots/ or a checkpoint)."""
    for folder in list(member_file.resolve().parents)[:4]:
        if (folder / "aligners.yaml").exists() and (folder / "config.yaml").exists():
            return folder
    return None


def _only_aligners(state: dict[str, Any], path: Path) -> None:
    spec = state.get("spec")
    if not isinstance(spec, dict):
        from alignrl.checkpoints import CheckpointError

        raise CheckpointError(
            f"{path}: not a usable member checkpoint: its spec is a {type(spec).__name__}, "
            "not a member record"
        )
    team = spec.get("team")
    if team != "aligner":
        raise ExportError(
            f"{path}: member {spec.get('id')!r} is a {team}; only aligners can be exported "
            "(a misaligner's actions mean nothing to an instrument)"
        )


def _member(state: dict[str, Any], path: Path) -> Agent:
    """The member a checkpoint holds, without its experience: a checkpoint's replay or
    rollout is shaped for the league's env slots, and a policy needs none of it."""
    from alignrl.checkpoints import CheckpointError

    _only_aligners(state, path)
    weights = {key: value for key, value in state.items() if key != "replay"}
    try:
        agent = Agent(MemberSpec.from_dict(weights["spec"]))
        agent.load_state_dict(weights)
    except (KeyError, TypeError, ValueError, RuntimeError) as error:
        raise CheckpointError(f"{path}: not a usable member checkpoint: {error}") from None
    return agent


def _league_source(run_dir: Path, member: str | None) -> PolicySource:
    from alignrl.checkpoints import load_checkpoint

    config, config_file = _league_config(run_dir)
    best_json = run_dir / "best" / "best.json"
    try:
        ranked = json.loads(best_json.read_text()) if best_json.exists() else []
    except json.JSONDecodeError as error:
        raise ExportError(f"{best_json} is not valid JSON ({error})") from None
    if member is None:
        if not ranked:
            raise ExportError(
                f"{run_dir} has no evaluated aligner yet ({best_json} is missing or empty): "
                f"name one with --member ID; members: {', '.join(_member_ids(run_dir)) or 'none'}"
            )
        member, chosen_as = str(ranked[0]["member"]), "champion"
        member_file = run_dir / "best" / f"{member}.pt"
    else:
        chosen_as = "--member"
        member_file = run_dir / "best" / f"{member}.pt"
        latest = run_dir / "checkpoints" / "LATEST"
        if not member_file.exists() and latest.exists():
            folder = run_dir / "checkpoints" / latest.read_text().strip()
            member_file = folder / "members" / f"{member}.pt"
        if not member_file.exists():
            raise ExportError(
                f"{run_dir} has no member {member!r}; its members: "
                f"{', '.join(_member_ids(run_dir)) or 'none'}"
            )
    agent = _member(load_checkpoint(member_file), member_file)
    best = next((row for row in ranked if row.get("member") == member), None)
    return PolicySource(
        agent, member_file, "league", chosen_as, run_dir, config, config_file, best=best
    )


def _training_source(run_dir: Path | None, checkpoint: Path, chosen_as: str) -> PolicySource:
    from alignrl.checkpoints import CheckpointError, load_checkpoint
    from alignrl.runs.training_runs import load_policy

    try:
        agent, config = load_policy(checkpoint)
    except CheckpointError:
        raise  # names the file already
    except (KeyError, TypeError, ValueError, RuntimeError, AttributeError) as error:
        # ValueError includes the config's own errors and a tensor that does not fit.
        reason = f"{error}" if not isinstance(error, KeyError) else f"it has no {error}"
        raise CheckpointError(f"{checkpoint}: not a usable training checkpoint: {reason}") from None
    state = load_checkpoint(checkpoint)
    env_steps = state.get("env_steps")
    if env_steps is not None and (isinstance(env_steps, bool) or not isinstance(env_steps, int)):
        raise CheckpointError(f"{checkpoint}: env_steps is {env_steps!r}, not a whole number")
    config_file = (
        run_dir / "config.yaml" if run_dir and (run_dir / "config.yaml").exists() else None
    )
    return PolicySource(
        agent,
        checkpoint,
        "training",
        chosen_as,
        run_dir,
        config,
        config_file,
        env_steps=int(env_steps) if env_steps is not None else None,
    )


def resolve_source(run: str | Path, member: str | None = None) -> PolicySource:
    """The aligner RUN names: a league run's champion (first of best/best.json) or its
    `member` (best/<id>.pt, else the newest checkpoint's file); a training run's
    checkpoints/best.pt; or a member/checkpoint .pt file."""
    from alignrl.checkpoints import load_checkpoint

    path = Path(run)
    if not path.exists():
        raise ExportError(
            f"{path} does not exist: give a league run directory, a training run directory "
            "or a member .pt file"
        )
    if path.is_dir():
        if (path / "aligners.yaml").exists():
            source = _league_source(path, member)
        elif member is not None:
            raise ExportError(
                f"--member picks a member of a league run; {path} is not one (no aligners.yaml)"
            )
        elif (path / "checkpoints" / "best.pt").exists():
            source = _training_source(path, path / "checkpoints" / "best.pt", "best checkpoint")
        else:
            raise ExportError(
                f"{path} is neither a league run (no aligners.yaml) nor a training run with "
                "an evaluated policy (no checkpoints/best.pt)"
            )
    else:
        if member is not None:
            raise ExportError(f"--member picks a member of a league run, not of the file {path}")
        state = load_checkpoint(path)
        if state.get("format") == MEMBER_FORMAT:
            agent = _member(state, path)
            root = _league_root(path)
            if root is None:  # a member file on its own: the run settings are the defaults
                from alignrl.config import parse_experiment

                history = agent.spec.observation_shape[0]
                config = parse_experiment({"name": agent.id, "history": history}, str(path))
                source = PolicySource(agent, path, "member", "file", None, config, None)
            else:
                config, config_file = _league_config(root)
                source = PolicySource(agent, path, "league", "file", root, config, config_file)
        else:
            run_dir = path.parent.parent if path.parent.name == "checkpoints" else None
            source = _training_source(run_dir, path, "file")
    _check_shapes(source)
    return source


def _check_shapes(source: PolicySource) -> None:
    spec, config = source.agent.spec, source.config
    knobs = len(source.task.knobs)
    if spec.observation_shape[0] != config.history or spec.action_dim != knobs + 1:
        where = source.config_file or "the default run settings"
        raise ExportError(
            f"{source.member_file}: member {spec.id!r} reads {spec.observation_shape[0]} "
            f"history rows and acts on {spec.action_dim - 1} knob(s), but {where} has "
            f"history {config.history} and task {source.task.name!r} with {knobs} knob(s)"
        )
