"""The scenario recorder: sweeps a lens across its interval and stores the focus curve
(seed section 4.3).

Per scenario: reset the apparatus, then repeatedly set a voltage, acquire an image, store the
pair (voltage, edge width) and raise the voltage by a margin, until the interval is swept.

* `constant` margin: a fixed step (default 1/50 of the interval: 51 acquisitions).
* `adaptive` margin: finer near the focus minimum. A coarse pre-scan (default 9 acquisitions,
  not stored) finds the sharpest edge width w_min; the recorded sweep then steps by
  min_step * (w / w_min)^2, clipped to [min_step, max_step], so the points crowd where the
  image is sharp and thin out where it is hopelessly blurred. On the `synthetic` preset a
  median of 26 acquisitions is stored per scenario (20 to 34).

An acquisition that fails (no edges far out of focus, a driver fault) is not stored; a driver
fault is retried first (and does not coarsen the steps). The row counts failures in
`n_failed`. A scenario with fewer than 5 measurable points is not written, and is reported.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from multiprocessing import get_context
from typing import Any, Literal

import numpy as np

from alignrl.apparatus.base import Apparatus, ApparatusError, MeasurementError
from alignrl.apparatus.scenarios import MIN_PAIRS, ScenarioRecord

__all__ = ["SweepPlan", "scenario_seed", "sweep", "sweep_plan"]

DRIVER_RETRIES = 2  # extra attempts after a driver fault, per acquisition
RESOLUTION_PER_SPAN = 1e-5  # sweep voltages sit on a grid of 1e-5 of the interval (1 mV on
# 100 V), like the DAC of a lens supply; it keeps the stored numbers short
WIDTH_DECIMALS = 4  # edge widths are stored to 1e-4 px, far below their noise

StepRule = Literal["constant", "adaptive"]


@dataclass(frozen=True)
class SweepPlan:
    """How one knob is swept. Voltages in volts."""

    knob: str
    low: float
    high: float
    step: StepRule = "adaptive"
    constant_step_v: float = 2.0
    min_step_v: float = 1.0
    max_step_v: float = 10.0
    prescan_points: int = 9

    def __post_init__(self) -> None:
        if not self.low < self.high:
            raise ValueError(f"sweep of {self.knob!r}: low {self.low} must be below {self.high}")
        if self.step not in ("constant", "adaptive"):
            raise ValueError(f"step must be 'constant' or 'adaptive', not {self.step!r}")
        for name in ("constant_step_v", "min_step_v", "max_step_v"):
            if not getattr(self, name) > 0:
                raise ValueError(f"sweep of {self.knob!r}: {name} must be positive")
        if self.min_step_v > self.max_step_v:
            raise ValueError("min_step_v must not exceed max_step_v")
        smallest = self.constant_step_v if self.step == "constant" else self.min_step_v
        if smallest < 10 * self.resolution:
            raise ValueError(
                f"sweep of {self.knob!r}: a step of {smallest:g} is below 10 grid steps "
                f"({self.resolution:g}) of the interval"
            )
        if self.prescan_points < 3:
            raise ValueError("prescan_points must be at least 3")

    @property
    def resolution(self) -> float:
        """Grid of the set voltages, volts."""
        return (self.high - self.low) * RESOLUTION_PER_SPAN

    def on_grid(self, voltage: float) -> float:
        steps = round((voltage - self.low) / self.resolution)
        # round(.., 12) drops the float dust of the multiplication (47.30000000000001).
        return float(min(round(self.low + steps * self.resolution, 12), self.high))

    @property
    def max_pairs(self) -> int:
        """The most points one sweep can store: the header's pair columns."""
        smallest = self.constant_step_v if self.step == "constant" else self.min_step_v
        return max(MIN_PAIRS, math.floor((self.high - self.low) / smallest + 1e-9) + 1)


def sweep_plan(
    knobs: Mapping[str, tuple[float, float]], knob: str = "defocus", step: StepRule = "adaptive"
) -> SweepPlan:
    """Default plan for a knob: steps scaled to its interval."""
    if knob not in knobs:
        raise ValueError(f"the apparatus has no knob {knob!r}; it has {', '.join(knobs)}")
    low, high = (float(v) for v in knobs[knob])
    span = high - low
    return SweepPlan(
        knob=knob,
        low=low,
        high=high,
        step=step,
        constant_step_v=span / 50,
        min_step_v=span / 100,
        max_step_v=span / 10,
    )


def scenario_seed(base_seed: int, scenario: int) -> int:
    """The reset seed of scenario i: independent of worker count and of appending."""
    return int(np.random.SeedSequence([base_seed, scenario]).generate_state(1)[0])


def _acquire(apparatus: Apparatus) -> tuple[float | None, bool]:
    """One measurement: (edge width or None, whether the frame had no edges).

    A driver fault is retried; no edges is a property of the setting, so it is not.
    """
    for _ in range(1 + DRIVER_RETRIES):
        try:
            return float(apparatus.measure()), False
        except MeasurementError:
            return None, True
        except ApparatusError:
            continue
    return None, False


def sweep(apparatus: Apparatus, plan: SweepPlan, scenario: int, seed: int) -> ScenarioRecord:
    """Record one scenario. The record may hold fewer than MIN_PAIRS points (`usable`)."""
    apparatus.reset(seed)
    failed = 0
    w_min = None
    if plan.step == "adaptive":
        scan = np.linspace(plan.low, plan.high, plan.prescan_points)
        widths = []
        for voltage in scan:
            apparatus.write({plan.knob: float(voltage)})
            width, _ = _acquire(apparatus)
            if width is not None:
                widths.append(width)
        w_min = min(widths) if widths else None
    voltages: list[float] = []
    edge_widths: list[float] = []
    voltage = plan.low
    step = plan.constant_step_v if plan.step == "constant" else plan.min_step_v
    while True:
        apparatus.write({plan.knob: voltage})
        width, no_edges = _acquire(apparatus)
        if width is None:
            failed += 1
        else:
            voltages.append(voltage)
            edge_widths.append(round(width, WIDTH_DECIMALS))
        if voltage >= plan.high:
            break
        if plan.step == "constant":
            step = plan.constant_step_v
        elif width is not None and w_min is not None:
            step = plan.min_step_v * (width / w_min) ** 2
        elif no_edges or w_min is None:
            step = plan.max_step_v  # nothing to see here: cross it quickly
        # else: a driver fault; keep the last step, the region may be the one that matters
        if plan.step == "adaptive":
            step = min(max(step, plan.min_step_v), plan.max_step_v)
        # On the supply's grid, at least one grid step on, and exactly on the upper bound.
        voltage = min(max(plan.on_grid(voltage + step), voltage + plan.resolution), plan.high)
    return ScenarioRecord(
        scenario=scenario,
        seed=seed,
        knob=plan.knob,
        low=plan.low,
        high=plan.high,
        voltages=np.asarray(voltages),
        edge_widths=np.asarray(edge_widths),
        n_failed=failed,
    )


# --- parallel recording (simulated apparatus only: a real column is one process) ---------

_worker_state: dict[str, Any] = {}


def _worker_init(factory: Callable[[], Apparatus], plan: SweepPlan, base_seed: int) -> None:
    _worker_state.update(apparatus=factory(), plan=plan, base_seed=base_seed)


def _worker_sweep(scenario: int) -> tuple[int, ScenarioRecord]:
    state = _worker_state
    seed = scenario_seed(state["base_seed"], scenario)
    return scenario, sweep(state["apparatus"], state["plan"], scenario, seed)


def sweep_many(
    factory: Callable[[], Apparatus],
    plan: SweepPlan,
    scenarios: range,
    base_seed: int,
    workers: int = 1,
    apparatus: Apparatus | None = None,
) -> Iterator[tuple[int, ScenarioRecord]]:
    """Sweep scenarios in order, yielding (scenario, record) as each finishes.

    Serially, `apparatus` is used if given (a real column is opened once), else `factory()`.
    With workers > 1 each process builds its own apparatus with `factory` (which must be
    picklable); rows still come back in scenario order.
    """
    if workers <= 1:
        apparatus = apparatus if apparatus is not None else factory()
        for scenario in scenarios:
            yield scenario, sweep(apparatus, plan, scenario, scenario_seed(base_seed, scenario))
        return
    context = get_context("spawn")
    pool = context.Pool(workers, initializer=_worker_init, initargs=(factory, plan, base_seed))
    try:
        yield from pool.imap(_worker_sweep, scenarios, chunksize=1)
        pool.close()
    finally:
        pool.terminate()
        pool.join()
