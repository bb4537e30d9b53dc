"""Members' specs, and aligners that start from trained ones (`init_from`, `init_replay`).

`member_spec` gives the shapes a member of either team is built with. `warm_starts` resolves
each `init_from` aligner's learner against the checkpoint or export it names and checks that
its networks fit this league, before any file of the run is written; `start_from` then
loads the trained aligner into the league's member.
"""

from __future__ import annotations

from alignrl.agents.agent import Agent, MemberSpec
from alignrl.checkpoints import CheckpointError
from alignrl.config.learner import LearnerConfig
from alignrl.config_reading import ConfigError
from alignrl.league.config import LeagueConfig, MemberConfig, Roster
from alignrl.runs.training_runs import team_spec

__all__ = ["NETWORK_KEYS", "member_spec", "start_from", "warm_starts"]


def member_spec(member: MemberConfig, team: str, config: LeagueConfig) -> MemberSpec:
    """A roster member of `team` as this league builds it (runs.training_runs.team_spec)."""
    return team_spec(member.id, team, member.learner, config)


# Learner settings that shape a member's networks: a warm-started aligner keeps its source's.
NETWORK_KEYS = (
    "algorithm",
    "encoder",
    "encoder_kwargs",
    "hidden",
    "secret_critics",
    "shared_critic_encoder",
)


def warm_starts(
    config: LeagueConfig, aligners: Roster
) -> tuple[Roster, dict[str, tuple[Agent, bool]]]:
    """The aligner roster with each `init_from` member's learner resolved, and the trained
    aligners those members start from (with whether their replay comes along). A
    warm-started member takes its source's learner settings; the roster's own `learner:`
    keys override the rest (a lower learning_rate for fine-tuning, say), and a key that
    shapes the networks must agree with the source's. A source is anything
    alignrl.runs.sources resolves, but it must bring its critics: an export or a shipped
    champion (champion:NAME) without a learner state holds its acting network alone, and a
    warm start with fresh critics would train the policy on their noise, so it is refused.
    Every check is made here, before the run directory is written."""
    from alignrl.runs.sources import ExportError, require_learner_state, resolve_source

    task = config.resolved_task()
    members, sources = [], {}
    for member in aligners.members:
        if member.init_from is None:
            members.append(member)
            continue
        where = f"aligner {member.id!r}: init_from {member.init_from}"
        try:
            source = resolve_source(member.init_from)
            require_learner_state(source, member.init_from, "a warm start")
        except (ExportError, CheckpointError, OSError, ValueError) as error:
            raise ConfigError(f"{where}: {error}") from None
        if tuple(source.task.knobs) != tuple(task.knobs):
            raise ConfigError(
                f"{where}: trained on task {source.task.name!r} (knobs "
                f"{', '.join(source.task.knobs)}), but this league plays {task.name!r} (knobs "
                f"{', '.join(task.knobs)})"
            )
        spec = source.agent.spec
        inherited = LearnerConfig(algorithm=spec.algorithm, **spec.hyperparameters)
        given = sorted(member.learner.model_fields_set)
        clash = [
            key
            for key in NETWORK_KEYS
            if key in given and getattr(member.learner, key) != getattr(inherited, key)
        ]
        if clash:
            theirs = ", ".join(f"{key}={getattr(inherited, key)!r}" for key in clash)
            raise ConfigError(
                f"{where}: its networks were built with {theirs}; leave these out of the "
                f"member's learner: block or give the same values"
            )
        learner = inherited.model_copy(update={key: getattr(member.learner, key) for key in given})
        if member.init_replay and (
            not source.agent.learner.keeps_replay or source.agent.experience.size == 0
        ):
            raise ConfigError(
                f"{where}: init_replay needs a SAC checkpoint that holds its replay (a "
                f"training run's checkpoints/last.pt); this one has none"
            )
        if member.init_replay and learner.buffer_size != inherited.buffer_size:
            raise ConfigError(
                f"{where}: init_replay keeps the source's replay of capacity "
                f"{inherited.buffer_size}; leave buffer_size out or give the same"
            )
        resolved = MemberConfig(
            id=member.id,
            learner=learner,
            init_from=member.init_from,
            init_replay=member.init_replay,
        )
        wanted = member_spec(resolved, "aligner", config)
        if (wanted.observation_shape, wanted.action_dim, wanted.secret_dim) != (
            spec.observation_shape,
            spec.action_dim,
            spec.secret_dim,
        ):
            raise ConfigError(
                f"{where}: it reads {spec.observation_shape[0]} history rows of "
                f"{spec.observation_shape[1]} features, this league's aligners "
                f"{wanted.observation_shape[0]} of {wanted.observation_shape[1]} (history: "
                f"{config.history})"
            )
        members.append(resolved)
        sources[member.id] = (source.agent, member.init_replay)
    return aligners.model_copy(update={"members": members}), sources


def start_from(agent: Agent, source: Agent, replay: bool) -> None:
    """`agent` takes the trained `source`'s weights, critics, optimizers, entropy coefficient
    and steps seen (its random warm-up is behind it), at its own learning rate; the replay
    only with `replay` (init_replay), else the league fills a new one."""
    agent.load_state_dict(source.state_dict(replay=replay))
    agent.set_learning_rate(float(agent.spec.hyperparameters["learning_rate"]))
