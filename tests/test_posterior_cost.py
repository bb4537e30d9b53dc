"""What FamilyPosterior's cost cuts keep (issue 61, item 4): its likelihood computed a chunk of
columns at a time into buffers gives the plain formulas' numbers bit for bit; buffers reused
from one alignment to the next, a copy's own buffers, cached first draws and priors leave
every decision as a fresh posterior makes it; and benchmarks/posterior_cost.py times an
evaluation and checks its results against a reference."""

from __future__ import annotations

import copy
import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

import benchmarks.posterior_cost as cost_module
from alignrl.deploy.policy import load_deployable
from alignrl.envs.endings import with_ending
from alignrl.posterior.inference import SCALE_FREE, FamilyPosterior
from alignrl.posterior.models import ColumnModels, focus_box
from benchmarks.posterior_cost import main

BOX = focus_box(saturation_px=(10.0, 80.0))
# An alignment's readings (setting, px or NaN, side), as the champion's walk reads them: the
# column as found, then from below, one frame without edges, then near focus
READINGS = [
    (0.31, 21.4, 0.0),
    (0.06, 4.49, 1.0),
    (0.015, 10.4, 1.0),
    (0.85, math.nan, 1.0),
    (0.10, 2.93, 1.0),
    (0.088, 2.71, 1.0),
]


def _champion_like(**options: object) -> FamilyPosterior:
    """The champion's posterior (scale-free, far noise, the entropy rule) with fewer columns."""
    settings = {"draws": 64, "far_noise": 0.1, "probe_rule": "entropy", **SCALE_FREE}
    return FamilyPosterior(BOX, **{**settings, **options})


def _decisions(posterior: FamilyPosterior, readings: list[tuple[float, float, float]]) -> list:
    """Every answer of an alignment over `readings` (after each: final, probe, decide)."""
    posterior.begin()
    answers = []
    for reading in readings:
        posterior.observe(*reading)
        answers += [posterior.final(), posterior.probe(), posterior.decide()]
    return answers


@pytest.mark.parametrize(
    "options",
    [
        {},  # the champion's: scale-free, one specimen point
        {"scale_free": False, "specimen_points": 3},  # the box's own pixels
        {"far_noise": 0.0, "probe_rule": "variance"},
    ],
)
def test_the_chunked_likelihood_gives_the_plain_formulas_numbers(options: dict) -> None:
    posterior = _champion_like(**options)
    posterior.begin()
    for setting, reading, side in READINGS[1:]:
        plain = copy.copy(posterior)
        if posterior._scale is not None:
            plain._scale = dataclasses.replace(posterior._scale)  # its own sums, as they are
        expected = posterior._posterior * plain._likelihood(setting, reading, side)
        weighed = posterior._weigh(posterior._posterior, setting, reading, side)
        assert np.array_equal(weighed, expected)
        if posterior._scale is not None:
            assert np.array_equal(posterior._scale.sum0, plain._scale.sum0)
            assert np.array_equal(posterior._scale.sum1, plain._scale.sum1)
            assert posterior._scale.readings == plain._scale.readings
        posterior._posterior = posterior._drifted(weighed)


def test_columns_of_their_own_far_noise_weigh_as_the_plain_formulas() -> None:
    """use_columns with a far noise per column (a calibration's evidence), columns_apart."""
    posterior = FamilyPosterior(BOX, draws=8, columns_apart=True, far_noise=0.05)
    rows = np.random.default_rng(0).random((12, 17))
    posterior.use_columns(rows, np.linspace(0.05, 0.3, 12))
    posterior.begin()
    plain = copy.copy(posterior)
    expected = posterior._posterior * plain._likelihood(0.4, 7.5, 1.0)
    assert np.array_equal(posterior._weigh(posterior._posterior, 0.4, 7.5, 1.0), expected)


def test_buffers_reused_after_another_alignment_decide_as_a_fresh_posterior() -> None:
    used = _champion_like()
    _decisions(used, [(0.7, 18.0, 0.0), (0.5, 9.0, 1.0), (0.62, 3.4, 1.0)])
    again = _decisions(used, READINGS)
    fresh = _decisions(_champion_like(), READINGS)
    assert again == fresh
    assert used.models is not used._initial  # the columns were drawn again on the way


def test_a_copy_makes_its_own_buffers_and_each_decides_as_alone() -> None:
    """ending.py copies one posterior for every episode: a copy made in mid-alignment goes
    on without touching the original's numbers, and the original without touching its."""
    original = _champion_like()
    original.begin()
    for reading in READINGS[:3]:
        original.observe(*reading)
    twin = copy.copy(original)
    original.observe(*READINGS[3])
    twin.observe(0.4, 12.0, 1.0)
    assert twin._posterior is not original._posterior
    assert twin._scale.sum0 is not original._scale.sum0

    def alone(readings: list[tuple[float, float, float]]) -> tuple:
        posterior = _champion_like()
        posterior.begin()
        for reading in readings:
            posterior.observe(*reading)
        return posterior.final(), posterior.probe()

    assert (original.final(), original.probe()) == alone(READINGS[:4])
    assert (twin.final(), twin.probe()) == alone([*READINGS[:3], (0.4, 12.0, 1.0)])


@pytest.mark.parametrize("scale_free", [True, False])
def test_a_collapse_starts_again_from_the_prior_and_renewal_goes_on(scale_free: bool) -> None:
    """A reading no state explains (every state ruled out) leaves the prior, as the plain
    formulas did; the readings after it are weighed, and (in the box's own pixels, where the
    collapse left no scale sums to doubt every column alike) the columns drawn again, every
    reading weighed on them, the collapse again among them."""
    options = {} if scale_free else {"scale_free": False, "specimen_points": 3}
    posterior = _champion_like(**options)
    posterior.begin()
    for reading in READINGS[1:3]:
        posterior.observe(*reading)
    with np.errstate(over="ignore"):
        posterior.observe(0.2, 1e300, 1.0)  # no column reads this: every state ruled out
        assert np.array_equal(posterior._posterior, posterior._prior)
        drawn = posterior.models
        for reading in [*READINGS[4:], (0.095, 2.75, 1.0)]:
            posterior.observe(*reading)
    assert (posterior.models is not drawn) == (not scale_free)
    assert math.isclose(float(posterior._posterior.sum()), 1.0)
    setting, chance = posterior.final()
    assert 0.0 <= setting <= 1.0 and 0.0 <= chance <= 1.0


def test_the_first_draw_and_prior_are_made_once_and_kept_read_only() -> None:
    first, second = _champion_like(), _champion_like()
    assert first.models is second.models and first._prior is second._prior
    with pytest.raises(ValueError, match="read-only"):
        first.models.lag[0, 0, 0] = 1.0
    assert isinstance(first.models, ColumnModels)


@pytest.fixture
def light_champion(monkeypatch: pytest.MonkeyPatch) -> None:
    """champion:focus-v2 with a posterior of 16 columns in place of its 1,024."""
    champion = load_deployable("champion:focus-v2")
    light = dataclasses.replace(champion, task=with_ending(champion.task, posterior_draws=16))
    monkeypatch.setattr(cost_module, "load_deployable", lambda spec: light)


def test_the_benchmark_times_a_session_and_checks_it_against_a_reference(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], light_champion: None
) -> None:
    reference = tmp_path / "reference.json"
    argv = ["--scenarios", "2", "--kinds", "analytic"]
    assert main([*argv, "--save-reference", str(reference)]) == 0
    table = capsys.readouterr().out
    assert "CPU-s/alignment" in table and "analytic" in table and "written to" in table
    saved = json.loads(reference.read_text())
    records = saved["results"]["analytic"]["records"]
    assert len(records) == 2 and all(record["posterior"] for record in records)
    assert main([*argv, "--reference", str(reference)]) == 0
    assert "results the same as" in capsys.readouterr().out
    # a result changed in its last bit is a difference, named
    first = records[0]["trajectory"][0]
    first[0] = repr(float(np.nextafter(float(first[0]), math.inf)))
    reference.write_text(json.dumps(saved))
    assert main([*argv, "--reference", str(reference)]) == 1
    out = capsys.readouterr().out
    assert "DIFFER" in out and "analytic: alignment 0: trajectory" in out


def test_fewer_draws_are_another_session_and_say_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], light_champion: None
) -> None:
    """--draws lays the posterior's columns over the card's: the table says it, its results
    are another session's, and a reference of the card's draws is refused for them."""
    reference = tmp_path / "reference.json"
    argv = ["--scenarios", "1", "--kinds", "analytic"]
    assert main([*argv, "--save-reference", str(reference)]) == 0
    card = json.loads(reference.read_text())
    capsys.readouterr()
    fewer = tmp_path / "fewer.json"
    assert main([*argv, "--draws", "32", "--save-reference", str(fewer)]) == 0
    out = capsys.readouterr().out
    assert "its posterior drawing 32 columns" in out and "aligned" in out
    saved = json.loads(fewer.read_text())
    assert saved["options"]["draws"] == 32 and "draws" not in card["options"]
    assert saved["results"] != card["results"]
    with pytest.raises(SystemExit):
        main([*argv, "--draws", "32", "--reference", str(reference)])
    assert "holds other sessions" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([*argv, "--draws", "4"])
    assert "--draws: posterior_draws must be in [16, 4096]" in capsys.readouterr().err
