"""The league loop (seed section 3): two teams, matched, rated and trained against each other.

One iteration:
1. the matchmaker picks an aligner and a misaligner (one of them the iteration's learner,
   the other drawn by PFSP / uniform / latest from the other team, snapshots included);
2. they play `schedule.matches` matches: the misaligner chooses each start, the aligner
   aligns from it; the aligner learns from the seed's reward, the misaligner is paid what the
   aligner did not recover (the zero-sum payoff of alignrl.envs.rewards);
3. both are rated (Elo, the aligner's score is its success rate) and the payoff recorded;
4. every active member that played stores its experience and learns (snapshots are frozen);
5. the curriculum steps with the aligner's successes.
On a schedule: frozen snapshots join the opponent pool, the weakest members copy stronger ones
(population-based training, with perturbed learning rates and recorded lineage), the best
aligners by rating run an evaluation session, and the league is checkpointed.

A run lives in runs/<name>/:

    config.yaml, aligners.yaml, misaligners.yaml   the resolved experiment and rosters
    checkpoints/LATEST                              names the newest complete checkpoint
    checkpoints/iteration-NNNNNN/                   league.pt + members/<id>.pt (atomic)
    snapshots/<id>@<iteration>.pt                   frozen members of the opponent pool
    initial/<id>.pt                                 the members as they started
    best/<id>.pt, best/best.json                    the best aligners by evaluation session
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
alignrl.league.pbt; this module holds the loop and the run directory.
"""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from alignrl.agents.agent import Agent, MemberSpec
from alignrl.checkpoints import (
    CheckpointError,
    atomic_write_text,
    load_checkpoint,
    remove_partial_writes,
    save_checkpoint,
)
from alignrl.config import dump_experiment
from alignrl.envs import Curriculum
from alignrl.league.backends import Backend, backend_class
from alignrl.league.config import LeagueConfig, Roster, parse_league
from alignrl.league.matches import MatchResult, UniformStarts, WorkerFailedError
from alignrl.league.matchmaking import Matchmaker, MatchmakingConfig, OpponentPool
from alignrl.league.pbt import choose_replacements, copy_id, copy_member, learning_rate
from alignrl.league.ratings import EloConfig, PayoffTable, Ratings
from alignrl.league.warm_starts import member_spec, start_from, warm_starts
from alignrl.metrics import (
    EPISODE_COLUMNS,
    LEAGUE_EVALUATION_COLUMNS,
    LEAGUE_ITERATION_COLUMNS,
    LINEAGE_COLUMNS,
    CsvLog,
    truncate_csv,
)
from alignrl.training import evaluate_policy
from alignrl.yaml_io import read_yaml_file

# WorkerFailedError (alignrl.league.matches) is named here for the CLI, which catches it.
__all__ = ["League", "WorkerFailedError", "leaderboard"]

STATE_FORMAT = "alignrl-league-1"


class League:
    """Both teams, their ratings and opponent pool, and the run directory.

    A league improves aligners by making them play misaligners that learn to find the
    starts they fail from, in a zero-sum game. Each `step` pairs a learner with an opponent
    from the other team (PFSP, uniform or latest; snapshots included), plays and rates
    their matches and lets the active members learn; on a schedule `run` freezes snapshots,
    lets the weakest copy the strongest (`exploit_and_explore`), judges the top aligners on
    held-out scenarios (`evaluate`) and checkpoints. All randomness comes from one numpy
    generator and torch's stream, both checkpointed, so a resumed league plays on as if it
    had never stopped."""

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
        self.ratings = Ratings(EloConfig(config.ratings.initial, config.ratings.k_factor))
        self.payoff = PayoffTable()
        self.pool = OpponentPool(config.matchmaking.max_snapshots)
        mm = config.matchmaking
        self.matchmaker = Matchmaker(
            MatchmakingConfig(
                {"pfsp": mm.pfsp, "uniform": mm.uniform, "latest": mm.latest}, mm.weighting
            )
        )
        for team, roster in self.rosters.items():
            for member in roster.members:
                agent = Agent(member_spec(member, team, config), config.envs, config.device)
                self._add_member(agent)
        knobs = len(config.resolved_task().knobs)
        self.uniform_starts = UniformStarts(
            MemberSpec(UniformStarts.ID, "misaligner", "sac", (1, knobs + 2), knobs, knobs)
        )
        cc = config.curriculum
        self.curriculum = (
            Curriculum(
                level=cc.level,
                minimum=min(cc.level, cc.step),
                step=cc.step,
                window=cc.window,
                raise_at=cc.raise_at,
                lower_at=cc.lower_at,
            )
            if cc.enabled
            else None
        )
        if self.curriculum:
            self.backend.set_complexity(self.curriculum.level)
        self.iteration = 0
        self.env_steps = 0
        self.best: dict[str, dict[str, Any]] = {}  # aligner id -> its best evaluation
        self._snapshot_cache: dict[str, Agent] = {}
        self._tensorboard = None
        self._purge_step: int | None = None  # resumed: TensorBoard drops events from here on
        metrics = self.run_dir / "metrics"
        self.iteration_log = CsvLog(
            metrics / "iterations.csv", list(LEAGUE_ITERATION_COLUMNS), key="iteration"
        )
        self.evaluation_log = CsvLog(
            metrics / "evaluations.csv", list(LEAGUE_EVALUATION_COLUMNS), key="iteration"
        )
        self.lineage_log = CsvLog(metrics / "lineage.csv", list(LINEAGE_COLUMNS), key="iteration")
        self._member_logs: dict[str, tuple[CsvLog, CsvLog]] = {}

    # --- members ------------------------------------------------------------------------

    def _add_member(self, agent: Agent, rating: float | None = None) -> None:
        self.members[agent.id] = agent
        self.pool.add_member(agent.id, agent.spec.team)
        if agent.id not in self.ratings:
            self.ratings.add(agent.id, rating)

    def _member_log(self, member: str) -> tuple[CsvLog, CsvLog]:
        if member not in self._member_logs:
            folder = self.run_dir / "metrics" / "members" / member
            metrics = self.members[member].metric_names
            self._member_logs[member] = (
                CsvLog(folder / "updates.csv", ["env_steps", "updates", *metrics]),
                CsvLog(folder / "episodes.csv", list(EPISODE_COLUMNS)),
            )
        return self._member_logs[member]

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
        if (run_dir / "config.yaml").exists():
            raise FileExistsError(
                f"{run_dir} already holds a run: continue it with `alignrl league resume "
                f"{run_dir}` or choose another --name"
            )
        aligners, sources = warm_starts(config, aligners)
        run_dir.mkdir(parents=True, exist_ok=True)
        for name, roster in (("aligners.yaml", aligners), ("misaligners.yaml", misaligners)):
            atomic_write_text(
                run_dir / name, yaml.safe_dump(roster.model_dump(mode="json"), sort_keys=False)
            )
        league = cls(config, aligners, misaligners, run_dir)
        for member_id, (source, replay) in sources.items():
            start_from(league.members[member_id], source, replay)
        for member_id, agent in league.members.items():  # the starting point
            agent.save(run_dir / "initial" / f"{member_id}.pt")
        # Iteration 0 checkpointed (warm starts included), and config.yaml last: a run killed
        # before it is no run and starts again; one killed after resumes from its start.
        league.checkpoint()
        atomic_write_text(run_dir / "config.yaml", dump_experiment(config))
        return league

    @classmethod
    def resume(cls, run_dir: str | Path, read_only: bool = False) -> League:
        """The league as of its last checkpoint. To continue it, metrics written after that
        checkpoint are dropped (they will be written again); `read_only` (status,
        leaderboard) leaves every file as it is, also while the league runs elsewhere."""
        from alignrl.league.config import load_roster

        run_dir = Path(run_dir)
        path = run_dir / "config.yaml"
        if not path.exists():
            raise FileNotFoundError(f"{run_dir} is not a league run (no config.yaml)")
        config = parse_league(read_yaml_file(path), str(path))
        league = cls(
            config,
            load_roster(run_dir / "aligners.yaml", "aligner"),
            load_roster(run_dir / "misaligners.yaml", "misaligner"),
            run_dir,
        )
        latest = run_dir / "checkpoints" / "LATEST"
        if latest.exists():
            league._restore(run_dir / "checkpoints" / latest.read_text().strip())
        if not read_only:
            league._cut_back_to_checkpoint()
        return league

    def _state(self) -> dict[str, Any]:
        return {
            "format": STATE_FORMAT,
            "iteration": self.iteration,
            "env_steps": self.env_steps,
            "members": {i: agent.spec.to_dict() for i, agent in self.members.items()},
            "ratings": self.ratings.state_dict(),
            "payoff": self.payoff.state_dict(),
            "pool": self.pool.state_dict(),
            "best": json.dumps(self.best),
            "curriculum": self.curriculum.state_dict() if self.curriculum else {},
            "numpy_rng": self.rng.bit_generator.state,
            "torch_rng": torch.get_rng_state(),
            "config": dump_experiment(self.config),
        }

    def checkpoint(self) -> Path:
        """A new checkpoint folder (members first, league state last), then LATEST names
        it; only after that are older folders removed, and the snapshots the pool no longer
        lists. A kill at any moment leaves LATEST naming a complete checkpoint and all it
        refers to; a write that fails (a full disk) removes the new folder and leaves the
        previous checkpoint as it was."""
        root = self.run_dir / "checkpoints"
        folder = root / f"iteration-{self.iteration:06d}"
        if self._tensorboard is not None:
            self._tensorboard.flush()  # the events up to this checkpoint are on disk
        try:
            for member_id, agent in self.members.items():
                agent.save(folder / "members" / f"{member_id}.pt", replay=True)
            save_checkpoint(folder / "league.pt", self._state())
            atomic_write_text(root / "LATEST", folder.name + "\n")
        except OSError:
            if self._latest() != folder.name:
                shutil.rmtree(folder, ignore_errors=True)
            raise
        self._remove_unreferenced()
        return folder

    def _latest(self) -> str | None:
        latest = self.run_dir / "checkpoints" / "LATEST"
        return latest.read_text().strip() if latest.exists() else None

    def _remove_unreferenced(self) -> None:
        """Checkpoint folders other than LATEST's, and snapshot files its pool does not list
        (pruned from it, or frozen after it by a run that was killed)."""
        current = self._latest()
        for folder in (self.run_dir / "checkpoints").glob("iteration-*"):
            if folder.name != current and folder.is_dir():
                shutil.rmtree(folder, ignore_errors=True)
        listed = {snapshot.id for team in ("aligner", "misaligner")
                  for snapshot in self.pool.snapshots(team)}  # fmt: skip
        for path in (self.run_dir / "snapshots").glob("*.pt"):
            if path.stem not in listed:
                path.unlink(missing_ok=True)

    def _cut_back_to_checkpoint(self) -> None:
        """Before a resumed league continues: every file written after its checkpoint goes
        back to what that checkpoint knew (metrics rows, snapshots, unfinished checkpoints and
        writes, TensorBoard events), for the run to write it again."""
        self._remove_unreferenced()
        for folder in ("checkpoints", "snapshots", "best", "metrics", "initial"):
            remove_partial_writes(self.run_dir / folder)
        for log in (self.iteration_log, self.evaluation_log, self.lineage_log):
            log.truncate_after(self.iteration)
        # Every member's, also one that a PBT copy after the checkpoint made (it comes back).
        for path in sorted((self.run_dir / "metrics" / "members").glob("*/*.csv")):
            truncate_csv(path, "env_steps", self.env_steps)
        self._purge_step = self.iteration + 1

    def _restore(self, folder: Path) -> None:
        state = load_checkpoint(folder / "league.pt", self.config.device)
        if state.get("format") != STATE_FORMAT:
            raise CheckpointError(f"{folder}/league.pt: format {state.get('format')!r}")
        self.members, self._snapshot_cache = {}, {}
        self.pool = OpponentPool(self.config.matchmaking.max_snapshots)
        for member_id in state["members"]:
            self.members[member_id] = Agent.load(
                folder / "members" / f"{member_id}.pt", self.config.envs, self.config.device
            )
        self.pool.load_state_dict(state["pool"])
        self.ratings.load_state_dict(state["ratings"])
        self.payoff.load_state_dict(state["payoff"])
        self.best = json.loads(state["best"])
        self.iteration, self.env_steps = int(state["iteration"]), int(state["env_steps"])
        if self.curriculum and state["curriculum"]:
            self.curriculum.load_state_dict(state["curriculum"])
            self.backend.set_complexity(self.curriculum.level)
        self.rng.bit_generator.state = state["numpy_rng"]
        torch.set_rng_state(state["torch_rng"])

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
            aligner, misaligner, matches - uniform, self.rng, learning, on_episode
        )
        played = result
        if uniform:
            self.uniform_starts.rng = np.random.default_rng(int(self.rng.integers(2**62)))
            extra = self.backend.play(
                aligner, self.uniform_starts, uniform, self.rng, {pairing.aligner}, on_episode
            )
            played = result.joined(extra)
            self._board().add_scalar("league/uniform_success_rate", extra.success_rate,
                                     self.iteration + 1)  # fmt: skip
        self.env_steps += sum(played.acquisitions)  # every image of every match
        self.iteration += 1
        # Ratings, payoffs and the success rate logged: the rated matches, the misaligner's.
        self.ratings.update(pairing.aligner, pairing.misaligner, result.success_rate)
        self.payoff.add(pairing.aligner, pairing.misaligner, result.matches, sum(result.successes))
        self.ratings.record(self.iteration)
        self.payoff.record(self.iteration)
        self._log_members(played, aligner, complexity)
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
            "aligner_rating": round(self.ratings.rating(pairing.aligner), 2),
            "misaligner_rating": round(self.ratings.rating(pairing.misaligner), 2),
            "complexity": round(complexity, 4),
            "seconds": round(time.perf_counter() - started, 3),
        }
        self.iteration_log.write([row])
        board = self._board()
        board.add_scalar("league/success_rate", result.success_rate, self.iteration)
        board.add_scalar("league/complexity", complexity, self.iteration)
        for player, rating in self.ratings.ranking(list(self.members)):
            board.add_scalar(f"rating/{player}", rating, self.iteration)
        return row

    def _log_members(self, result: MatchResult, aligner: Agent, complexity: float) -> None:
        for member, rows in result.updates.items():
            if member not in self.members or not rows:
                continue
            updates_log, _ = self._member_log(member)
            agent = self.members[member]
            stride = max(1, len(rows) // 10)  # a few rows per iteration, not every step
            first = agent.updates - len(rows) + 1
            updates_log.write(
                [
                    {
                        "env_steps": self.env_steps,
                        "updates": first + i,
                        **{key: round(value, 6) for key, value in rows[i].items()},
                    }
                    for i in range(0, len(rows), stride)
                ]
            )
        if aligner.id in self.members:
            _, episodes_log = self._member_log(aligner.id)
            episodes_log.write(
                [
                    {
                        "env_steps": self.env_steps,
                        "episode": (self.iteration - 1) * self.config.schedule.matches + i + 1,
                        "return": round(ret, 5),
                        "success": int(ok),
                        "acquisitions": acq,
                        "complexity": complexity,
                    }
                    for i, (ret, ok, acq) in enumerate(
                        zip(result.returns, result.successes, result.acquisitions, strict=True)
                    )
                ]
            )

    def _board(self):
        if self._tensorboard is None:
            from torch.utils.tensorboard import SummaryWriter

            self._tensorboard = SummaryWriter(
                str(self.run_dir / "tensorboard"), purge_step=self._purge_step
            )
        return self._tensorboard

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
            ranking = self.ratings.ranking(self.pool.active(team))
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
                self.lineage_log.write([change])
                changes.append(change)
        return changes

    def session(self, agent: Agent, scenarios: int | None = None, name: str | None = None):
        """A held-out evaluation session of `agent` (mean actions) on the league's
        eval_apparatus, judged at the task's spec; training's random streams are untouched."""
        cfg = self.config
        with torch.random.fork_rng(devices=[]):
            return evaluate_policy(
                lambda observation: agent.act(observation, deterministic=True),
                cfg.eval_apparatus,
                cfg.eval_apparatus_args,
                cfg.resolved_task(),
                cfg.history,
                scenarios or cfg.schedule.eval_scenarios,
                name=name or agent.id,
            )

    def evaluate(self) -> list[dict[str, Any]]:
        """The top aligners by rating run an evaluation session each; the best by
        evaluation are kept in best/."""
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
                "rating": round(rating, 2),
            }
            rows.append(row)
            previous = self.best.get(member_id)
            if previous is None or (result.successes, -result.median_acquisitions) > (
                previous["successes"],
                -previous["median_acquisitions"],
            ):
                self.best[member_id] = row
                self.members[member_id].save(self.run_dir / "best" / f"{member_id}.pt")
        self.evaluation_log.write(rows)
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

    def champion(self) -> dict[str, Any] | None:
        """The best aligner by evaluation session, side by side with the same member as it
        started (untrained), on the same held-out scenarios."""
        path = self.run_dir / "best" / "best.json"
        if not path.exists():
            return None
        ranked = json.loads(path.read_text())
        if not ranked:
            return None
        best = ranked[0]
        champion = Agent.load(self.run_dir / "best" / f"{best['member']}.pt")
        base = best["member"].split("-pbt")[0]
        untrained = Agent.load(self.run_dir / "initial" / f"{base}.pt")
        sessions = {}
        for label, agent in (("champion", champion), ("untrained", untrained)):
            result = self.session(agent)
            sessions[label] = {
                "member": agent.id,
                "successes": result.successes,
                "scenarios": result.scenarios,
                "median_acquisitions": result.median_acquisitions,
            }
        return sessions

    def close(self) -> None:
        """Release the backend's workers (a Ray backend's actors); the run directory is
        untouched."""
        self.backend.close()

    # --- the loop -----------------------------------------------------------------------

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
        while self.iteration < schedule.iterations:
            row = self.step()
            matches_done += row["matches"]
            rate = matches_done / max(time.perf_counter() - started, 1e-9)
            bar.update(1)
            bar.set_postfix(matches_per_s=f"{rate:.1f}", success=f"{row['success_rate']:.2f}")
            it = self.iteration
            if it % schedule.snapshot_every == 0:
                self.snapshot()
            if self.config.pbt.enabled and it % schedule.pbt_every == 0:
                for change in self.exploit_and_explore():
                    if log:
                        log(
                            f"iteration {it}: {change['member']} copies {change['parent']}, "
                            f"replacing {change['replaced']}"
                        )
            if it % schedule.evaluate_every == 0 or it == schedule.iterations:
                for evaluation in self.evaluate():
                    if log:
                        log(
                            f"iteration {it}: {evaluation['member']} aligned "
                            f"{evaluation['successes']}/{evaluation['scenarios']} held-out, "
                            f"median {evaluation['median_acquisitions']:g} acquisitions"
                        )
            if it % schedule.checkpoint_every == 0 or it == schedule.iterations:
                folder = self.checkpoint()
                if log:
                    log(f"checkpoint {folder.name}")
        bar.close()
        if self._tensorboard is not None:
            self._tensorboard.flush()


def leaderboard(league: League) -> list[dict[str, Any]]:
    """Every active member and kept snapshot, per team, best rated first."""
    rows = []
    for team in ("aligner", "misaligner"):
        for player in league.pool.candidates(team):
            spec = league.player(player).spec
            best = league.best.get(player, {})
            rows.append(
                {
                    "member": player,
                    "team": team,
                    "architecture": spec.architecture,
                    "learner": spec.algorithm,
                    "rating": round(league.ratings.rating(player), 1),
                    "snapshot": league.pool.is_snapshot(player),
                    "successes": best.get("successes"),
                    "scenarios": best.get("scenarios"),
                    "median_acquisitions": best.get("median_acquisitions"),
                    "parent": spec.parent,
                }
            )
    return sorted(rows, key=lambda row: (row["team"], -row["rating"]))
