"""League experiments and team rosters, loaded strictly from YAML.

A league experiment (experiments/league-*.yaml) names the apparatus, the task, one roster
file per team (populations/*.yaml), the schedule and the matchmaking; a roster lists a team's
starting members, each with its learner (the `learner:` block of a training experiment).
An unknown key, a wrong type, a missing file or an impossible value stops with the file, the
key path and what was expected.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field, field_validator, model_validator

from alignrl.apparatus.registry import spec_form
from alignrl.config.learner import LearnerConfig
from alignrl.config.run import RunConfig
from alignrl.config_reading import (
    SEED_LIMIT,
    ConfigError,
    Count,
    EnvSteps,
    Scenarios,
    _Strict,
    check_file_name,
    overridden,
    parse_config,
    read_layered,
    read_yaml,
)
from alignrl.evaluation.session import TEST_SEED, VALIDATION_SEED
from alignrl.league.matchmaking import MAX_MEMBERS, MatchmakingConfig, Members
from alignrl.league.ratings import RatingConfig

__all__ = [
    "LeagueConfig",
    "MemberConfig",
    "RayConfig",
    "RayWorkerConfig",
    "Roster",
    "load_league",
    "load_roster",
    "parse_league",
]

# The upper bounds of a league's counts (as alignrl/config_reading.py bounds env steps and
# alignments): the shipped leagues run 600 iterations of 64 matches at most, a team of a few
# members; an iteration takes seconds at least, so 10^6 of them are weeks.
MAX_ITERATIONS = 10**6  # league iterations, and iterations between snapshots, steps, saves
MAX_MATCHES = 10**5  # matches (alignment episodes) of one iteration
Iterations = Annotated[Count, Field(le=MAX_ITERATIONS)]


class MemberConfig(_Strict):
    id: str = Field(min_length=1, description="unique member id, e.g. aligner-gtrxl-sac")
    learner: LearnerConfig = Field(
        default_factory=LearnerConfig, description="same keys as a training experiment's learner"
    )
    init_from: str | None = Field(
        None,
        description="(aligners) start from a trained aligner: a training run, a league run "
        "(its champion), a member .pt file, relative to the working directory, or an export "
        "or champion:NAME that ships its learner state",
    )

    init_replay: bool = Field(
        False,
        description="(with init_from, SAC) also take the source's replay: init_from must then "
        "name a checkpoint that holds one (a training run's checkpoints/last.pt)",
    )

    @model_validator(mode="after")
    def _id_is_a_name(self) -> MemberConfig:
        check_file_name(self.id, f"member id {self.id[:100]!r}")
        if self.init_from is not None and not self.init_from.strip():
            raise ValueError(f"member {self.id!r}: init_from is empty")
        if self.init_replay and self.init_from is None:
            raise ValueError(f"member {self.id!r}: init_replay needs init_from")
        return self


class Roster(_Strict):
    team: Literal["aligner", "misaligner"] = Field(description="which side these members play")
    members: list[MemberConfig] = Field(
        min_length=1, max_length=MAX_MEMBERS, description="the team's starting members"
    )

    @model_validator(mode="after")
    def _unique_ids(self) -> Roster:
        ids = [member.id for member in self.members]
        doubles = sorted({i for i in ids if ids.count(i) > 1})
        if doubles:
            raise ValueError(f"member ids must be unique; repeated: {', '.join(doubles)}")
        if self.team != "aligner":
            warm = [member.id for member in self.members if member.init_from is not None]
            if warm:
                raise ValueError(
                    f"init_from starts aligners from trained ones; misaligners "
                    f"{', '.join(warm)} start fresh (remove it)"
                )
        return self


class ScheduleConfig(_Strict):
    iterations: Iterations = Field(200, ge=1, description="league iterations to run")
    aligner_steps: EnvSteps | None = Field(
        None,
        ge=1,
        description="also stop after the iteration in which an active aligner has taken this "
        "many steps (comparisons at equal aligner env steps); null: iterations alone",
    )
    matches: Count = Field(
        32, ge=1, le=MAX_MATCHES, description="matches (alignment episodes) per iteration"
    )
    snapshot_every: Iterations = Field(25, ge=1, description="iterations between frozen snapshots")
    pbt_every: Iterations = Field(50, ge=1, description="iterations between exploit/explore steps")
    evaluate_every: Iterations = Field(
        50, ge=1, description="iterations between evaluation sessions"
    )
    eval_scenarios: Scenarios = Field(100, ge=1, description="alignments per evaluation session")
    checkpoint_every: Iterations = Field(10, ge=1, description="iterations between checkpoints")
    keep_best: Members = Field(3, ge=1, description="best members kept per team")
    uniform_starts: float = Field(
        0.0,
        ge=0,
        lt=1,
        description="share of a learning aligner's matches started uniformly, not by a "
        "misaligner (unrated)",
    )


class SessionsConfig(_Strict):
    """The league's evaluation sessions on eval_apparatus: validation sessions choose, the
    test session reports (docs/league.md)."""

    validation_seed: Count = Field(
        VALIDATION_SEED,
        ge=0,
        lt=SEED_LIMIT,
        description="seed of the validation sessions' scenarios and starts: they choose the "
        "best members, the champion and the checkpoints kept",
    )
    test_seed: Count = Field(
        TEST_SEED,
        ge=0,
        lt=SEED_LIMIT,
        description="seed of the test session that reports the champion at the end: never "
        "used for a choice; must differ from validation_seed",
    )
    test_scenarios: Scenarios | None = Field(
        None, ge=1, description="alignments of the test session; null: schedule.eval_scenarios"
    )
    test_classical: list[str] | None = Field(
        None,
        description="classical controllers beside the champion on the test session; null: "
        "the task's (alignrl baselines)",
    )

    @model_validator(mode="after")
    def _test_is_not_validation(self) -> SessionsConfig:
        if self.test_seed == self.validation_seed:
            raise ValueError(
                f"test_seed and validation_seed are both {self.test_seed}: the test session "
                "must not replay the scenarios that chose the champion; give it another seed"
            )
        return self


# A copied learning rate is multiplied by one of these: 0 would stop its learning, a negative
# factor would make the rate negative, and beyond 10x one copy leaves the sane range.
PerturbFactor = Annotated[float, Field(gt=0, le=10)]


class PBTConfig(_Strict):
    enabled: bool = Field(True, description="weakest members copy stronger ones")
    fraction: float = Field(0.34, gt=0, lt=1, description="share of a team replaced per step")
    perturb: tuple[PerturbFactor, PerturbFactor] = Field(
        (0.8, 1.25), description="factors a copied learning rate is multiplied by"
    )
    min_gap: float = Field(
        2.0,
        ge=0,
        description="lead a member's rating ordinal (mu - 3 sigma) needs over the one it replaces",
    )


class RayWorkerConfig(_Strict):
    """One Ray worker: the microscope it drives (an apparatus spec, `envs` copies stepped
    together) and where it may run."""

    apparatus: str | None = Field(
        None, description="apparatus spec of this worker's microscope; null: the experiment's"
    )
    apparatus_args: dict[str, Any] | None = Field(
        None,
        description="its arguments; null: the experiment's apparatus_args where apparatus is "
        "null too, else none",
    )
    envs: Count | None = Field(
        None, ge=1, le=1024, description="apparatus copies stepped together; null: the experiment's"
    )
    resources: dict[str, float] = Field(
        default_factory=dict,
        description="Ray resources it needs, e.g. {microscope-a: 1}: it then runs only on the PC "
        "started with them",
    )

    @field_validator("apparatus")
    @classmethod
    def _a_spec(cls, spec: str | None) -> str | None:
        if spec is not None:
            spec_form(spec)  # the form only: a driver may import only on its microscope's PC
        return spec


DEFAULT_RAY_WORKERS = 2  # workers on the experiment's apparatus when ray.workers is null


class RayConfig(_Strict):
    """The Ray workers of `backend: ray` (docs/scaling.md)."""

    address: str | None = Field(
        None,
        description="Ray cluster to join, e.g. 192.168.1.10:6379 or auto; null: start Ray on "
        "this machine",
    )
    workers: list[RayWorkerConfig] | None = Field(
        None,
        min_length=1,
        description="one worker per microscope; null: 2 workers on the experiment's apparatus",
    )
    max_restarts: Count = Field(
        3, ge=0, le=100, description="times a lost worker is restarted within one iteration"
    )
    num_cpus_per_worker: float = Field(1.0, gt=0, description="CPUs Ray reserves per worker")


class LeagueConfig(RunConfig):
    """A league: the run settings of every experiment (RunConfig: apparatus of the matches,
    held-out apparatus, task, history, envs = matches side by side), plus the rosters and
    the schedule."""

    name: str = Field("league", min_length=1, description="run name (runs/<name>/)")
    backend: Literal["inprocess", "ray"] = Field(
        "inprocess", description="where matches are played: here, or on Ray workers"
    )
    ray: RayConfig = Field(
        default_factory=RayConfig, description="the workers of backend ray (docs/scaling.md)"
    )
    aligners: str = Field("populations/aligners.yaml", description="aligner roster file")
    misaligners: str = Field("populations/misaligners.yaml", description="misaligner roster")
    schedule: ScheduleConfig = Field(
        default_factory=ScheduleConfig,
        description="league length; when to snapshot, copy, evaluate, save",
    )
    matchmaking: MatchmakingConfig = Field(
        default_factory=MatchmakingConfig, description="how each match's opponent is drawn"
    )
    ratings: RatingConfig = Field(
        default_factory=RatingConfig, description="ratings (openskill) and their anchors"
    )
    sessions: SessionsConfig = Field(
        default_factory=SessionsConfig,
        description="seeds and size of the validation sessions (choose) and the test session "
        "(reports)",
    )
    pbt: PBTConfig = Field(
        default_factory=PBTConfig, description="population-based training (exploit/explore)"
    )
    design: bool = Field(
        False,
        description="misaligners design the instrument inside the family's box as well as the "
        "start (an apparatus family:NAME; alignrl.envs.design)",
    )
    payoff: Literal["improvement", "regret"] = Field(
        "improvement",
        description="what a misaligner's move scores: what the aligner did not recover (the "
        "seed's), or the aligner's regret against the reference on a twin of the column",
    )
    reference: Literal["hyperbola", "golden-section"] = Field(
        "hyperbola", description="the controller the regret payoff is measured against"
    )

    @model_validator(mode="after")
    def _classical_controllers_align_the_task(self) -> LeagueConfig:
        from alignrl.evaluation.baselines import get_baseline
        from alignrl.evaluation.controllers import check_controller

        task = self.resolved_task()
        keys = [("ratings.anchors", name) for name in self.ratings.anchors or {}]
        keys += [("sessions.test_classical", name) for name in self.sessions.test_classical or []]
        for key, name in keys:
            try:
                check_controller(get_baseline(name), task)
            except ValueError as error:
                raise ValueError(f"{key}: {error}") from None
        return self

    def anchor_ratings(self) -> dict[str, float]:
        """The anchors and their fixed mean ratings (`ratings.anchors`, or its default)."""
        if self.ratings.anchors is not None:
            return dict(self.ratings.anchors)
        # The hyperbola fit takes under a millisecond a match on the shipped recordings; the
        # multi-knob routines tens of images (stigmator-search 40 ms on the analytic column,
        # 13 min more for experiments/stigmation.yaml's 19,200 rated matches): chosen only.
        if len(self.resolved_task().knobs) == 1:
            return {"hyperbola": self.ratings.mu}
        return {}

    def test_classical(self) -> list[str]:
        """The classical controllers of the test session (`sessions.test_classical`, or the
        task's: none for a task without its own)."""
        if self.sessions.test_classical is not None:
            return list(self.sessions.test_classical)
        from alignrl.evaluation.baselines import TASK_BASELINES

        return list(TASK_BASELINES.get(self.resolved_task().name, {}))

    def design_names(self) -> tuple[str, ...]:
        """What a designing misaligner chooses (alignrl.envs.design), read from one apparatus
        of the spec (once per spec: every member's shape asks); () where the misaligners place
        starts only."""
        if not self.design:
            return ()
        return _design_names(self.apparatus, json.dumps(self.apparatus_args, sort_keys=True))

    def misaligner_shape(self) -> tuple[tuple[int, int], int]:
        """As RunConfig's; with `design`, a designer's [1, draw (d), complexity] answered with
        a start per knob and d design values."""
        if not self.design:
            return super().misaligner_shape()
        from alignrl.envs.design import designer_input_shape

        names = self.design_names()
        return designer_input_shape(len(names)), len(self.resolved_task().knobs) + len(names)

    def apparatus_specs(self) -> list[tuple[str, str, dict[str, Any]]]:
        """The experiment's apparatus and every Ray worker's microscope."""
        workers = [
            (f"ray.workers[{number}].apparatus", worker.apparatus, worker.apparatus_args or {})
            for number, worker in enumerate(self.ray.workers or [])
            if worker.apparatus is not None
        ]
        return [*super().apparatus_specs(), *workers]

    def ray_workers(self) -> list[RayWorkerConfig]:
        """The Ray workers with every null filled in from the experiment (new objects)."""
        listed = self.ray.workers or [RayWorkerConfig()] * DEFAULT_RAY_WORKERS
        resolved = []
        for worker in listed:
            if worker.apparatus_args is not None:
                arguments = worker.apparatus_args
            else:
                arguments = self.apparatus_args if worker.apparatus is None else {}
            resolved.append(
                RayWorkerConfig(
                    apparatus=worker.apparatus or self.apparatus,
                    apparatus_args=dict(arguments),
                    envs=worker.envs or self.envs,
                    resources=dict(worker.resources),
                )
            )
        return resolved


@functools.lru_cache(maxsize=16)
def _design_names(spec: str, arguments: str) -> tuple[str, ...]:
    from alignrl.apparatus.registry import make_apparatus
    from alignrl.envs.design import designs_columns

    try:
        unit = make_apparatus(spec, json.loads(arguments))
    except (OSError, ValueError, TypeError) as error:
        raise ConfigError(f"apparatus {spec}: {error}") from None
    if not designs_columns(unit):
        raise ConfigError(
            f"design: true needs an apparatus whose column a misaligner can choose, an "
            f"instrument family with ranges (family:NAME); {spec} is not one"
        )
    return unit.design_names()


def load_roster(path: str | Path, team: str | None = None) -> Roster:
    """A team roster (populations/*.yaml); `team`, when given, must match its `team:`."""
    path = Path(path)
    roster = parse_config(Roster, read_yaml(path, "roster"), str(path))
    if team is not None and roster.team != team:
        raise ConfigError(f"{path}: team is {roster.team!r}, but it is used as the {team} roster")
    return roster


def parse_league(data: Any, source: str = "league config") -> LeagueConfig:
    return parse_config(LeagueConfig, data, source)


def load_league(
    path: str | Path, overrides: Sequence[str] = ()
) -> tuple[LeagueConfig, Roster, Roster]:
    """A league experiment (its `base:` chain merged in) and its two rosters. Roster paths
    are read relative to the working directory first, then to the parent of the folder of
    the chain's first experiment, the one without a base (experiments/ -> the repo): an
    overlay names rosters as its base does."""
    layers = read_layered(Path(path), "league config")
    data, source = overridden(layers.data, layers.source, overrides)  # --set key.path=value
    config = parse_config(LeagueConfig, data, source, check_device=True)
    rosters = []
    for team, name in (("aligner", config.aligners), ("misaligner", config.misaligners)):
        candidate = Path(name)
        if not candidate.exists() and not candidate.is_absolute():
            candidate = layers.root.resolve().parent.parent / name
        if not candidate.exists():
            raise ConfigError(f"{layers.source}: {team}s: roster file {name} does not exist")
        rosters.append(load_roster(candidate, team))
    aligners, misaligners = rosters
    clash = {m.id for m in aligners.members} & {m.id for m in misaligners.members}
    if clash:
        raise ConfigError(f"{layers.source}: ids used in both teams: {', '.join(sorted(clash))}")
    named = {m.id for m in aligners.members} | {m.id for m in misaligners.members}
    anchors = sorted(named & set(config.anchor_ratings()))
    if anchors:
        raise ConfigError(
            f"{layers.source}: member ids {', '.join(anchors)} are the names of anchors "
            "(ratings.anchors): rename the members"
        )
    return config, aligners, misaligners
