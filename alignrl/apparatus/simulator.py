"""The scenario simulator: an Apparatus that replays recorded focus sweeps (seed section 4.2).

`reset` picks a recorded scenario; `measure` returns the recorded edge width at the current
voltage by linear interpolation between the recorded points, with optional multiplicative
re-measurement noise; `optimum` is the minimum of the recorded curve refined by fitting the
focus curve near it. A voltage outside the span a scenario could measure raises
`NoEdgesError`, exactly as the recorded instrument did.

`query` answers many (scenario, voltage) pairs at once in numpy; simulators replaying one
recording offer the BatchedQueries capability (alignrl/apparatus/base.py: `batch_key`,
`measure_batch`), so that a vectorized env writes and measures all of them in one query.

Varied replay (`randomize`): each reset also draws how this column differs from the recorded
one, so that pre-training meets many microscopes instead of one (domain randomization for the
step to another instrument, seed section 6.3). With the recorded optimum o, a shift s, a
steepness factor g and a width factor c, the replayed column reads at setting V

    width(V) = c * recorded_width(o + g * (V - o - s))

so its optimum sits at o + s (kept inside the interval), its focus curve is g times as steep
and every edge width, the best one included, c times as wide. The span where edges are
measurable shrinks or grows with 1 / g around the new optimum. Without `randomize` the
recording is replayed as it is, bit for bit.

`randomize: {family: NAME}` (or a family file's path) draws the same three from an
instrument family (alignrl/apparatus/family.py), where it applies to a replay: the optimum
at the family's `optimum_fraction` of the interval, the steepness so that the curve's blur
per interval is the family's `blur_px_per_interval` (g = B / B_recorded), and the widths so
that the in-focus probe is the family's `floor_sigma_px` (c = sigma0 / sigma0_recorded). The
recording's own B and sigma0 are estimated from its curves once (`recorded_column`). Its
curve shape, noise, drift and hysteresis stay the recorded column's.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, get_args

import numpy as np

from alignrl.apparatus.base import NoEdgesError, check_write
from alignrl.apparatus.edge_profiles import TEN_NINETY_PER_SIGMA
from alignrl.apparatus.family import draw_column
from alignrl.apparatus.family_box import FocusFamily, family_path, load_family
from alignrl.apparatus.scenarios import ScenarioSet, read_scenarios

__all__ = [
    "DEFAULT_SCENARIOS",
    "Randomization",
    "ScenarioSimulator",
    "default_scenarios_path",
    "measure_batch",
    "split_indices",
]

DEFAULT_SCENARIOS = Path(__file__).resolve().parent.parent / "data" / "scenarios-synthetic.csv.gz"
HELD_OUT_EVERY = 10  # split "test" holds out every 10th scenario; "train" keeps the rest
RANDOMIZE_STREAM = 2  # second entropy word of the randomization generator (see reset)
OPTIMUM_MARGIN = 0.05  # a shifted optimum stays this share of the interval inside it

Split = Literal["all", "train", "test"]
SPLITS: tuple[str, ...] = get_args(Split)


def _shown(value: object, limit: int = 60) -> str:
    """An argument as echoed in a message, cut short."""
    text = repr(value)
    return text if len(text) <= limit else f"{text[:limit]}..."


def default_scenarios_path() -> Path:
    """The shipped 2000-scenario recording of the `synthetic` preset."""
    if not DEFAULT_SCENARIOS.exists():
        raise FileNotFoundError(
            f"the default scenario set {DEFAULT_SCENARIOS} is missing; regenerate it with "
            "`make scenarios`"
        )
    return DEFAULT_SCENARIOS


@dataclass(frozen=True)
class Randomization:
    """How far a varied replay may differ from the recorded column (see the module doc).

    shift_v: the optimum moves uniformly within +-shift_v volts (kept inside the interval).
    gain: (low, high) of the steepness factor g, drawn log-uniformly.
    width: (low, high) of the edge-width factor c, drawn log-uniformly.
    """

    shift_v: float = 0.0
    gain: tuple[float, float] = (1.0, 1.0)
    width: tuple[float, float] = (1.0, 1.0)
    family: FocusFamily | None = None  # draw from an instrument family instead

    @classmethod
    def parse(cls, value: object) -> Randomization | None:
        """From the `randomize` argument: None, or a mapping with the fields above. Any
        other key, a negative shift, a factor range that is not 0 < low <= high: ValueError
        naming it."""
        if value is None:
            return None
        if not isinstance(value, Mapping):
            raise ValueError(
                "randomize must be a mapping such as {shift_v: 20, gain: [0.8, 2], "
                f"width: [0.9, 1.5]}}, got {_shown(value)}"
            )
        unknown = sorted(map(str, set(value) - {"shift_v", "gain", "width", "family"}))
        if unknown:
            raise ValueError(
                f"randomize: unknown key(s) {_shown(', '.join(unknown))} "
                "(it takes: shift_v, gain, width; or family alone)"
            )
        if "family" in value:
            if len(value) > 1:
                raise ValueError(
                    "randomize: family draws the shift, gain and width itself: give it alone"
                )
            return cls(family=_family(value["family"]))
        shift = value.get("shift_v", 0.0)
        if (
            isinstance(shift, bool)
            or not isinstance(shift, int | float)
            or not (math.isfinite(shift) and shift >= 0)
        ):
            raise ValueError(
                f"randomize.shift_v must be a number of volts >= 0, got {_shown(shift)}"
            )
        ranges = {}
        for key in ("gain", "width"):
            pair = value.get(key, (1.0, 1.0))
            ok = (
                isinstance(pair, list | tuple)
                and len(pair) == 2
                and all(
                    isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)
                    for x in pair
                )
                and 0 < pair[0] <= pair[1]
            )
            if not ok:
                raise ValueError(
                    f"randomize.{key} must be [low, high] with 0 < low <= high, got {_shown(pair)}"
                )
            ranges[key] = (float(pair[0]), float(pair[1]))
        return cls(float(shift), ranges["gain"], ranges["width"])

    def draw(self, rng: np.random.Generator) -> tuple[float, float, float]:
        """(shift in V, steepness factor, width factor) for one scenario (not for a family:
        `draw_family`)."""
        shift = float(rng.uniform(-self.shift_v, self.shift_v)) if self.shift_v else 0.0
        gain, width = (
            float(np.exp(rng.uniform(np.log(low), np.log(high))))
            for low, high in (self.gain, self.width)
        )
        return shift, gain, width


def _family(value: object) -> FocusFamily:
    """randomize.family: a shipped family's name or a family file's path."""
    if not isinstance(value, str) or not value:
        raise ValueError(f"randomize.family must name a family or a file, got {_shown(value)}")
    try:
        path = family_path(value)
    except ValueError as error:
        raise ValueError(f"randomize.family: no family {_shown(value)} ({error})") from None
    if not path.exists():
        raise ValueError(f"randomize.family: no family file {_shown(value)}")
    return load_family(path)


def recorded_column(
    voltages: np.ndarray, widths: np.ndarray, n_pairs: np.ndarray, optima: np.ndarray, span: float
) -> tuple[float, float]:
    """(blur px per interval, in-focus sigma px) of a recording, the medians over its rows:
    sigma0 = best width / 2.563; the blur from the curve where it grows linearly, widths of
    3-8 x the best: sigma ~ gain |V - V_opt|, B = gain x the interval's width."""
    valid = np.arange(voltages.shape[1])[None, :] < n_pairs[:, None]
    best = np.min(np.where(valid, widths, np.inf), axis=1)
    ratio = widths / best[:, None]
    linear = valid & (ratio >= 3.0) & (ratio <= 8.0)
    distance = np.abs(voltages - optima[:, None])
    with np.errstate(divide="ignore", invalid="ignore"):
        gains = widths / TEN_NINETY_PER_SIGMA / distance
    gains = gains[linear & (distance > 0)]
    blur = float(np.median(gains)) * span if gains.size else float("nan")
    return blur, float(np.median(best)) / TEN_NINETY_PER_SIGMA


def split_indices(n_scenarios: int, split: Split) -> np.ndarray:
    """Row indices of a split: "test" is every 10th row (9, 19, ...), "train" the others."""
    rows = np.arange(n_scenarios)
    held_out = rows % HELD_OUT_EVERY == HELD_OUT_EVERY - 1
    if split == "all":
        return rows
    if split == "test":
        return rows[held_out]
    if split == "train":
        return rows[~held_out]
    raise ValueError(f"split must be 'all', 'train' or 'test', not {split!r}")


def refined_minima(voltages: np.ndarray, widths: np.ndarray, n_pairs: np.ndarray) -> np.ndarray:
    """Voltage of each curve's minimum, refined by a local fit of the focus curve.

    Near focus the edge width follows w^2 = a (V - b)^2 + c (a Gaussian probe), so a parabola
    in w^2 through the recorded minimum and its neighbours has its vertex b at the optimum.
    The vertex is kept within the neighbouring recorded points; a flat or inverted fit falls
    back to the recorded minimum.
    """
    rows = np.arange(voltages.shape[0])
    valid = np.arange(voltages.shape[1])[None, :] < n_pairs[:, None]
    best = np.argmin(np.where(valid, widths, np.inf), axis=1)
    # Five points centred on the minimum where the row allows.
    first = np.clip(best - 2, 0, np.maximum(n_pairs - 5, 0))
    window = first[:, None] + np.arange(5)[None, :]
    v = voltages[rows[:, None], window]
    w2 = widths[rows[:, None], window] ** 2
    centre = v.mean(axis=1, keepdims=True)
    x = v - centre
    design = np.stack([x**2, x, np.ones_like(x)], axis=2)  # (S, 5, 3)
    normal = np.einsum("sij,sik->sjk", design, design)
    rhs = np.einsum("sij,si->sj", design, w2)
    # Five distinct voltages make every normal matrix invertible.
    coefficients = np.linalg.solve(normal, rhs[..., None])[..., 0]
    a, b = coefficients[:, 0], coefficients[:, 1]
    recorded = voltages[rows, best]
    with np.errstate(divide="ignore", invalid="ignore"):
        vertex = centre[:, 0] - b / (2 * a)
    lower = voltages[rows, np.maximum(best - 1, 0)]
    upper = voltages[rows, np.minimum(best + 1, n_pairs - 1)]
    ok = (a > 0) & np.isfinite(vertex)
    return np.where(ok, np.clip(vertex, lower, upper), recorded)


class ScenarioSimulator:
    """Replays a scenario CSV as an Apparatus (`csv:PATH`).

    Parameters
    ----------
    path: the scenario file; None for the shipped default set of the `synthetic` preset.
    noise: relative std of the re-measurement noise (0.02 = 2 %); 0 replays exactly.
    split: "all", "train" (9 of 10 scenarios) or "test" (the held-out tenth).
    seed: seeds scenario choice and noise when `reset` is called without a seed.
    randomize: None (replay the recording), or how far each scenario's column may differ
        from it: {shift_v: V, gain: [low, high], width: [low, high]} (see `Randomization`).
    """

    def __init__(
        self,
        path: str | Path | None = None,
        noise: float = 0.0,
        split: Split = "all",
        seed: int | None = None,
        scenarios: ScenarioSet | None = None,
        randomize: Mapping[str, object] | None = None,
    ) -> None:
        # Errors in the arguments name the recording they were given for.
        source = scenarios.path if scenarios is not None else str(path or "csv:default")
        try:
            self.randomize = Randomization.parse(randomize)
        except ValueError as error:
            raise ValueError(f"{source}: {error}") from None
        # This scenario's variation: optimum shift (V), steepness and width factors.
        self._shift, self._gain, self._scale = 0.0, 1.0, 1.0
        self._recorded: tuple[float, float] | None = None  # its (blur, sigma0): recorded_column
        if isinstance(noise, bool) or not isinstance(noise, int | float):
            raise ValueError(
                f"{source}: noise must be a number (relative std, e.g. 0.02), got {_shown(noise)}"
            )
        if not 0.0 <= noise < 1.0:
            raise ValueError(f"{source}: noise must be a relative std in [0, 1), got {noise}")
        if split not in SPLITS:
            raise ValueError(
                f"{source}: split must be {', '.join(map(repr, SPLITS))}, got {_shown(split)}"
            )
        self.scenarios = (
            scenarios
            if scenarios is not None
            else read_scenarios(path if path is not None else default_scenarios_path())
        )
        self.noise = float(noise)
        self.split: Split = split
        self.indices = split_indices(len(self.scenarios), split)
        if self.indices.size == 0:
            raise ValueError(f"split {split!r} of {self.scenarios.path} holds no scenario")
        data = self.scenarios
        self.knob = data.knob
        self.knobs: Mapping[str, tuple[float, float]] = {
            data.knob: (float(data.lows.min()), float(data.highs.max()))
        }
        self.optima = refined_minima(data.voltages, data.edge_widths, data.n_pairs)
        rows = np.arange(len(data))
        self._first_v = data.voltages[:, 0]
        self._last_v = data.voltages[rows, data.n_pairs - 1]
        # Flatten all rows into one sorted array: row s is shifted by s * stride, so a single
        # searchsorted locates (scenario, voltage) pairs for every row at once.
        self._origin = float(data.voltages.min())
        self._stride = float(data.voltages.max() - self._origin) + 1.0
        self._width = data.voltages.shape[1]
        self._flat = (data.voltages - self._origin + rows[:, None] * self._stride).ravel()
        self._seeds = np.random.SeedSequence(seed)
        # Each row's recorded width at its recorded optimum, asked once per episode start.
        self._best_widths = self.query(rows, self.optima)
        self.acquisitions = 0
        self.reset(seed)

    # --- batched path -------------------------------------------------------------------

    def query(self, scenario_rows: np.ndarray, voltages: np.ndarray) -> np.ndarray:
        """Recorded edge widths (px) at many (row, voltage) pairs; NaN outside a row's span.

        `scenario_rows` are row indices into the file (0..len-1), not scenario ids.
        """
        rows = np.asarray(scenario_rows, dtype=np.int64)
        volts = np.asarray(voltages, dtype=np.float64)
        rows, volts = np.broadcast_arrays(rows, volts)
        data = self.scenarios
        keys = volts - self._origin + rows * self._stride
        position = np.searchsorted(self._flat, keys, side="right") - rows * self._width
        upper = np.clip(position, 1, data.n_pairs[rows] - 1)
        lower = upper - 1
        v0, v1 = data.voltages[rows, lower], data.voltages[rows, upper]
        w0, w1 = data.edge_widths[rows, lower], data.edge_widths[rows, upper]
        result = w0 + (volts - v0) * (w1 - w0) / (v1 - v0)
        outside = (volts < self._first_v[rows]) | (volts > self._last_v[rows])
        return np.where(outside, np.nan, result)

    def batch_key(self) -> int:
        """BatchedQueries: simulators replaying one parsed recording share the key."""
        return id(self.scenarios)

    def measure_batch(self, units: Sequence[ScenarioSimulator], settings: np.ndarray) -> np.ndarray:
        """BatchedQueries: `measure_batch` of the module on `units`, `settings` one column
        (this simulator's one knob) per unit."""
        return measure_batch(list(units), np.asarray(settings)[:, 0])

    # --- the Apparatus protocol ---------------------------------------------------------

    def reset(self, seed: int | None = None) -> None:
        """Pick a scenario of the split; the knob starts at the middle of its interval."""
        if seed is None:
            seed = int(self._seeds.spawn(1)[0].generate_state(1)[0])
        self._rng = np.random.default_rng(seed)
        self.row = int(self.indices[self._rng.integers(self.indices.size)])
        low, high = self.knobs[self.knob]
        self._voltage = 0.5 * (low + high)
        if self.randomize is not None:  # its own stream: the noise draws stay as they were
            variation = np.random.default_rng([seed, RANDOMIZE_STREAM])
            if self.randomize.family is None:
                self._shift, self._gain, self._scale = self.randomize.draw(variation)
            else:
                self._draw_family(self.randomize.family, variation)

    # --- the varied column (identity without `randomize`) --------------------------------

    def _draw_family(self, family: FocusFamily, rng: np.random.Generator) -> None:
        """This scenario's shift, steepness and widths from a family's draw (module doc)."""
        column = draw_column(family, rng)
        low, high = self.knobs[self.knob]
        if self._recorded is None:
            data = self.scenarios
            self._recorded = recorded_column(
                data.voltages, data.edge_widths, data.n_pairs, self.optima, high - low
            )
        blur, sigma0 = self._recorded
        fraction = (column.optimum - column.low) / column.width
        self._shift = low + fraction * (high - low) - self._recorded_optimum()
        self._gain = column.blur_px_per_interval / blur if math.isfinite(blur) else 1.0
        self._scale = column.floor_sigma_px / sigma0

    def _recorded_optimum(self) -> float:
        return float(self.optima[self.row])

    def _optimum(self) -> float:
        """This scenario's optimum: the recorded one shifted, kept inside the interval."""
        recorded = self._recorded_optimum()
        if self.randomize is None:
            return recorded
        low, high = self.knobs[self.knob]
        margin = OPTIMUM_MARGIN * (high - low)
        return float(np.clip(recorded + self._shift, low + margin, high - margin))

    def recorded_voltage(self, voltage: float | np.ndarray) -> float | np.ndarray:
        """Where on the recorded curve a setting of this scenario's column reads."""
        if self.randomize is None:
            return voltage
        recorded = self._recorded_optimum()
        return recorded + self._gain * (voltage - self._optimum())

    @property
    def steepness(self) -> float:
        """This scenario's steepness factor g (1 without `randomize`)."""
        return self._gain

    @property
    def width_factor(self) -> float:
        """This scenario's edge-width factor c (1 without `randomize`)."""
        return self._scale

    def read(self) -> dict[str, float]:
        return {self.knob: self._voltage}

    def write(self, values: Mapping[str, float]) -> None:
        check_write(self.knobs, values)
        if self.knob in values:
            self._voltage = float(values[self.knob])

    def measure(self) -> float:
        self.acquisitions += 1
        reading = self.recorded_voltage(self._voltage)
        width = float(self.query(np.array([self.row]), np.array([reading]))[0]) * self._scale
        if np.isnan(width):
            first, last = (
                self._setting_of(self._first_v[self.row]),
                self._setting_of(self._last_v[self.row]),
            )
            raise NoEdgesError(
                f"no edges: {self._voltage:g} V is outside the span [{first:g}, {last:g}] V "
                f"where scenario {int(self.scenarios.scenario_ids[self.row])} was measurable"
            )
        if self.noise > 0:
            width *= max(0.05, 1.0 + self.noise * float(self._rng.standard_normal()))
        return width

    def image(self) -> np.ndarray | None:
        return None

    def optimum(self) -> dict[str, float]:
        return {self.knob: self._optimum()}

    def best_quality(self) -> float:
        """The curve's edge width (px) at the optimum, without re-measurement noise."""
        return float(self._best_widths[self.row]) * self._scale

    def _setting_of(self, recorded_voltage: float) -> float:
        """The setting of this scenario's column that reads `recorded_voltage`."""
        if self.randomize is None:
            return float(recorded_voltage)
        return self._optimum() + (recorded_voltage - self._recorded_optimum()) / self._gain

    def reset_to(self, row: int, seed: int | None = None) -> None:
        """Start scenario `row` (a row index of the file), e.g. to walk a held-out split."""
        if not 0 <= row < len(self.scenarios):
            raise ValueError(
                f"row {row} is not in {self.scenarios.path} (0..{len(self.scenarios) - 1})"
            )
        self.reset(seed)
        self.row = int(row)


def measure_batch(simulators: list[ScenarioSimulator], voltages: np.ndarray) -> np.ndarray:
    """Set each simulator's knob and measure, all in one query; NaN where there are no edges.

    Equivalent to `write` + `measure` on each simulator in turn (same values, same noise
    draws from each simulator's own generator), without the per-call overhead. All
    simulators must replay the same recording.
    """
    first = simulators[0]
    rows = np.array([simulator.row for simulator in simulators])
    volts = np.asarray(voltages, dtype=np.float64)
    if any(simulator.randomize is not None for simulator in simulators):
        recorded = np.array([s.recorded_voltage(v) for s, v in zip(simulators, volts, strict=True)])
        widths = first.query(rows, recorded) * np.array([s.width_factor for s in simulators])
    else:
        widths = first.query(rows, volts)
    for position, simulator in enumerate(simulators):
        check_write(simulator.knobs, {simulator.knob: volts[position]})
        simulator._voltage = float(volts[position])
        simulator.acquisitions += 1
        if simulator.noise > 0 and np.isfinite(widths[position]):
            widths[position] *= max(
                0.05, 1.0 + simulator.noise * float(simulator._rng.standard_normal())
            )
    return widths
