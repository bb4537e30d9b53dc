"""`alignrl adapt`: a pre-trained aligner trains on a new instrument, every call shielded.

The new instrument is `fake_drivers:ParabolicLens`, a driver loaded by import path that, like
a real column, cannot tell its best edge width (the spec is absolute, --spec-px) but, being
simulated, knows its optimum (the critics' secret passes the shield).
"""

from __future__ import annotations

import copy
import csv
import json
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from alignrl.adaptation import adaptation_config
from alignrl.agents.agent import Agent
from alignrl.apparatus import MeasurementError, make_apparatus
from alignrl.apparatus.synthetic import PRESET_DIR, load_sem_config
from alignrl.apparatus.training_shield import TrainingShield
from alignrl.checkpoints import load_checkpoint
from alignrl.cli import main
from alignrl.config.experiment import parse_experiment
from alignrl.config.task_options import TaskOptions
from alignrl.envs import AlignmentEnv
from alignrl.envs.core import feature_layout
from alignrl.envs.hindsight import HindsightSecrets
from alignrl.envs.task import get_task
from alignrl.runs.sources import resolve_source
from alignrl.training import Trainer, start_adaptation
from alignrl.transitions import Transition

LENS = "fake_drivers:ParabolicLens"
SPEC_PX = 2.563 * 1.15  # 1.15 x the lens's best edge width (sigma0 = 1 px)
SMALL = {
    "encoder_kwargs": {"hidden": [32]},
    "hidden": [32, 32],
    "batch_size": 32,
    "learning_starts": 32,
    "random_steps": 64,
}


def _pretrained(root: Path, steps: int, learner: dict, complexity: float = 1.0) -> Path:
    """An aligner trained on the shipped recordings: the source of an adaptation."""
    settings = {
        "name": "source",
        "seed": 3,
        "envs": 4,
        "complexity": complexity,
        "learner": learner,
        "budget": {"env_steps": steps, "eval_every": steps, "eval_scenarios": 4},
    }
    Trainer.create(parse_experiment(settings), root).run(progress=False)
    return root / "source"


@pytest.fixture(scope="module")
def small_source(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _pretrained(tmp_path_factory.mktemp("pre"), 200, SMALL)


def _config(source, steps: int, name: str = "adapted", **changes):
    """The adaptation config of these tests: the fake lens, 4 envs, an absolute spec."""
    return adaptation_config(
        source,
        name=name,
        apparatus=changes.pop("apparatus", LENS),
        apparatus_args=changes.pop("apparatus_args", {}),
        steps=steps,
        eval_scenarios=4,
        envs=4,
        seed=1,
        spec_px=SPEC_PX,
        **changes,
    )


def _adapt(source_dir: Path, root: Path, steps: int, **changes) -> Trainer:
    source = resolve_source(source_dir)
    return start_adaptation(_config(source, steps, **changes), source, root)


def test_an_adaptation_starts_from_the_source_with_an_empty_replay(
    small_source: Path, tmp_path: Path
) -> None:
    source = resolve_source(small_source)
    trainer = _adapt(small_source, tmp_path, 100)
    histories = np.random.default_rng(0).uniform(-1, 1, (16, 8, 7)).astype(np.float32)
    np.testing.assert_array_equal(
        trainer.agent.act(histories), source.agent.act(histories)
    )  # the policy, and the critics and entropy coefficient with it
    for name, value in source.agent.learner.state_dict().items():
        if isinstance(value, torch.Tensor):
            assert torch.equal(trainer.agent.learner.state_dict()[name], value), name
    assert trainer.agent.replay.size == 0  # transitions of the old instrument stay behind
    assert trainer.agent.steps_seen == source.agent.steps_seen  # no random warm-up again
    config = yaml.safe_load((tmp_path / "adapted" / "config.yaml").read_text())
    assert config["adaptation"]["source_member"] == source.agent.id
    assert config["task_options"]["success_absolute_px"] == pytest.approx(SPEC_PX)
    # Checkpointed at once: a run killed before its first scheduled checkpoint resumes
    # from the source, not from an untrained aligner.
    resumed = Trainer.resume(tmp_path / "adapted")
    np.testing.assert_array_equal(resumed.agent.act(histories), source.agent.act(histories))
    trainer.run(progress=False)
    assert trainer.env_steps >= 100
    assert trainer.agent.steps_seen == source.agent.steps_seen + trainer.env_steps
    assert trainer.agent.replay.size == trainer.env_steps
    # The zero-shot session is on record at 0 steps, and what the run keeps as its best is
    # never worse on that session than what it started from.
    with (tmp_path / "adapted" / "metrics" / "evaluations.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert rows[0]["env_steps"] == "0" and len(rows) >= 2
    assert trainer.best_successes == max(int(row["successes"]) for row in rows)
    best = load_checkpoint(tmp_path / "adapted" / "checkpoints" / "best.pt")
    assert best["evaluation"]["successes"] == trainer.best_successes >= int(rows[0]["successes"])


def test_during_the_critic_warm_up_only_the_critics_learn(
    small_source: Path, tmp_path: Path
) -> None:
    source = resolve_source(small_source)
    trainer = _adapt(small_source, tmp_path, 120, critic_warmup_steps=120)
    histories = np.random.default_rng(0).uniform(-1, 1, (16, 8, 7)).astype(np.float32)
    critic_before = copy.deepcopy(trainer.agent.learner.q1.state_dict())
    trainer.run(progress=False)
    assert trainer.agent.updates > 0
    np.testing.assert_array_equal(trainer.agent.act(histories), source.agent.act(histories))
    after = trainer.agent.learner.q1.state_dict()
    assert any(not torch.equal(critic_before[k], v) for k, v in after.items())
    # Past the warm-up the policy learns too; the setting is on record and survives a resume.
    config = yaml.safe_load((tmp_path / "adapted" / "config.yaml").read_text())
    assert config["adaptation"]["critic_warmup_steps"] == 120
    config["budget"]["env_steps"] = 200
    (tmp_path / "adapted" / "config.yaml").write_text(yaml.safe_dump(config))
    resumed = Trainer.resume(tmp_path / "adapted")
    resumed.run(progress=False)
    assert not np.array_equal(resumed.agent.act(histories), source.agent.act(histories))
    # The learner's losses are on record every 50th update, counted on from the source's.
    with (tmp_path / "adapted" / "metrics" / "updates.csv").open() as handle:
        numbers = [int(row["updates"]) for row in csv.DictReader(handle)]
    start = source.agent.updates
    assert numbers == list(range((start // 50 + 1) * 50, resumed.agent.updates + 1, 50))


def test_hindsight_secrets_stand_the_sharpest_reading_in_for_the_optimum() -> None:
    hindsight = HindsightSecrets(np.array([True, False, True]), optimum="sharpest")
    position = lambda *values: np.array(values, float)[:, None]  # noqa: E731 (3 slots, 1 knob)
    hindsight.start({"position": position(0.1, 0.5, 0.9), "edge_width_px": [9.0, 1.0, 8.0]})
    observations = [np.full((3, 2, 2), float(t)) for t in range(4)]
    steps = [  # (positions after the step, widths read there, done)
        (position(0.4, 0.5, 0.7), [4.0, 1.0, 5.0], [False, False, False]),
        (position(0.6, 0.5, 0.6), [3.0, 1.0, 6.0], [False, False, True]),
        (position(0.5, 0.5, 0.2), [np.nan, 1.0, 7.0], [True, False, False]),
    ]
    released = []
    for t, (positions, widths, done) in enumerate(steps):
        infos = {
            "position": positions,
            "edge_width_px": np.array(widths),
            "start_position": position(0.0, 0.0, 0.3),  # the next episodes' first readings
            "start_edge_width_px": np.array([2.0, 2.0, 9.0]),
        }
        actions, rewards, told = np.full((3, 2), float(t)), np.full(3, float(t)), np.zeros((3, 1))
        step = Transition(
            observations[t], told, actions, rewards, observations[t + 1], told, np.array(done)
        )
        released += hindsight.step(step, infos)
    assert len(released) == 2  # slot 2 after two steps, then slot 0 after three; not slot 1
    episode = released[0]
    # Slot 2 visited 0.9 (8 px), 0.7 (5 px), 0.6 (6 px): the sharpest is 0.7.
    np.testing.assert_allclose(episode.secret[:, 0], [0.7 - 0.9, 0.0], atol=1e-6)
    np.testing.assert_allclose(episode.next_secret[:, 0], [0.0, 0.7 - 0.6], atol=1e-6)
    np.testing.assert_array_equal(episode.action[:, 0], [0.0, 1.0])
    np.testing.assert_array_equal(episode.done, [False, True])
    np.testing.assert_array_equal(episode.reward, [0.0, 1.0])
    np.testing.assert_array_equal(episode.observation[:, 0, 0], [0.0, 1.0])
    np.testing.assert_array_equal(episode.next_observation[:, 0, 0], [1.0, 2.0])
    # Slot 0: 0.1 (9 px), 0.4 (4), 0.6 (3), 0.5 (a failed reading): the sharpest is 0.6.
    secret, next_secret = released[1].secret[:, 0], released[1].next_secret[:, 0]
    np.testing.assert_allclose(secret, [0.5, 0.2, 0.0], atol=1e-6)
    np.testing.assert_allclose(next_secret, [0.2, 0.0, 0.1], atol=1e-6)


def _focus_episodes(hindsight: HindsightSecrets, count: int) -> list[tuple[float, float, float]]:
    """`count` focus episodes on the analytic `synthetic-b` column through `hindsight` (one
    blind slot): a scripted aligner jumps towards the optimum with a shrinking error and
    stops after 2-5 moves; the stop's setting is read twice (reading, verification image).
    Returns (true secret, stand-in secret, verification reading) at each stop."""
    column = make_apparatus("synthetic-b", {"analytic": True}, seed=1)
    low, high = column.knobs["defocus"]
    rng = np.random.default_rng(0)

    def read(x: float) -> float:
        column.write({"defocus": low + x * (high - low)})
        try:
            return column.measure()
        except MeasurementError:
            return float("nan")

    def infos(x: float, width: float) -> dict[str, np.ndarray]:
        return {
            "position": np.array([[x]]),
            "edge_width_px": np.array([width]),
            "start_position": np.array([[x]]),
            "start_edge_width_px": np.array([width]),
        }

    stops = []
    blank = np.zeros((1, 1))
    for episode in range(count):
        column.reset(episode)
        optimum = (column.optimum()["defocus"] - low) / (high - low)
        x = rng.uniform(0.05, 0.95)
        hindsight.start(infos(x, read(x)))
        moves = int(rng.integers(2, 6))
        for move in range(moves + 1):
            last = move == moves
            if not last:
                x += (optimum - x) * rng.uniform(0.6, 1.2) + rng.normal(0, 0.03 / (move + 1))
                x = float(np.clip(x, 0.0, 1.0))
            width = read(x)  # the last one: the verification image at the stop
            step = Transition(blank, blank, blank, np.zeros(1), blank, blank, np.array([last]))
            released = hindsight.step(step, infos(x, width))
        (episode,) = released
        stops.append((optimum - x, float(episode.next_secret[-1, 0]), width))
    return stops


def test_hindsight_posterior_tells_a_borderline_stop_how_far_the_optimum_is() -> None:
    """A stop on a reading at the spec's edge is a few volts from the optimum: the sharpest
    reading says "at the optimum" there; the posterior on the pooled focus curve says how
    far, and the curve it pools is the column's own."""
    sharpest = _focus_episodes(HindsightSecrets(np.array([True]), optimum="sharpest"), 400)
    hindsight = HindsightSecrets(np.array([True]), optimum="posterior")
    posterior = _focus_episodes(hindsight, 400)
    slope, best, noise = hindsight.posterior.curve
    # The preset's probe: sigma^2 = sigma0^2 + (gain x interval x setting)^2, read near focus
    # at reading_ratio x 2.563 sigma, with a relative reading noise of noise_rel.
    preset = load_sem_config(PRESET_DIR / "synthetic-b.yaml")
    calibration = preset.analytic_calibration
    low, high = preset.defocus_interval_v
    px_per_sigma = calibration.reading_ratio[0] * 2.563
    assert np.sqrt(slope) == pytest.approx(
        px_per_sigma * preset.gain_px_per_v * (high - low), rel=0.15
    )
    assert best == pytest.approx(px_per_sigma * preset.probe_sigma0_px, rel=0.1)
    assert 0.01 < noise < 0.08  # the preset's reading noise at focus: noise_rel, 2.4 %
    truth, stand_in, verification = (np.array(values) for values in zip(*posterior, strict=True))
    assert np.allclose(truth, [row[0] for row in sharpest])  # the same episodes both times
    borderline = verification > 1.15 * best
    assert borderline.sum() > 20
    errors_sharpest = np.abs(np.array([row[1] for row in sharpest]) - truth)[borderline]
    errors_posterior = np.abs(stand_in - truth)[borderline]
    assert np.median(errors_posterior) < 0.7 * np.median(errors_sharpest)
    # ... without losing the aligned stops: there both are near the optimum.
    aligned = verification < 1.05 * best
    assert np.median(np.abs(stand_in - truth)[aligned]) * (high - low) < 1.5  # volts


@pytest.mark.parametrize("hindsight", [True, False])
def test_on_a_column_without_a_secret_the_critics_learn_from_hindsight(
    small_source: Path, tmp_path: Path, hindsight: bool
) -> None:
    source = resolve_source(small_source)
    config = _config(source, 160, apparatus="fake_drivers:BlindLens", hindsight_secrets=hindsight)
    trainer = start_adaptation(config, source, tmp_path)
    trainer.run(progress=False)
    replay = trainer.agent.replay
    size = replay.size
    secret, next_secret = replay.secret[:size], replay.next_secret[:size]
    if not hindsight:
        assert size == trainer.env_steps and not secret.any() and not next_secret.any()
        return
    done = replay.done[:size]
    assert 0 < size < trainer.env_steps  # the episodes in flight are held back
    assert done[-1] == 1.0  # whole episodes only
    knobs = feature_layout(1)["knobs"]
    position = (replay.observation[:size, -1, knobs][:, 0] + 1.0) / 2.0
    next_position = (replay.next_observation[:size, -1, knobs][:, 0] + 1.0) / 2.0
    stand_in = position + secret[:, 0]
    ends = np.flatnonzero(done) + 1
    for start, end in zip(np.r_[0, ends[:-1]], ends, strict=True):
        # Every step of an episode points at one and the same stand-in optimum ...
        np.testing.assert_allclose(stand_in[start:end], stand_in[start], atol=1e-5)
        np.testing.assert_allclose(
            next_position[start:end] + next_secret[start:end, 0], stand_in[start], atol=1e-5
        )
    assert np.abs(secret).max() > 0.05  # ... and it is not the optimum everywhere


def test_every_call_of_an_adaptation_passes_the_shield_and_is_on_record(
    small_source: Path, tmp_path: Path
) -> None:
    trainer = _adapt(
        small_source,
        tmp_path,
        300,
        limits={"defocus": (20.0, 80.0)},
        max_step={"defocus": 4.0},
    )
    units = trainer.env.episodes.apparatus
    assert all(isinstance(unit, TrainingShield) for unit in units)
    trainer.run(progress=False)
    audit = [
        json.loads(line) for line in (tmp_path / "adapted" / "audit.jsonl").read_text().splitlines()
    ]
    sent = [entry for entry in audit if entry["event"] == "write" and entry["sent"]]
    assert sent and all(20.0 <= entry["value"]["defocus"] <= 80.0 for entry in sent)
    # What reached the drivers: inside the limits, and every aligner step within 4 V (the
    # first write after a reset starts the episode: a jump by design).
    for unit in units:
        writes = [w["defocus"] for w in unit.inner.writes]
        assert writes and all(20.0 <= v <= 80.0 for v in writes)
    steps, position = [], {}
    for entry in audit:  # the records of all apparatus interleave: each names its unit
        unit = entry["unit"]
        if entry["event"] == "reset":
            position[unit] = None
        elif entry["event"] == "write" and entry["sent"]:
            if position[unit] is not None:
                steps.append(abs(entry["value"]["defocus"] - position[unit]))
            position[unit] = entry["value"]["defocus"]
    assert steps and max(steps) <= 4.0 + 1e-9
    training = {unit.unit for unit in units}
    measured = sum(e["event"] == "measure" and e["unit"] in training for e in audit)
    assert measured == sum(unit.inner.calls for unit in units) >= 300  # every image on record
    # The evaluation sessions' apparatus is shielded and on record too.
    assert {e["unit"] for e in audit} - training


def test_limits_that_do_not_fit_the_instrument_write_nothing(
    small_source: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code = main(
        [
            "adapt",
            "--from",
            str(small_source),
            "--apparatus",
            LENS,
            "--steps",
            "50",
            "--spec-px",
            "3",
            "--limits",
            '{"defocus": [-10, 50]}',
            "--runs-dir",
            str(tmp_path / "runs"),
            "--quiet",
        ]
    )
    assert code == 2
    assert "inside the apparatus's interval" in capsys.readouterr().err
    assert not (tmp_path / "runs").exists() or not any((tmp_path / "runs").rglob("*.yaml"))


def test_adapt_runs_from_the_command_line_and_resumes(small_source: Path, tmp_path: Path) -> None:
    args = ["--runs-dir", str(tmp_path), "--quiet", "--json"]
    common = ["adapt", "--from", str(small_source), "--apparatus", LENS, "--spec-px", "3"]
    assert main([*common, "--steps", "120", "--eval-scenarios", "3", *args]) == 0
    member = resolve_source(small_source).agent.id
    run = tmp_path / f"{member}-on-fake_drivers-ParabolicLens"
    assert (run / "audit.jsonl").exists() and (run / "checkpoints" / "last.pt").exists()
    # A second start of the same run is refused; --resume continues it (here: already done).
    assert main([*common, "--steps", "120", *args]) == 2
    assert main(["adapt", "--resume", str(run), "--quiet", "--json"]) == 0
    # --resume --steps N goes on to a new budget, with the source's learner as it left it.
    assert main(["adapt", "--resume", str(run), "--steps", "160", "--quiet", "--json"]) == 0
    assert Trainer.resume(run).env_steps == 160


def _near_focus_successes(agent: Agent, gain: float, scenarios: int = 40) -> int:
    task = TaskOptions(success_absolute_px=SPEC_PX).apply(get_task("focus"))
    lens = make_apparatus(LENS, {"gain_px_per_v": gain})
    env = AlignmentEnv(apparatus=lens, task=task, complexity=0.2)
    successes = 0
    for index in range(scenarios):
        observation, _ = env.reset(seed=5000 + index)
        while True:
            observation, _, terminated, _, info = env.step(agent.act(observation))
            if terminated:
                break
        successes += int(info["success"])
    return successes


@pytest.mark.learning
def test_adaptation_lifts_success_on_a_new_lens(tmp_path: Path) -> None:
    """An aligner pre-trained briefly on the recordings (near focus, as in test_training)
    meets an analytic lens with another focus curve; 3000 shielded steps there lift it."""
    source = _pretrained(
        tmp_path,
        3000,
        {
            "encoder_kwargs": {"hidden": [64]},
            "hidden": [64, 64],
            "batch_size": 128,
            "learning_starts": 300,
            "random_steps": 600,
        },
        complexity=0.2,
    )
    before = _near_focus_successes(resolve_source(source).agent, gain=0.2)
    trainer = _adapt(source, tmp_path, 3000, apparatus_args={"gain_px_per_v": 0.2}, complexity=0.2)
    trainer.run(progress=False)
    after = _near_focus_successes(trainer.agent, gain=0.2)
    assert before <= 20, before
    assert after >= before + 6, (before, after)


def test_a_shielded_evaluation_session_is_the_same_session(
    small_source: Path, tmp_path: Path
) -> None:
    # Sessions on the recordings walk the held-out rows in order (reset_to): the shield must
    # pass that through, or an adaptation's zero-shot figure would be another session's.
    from alignrl.adaptation import adaptation_shield
    from alignrl.config.adaptation import AdaptationConfig
    from alignrl.training import evaluate_policy

    source = resolve_source(small_source)
    act = lambda history: source.agent.act(history, deterministic=True)  # noqa: E731
    args = {"noise": 0.02, "split": "test"}
    shield = adaptation_shield(
        AdaptationConfig(source="s", source_member="m", source_steps=0), tmp_path / "a.jsonl"
    )
    plain = evaluate_policy(act, "csv:default", args, source.task, 8, 6)
    shielded = evaluate_policy(act, "csv:default", args, source.task, 8, 6, shield=shield)
    assert [r.trajectory for r in plain.records] == [r.trajectory for r in shielded.records]
    records = (tmp_path / "a.jsonl").read_text().splitlines()
    assert any(json.loads(line).get("row") is not None for line in records)


def test_an_adaptation_steps_at_its_own_learning_rate(small_source: Path, tmp_path: Path) -> None:
    """The source's optimizer state carries the source's step size; the adaptation config's
    learning rate (by default the source's) is the one its optimizers use."""
    source = resolve_source(small_source)
    config = _config(source, 50, name="slower")
    assert config.learner.learning_rate == source.agent.spec.hyperparameters["learning_rate"]
    slower = config.model_copy(
        update={"learner": config.learner.model_copy(update={"learning_rate": 1e-5})}
    )
    trainer = start_adaptation(slower, source, tmp_path)
    learner = trainer.agent.learner
    for optimizer in (learner.actor_optimizer, learner.critic_optimizer, learner.alpha_optimizer):
        assert [group["lr"] for group in optimizer.param_groups] == [1e-5]


def test_train_given_an_adaptation_config_starts_from_its_source(
    small_source: Path, tmp_path: Path
) -> None:
    """A YAML with an `adaptation:` section (a run's config.yaml with other settings) run by
    `alignrl train` adapts the source, with its zero-shot session at 0 steps, as `alignrl
    adapt` does; it never trains an aligner from scratch."""
    from alignrl.cli import main
    from alignrl.config.experiment import dump_experiment

    source = resolve_source(small_source)
    config = _config(source, 40, name="from-yaml")
    path = tmp_path / "from-yaml.yaml"
    path.write_text(dump_experiment(config))
    assert main(["train", str(path), "--runs-dir", str(tmp_path / "runs"), "--quiet"]) == 0
    with (tmp_path / "runs" / "from-yaml" / "metrics" / "evaluations.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert rows[0]["env_steps"] == "0"  # the source, judged before any adaptation step
    adapted = load_checkpoint(tmp_path / "runs" / "from-yaml" / "checkpoints" / "last.pt")
    assert adapted["agent"]["steps_seen"] == source.agent.steps_seen + 40


def test_hindsight_secrets_have_a_room_of_their_own() -> None:
    # Below training and adaptation (numpy only), the pooled curve in the posterior's room;
    # the config's adaptation section reads the same names, not a copy.
    import alignrl.adaptation as adaptation
    import alignrl.config.adaptation as config
    import alignrl.envs.hindsight as hindsight
    from alignrl.posterior.hindsight import PooledCurve

    assert isinstance(hindsight.HindsightSecrets([True]).posterior, PooledCurve)
    assert not hasattr(adaptation, "HindsightSecrets")  # no re-export: one name, one place
    assert not hasattr(config, "HINDSIGHT_OPTIMA")
    # One copy, not two that agree: the config's field takes the hindsight module's names.
    field = config.AdaptationConfig.model_fields["hindsight_optimum"]
    assert field.annotation is hindsight.HindsightOptimum
