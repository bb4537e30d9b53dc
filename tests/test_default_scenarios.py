"""The shipped 2000-scenario set is what `make scenarios` records on the `synthetic` preset."""

from __future__ import annotations

import numpy as np
import pytest

from alignrl.apparatus import ScenarioSimulator, make_apparatus, read_scenarios
from alignrl.apparatus.recorder import scenario_seed, sweep, sweep_plan
from alignrl.apparatus.simulator import DEFAULT_SCENARIOS, refined_minima


@pytest.fixture(scope="module")
def shipped():
    return read_scenarios(DEFAULT_SCENARIOS)


def test_the_shipped_set_is_complete_and_valid(shipped) -> None:
    assert len(shipped) == 2000
    assert list(shipped.scenario_ids) == list(range(2000))
    assert shipped.knob == "defocus"
    assert list(shipped.seeds[:3]) == [scenario_seed(0, i) for i in range(3)]


@pytest.mark.parametrize("scenario", [0, 1733])
def test_rows_regenerate_from_their_seed(shipped, scenario: int) -> None:
    """Recording a scenario again on this machine gives its shipped focus curve.

    Exact bytes may differ across CPUs (FFT and OpenCV take different SIMD paths), so the
    check is physical: the same optimum and the same curve within the measurement noise.
    """
    sem = make_apparatus("synthetic")
    fresh = sweep(sem, sweep_plan(sem.knobs), scenario, int(shipped.seeds[scenario]))
    assert fresh is not None
    stored = shipped.record(scenario)
    simulator = ScenarioSimulator(scenarios=shipped)
    fresh_optimum = refined_minima(
        fresh.voltages[None], fresh.edge_widths[None], np.array([fresh.voltages.size])
    )[0]
    assert fresh_optimum == pytest.approx(float(simulator.optima[scenario]), abs=0.5)
    replayed = simulator.query(np.full(fresh.voltages.size, scenario), fresh.voltages)
    near = np.abs(fresh.voltages - fresh_optimum) < 20.0  # far out, widths saturate and scatter
    np.testing.assert_allclose(fresh.edge_widths[near], replayed[near], rtol=0.1)
    assert stored.n_failed == fresh.n_failed or abs(stored.n_failed - fresh.n_failed) <= 1
