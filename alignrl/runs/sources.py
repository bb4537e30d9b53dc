"""What a policy spec names, decided in one place. `locate_source` reads a path or a name into
a `Location`: a league run, a training run, a member or checkpoint .pt file, a folder that
`alignrl export` wrote, or `champion:NAME`, a shipped champion (package data under
alignrl/champions/, read through importlib.resources, so it is there in an installed wheel).
`resolve_source` loads the trained aligner a location holds into a `PolicySource`: export,
align, evaluate, adapt and the league's warm starts all ask it.

A league run gives its champion (the first of best/best.json) or a member by id, a training
run its checkpoints/best.pt. An exported folder or a champion gives the member its card
describes with the acting network's weights of its policy.safetensors. Where the export was
made with --with-learner-state, its learner.safetensors and learner.json (no pickle:
alignrl.runs.learner_state) bring the critics, target critics, entropy coefficient and
optimizers too, and it can be adapted and warm-started from as a run can; without them it
acts and can be exported again, but holds no learner state (`PolicySource.learner_state`)
and is refused where one is needed (`require_learner_state`). The replay is never exported.
A graph export (ONNX, TorchScript) is run by alignrl.deploy.loading and holds no weights to
load into a learner. A file of a safetensors export (its policy.safetensors, as an
adaptation's config records its source, learner.safetensors, learner.json, card.json) names
the export folder it lies in.

A source is checked before it is handed out: only aligners (a misaligner's actions mean
nothing to an instrument), and a member whose history and knobs fit its run's settings.
`ExportError` is the error of a run or a policy that cannot be used (alignrl.deploy raises
it too); `PolicySpecError` that of a spec that names nothing.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from importlib import resources
from importlib.resources.abc import Traversable
from pathlib import Path
from typing import Any

from alignrl.agents.agent import MEMBER_FORMAT, POLICY_FORMAT, Agent, MemberSpec
from alignrl.checkpoints import CheckpointError, load_checkpoint
from alignrl.config.run import RunConfig
from alignrl.config_reading import ConfigError, parse_config
from alignrl.envs.task import Task
from alignrl.runs.learner_state import (
    LEARNER_FILE,
    LearnerStateError,
    file_sha256,
    has_learner_state,
    load_learner_state,
    read_json_file,
)
from alignrl.runs.state import CONFIG_FILE, checked_knobs, recorded_knobs, run_config_data

__all__ = [
    "CHAMPION_PREFIX",
    "MAX_CARD_BYTES",
    "EvaluationSchedule",
    "ExportError",
    "Location",
    "MissingSourceError",
    "PolicySource",
    "PolicySpecError",
    "champion_folder",
    "locate_source",
    "read_card_file",
    "require_learner_state",
    "resolve_source",
    "shipped_champions",
]

CHAMPION_PREFIX = "champion:"
# The shipped champions, one folder each: package data, never a path from the source tree.
CHAMPIONS: Traversable = resources.files("alignrl") / "champions"
EXPORTED_KINDS = ("export", "champion")  # locations whose policy is a folder with card.json
# Files of a safetensors export that name their folder when given as a spec (none of them
# is a torch checkpoint).
EXPORT_FILES = ("card.json", "policy.safetensors", "learner.safetensors", "learner.json")
# The largest card.json read (refused by its size before it is parsed): an export's is 7-8 kB,
# a league member's with a thousand evaluation sessions some 300 kB.
MAX_CARD_BYTES = 8 << 20


class ExportError(ValueError):
    """A run that names no usable aligner, an export that cannot be done, or an exported
    policy that cannot be used."""


class PolicySpecError(ExportError):
    """A policy spec that names nothing usable: an unknown champion, or a folder that is no
    run and no export."""


class MissingSourceError(PolicySpecError):
    """A policy spec naming a path where there is nothing."""


@dataclass(frozen=True)
class Location:
    """What a spec names. kind: "league" (a league run directory), "training" (an `alignrl
    train` run directory), "checkpoint" (a .pt file: a member or a training checkpoint),
    "export" (a folder `alignrl export` wrote) or "champion" (a shipped champion's folder)."""

    spec: str  # as given
    kind: str
    path: Path
    member: str | None = None  # a league run's member by id (--member)

    @property
    def exported(self) -> bool:
        return self.kind in EXPORTED_KINDS


@dataclass(frozen=True)
class EvaluationSchedule:
    """The evaluation sessions a run held: `scenarios` alignments every `every` `unit`."""

    scenarios: int
    every: int
    unit: str  # "iterations" (a league) or "env steps" (a training run)


@dataclass(frozen=True)
class PolicySource:
    """The aligner a spec names (to export, align, adapt or warm-start from) and where it
    came from.

    kind: "league", "training", "member" (a member file outside any run), "export" or
    "champion"; chosen_as: how the spec named it ("champion", "--member", "best checkpoint",
    "file", "exported policy", "shipped champion"). `config` holds the run settings
    (alignrl.config.run.RunConfig: apparatus, task, history) of the run, of the card of an
    export, or the defaults where none was found (config_file None).
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
    sessions: EvaluationSchedule | None = None  # a run's evaluation sessions, where it says
    card: dict[str, Any] | None = None  # export, champion: the card.json it was exported with
    # Per task knob, its interval on the training apparatus and max_step, as the run
    # recorded them (knobs.json) or the export's card lists them; None where neither does.
    knobs: list[dict[str, Any]] | None = None
    # export, champion: the learner.safetensors loaded into the agent, where it ships one
    learner_file: Path | None = None
    # the run's acting_options laid over its task options (its own sessions acted without)
    acting_options: dict[str, Any] | None = None

    @property
    def task(self) -> Task:
        return self.config.resolved_task()

    @property
    def learner_state(self) -> bool:
        """Whether the agent holds its trained critics, optimizers and entropy coefficient:
        a run or a member file does; an export or a champion only where it ships its
        learner state (`learner_file`), else it brings its acting network alone (the rest
        freshly initialised)."""
        return self.kind not in EXPORTED_KINDS or self.learner_file is not None

    @property
    def updates(self) -> int:
        """Learner updates behind the policy (an export's card records them)."""
        if self.card is not None:
            return int(self.card["member"]["updates"])
        return self.agent.updates


def require_learner_state(source: PolicySource, named: str, use: str, instead: str = "") -> None:
    """ExportError unless `source` holds a learner's state: `use` ("adapt", "a warm start")
    trains on from the critics, optimizers and entropy coefficient of the source `named`
    (as the user gave it), which an export or a shipped champion does not bring. `instead`:
    what else would do, appended to the message."""
    if source.learner_state:
        return
    origin = ((source.card or {}).get("source") or {}).get("member_file")
    what = "a shipped champion" if source.kind == "champion" else "an exported policy"
    raise ExportError(
        f"{named} is {what}: it ships its acting network alone, no critics, optimizers or "
        f"entropy coefficient, and {use} trains on from those; give the league run, training "
        "run or member .pt file it was exported from"
        + (f" (its card names {origin})" if origin else "")
        + ", or an export of it made with --with-learner-state"
        + instead
    )


# --- where a spec points ------------------------------------------------------------------


def shipped_champions() -> list[str]:
    """The names champion:NAME takes: the folders of alignrl/champions/. Hidden folders are
    exports still being written (alignrl export stages beside --out)."""
    if not CHAMPIONS.is_dir():
        return []
    return sorted(
        entry.name
        for entry in CHAMPIONS.iterdir()
        if entry.is_dir() and not entry.name.startswith(".")
    )


def champion_folder(name: str) -> Path:
    """The folder of the shipped champion `name`; PolicySpecError listing the shipped ones
    where there is no such champion."""
    shipped = shipped_champions()
    if name not in shipped:
        known = ", ".join(shipped) if shipped else f"none ({CHAMPIONS} holds no champion)"
        raise PolicySpecError(f"no shipped champion {name!r}; shipped champions: {known}")
    folder = CHAMPIONS / name
    if not isinstance(folder, Path):  # a zipped install: the loaders read files on disk
        raise PolicySpecError(
            f"champion:{name} lies inside an archive ({folder}); install alignrl unpacked "
            "(pip install the wheel) to run its champions"
        )
    return folder


def _shipped(folder: Path) -> bool:
    """Whether `folder` is a shipped champion's (given by its path, as an adaptation's
    config records its source)."""
    if not isinstance(CHAMPIONS, Path) or folder.name not in shipped_champions():
        return False
    return folder.resolve() == (CHAMPIONS / folder.name).resolve()


def locate_source(spec: str | Path, member: str | None = None) -> Location:
    """What `spec` names (see Location), without loading it. `member` picks a member of a
    league run. MissingSourceError where nothing is at the path, PolicySpecError where what
    is there is none of these."""
    text = str(spec)
    if text.startswith(CHAMPION_PREFIX):
        kind, path = "champion", champion_folder(text[len(CHAMPION_PREFIX) :])
    else:
        path = Path(spec)
        if path.is_file() and path.name in EXPORT_FILES and (path.parent / "card.json").is_file():
            path = path.parent  # a file of a safetensors export: the export it lies in
        if not path.exists():
            raise MissingSourceError(
                f"unknown policy {text!r}: {path} does not exist; give a league run "
                "directory, a training run directory, a member or checkpoint .pt file, an "
                "exported policy directory, or champion:NAME"
            )
        if not path.is_dir():
            kind = "checkpoint"
        elif (path / "aligners.yaml").exists():
            kind = "league"
        elif (path / "checkpoints" / "best.pt").exists():
            kind = "training"
        elif (path / "card.json").exists():
            kind = "champion" if _shipped(path) else "export"
        else:
            raise PolicySpecError(
                f"{path} is neither a league run (no aligners.yaml), a training run with an "
                "evaluated policy (no checkpoints/best.pt) nor an exported policy (no card.json)"
            )
    if member is not None and kind != "league":
        what = f"the file {path}" if kind == "checkpoint" else f"{text} (no aligners.yaml)"
        raise ExportError(f"--member picks a member of a league run, not of {what}")
    return Location(text, kind, path, member)


def resolve_source(spec: str | Path | Location, member: str | None = None) -> PolicySource:
    """The aligner `spec` names: a league run's champion (first of best/best.json) or its
    `member` (best/<id>.pt, else the newest checkpoint's file); a training run's
    checkpoints/best.pt; a member/checkpoint .pt file; the member of a safetensors export or
    of a shipped champion (champion:NAME), its acting network loaded; it acts with its run's
    `acting_options` (alignrl/config/run.py)."""
    location = spec if isinstance(spec, Location) else locate_source(spec, member)
    path = location.path
    if location.kind == "league":
        source = _league_source(path, location.member)
    elif location.kind == "training":
        source = _training_source(path, path / "checkpoints" / "best.pt", "best checkpoint")
    elif location.kind == "checkpoint":
        source = _file_source(path)
    else:
        source = _exported_source(location)
    _check_shapes(source)
    try:
        if source.card is not None:
            knobs = checked_knobs(source.card.get("knobs"), source.task, str(source.config_file))
        else:
            knobs = recorded_knobs(source.run_dir, source.task) if source.run_dir else None
    except ValueError as error:  # a damaged knobs.json or card: named, never a traceback
        raise ExportError(str(error)) from None
    # The policy acts as its run says it does once trained (RunConfig.acting_options).
    laid = source.config.acting_options
    acting = laid.model_dump(exclude_none=True) if laid is not None else None
    config = source.config.acting()
    return dataclasses.replace(source, config=config, knobs=knobs, acting_options=acting)


# --- league and training runs -------------------------------------------------------------


def _member_ids(run_dir: Path) -> list[str]:
    """Members with a file in best/ or in the newest checkpoint."""
    ids = {path.stem for path in (run_dir / "best").glob("*.pt")}
    latest = run_dir / "checkpoints" / "LATEST"
    if latest.exists():
        folder = run_dir / "checkpoints" / latest.read_text().strip() / "members"
        ids |= {path.stem for path in folder.glob("*.pt")}
    return sorted(ids)


def _whole(value: Any, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ConfigError(f"{where} is {value!r}, not a whole number of at least 1")
    return value


def _league_config(run_dir: Path) -> tuple[RunConfig, Path, EvaluationSchedule | None]:
    """A league run's settings from its config.yaml: the keys every run has (RunConfig),
    read strictly, and its evaluation schedule; the league's own keys (rosters, matchmaking,
    PBT) are the league's business (alignrl.league.config)."""
    path = run_dir / CONFIG_FILE
    try:
        data = run_config_data(run_dir, "league run")
    except FileNotFoundError as error:
        raise ExportError(str(error)) from None
    settings = {key: value for key, value in data.items() if key in RunConfig.model_fields}
    config = parse_config(RunConfig, settings, str(path))
    schedule = data.get("schedule")
    sessions = None
    if isinstance(schedule, dict) and {"eval_scenarios", "evaluate_every"} <= set(schedule):
        sessions = EvaluationSchedule(
            _whole(schedule["eval_scenarios"], f"{path}: schedule.eval_scenarios"),
            _whole(schedule["evaluate_every"], f"{path}: schedule.evaluate_every"),
            "iterations",
        )
    return config, path, sessions


def _league_root(member_file: Path) -> Path | None:
    """The league run a member file lies in (best/, initial/, snapshots/ or a checkpoint)."""
    for folder in list(member_file.resolve().parents)[:4]:
        if (folder / "aligners.yaml").exists() and (folder / CONFIG_FILE).exists():
            return folder
    return None


def _only_aligners(state: dict[str, Any], path: Path) -> None:
    spec = state.get("spec")
    if not isinstance(spec, dict):
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
    _only_aligners(state, path)
    weights = {key: value for key, value in state.items() if key != "replay"}
    try:
        agent = Agent(MemberSpec.from_dict(weights["spec"]))
        agent.load_state_dict(weights)
    except (KeyError, TypeError, ValueError, RuntimeError) as error:
        raise CheckpointError(f"{path}: not a usable member checkpoint: {error}") from None
    return agent


def _league_source(run_dir: Path, member: str | None) -> PolicySource:
    config, config_file, sessions = _league_config(run_dir)
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
        agent,
        member_file,
        "league",
        chosen_as,
        run_dir,
        config,
        config_file,
        best=best,
        sessions=sessions,
    )


def _training_source(run_dir: Path | None, checkpoint: Path, chosen_as: str) -> PolicySource:
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
    config_file = run_dir / CONFIG_FILE if run_dir and (run_dir / CONFIG_FILE).exists() else None
    budget = config.budget
    return PolicySource(
        agent,
        checkpoint,
        "training",
        chosen_as,
        run_dir,
        config,
        config_file,
        env_steps=int(env_steps) if env_steps is not None else None,
        sessions=EvaluationSchedule(budget.eval_scenarios, budget.eval_every, "env steps"),
    )


def _file_source(path: Path) -> PolicySource:
    """A .pt file: a league member (in its run, or on its own) or a training checkpoint."""
    state = load_checkpoint(path)
    if state.get("format") != MEMBER_FORMAT:
        run_dir = path.parent.parent if path.parent.name == "checkpoints" else None
        return _training_source(run_dir, path, "file")
    agent = _member(state, path)
    root = _league_root(path)
    if root is None:  # a member file on its own: the run settings are the defaults
        from alignrl.config.experiment import parse_experiment

        history = agent.spec.observation_shape[0]
        config = parse_experiment({"name": agent.id, "history": history}, str(path))
        return PolicySource(agent, path, "member", "file", None, config, None)
    config, config_file, sessions = _league_config(root)
    return PolicySource(agent, path, "league", "file", root, config, config_file, sessions=sessions)


# --- exports and champions ----------------------------------------------------------------


def read_card_file(card_path: Path) -> dict[str, Any]:
    """card.json, as every reader of a card reads it (here and alignrl.deploy.card_schema's
    read_card, which checks it field by field): at most MAX_CARD_BYTES, refused by its size
    before it is parsed; no key twice in one object; no deeper than a card nests; a mapping;
    and its posterior settings within what an instrument family can give them
    (alignrl.posterior.calibration.posterior_options_problem). ExportError naming the file."""
    from alignrl.posterior.calibration import posterior_options_problem

    if not card_path.is_file():
        raise ExportError(f"{card_path} is missing: {card_path.parent} is not an exported policy")
    card = read_json_file(card_path, MAX_CARD_BYTES, ExportError, "a card")
    if not isinstance(card, dict):
        raise ExportError(f"{card_path} holds a {type(card).__name__}, not a policy card")
    task = card.get("task")
    options = task.get("options") if isinstance(task, dict) else None
    bound = posterior_options_problem(options) if isinstance(options, dict) else None
    if bound is not None:
        raise ExportError(f"{card_path}: task.options.{bound[0]} {bound[1]}")
    return card


def _card_field(card: Any, card_path: Path, *keys: str) -> Any:
    """card[keys[0]][keys[1]]...; an ExportError naming the field where it is missing."""
    value = card
    for depth, key in enumerate(keys):
        if not isinstance(value, dict) or key not in value:
            field = ".".join(keys[: depth + 1])
            raise ExportError(f"{card_path} is incomplete or inconsistent: it has no {field}")
        value = value[key]
    return value


def _exported_source(location: Location) -> PolicySource:
    """The member of a safetensors export or a champion: rebuilt from its card's member
    spec, its acting network (and steps seen) loaded from policy.safetensors; the run
    settings its card records (training apparatus, task and options, history)."""
    folder = location.path
    card_path = folder / "card.json"
    what = f"champion:{folder.name}" if location.kind == "champion" else f"the export {folder}"
    card = read_card_file(card_path)
    export_format = _card_field(card, card_path, "export_format")
    if export_format != "safetensors":
        origin = (card.get("source") or {}).get("member_file") if isinstance(card, dict) else None
        raise ExportError(
            f"{what} is a graph export ({export_format}): it runs (alignrl align, alignrl "
            "evaluate) but holds no weights to load into a learner; give its safetensors "
            f"export or the run it was exported from{f' ({origin})' if origin else ''}"
        )
    fields = {
        field.name: _card_field(card, card_path, "member", field.name)
        for field in dataclasses.fields(MemberSpec)
    }
    _only_aligners({"spec": fields}, card_path)
    try:
        spec = MemberSpec.from_dict(fields)
    except (TypeError, ValueError) as error:
        raise ExportError(f"{card_path}: member is not a member spec: {error}") from None
    policy_file = _card_field(card, card_path, "policy_file")
    if policy_file != "policy.safetensors":
        raise ExportError(f"{card_path}: policy_file is {policy_file!r}, not policy.safetensors")
    weights_file = folder / policy_file
    if not weights_file.is_file():
        raise ExportError(f"policy file {weights_file} is missing")
    recorded = card.get("policy_sha256")
    if recorded is not None and file_sha256(weights_file) != recorded:
        raise ExportError(
            f"{card_path}: policy_sha256 {recorded} is not the SHA-256 of {weights_file}: the "
            "card and the policy file are not of one export; export it again"
        )
    steps_seen = _card_field(card, card_path, "member", "steps_seen")
    updates = _card_field(card, card_path, "member", "updates")
    if isinstance(updates, bool) or not isinstance(updates, int) or updates < 0:
        raise ExportError(f"{card_path}: member.updates is {updates!r}, not a whole number")
    agent = Agent(spec)
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    try:
        weights = load_file(str(weights_file), device="cpu")
        agent.load_policy_state(
            {
                "format": POLICY_FORMAT,
                "spec": spec.to_dict(),
                "policy": weights,
                "steps_seen": steps_seen,
            }
        )
    except (OSError, ValueError, RuntimeError, SafetensorError) as error:
        raise ExportError(
            f"policy file {weights_file} does not fit the member its card.json describes "
            f"({str(error).strip()[:300]}): export it again"
        ) from None
    settings = {
        "name": spec.id,
        "task": _card_field(card, card_path, "task", "name"),
        "task_options": _card_field(card, card_path, "task", "options"),
        "history": _card_field(card, card_path, "history"),
        **{
            key: _card_field(card, card_path, "training", key)
            for key in ("apparatus", "apparatus_args", "eval_apparatus", "eval_apparatus_args")
        },
    }
    config = parse_config(RunConfig, settings, f"{card_path} (its training and task)")
    learner_file = None
    if has_learner_state(folder):  # critics, optimizers and counters: checked, then loaded
        try:
            load_learner_state(folder, agent, card)
        except LearnerStateError as error:
            raise ExportError(str(error)) from None
        learner_file = folder / LEARNER_FILE
    chosen_as = "shipped champion" if location.kind == "champion" else "exported policy"
    return PolicySource(
        agent,
        weights_file,
        location.kind,
        chosen_as,
        None,
        config,
        card_path,
        card=card,
        learner_file=learner_file,
    )


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
