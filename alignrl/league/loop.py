"""The league loop (seed section 3): two teams, matched, rated and trained against each other.

One iteration:
1. the matchmaker picks an aligner and a misaligner (one of them the iteration's learner,
   the other drawn by PFSP / uniform / latest from the other team, snapshots included);
2. they play `schedule.matches` matches: the misaligner chooses each start, the aligner
   aligns from it; the aligner learns from the seed's reward, the misaligner is paid what the
   aligner did not recover (the zero-sum payoff of alignrl.envs.rewards);
3. both are rated (openskill, one update per match: the aligner's score is its success) and
   the payoff recorded; the anchors (classical controllers of fixed rating) align the same
   columns from the same starts, and each match against them rates the aligner only;
4. every active member that played stores its experience and learns (snapshots are frozen);
5. the curriculum steps with the aligner's successes.
On a schedule: frozen snapshots join the opponent pool, the weakest members copy stronger ones
(population-based training, with perturbed learning rates and recorded lineage), the best
aligners by rating run a validation session, and the league is checkpointed. Once finished,
the champion (the best by validation) is reported on a test session of its own
(alignrl.league.sessions).

A run lives in runs/<name>/:

    config.yaml, aligners.yaml, misaligners.yaml   the resolved experiment and rosters
    .lock                                           while a process works on the run
    knobs.json                                      the knobs' intervals and steps, for export
    checkpoints/LATEST                              names the newest complete checkpoint
    checkpoints/iteration-NNNNNN/                   league.pt + members/<id>.pt (atomic)
    snapshots/<id>@<iteration>.pt                   frozen members of the opponent pool
    initial/<id>.pt                                 the members as they started
    best/<id>.pt, best/best.json                    the best aligners by validation session
    test.json                                       the champion's test session (at the end)
    metrics/iterations.csv, metrics/evaluations.csv, metrics/lineage.csv
    metrics/members/<id>/updates.csv|episodes.csv   per-member learner figures (alignrl report)
    tensorboard/

Whatever the newest checkpoint refers to stays on disk until a newer one is LATEST (a
snapshot leaving the pool is deleted only then), so a run killed at any moment resumes; the
resumed run cuts every file back to that checkpoint (metrics rows, snapshots frozen after it,
TensorBoard events) and, being deterministic given it, writes them again as they were.

Matches run through the backend `backend:` names (alignrl.league.backends: in this process,
or on Ray workers where the microscopes are, alignrl.league.ray_backend and docs/scaling.md);
League sees only the MatchResult either gives back. Members' shapes and warm starts from
trained aligners are in alignrl.league.warm_starts, the population-based training rule in
alignrl.league.pbt, writing and reading checkpoints in alignrl.league.checkpointing, the
metrics CSVs and TensorBoard events in alignrl.league.logs; this module holds the loop.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from alignrl.agents.agent import Agent
from alignrl.checkpoints import CheckpointError, atomic_write_text
from alignrl.config.experiment import dump_experiment
from alignrl.config_reading import ConfigError
from alignrl.envs import Curriculum
from alignrl.intervals import success_text
from alignrl.league.backends import Backend, backend_class
from alignrl.league.checkpointing import (
    STATE_FORMAT,
    latest_checkpoint,
    read_checkpoint,
    remove_partial_files,
    remove_unreferenced,
    write_checkpoint,
)
from alignrl.league.config import LeagueConfig, Roster, parse_league
from alignrl.league.logs import LeagueLogs
from alignrl.league.matches import MatchResult, UniformStarts, WorkerFailedError
from alignrl.league.matchmaking import Matchmaker, OpponentPool
from alignrl.league.pbt import choose_replacements, copy_id, copy_member, learning_rate
from alignrl.league.ratings import PayoffTable, Rating, Ratings
from alignrl.league.sessions import (
    VALIDATION,
    champion_test_session,
    policy_session,
    write_test,
)
from alignrl.league.standings import leaderboard
from alignrl.league.warm_starts import member_spec, start_from, warm_starts
from alignrl.runs.state import (
    CONFIG_FILE,
    knob_limits,
    record_knobs,
    restore_rng,
    rng_state,
    run_config_data,
)

# WorkerFailedError (alignrl.league.matches) is named here for the CLI, which catches it;
# STATE_FORMAT (alignrl.league.checkpointing) for older importers, leaderboard
# (alignrl.league.standings) for its callers.
__all__ = ["STATE_FORMAT", "League", "WorkerFailedError", "leaderboard"]


class League:
    """Both teams, their ratings and opponent pool, and the run directory.

    A league improves aligners by making them play misaligners that learn to find the
    starts they fail from, in a zero-sum game. Each `step` pairs a learner with an opponent
    from the other team (PFSP, uniform or latest; snapshots included), plays and rates
    their matches and lets the active members learn; on a schedule `run` freezes snapshots,
    lets the weakest copy the strongest (`exploit_and_explore`), judges the top aligners on
    validation sessions (`evaluate`) and checkpoints; once finished, `test` reports the
    champion on a test session that chose nothing. Ratings are openskill's, pinned to the
    anchors: classical controllers that align twins of the same columns from the same starts
    and whose ratings never move. All randomness comes from one numpy generator and torch's
    stream, both checkpointed, so a resumed league plays on as if it had never stopped."""

    def __init__(
        self, config: LeagueConfig, aligners: Roster, misaligners: Roster, run_dir: Path
    ) -> None:
        self.config, self.run_dir = config, Path(run_dir)
        self.rosters = {"aligner": aligners, "misaligner": misaligners}
        torch.set_num_threads(config.threads)
        torch.manual_seed(config.seed)
        self.rng = np.random.default_rng(config.seed)
        self.backend: Backend = backend_class(config.backend)(config)
        self.members: dict[str, Agent] = {}
        self.ratings = Ratings(config.ratings)
        anchors = config.anchor_ratings()
        clash = sorted(set(anchors) & {m.id for r in (aligners, misaligners) for m in r.members})
        if clash:
            raise ConfigError(
                f"member ids {', '.join(clash)} are the names of anchors (ratings.anchors): "
                "rename the members"
            )
        for anchor, mu in anchors.items():
            self.ratings.pin(anchor, mu)
        self.payoff = PayoffTable()
        # The matches against the anchors: (aligner, anchor) -> the aligner's score; per
        # anchor [matches, those it aligned within spec]; rated matches without anchors.
        self.anchor_payoff = PayoffTable()
        self.anchor_record: dict[str, list[int]] = {anchor: [0, 0] for anchor in anchors}
        self.unanchored = 0
        self.pool = OpponentPool(config.matchmaking.max_snapshots)
        self.matchmaker = Matchmaker(config.matchmaking)
        for team, roster in self.rosters.items():
            for member in roster.members:
                agent = Agent(member_spec(member, team, config), config.envs, config.device)
                self._add_member(agent)
        knobs = len(config.resolved_task().knobs)
        self.uniform_starts = UniformStarts.for_shape(*config.misaligner_shape(), knobs)
        self.design_names = config.design_names()  # what a designing misaligner chooses
        self.curriculum = Curriculum.from_config(config.curriculum)
        if self.curriculum:
            self.backend.set_complexity(self.curriculum.level)
        self.iteration = 0
        self.env_steps = 0
        self.best: dict[str, dict[str, Any]] = {}  # aligner id -> its best evaluation
        self._snapshot_cache: dict[str, Agent] = {}
        self.logs = LeagueLogs(self.run_dir)

    # --- members ------------------------------------------------------------------------

    def _add_member(self, agent: Agent, rating: Rating | None = None) -> None:
        self.members[agent.id] = agent
        self.pool.add_member(agent.id, agent.spec.team)
        if agent.id not in self.ratings:
            self.ratings.add(agent.id, rating)

    def player(self, player: str) -> Agent:
        """An active member, or a frozen snapshot loaded from its file."""
        if player in self.members:
            return self.members[player]
        if player not in self._snapshot_cache:
            self._snapshot_cache = {  # a small cache: snapshots come and go
                key: value for key, value in self._snapshot_cache.items() if key in self.pool
            }
            # Building a network draws on torch's random stream: loading a snapshot must not,
            # or a resumed league (which loads it at another moment) would play differently.
            with torch.random.fork_rng(devices=[]):
                self._snapshot_cache[player] = Agent.load(
                    self._snapshot_path(player), self.config.envs, self.config.device
                )
        return self._snapshot_cache[player]

    def _snapshot_path(self, player: str) -> Path:
        return self.run_dir / "snapshots" / f"{player}.pt"

    # --- run directory ------------------------------------------------------------------

    @classmethod
    def create(
        cls,
        config: LeagueConfig,
        aligners: Roster,
        misaligners: Roster,
        runs_root: str | Path = "runs",
    ) -> League:
        run_dir = Path(runs_root) / config.name
        backend_class(config.backend)  # a backend that cannot run here stops before any file
        if (run_dir / CONFIG_FILE).exists():
            raise FileExistsError(
                f"{run_dir} already holds a run: continue it with `alignrl league resume "
                f"{run_dir}`, choose another --name, or replace it with --force"
            )
        aligners, sources = warm_starts(config, aligners)
        knobs = _training_knobs(config)
        run_dir.mkdir(parents=True, exist_ok=True)
        for name, roster in (("aligners.yaml", aligners), ("misaligners.yaml", misaligners)):
            atomic_write_text(
                run_dir / name, yaml.safe_dump(roster.model_dump(mode="json"), sort_keys=False)
            )
        if knobs is not None:
            record_knobs(run_dir, config.apparatus, knobs)
        league = cls(config, aligners, misaligners, run_dir)
        for member_id, (source, replay) in sources.items():
            start_from(league.members[member_id], source, replay)
        for member_id, agent in league.members.items():  # the starting point
            agent.save(run_dir / "initial" / f"{member_id}.pt")
        # Iteration 0 checkpointed (warm starts included), and config.yaml last: a run killed
        # before it is no run and starts again; one killed after resumes from its start.
        league.checkpoint()
        atomic_write_text(run_dir / CONFIG_FILE, dump_experiment(config))
        return league

    @classmethod
    def resume(cls, run_dir: str | Path, read_only: bool = False) -> League:
        """The league as of its last checkpoint. To continue it, metrics written after that
        checkpoint are dropped (they will be written again); `read_only` (status,
        leaderboard) leaves every file as it is, also while the league runs elsewhere."""
        from alignrl.league.config import load_roster

        run_dir = Path(run_dir)
        config = parse_league(run_config_data(run_dir, "league run"), str(run_dir / CONFIG_FILE))
        league = cls(
            config,
            load_roster(run_dir / "aligners.yaml", "aligner"),
            load_roster(run_dir / "misaligners.yaml", "misaligner"),
            run_dir,
        )
        latest = latest_checkpoint(run_dir)
        if latest is not None:
            league._restore(run_dir / "checkpoints" / latest)
        if not read_only:
            league._cut_back_to_checkpoint()
        return league

    def _state(self) -> dict[str, Any]:
        return {
            "format": STATE_FORMAT,
            "iteration": self.iteration,
            "env_steps": self.env_steps,
            "members": {i: agent.spec.to_dict() for i, agent in self.members.items()},
            "ratings": json.dumps(self.ratings.state_dict()),
            "payoff": self.payoff.state_dict(),
            "anchors": json.dumps(
                {
                    "payoff": self.anchor_payoff.state_dict(),
                    "record": self.anchor_record,
                    "unanchored": self.unanchored,
                }
            ),
            "pool": self.pool.state_dict(),
            "best": json.dumps(self.best),
            "curriculum": self.curriculum.state_dict() if self.curriculum else {},
            **rng_state(self.rng),
            "config": dump_experiment(self.config),
        }

    def checkpoint(self) -> Path:
        """A new checkpoint (alignrl.league.checkpointing: members first, league state last,
        then LATEST), and only then older folders and the snapshots the pool no longer lists
        removed. A kill at any moment leaves a complete checkpoint to resume from."""
        self.logs.flush()  # the events up to this checkpoint are on disk
        folder = write_checkpoint(self.run_dir, self.iteration, self.members, self._state())
        remove_unreferenced(self.run_dir, self._listed_snapshots())
        return folder

    def _listed_snapshots(self) -> set[str]:
        return {
            snapshot.id
            for team in ("aligner", "misaligner")
            for snapshot in self.pool.snapshots(team)
        }

    def _cut_back_to_checkpoint(self) -> None:
        """Before a resumed league continues: every file written after its checkpoint goes
        back to what that checkpoint knew (metrics rows, snapshots, unfinished checkpoints and
        writes, TensorBoard events), for the run to write it again."""
        remove_unreferenced(self.run_dir, self._listed_snapshots())
        remove_partial_files(self.run_dir)
        self.logs.cut_back(self.iteration, self.env_steps)

    def _restore(self, folder: Path) -> None:
        state, self.members = read_checkpoint(folder, self.config.envs, self.config.device)
        self._snapshot_cache = {}
        self.pool = OpponentPool(self.config.matchmaking.max_snapshots)
        self.pool.load_state_dict(state["pool"])
        self.ratings.load_state_dict(json.loads(state["ratings"]))
        for anchor, mu in self.config.anchor_ratings().items():
            if anchor not in self.ratings:  # named after the checkpoint: pinned from now on
                self.ratings.pin(anchor, mu)
        self.payoff.load_state_dict(state["payoff"])
        anchors = json.loads(state["anchors"])
        self.anchor_payoff.load_state_dict(anchors["payoff"])
        self.anchor_record = {name: list(record) for name, record in anchors["record"].items()}
        self.unanchored = int(anchors["unanchored"])
        self.best = json.loads(state["best"])
        self.iteration, self.env_steps = int(state["iteration"]), int(state["env_steps"])
        if self.curriculum and state["curriculum"]:
            self.curriculum.load_state_dict(state["curriculum"])
            self.backend.set_complexity(self.curriculum.level)
        try:
            restore_rng(self.rng, state)
        except ValueError as error:
            raise CheckpointError(f"{folder}/league.pt: {error}") from None

    # --- one iteration -----------------------------------------------------------------

    def step(self) -> dict[str, Any]:
        started = time.perf_counter()
        pairing = self.matchmaker.select_pair(self.rng, self.payoff, self.pool, self.iteration)
        aligner, misaligner = self.player(pairing.aligner), self.player(pairing.misaligner)
        learning = {p for p in (pairing.aligner, pairing.misaligner) if p in self.members}
        complexity = self.backend.complexity

        def on_episode(success: bool) -> None:
            if self.curriculum:
                self.backend.set_complexity(self.curriculum.record(success))

        matches = self.config.schedule.matches
        # On an aligner's turn a share of its matches start uniformly (unrated): the
        # misaligners hunt its weaknesses, these keep the starts it is judged on in view.
        uniform = 0
        if pairing.learner == pairing.aligner:
            uniform = min(round(matches * self.config.schedule.uniform_starts), matches - 1)
        result = self.backend.play(
            aligner, misaligner, matches - uniform, self.rng, learning, on_episode, anchored=True
        )
        played = result
        if uniform:
            self.uniform_starts.rng = np.random.default_rng(int(self.rng.integers(2**62)))
            extra = self.backend.play(
                aligner, self.uniform_starts, uniform, self.rng, {pairing.aligner}, on_episode
            )
            played = result.joined(extra)
            self.logs.add_scalar(
                "league/uniform_success_rate", extra.success_rate, self.iteration + 1
            )
        self.env_steps += sum(played.acquisitions)  # every image of every match
        self.iteration += 1
        # Ratings, payoffs and the success rate logged: the rated matches, the misaligner's.
        # The aligner's rated score: its success, or under the regret payoff how it fared
        # against the reference (alignrl.envs.design).
        self.ratings.update(pairing.aligner, pairing.misaligner, result.rated)
        self.payoff.add(pairing.aligner, pairing.misaligner, result.matches, sum(result.rated))
        self._rate_against_anchors(pairing.aligner, result)
        self.ratings.record(self.iteration)
        self.payoff.record(self.iteration)
        first_episode = (self.iteration - 1) * self.config.schedule.matches + 1
        # The pairing's id, not the player's: a snapshot loaded from file carries its live
        # member's id, and its matches are not that member's episodes.
        self.logs.write_members(
            played, self.members, pairing.aligner, self.env_steps, first_episode, complexity
        )
        self.logs.write_designs(
            self.iteration, aligner.id, misaligner.id, result, self.design_names
        )
        row = {
            "iteration": self.iteration,
            "env_steps": self.env_steps,
            "aligner": pairing.aligner,
            "misaligner": pairing.misaligner,
            "learner": pairing.learner,
            "matches": played.matches,
            "success_rate": round(result.success_rate, 4),
            "mean_acquisitions": round(float(np.mean(played.acquisitions)), 3),
            "aligner_payoff": round(float(np.mean(result.payoffs)), 4),
            "aligner_rating": round(self.ratings.rating(pairing.aligner).mu, 2),
            "misaligner_rating": round(self.ratings.rating(pairing.misaligner).mu, 2),
            "complexity": round(complexity, 4),
            "seconds": round(time.perf_counter() - started, 3),
        }
        self.logs.iterations.write([row])
        self.logs.add_scalar("league/success_rate", result.success_rate, self.iteration)
        self.logs.add_scalar("league/complexity", complexity, self.iteration)
        for player, rating in self.ratings.ranking(list(self.members)):
            self.logs.add_scalar(f"rating/{player}", rating.mu, self.iteration)
        return row

    def _rate_against_anchors(self, aligner: str, result: MatchResult) -> None:
        """Each anchor's matches of the batch rate the aligner (never the anchor)."""
        for anchor, scores in result.anchor_scores.items():
            self.ratings.update(aligner, anchor, scores)
            self.anchor_payoff.add(aligner, anchor, len(scores), sum(scores))
            record = self.anchor_record.setdefault(anchor, [0, 0])
            record[0] += len(scores)
            record[1] += sum(result.anchor_successes[anchor])
        if self.anchor_record:
            self.unanchored += result.matches - result.anchored

    # --- snapshots, PBT, evaluation ---------------------------------------------------

    def snapshot(self) -> list[str]:
        """Freeze every active member into the opponent pool. The files of snapshots it
        pushes out stay until the next checkpoint, which no longer lists them, is LATEST."""
        frozen = []
        for member_id, agent in self.members.items():
            snapshot_id = self.pool.freeze(member_id, self.iteration)
            agent.save(self._snapshot_path(snapshot_id))
            self.ratings.add(snapshot_id, self.ratings.rating(member_id))
            frozen.append(snapshot_id)
        return frozen

    def exploit_and_explore(self) -> list[dict[str, Any]]:
        """Per team, the weakest members by rating are replaced by copies of the strongest
        (weights, optimizer state, hyperparameters), with a perturbed learning rate
        (alignrl.league.pbt)."""
        pbt, changes = self.config.pbt, []
        for team in ("aligner", "misaligner"):
            # Ranked, and the lead measured, by the ordinal mu - 3 sigma.
            ranking = [(m, r.ordinal) for m, r in self.ratings.ranking(self.pool.active(team))]
            rates = {member: learning_rate(self.members[member].spec) for member, _ in ranking}
            for replacement in choose_replacements(
                ranking, rates, pbt.fraction, pbt.min_gap, pbt.perturb, self.rng
            ):
                new_id = copy_id(replacement.parent, self.iteration, replacement.position)
                copy = copy_member(
                    self.members[replacement.parent],
                    new_id,
                    replacement.learning_rate,
                    self.config.envs,
                    self.config.device,
                )
                del self.members[replacement.replaced]
                self.pool.remove_member(replacement.replaced)
                self._add_member(copy, self.ratings.rating(replacement.parent))
                change = {
                    "iteration": self.iteration,
                    "member": new_id,
                    "parent": replacement.parent,
                    "replaced": replacement.replaced,
                    "learning_rate": f"{replacement.learning_rate:.3g}",
                }
                self.logs.lineage.write([change])
                changes.append(change)
        return changes

    def session(
        self,
        agent: Agent,
        scenarios: int | None = None,
        name: str | None = None,
        seed: int | None = None,
    ):
        """A session of `agent` (mean actions) on the league's eval_apparatus, judged at the
        task's spec, on the validation scenarios unless `seed` names others; training's
        random streams are untouched."""
        cfg = self.config
        return policy_session(
            agent,
            cfg,
            cfg.sessions.validation_seed if seed is None else seed,
            scenarios or cfg.schedule.eval_scenarios,
            name or agent.id,
        )

    def evaluate(self) -> list[dict[str, Any]]:
        """The top aligners by rating run a validation session each; the best by validation
        are kept in best/ (the first is the champion)."""
        cfg, rows = self.config, []
        top = self.ratings.ranking(self.pool.active("aligner"))[: cfg.schedule.keep_best]
        for member_id, rating in top:
            result = self.session(self.members[member_id], name=member_id)
            row = {
                "iteration": self.iteration,
                "member": member_id,
                "successes": result.successes,
                "scenarios": result.scenarios,
                "median_acquisitions": result.median_acquisitions,
                "p90_acquisitions": result.p90_acquisitions,
                "rating": round(rating.mu, 2),
            }
            rows.append(row)
            previous = self.best.get(member_id)
            if previous is None or (result.successes, -result.median_acquisitions) > (
                previous["successes"],
                -previous["median_acquisitions"],
            ):
                self.best[member_id] = {**row, "session": VALIDATION}
                self.members[member_id].save(self.run_dir / "best" / f"{member_id}.pt")
        self.logs.evaluations.write(rows)
        ranked = sorted(
            self.best.values(), key=lambda r: (-r["successes"], r["median_acquisitions"])
        )
        keep = {row["member"] for row in ranked[: cfg.schedule.keep_best]}
        # best.json before the files it stops listing go: it never names a missing one.
        atomic_write_text(
            self.run_dir / "best" / "best.json",
            json.dumps(ranked[: cfg.schedule.keep_best], indent=2),
        )
        for path in (self.run_dir / "best").glob("*.pt"):
            if path.stem not in keep:
                path.unlink(missing_ok=True)
        self.best = {member: row for member, row in self.best.items() if member in keep}
        return rows

    def test(self) -> dict[str, Any] | None:
        """The champion (the best by validation session) on the test session, beside the
        same member as it started (untrained) and the classical controllers, all on the same
        scenarios of the test seed, which chose nothing; written to test.json. None before the
        first validation session."""
        path = self.run_dir / "best" / "best.json"
        ranked = json.loads(path.read_text()) if path.exists() else []
        if not ranked:
            return None
        chosen = ranked[0]
        champion = Agent.load(self.run_dir / "best" / f"{chosen['member']}.pt")
        base = chosen["member"].split("-pbt")[0]
        untrained = Agent.load(self.run_dir / "initial" / f"{base}.pt")
        data = champion_test_session(self.config, champion, untrained, chosen, self.iteration)
        write_test(self.run_dir, data)
        return data

    def close(self) -> None:
        """Release the backend's workers (a Ray backend's actors); the run directory is
        untouched."""
        self.backend.close()

    # --- the loop -----------------------------------------------------------------------

    def finished(self) -> bool:
        """Whether the schedule is done: every iteration played, or an active aligner has
        taken `schedule.aligner_steps` steps."""
        schedule = self.config.schedule
        if self.iteration >= schedule.iterations:
            return True
        if schedule.aligner_steps is None:
            return False
        steps = [self.members[m].steps_seen for m in self.pool.active("aligner")]
        return max(steps, default=0) >= schedule.aligner_steps

    def run(self, progress: bool = True, log: Callable[[str], None] | None = None) -> None:
        from tqdm import tqdm

        schedule = self.config.schedule
        bar = tqdm(
            total=schedule.iterations,
            initial=self.iteration,
            unit="it",
            disable=not progress,
            desc=self.config.name,
            dynamic_ncols=True,
        )
        matches_done, started = 0, time.perf_counter()
        while not self.finished():
            row = self.step()
            matches_done += row["matches"]
            rate = matches_done / max(time.perf_counter() - started, 1e-9)
            bar.update(1)
            bar.set_postfix(matches_per_s=f"{rate:.1f}", success=f"{row['success_rate']:.2f}")
            it, last = self.iteration, self.finished()
            if it % schedule.snapshot_every == 0:
                self.snapshot()
            # No copy at the last iteration: no training follows, and a copy would only
            # duplicate its parent (same weights, same rating) in the weakest's place.
            if self.config.pbt.enabled and it % schedule.pbt_every == 0 and not last:
                for change in self.exploit_and_explore():
                    if log:
                        log(
                            f"iteration {it}: {change['member']} copies {change['parent']}, "
                            f"replacing {change['replaced']}"
                        )
            if it % schedule.evaluate_every == 0 or last:
                for evaluation in self.evaluate():
                    if log:
                        log(
                            f"iteration {it}: {evaluation['member']} aligned "
                            f"{success_text(evaluation['successes'], evaluation['scenarios'])} "
                            "on validation, "
                            f"median {evaluation['median_acquisitions']:g} acquisitions"
                        )
            if it % schedule.checkpoint_every == 0 or last:
                folder = self.checkpoint()
                if log:
                    log(f"checkpoint {folder.name}")
        bar.close()
        self.logs.flush()


def _training_knobs(config: LeagueConfig) -> list[dict[str, Any]] | None:
    """The task knobs' intervals and steps on the league's apparatus, for knobs.json. None
    where it cannot be opened on this machine (a Ray league whose drivers live on the
    microscopes' PCs): an export of such a run opens the apparatus to read them, as one of a
    run made before alignrl recorded them does."""
    from alignrl.apparatus.base import ApparatusError
    from alignrl.apparatus.registry import make_apparatus

    try:
        apparatus = make_apparatus(config.apparatus, config.apparatus_args)
    except (ApparatusError, ImportError, OSError, ValueError):
        return None
    return knob_limits(config.resolved_task(), apparatus.knobs)
