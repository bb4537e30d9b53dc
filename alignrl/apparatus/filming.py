"""Filming an alignment: an apparatus wrapper that keeps one `Reading` per acquisition (the
knob settings it was taken at, its edge width, its image) in a `Film`, for `alignrl align
--gif` and `alignrl evaluate --gif` (drawn by alignrl/animation.py).

A film holds the acquisitions since the apparatus's last reset, or, given a scenario seed,
those since its last reset with that seed: the one scenario of an evaluation session to show
(`alignrl.evaluation.session.reset_scenario` resets scenario i with `scenario_seed(S, i)`).

The wrapper passes every call through unchanged and sends the apparatus nothing of its own
beyond `image()` after each filmed acquisition (the last image, which takes none) and, on a
simulator, `optimum()`. The settings are those the calls through it read and wrote: under a
shield's dry run, whose writes never reach it, the film shows the column where it stays.
Every capability of the wrapped apparatus passes through as well, except a batched query
(`BatchedQueries`, alignrl/apparatus/base.py), which would measure around the film: a filmed
scenario simulator answers one query at a time (the same values).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from alignrl.animation import Reading
from alignrl.apparatus.base import Apparatus, ApparatusError, knows_optimum
from alignrl.apparatus.guard import ShieldStop

__all__ = ["MAX_IMAGE_PIXELS", "Film", "FilmedApparatus", "drawable_image", "take_reading"]

NOT_FILMED = frozenset({"batch_key", "measure_batch"})  # they would measure around the film
MAX_IMAGE_PIXELS = 8192 * 8192  # the largest frame a film keeps (a 16k scan is not filmed)


def drawable_image(image: Any) -> np.ndarray | None:
    """`image` (what a driver's image() answered) as a frame a film can draw: a finite real
    2-D array of at most MAX_IMAGE_PIXELS; None for anything else (no image, a stack, NaN)."""
    if image is None:
        return None
    frame = np.asarray(image)
    if (
        frame.ndim != 2
        or frame.size == 0
        or frame.size > MAX_IMAGE_PIXELS
        or not (np.issubdtype(frame.dtype, np.integer) or np.issubdtype(frame.dtype, np.floating))
        or not np.all(np.isfinite(frame))
    ):
        return None
    return frame


@dataclass
class Film:
    """The readings of one alignment, and the knob intervals of its apparatus (a family
    column draws new ones at every reset). `scenario_seed`: film only the scenario reset with
    this seed (the last such reset, where it is reset more than once)."""

    scenario_seed: int | None = None
    readings: list[Reading] = field(default_factory=list)
    knobs: dict[str, tuple[float, float]] = field(default_factory=dict)
    rolling: bool = field(init=False)  # whether the scenario now on the apparatus is filmed

    def __post_init__(self) -> None:
        self.rolling = self.scenario_seed is None

    def start(self, seed: int | None, knobs: Mapping[str, tuple[float, float]]) -> None:
        """A reset with `seed`: a new film where it is the one to film."""
        self.rolling = self.scenario_seed is None or seed == self.scenario_seed
        if self.rolling:
            self.readings = []
            self.knobs = {name: (float(low), float(high)) for name, (low, high) in knobs.items()}


class FilmedApparatus:
    """`apparatus`, its acquisitions kept in `film` (see the module docstring)."""

    def __init__(
        self,
        apparatus: Apparatus,
        film: Film | None = None,
        knobs: Mapping[str, tuple[float, float]] | None = None,
    ) -> None:
        """`knobs`: the apparatus's intervals as already read (a driver's getter is read
        within a time limit by the caller); None: read them here."""
        self.inner = apparatus
        self.film = film if film is not None else Film()
        if self.film.scenario_seed is None:  # align: the column as found is the scenario
            self.film.start(None, apparatus.knobs if knobs is None else knobs)
        self._settings: dict[str, float] = {}  # as last read and written through the film

    @property
    def knobs(self) -> Mapping[str, tuple[float, float]]:
        return self.inner.knobs

    def reset(self, seed: int | None = None) -> None:
        self.inner.reset(seed)
        self._new_scenario(seed)

    def read(self) -> dict[str, float]:
        values = self.inner.read()
        self._settings = {knob: float(value) for knob, value in values.items()}
        return values

    def write(self, values: Mapping[str, float]) -> None:
        self.inner.write(values)
        self._settings.update({knob: float(value) for knob, value in values.items()})

    def measure(self) -> float:
        return self._filmed(self.inner.measure, float)

    def image(self) -> np.ndarray | None:
        return self.inner.image()

    def __getattr__(self, name: str) -> Any:
        if name in NOT_FILMED:
            raise AttributeError(name)
        attribute = getattr(self.__dict__["inner"], name)
        if name == "reset_to":  # a scenario simulator's reset to a row of its recording

            def reset_to(row: int, seed: int | None = None) -> None:
                attribute(row, seed)
                self._new_scenario(seed)

            return reset_to
        if name == "measure_directional":
            return lambda: self._filmed(attribute, lambda answer: float(answer[0]))
        if name == "measure_wobble":
            return lambda amplitude_v: self._filmed(
                lambda: attribute(amplitude_v), lambda _shift: None, kind="wobble", images=2
            )
        return attribute

    def _new_scenario(self, seed: int | None) -> None:
        self._settings = {}
        self.film.start(seed, self.inner.knobs)

    def _filmed(
        self,
        acquire: Callable[[], Any],
        width_of: Callable[[Any], float | None],
        kind: Literal["image", "wobble"] = "image",
        images: int = 1,
    ) -> Any:
        """Acquire, and keep the reading (also of a failed acquisition, without a width)."""
        try:
            answer = acquire()
        except ApparatusError:
            self._keep(None, kind, images)
            raise
        self._keep(width_of(answer), kind, images)
        return answer

    def _keep(self, width_px: float | None, kind: Literal["image", "wobble"], images: int) -> None:
        if self.film.rolling:
            reading = take_reading(self.inner, self._settings, width_px, kind, images)
            self.film.readings.append(reading)


def take_reading(
    unit: Apparatus,
    settings: Mapping[str, float],
    width_px: float | None,
    kind: Literal["image", "wobble"] = "image",
    images: int = 1,
) -> Reading:
    """The acquisition `unit` just made, at `settings`: its image and (a simulator's) optimum
    asked for now. A driver that fails to give them, or gives an image that is none (not a
    finite 2-D array of at most MAX_IMAGE_PIXELS), spoils the frame, never the alignment."""
    try:
        image = drawable_image(unit.image())
    except ShieldStop:  # a hung image() ended the work: that is not the film's to hide
        raise
    except Exception:  # any other failure of a driver's image() spoils this frame alone
        image = None
    try:
        optimum = unit.optimum() if knows_optimum(unit) else None
    except ApparatusError:
        optimum = None
    return Reading(
        settings=dict(settings),
        width_px=width_px,
        image=None if image is None else np.array(image, copy=True),
        optimum=None if optimum is None else dict(optimum),
        kind=kind,
        images=images,
    )
