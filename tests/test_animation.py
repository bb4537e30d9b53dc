"""Seeing an alignment (issue 23, item 7): the frames of alignrl/animation.py, the film that
alignrl/apparatus/filming.py keeps without changing what it films, and `alignrl evaluate
--gif` end to end (`alignrl align --gif`: tests/test_align.py; AlignmentEnv's render_mode:
tests/test_registration.py)."""

from __future__ import annotations

import itertools
import json
import re
from pathlib import Path

import numpy as np
import pytest
from PIL import Image, ImageSequence

from alignrl.animation import Reading, Scene, alignment_frames, check_gif_path, draw_frame
from alignrl.animation import write_gif as write_frames
from alignrl.apparatus import answers_batched, knows_optimum, make_apparatus
from alignrl.apparatus.base import NoEdgesError
from alignrl.apparatus.filming import Film, FilmedApparatus
from alignrl.apparatus.recorder import scenario_seed
from alignrl.cli import main
from alignrl.envs.task import get_task
from alignrl.evaluation.baselines import CLASSICAL
from alignrl.evaluation.session import run_session

KNOBS = {"defocus": (0.0, 100.0)}


def walk(images: bool) -> list[Reading]:
    """Four readings of a focus walk towards 60 V; with images, a bright square that blurs
    less as the walk nears focus."""
    readings = []
    for number, (setting, width) in enumerate([(20, 12.0), (40, 7.0), (55, 3.5), (60, 2.6)]):
        image = None
        if images:
            image = np.zeros((32, 32))
            image[8 + number : 24, 8:24] = 1.0
        readings.append(Reading({"defocus": float(setting)}, width, image, {"defocus": 60.0}))
    return readings


def frames_of(path: Path) -> list[np.ndarray]:
    with Image.open(path) as gif:
        return [np.asarray(frame.convert("RGB")) for frame in ImageSequence.Iterator(gif)]


# --- frames -------------------------------------------------------------------------------


def test_each_reading_is_a_frame_of_one_size_and_each_frame_differs() -> None:
    scene = Scene(KNOBS, "a walk", threshold_px=2.9, acquisitions=3, ending="aligned")
    frames = alignment_frames(walk(images=True), scene)
    assert len(frames) == 4
    assert {frame.shape for frame in frames} == {frames[0].shape}
    assert frames[0].ndim == 3 and frames[0].shape[2] == 3 and frames[0].dtype == np.uint8
    for before, after in itertools.pairwise(frames):
        assert np.any(before != after)


def test_a_frame_without_images_has_the_curve_panel_alone() -> None:
    with_images = draw_frame(walk(images=True), Scene(KNOBS))
    without = draw_frame(walk(images=False), Scene(KNOBS))
    assert without.shape[1] < with_images.shape[1]  # no image panel on its left


def test_a_frame_draws_one_walk_panel_per_knob() -> None:
    knobs = {"stigmator_x": (-100.0, 100.0), "stigmator_y": (-100.0, 100.0)}
    readings = [
        Reading({"stigmator_x": 10.0 * n, "stigmator_y": -5.0 * n}, 4.0 - n) for n in range(3)
    ]
    two = draw_frame(readings, Scene(knobs))
    one = draw_frame(readings, Scene({"stigmator_x": knobs["stigmator_x"]}))
    assert two.shape[0] > one.shape[0]


def test_a_frame_needs_a_reading() -> None:
    with pytest.raises(ValueError, match="at least one reading"):
        draw_frame([], Scene(KNOBS))
    with pytest.raises(IndexError, match="reading 4 of an alignment of 4"):
        draw_frame(walk(images=False), Scene(KNOBS), 4)


def test_the_gif_holds_every_frame_and_shows_the_last_longest(tmp_path: Path) -> None:
    frames = alignment_frames(walk(images=True), Scene(KNOBS, ending="aligned"))
    path = write_frames(frames, tmp_path / "walk.gif", frame_s=0.5, last_frame_s=2.0)
    with Image.open(path) as gif:
        assert gif.n_frames == 4 and gif.info["loop"] == 0
        durations = []
        for frame in ImageSequence.Iterator(gif):
            durations.append(frame.info["duration"])
    assert durations == [500, 500, 500, 2000]
    with pytest.raises(ValueError, match="differ in size"):
        write_frames([frames[0], frames[0][:-1]], tmp_path / "bad.gif")


@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("missing/walk.gif", "the folder .*missing does not exist"),
        ("walk.png", "ending in .gif"),
        ("folder.gif", "that is a folder"),
    ],
)
def test_a_gif_path_that_cannot_be_one_is_refused(tmp_path: Path, name: str, message: str) -> None:
    (tmp_path / "folder.gif").mkdir()
    with pytest.raises(ValueError, match=message):
        check_gif_path(tmp_path / name)
    assert check_gif_path(tmp_path / "walk.gif") == tmp_path / "walk.gif"


# --- the film -----------------------------------------------------------------------------


def test_the_film_keeps_each_acquisition_with_its_setting_width_and_image() -> None:
    film = Film()
    unit = FilmedApparatus(make_apparatus("synthetic", seed=1), film)
    unit.write({"defocus": 40.0})
    first = unit.measure()
    unit.write({"defocus": 45.0})
    second = unit.measure()
    assert [r.settings["defocus"] for r in film.readings] == [40.0, 45.0]
    assert [r.width_px for r in film.readings] == [first, second]
    assert all(r.image is not None and r.image.ndim == 2 for r in film.readings)
    assert not np.array_equal(film.readings[0].image, film.readings[1].image)
    assert film.readings[-1].optimum == unit.optimum()  # a simulator's secret, for the frame
    assert film.knobs["defocus"] == tuple(unit.knobs["defocus"])
    unit.reset(2)
    assert film.readings == []  # a new scenario, a new film


class BlankBelowTen:
    """A column whose frames below 10 V have no edges."""

    knobs = KNOBS

    def __init__(self) -> None:
        self.defocus = 50.0

    def reset(self, seed: int | None = None) -> None:
        self.defocus = 50.0

    def read(self) -> dict[str, float]:
        return {"defocus": self.defocus}

    def write(self, values: dict[str, float]) -> None:
        self.defocus = float(values["defocus"])

    def measure(self) -> float:
        if self.defocus < 10:
            raise NoEdgesError("no edges in this frame")
        return self.defocus / 10

    def image(self) -> np.ndarray | None:
        return np.full((4, 4), self.defocus)


def test_a_failed_acquisition_is_filmed_without_a_width_and_still_raised() -> None:
    film = Film()
    unit = FilmedApparatus(BlankBelowTen(), film)
    unit.write({"defocus": 5.0})
    with pytest.raises(NoEdgesError):
        unit.measure()
    assert len(film.readings) == 1 and film.readings[0].width_px is None
    assert film.readings[0].settings == {"defocus": 5.0} and film.readings[0].optimum is None
    assert draw_frame(film.readings, Scene(KNOBS)).ndim == 3  # drawn as "no edges"


def test_the_film_offers_what_the_apparatus_offers_but_a_batched_query() -> None:
    simulator = make_apparatus("csv:default", seed=0)
    filmed = FilmedApparatus(simulator)
    assert answers_batched([simulator]) and not answers_batched([filmed])
    assert knows_optimum(filmed) and filmed.optimum() == simulator.optimum()
    with pytest.raises(AttributeError):
        filmed.measure_batch  # noqa: B018


def test_a_filmed_session_is_the_session_and_films_the_scenario_asked_for() -> None:
    task = get_task("focus")

    def session(unit: object) -> object:
        return run_session(CLASSICAL["hyperbola"](), unit, task, scenarios=3, seed=5)

    plain = session(make_apparatus("csv:default", {"noise": 0.02}))
    film = Film(scenario_seed=scenario_seed(5, 1))
    filmed = session(FilmedApparatus(make_apparatus("csv:default", {"noise": 0.02}), film))
    assert [r.trajectory for r in filmed.records] == [r.trajectory for r in plain.records]
    record = filmed.records[1]
    # Every acquisition of alignment 1, then its verification image.
    assert len(film.readings) == record.acquisitions + 1
    assert [(r.settings["defocus"], r.width_px) for r in film.readings[:-1]] == list(
        record.trajectory
    )
    assert film.readings[-1].width_px == record.final_width_px


# --- alignrl evaluate --gif -----------------------------------------------------------------


def test_evaluate_writes_the_gif_of_the_alignment_asked_for(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "session.gif"
    code = main(
        [
            "evaluate",
            "--policy",
            "hyperbola",
            "--apparatus",
            "synthetic",
            "--scenarios",
            "2",
            "--gif",
            str(out),
            "--gif-scenario",
            "1",
            "--quiet",
            "--json",
        ]
    )
    payload = json.loads(capsys.readouterr().out)
    assert code == 0 and payload["gif"] == str(out)
    frames = frames_of(out)
    # A frame per acquisition of alignment 1 (the same session, run again), and one for its
    # verification image; the frame shows the acquired image beside the walk.
    again = run_session(
        CLASSICAL["hyperbola"](), make_apparatus("synthetic"), get_task("focus"), scenarios=2
    )
    assert len(frames) == again.records[1].acquisitions + 1
    assert all(np.any(a != b) for a, b in itertools.pairwise(frames))
    assert frames[0].shape == draw_frame(walk(images=True), Scene(KNOBS, "t", 2.9, 1, "e")).shape


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (["--gif", "{tmp}/missing/x.gif"], "--gif .*missing/x.gif: the folder .* does not exist"),
        (["--gif", "{tmp}/x.gif", "--gif-scenario", "2"], "alignments are 0 to 1"),
        (["--gif-scenario", "1"], "give --gif too"),
    ],
)
def test_evaluate_refuses_a_bad_gif_before_it_runs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], options: list[str], message: str
) -> None:
    filled = [option.replace("{tmp}", str(tmp_path)) for option in options]
    argv = ["evaluate", "--policy", "hyperbola", "--apparatus", "synthetic", "--scenarios", "2"]
    assert main([*argv, *filled]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and "Traceback" not in captured.err
    assert len(captured.err.strip().splitlines()) == 1
    assert captured.err.startswith("alignrl: error: ")
    assert re.search(message, captured.err)


def test_evaluate_films_one_apparatus_not_a_set(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["evaluate", "--policy", "hyperbola", "--set", "validation", "--gif", "x.gif"]) == 2
    assert "give --apparatus, not --set" in capsys.readouterr().err
