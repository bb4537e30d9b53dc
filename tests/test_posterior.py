"""The Bayesian autofocus that knows its column's model (alignrl/evaluation/posterior.py):
its reading model is the family's, it aligns a column whose model it knows, and it stays
inside the interval and its budget whatever the column does."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from alignrl.apparatus.base import NoEdgesError
from alignrl.apparatus.family import FamilyColumn
from alignrl.apparatus.family_box import BOUNDED, PAIR_FIELDS, FocusFamily, family_path, load_family
from alignrl.apparatus.instruments import instrument_names
from alignrl.cli import main
from alignrl.envs.ending import resample_for
from alignrl.envs.task import get_task
from alignrl.evaluation.controllers import CountingApparatus
from alignrl.evaluation.posterior import BayesianAutofocus
from alignrl.evaluation.session import run_session
from alignrl.posterior.inference import PROBE_RULES, SCALE_FREE, FamilyPosterior
from alignrl.posterior.models import FLAT_DECADES, MODEL_FIELDS, ColumnModels, focus_box, widened

# A posterior of 32 columns judging as many states as an episode's posterior of 32 does
SMALL = {"draws": 32, "resample": resample_for(32)}


def _instrument(name: str):
    return load_family(instrument_names("validation")[name])


def test_reading_model_matches_the_column():
    """The model's mean and spread at a focus error are those of the column's readings."""
    family = _instrument("val-mid")
    models = ColumnModels.of(family, draws=1, seed=0, model_noise=0.0)
    column = FamilyColumn(family, seed=3, analytic=True)
    width, lag = column.draw.width, column.draw.hysteresis_fraction
    for fraction in (0.0, 0.02, -0.05, 0.1):
        readings = []
        for seed in range(400):
            column.reset(seed)
            target = column._optimum + (fraction + lag) * width  # approached from below
            column.write({"defocus": target - 0.01 * width})
            column.write({"defocus": target})
            readings.append(column.measure())
        # the specimen's per-episode scale varies with the seed: marginalise it on a fine grid
        scales = np.linspace(-4, 4, 401)
        weights = np.exp(-0.5 * scales**2)
        weights /= weights.sum()
        _, mean, spread = models.reading(
            np.array([[[fraction]]]), models.specimen_rel * scales[None, :, None]
        )
        mean, spread = mean.ravel(), spread.ravel()
        expected = float(weights @ mean)
        variance = float(weights @ (spread**2 + mean**2)) - expected**2
        assert np.mean(readings) == pytest.approx(expected, rel=0.01)
        assert np.std(readings) == pytest.approx(math.sqrt(variance), rel=0.15)


def test_no_edges_chance_matches_the_column():
    family = load_family(instrument_names("validation")["val-mid"], no_edges_px=30.0)
    models = ColumnModels.of(family, draws=1, seed=0, model_noise=0.0)
    column = FamilyColumn(family, seed=0, analytic=True)
    failures, expected = 0, 0.0
    for seed in range(600):
        column.reset(seed)
        low = column.draw.low
        # 0.36 of the interval away from focus, towards the farther bound: near the
        # no-edges limit (30 px)
        fraction = 0.36 if column._optimum - low < 0.5 * column.draw.width else -0.36
        column.write({"defocus": column._optimum + fraction * column.draw.width})
        error = column.focus_error() / column.draw.width
        none, _, _ = models.reading(np.array([[[error]]]), np.zeros((1, 1, 1)))
        expected += float(none.ravel()[0]) / 600
        try:
            column.measure()
        except NoEdgesError:
            failures += 1
    assert 0.1 < expected < 0.9
    assert failures / 600 == pytest.approx(expected, abs=0.06)


def test_knowing_the_instrument_it_aligns_in_few_acquisitions():
    """On its own instrument's file (every parameter known, the optimum anywhere), it
    aligns every column of a session, where a controller that probes at random would not."""
    family = _instrument("val-mid")
    apparatus = FamilyColumn(family, analytic=True)
    session = run_session(
        BayesianAutofocus(family, name="oracle"), apparatus, get_task("focus"), scenarios=12, seed=5
    )
    assert session.successes == 12
    assert session.median_acquisitions <= 4


@pytest.mark.parametrize("rule", PROBE_RULES)
def test_knowing_only_a_box_it_still_aligns(rule):
    """Over a box around the column (its gain, floor, curve power and backlash unknown
    within ranges; 32 columns drawn from the box, drawn again as readings come), on a column
    inside the box, by each probe rule: nearly every column of a session in a few
    acquisitions (a setting written at random passes in about one in twenty; the "chance"
    rule with its score's sign turned, probing where the final setting gains least, aligned
    3 of 12 at 20)."""
    path = instrument_names("validation")["val-mid"]
    box = load_family(
        path,
        blur_px_per_interval=[15.0, 60.0],
        floor_sigma_px=[0.8, 1.6],
        curve_power=[1.6, 2.6],
        hysteresis_fraction=[0.0, 0.006],
    )
    controller = BayesianAutofocus(box, probe_rule=rule, **SMALL)
    assert controller.models.count == 32
    apparatus = FamilyColumn(load_family(path), analytic=True)
    session = run_session(controller, apparatus, get_task("focus"), scenarios=12, seed=1)
    assert session.successes >= 11
    assert session.median_acquisitions <= 4


def _decisions(controller: BayesianAutofocus, readings, factor: float) -> list[tuple[float, bool]]:
    """The controller's decision after each of `readings` (setting, px), the px times
    `factor`."""
    controller.begin()
    decisions = [controller.decide()]
    for setting, width in readings:
        controller.observe(setting, width * factor)
        decisions.append(controller.decide())
    return decisions


def test_a_scale_free_posterior_decides_alike_in_any_pixel_scale():
    """The same column imaged at another magnification (every reading 3.7 x wider) leads a
    scale_free posterior to the same probes and the same stop; the posterior in the box's
    pixels decides otherwise."""
    box = load_family(instrument_names("validation")["val-mid"], blur_px_per_interval=[15.0, 60.0])
    column = FamilyColumn(load_family(instrument_names("validation")["val-mid"]), analytic=True)
    column.reset(4)
    low, high = column.knobs["defocus"]
    readings = []
    for setting in (0.2, 0.7, 0.45, 0.5):
        column.write({"defocus": low + setting * (high - low)})
        readings.append((setting, column.measure()))
    free = BayesianAutofocus(box, draws=16, scale_free=True, specimen_points=1)
    once, wider = _decisions(free, readings, 1.0), _decisions(free, readings, 3.7)
    for (a, stop_a), (b, stop_b) in zip(once, wider, strict=True):
        assert a == pytest.approx(b, abs=1e-9) and stop_a == stop_b
    fixed = BayesianAutofocus(box, draws=16)
    assert _decisions(fixed, readings, 1.0) != _decisions(fixed, readings, 3.7)


def test_a_scale_free_posterior_aligns_a_column_at_another_magnification():
    """Over the box, on a column whose every reading is 3 x what the box's columns read:
    the scale_free posterior aligns most of eight, the posterior in the box's pixels few."""
    path = instrument_names("validation")["val-mid"]
    box = load_family(path, blur_px_per_interval=[15.0, 60.0], floor_sigma_px=[0.8, 1.6])
    successes = {}
    for scale_free in (True, False):
        apparatus = _Magnified(FamilyColumn(load_family(path), analytic=True), 3.0)
        options = {"scale_free": True, "specimen_points": 1} if scale_free else {}
        controller = BayesianAutofocus(box, **SMALL, **options)
        session = run_session(controller, apparatus, get_task("focus"), scenarios=8, seed=1)
        successes[scale_free] = session.successes
    assert successes[True] >= 6
    assert successes[False] <= 4


class _Magnified:
    """A column whose readings are `factor` x its own (another pixel size)."""

    def __init__(self, column, factor: float) -> None:
        self._column, self._factor = column, factor

    def __getattr__(self, name):
        return getattr(self._column, name)

    def measure(self):
        return self._factor * self._column.measure()

    def best_quality(self):
        return self._factor * self._column.best_quality()


class _Blind:
    """A column whose every frame has no edges."""

    def __init__(self) -> None:
        self.knobs = {"defocus": (-10.0, 30.0)}
        self.setting = 0.0
        self.written: list[float] = []

    def read(self):
        return {"defocus": self.setting}

    def write(self, values):
        value = float(values["defocus"])
        low, high = self.knobs["defocus"]
        assert low <= value <= high
        self.setting = value
        self.written.append(value)

    def measure(self):
        raise NoEdgesError("no edges anywhere")


def test_a_column_without_edges_ends_inside_the_interval_and_budget():
    family = _instrument("val-mid")
    blind = _Blind()
    counting = CountingApparatus(blind, budget=5)
    BayesianAutofocus(family, name="oracle").align(counting, "defocus", budget=5)
    assert counting.acquisitions <= 5
    assert blind.written and all(-10.0 <= value <= 30.0 for value in blind.written)


def test_a_setting_at_the_top_of_an_interval_that_rounds_is_written_inside_it():
    # set:validation's val-low-bound reads [-2000, -1.1e-13]: low + 1.0 x (high - low) is
    # 0.0, past high; the driver refused it and `evaluate --policy posterior-scale-free` ended
    blind = _Blind()
    low, high = -2000.0, -1.1368683772161603e-13
    blind.knobs = {"defocus": (low, high)}
    blind.setting = low
    assert low + 1.0 * (high - low) > high
    BayesianAutofocus(_instrument("val-mid"), name="oracle")._write(
        blind, "defocus", low, high - low, 1.0
    )
    assert blind.written[-1] == high


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("confidence", 1.0),
        ("confidence", 0.0),
        ("spec_relative", 1.0),
        ("draws", 0),
        ("optimum_prior", "anywhere"),
        ("probe_rule", "information"),
    ],
)
def test_bad_settings_are_refused(field, value):
    with pytest.raises(ValueError, match=field):
        BayesianAutofocus(_instrument("val-mid"), **{field: value})


def test_a_widened_box_holds_the_box_within_what_the_family_allows():
    box = load_family(family_path("focus"))
    wide = widened(box, 0.5)
    assert widened(box, 0.0) == box
    assert wide.optimum_fraction == box.optimum_fraction  # the prior's own business
    grew = 0
    for name in MODEL_FIELDS.values():
        (low, high), (wide_low, wide_high) = getattr(box, name), getattr(wide, name)
        lowest, highest = BOUNDED.get(name, (0.0, math.inf))
        assert lowest <= wide_low <= low <= high <= wide_high <= highest, name
        grew += (wide_low, wide_high) != (low, high)
        if low == high:
            assert (wide_low, wide_high) == (low, high), name  # a point stays a point
    assert grew >= 10
    gain_low, gain_high = wide.blur_px_per_interval  # log scale: 10-120 px by 12**0.5 each way
    assert gain_low == pytest.approx(10.0 / 12.0**0.5) and gain_high == pytest.approx(
        120.0 * 12.0**0.5
    )
    with pytest.raises(ValueError, match="reach"):
        widened(box, -0.1)


@pytest.mark.parametrize(
    ("name", "scenarios"),
    [("posterior", 4), ("posterior-scale-free", 4), ("posterior-robust", 2)],
)
def test_evaluate_runs_the_family_posterior_by_name(
    name: str, scenarios: int, capsys: pytest.CaptureFixture[str]
) -> None:
    """`alignrl evaluate --policy posterior` (or posterior-scale-free, posterior-robust): the
    posterior over the training box, on a validation instrument it was never given the file
    of (posterior-robust, four times the columns and 10 s an alignment, on the first two of
    the four: it aligns both at 5.5, as it does all four)."""
    argv = ["evaluate", "--policy", name, "--apparatus", "instrument:val-mid"]
    args = ["--apparatus-args", '{"analytic": true}', "--scenarios", str(scenarios)]
    assert main([*argv, *args, "--json", "--quiet"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["controller"] == name and report["task"] == "focus"
    assert report["successes"] >= scenarios - 1 and report["median_acquisitions"] <= 6


def test_far_noise_widens_the_spread_with_the_distance_from_focus_only():
    family = _instrument("val-steep")
    plain = ColumnModels.of(family, draws=1, seed=0, model_noise=0.03)
    far = ColumnModels.of(family, draws=1, seed=0, model_noise=0.03, far_noise=0.1)
    errors = np.array([[[0.0, 0.01, 0.05, 0.2]]])
    _, mean, spread = plain.reading(errors, np.zeros((1, 1, 1)))
    _, far_mean, far_spread = far.reading(errors, np.zeros((1, 1, 1)))
    assert np.array_equal(mean, far_mean)
    assert far_spread.ravel()[0] == pytest.approx(spread.ravel()[0])  # in focus: as before
    ratio = (far_spread / spread).ravel()
    assert np.all(np.diff(ratio) > 0) and ratio[-1] > 2  # the farther, the wider


def test_far_noise_keeps_two_far_readings_from_making_the_posterior_sure():
    """Two readings far below focus whose order is the wrong way round (on images, a grid
    blurred past its pitch reads narrower as it blurs more): without far_noise the oracle of
    val-steep is sure that focus lies below both and would end there unseen; with it, it
    probes on."""
    family = _instrument("val-steep")
    decisions = {}
    for far_noise in (0.0, 0.1):
        posterior = BayesianAutofocus(family, far_noise=far_noise)
        posterior.begin()
        for setting, reading in [(0.907, math.nan), (0.0414, 11.83), (0.0897, 19.81)]:
            posterior.observe(setting, reading)
        decisions[far_noise] = (posterior.final()[1], posterior.decide()[1])
    assert decisions[0.0][0] > 0.99 and decisions[0.0][1]
    assert decisions[0.1][0] < 0.9 and not decisions[0.1][1]
    with pytest.raises(ValueError, match="far_noise"):
        BayesianAutofocus(family, far_noise=-0.1)


def test_the_flat_bottom_is_weighed_log_uniformly_over_its_decades():
    """A row's flat-bottom fraction u places the column's flat bottom at 10^(-d (1 - u)) of
    the box's widest with FLAT_DECADES d, at u x the widest as the box draws it with 0; every
    other parameter where the box puts it."""
    box = load_family(family_path("focus"))
    rows = np.tile(np.linspace(0.0, 1.0, 5)[:, None], (1, len(PAIR_FIELDS)))
    uniform = ColumnModels.at(box, rows, 0.03)
    weighed = ColumnModels.at(box, rows, 0.03, flat_decades=2.0)
    widest = box.flat_fraction[1]
    assert np.allclose(uniform.flat.ravel(), np.linspace(0.0, 1.0, 5) * widest)
    assert np.allclose(weighed.flat.ravel(), widest * 10.0 ** (-2.0 * (1.0 - rows[:, 0])))
    assert np.array_equal(weighed.gain, uniform.gain) and np.array_equal(weighed.rows, rows)
    assert FamilyPosterior(box, draws=8).flat_decades == FLAT_DECADES > 0
    with pytest.raises(ValueError, match="flat_decades"):
        FamilyPosterior(box, draws=8, flat_decades=-1.0)


def test_a_steep_column_without_a_flat_bottom_does_not_make_the_box_posterior_sure():
    """Readings of a traced alignment on wide-interval (150 px of blur per interval, no flat
    bottom; focus approached from below at 0.571 of the interval): a reading in focus at
    0.5709, then one on the flank above. Weighing flat bottoms uniformly, the box's columns
    with a plateau wider than the column's passing window explain them as well and are sure:
    the posterior is 99 % sure of a setting 0.8 % of the interval below focus, outside the
    window, and the alignment ends there; weighed log-uniformly, it is not sure and reads on."""
    readings = [
        (0.4305, 34.156),
        (0.4778, 23.284),
        (0.8725, 27.44),
        (0.0874, math.nan),
        (0.5709, 3.2139),
        (0.5903, 8.705),
    ]
    chances = {}
    for decades in (0.0, FLAT_DECADES):
        posterior = FamilyPosterior(
            focus_box(), draws=1024, far_noise=0.1, flat_decades=decades, **SCALE_FREE
        )
        posterior.begin()
        for setting, reading in readings:
            posterior.observe(setting, reading)
        chances[decades] = posterior.final()
    assert chances[0.0][1] >= 0.99 and chances[0.0][0] < 0.571 - 0.006
    assert chances[FLAT_DECADES][1] < 0.99


def test_a_scale_free_posterior_reads_the_column_as_found_on_either_branch():
    """val-backlash (1.2 % of the interval against the approach), focus at 0.5 from below:
    the column found at 0.48 as if left from above, then a reading far above and one at 0.52,
    both from below (the model's readings, noise-free). Read as approached from below, the
    opening reading puts focus 1.3 % of the interval low and the scale-free oracle is sure of
    it; read on an unknown side (side 0: the mixture of the branches), it is nearly on
    focus."""
    family = _instrument("val-backlash")
    oracle = FamilyPosterior(family, draws=1)
    lag = float(oracle.models.lag.ravel()[0])
    half = float(oracle.models.spec_half_width(1.15).ravel()[0])

    def reading(error: float) -> float:
        _, mean, _ = oracle.models.reading(np.full((1, 1, 1, 1), error), np.zeros((1, 1, 1)))
        return float(mean.ravel()[0])

    trace = [(0.48, reading(0.48 + lag - 0.5))]
    trace += [(u, reading(u - lag - 0.5)) for u in (0.9, 0.52)]
    finals = {}
    for side in (1.0, 0.0):
        posterior = FamilyPosterior(family, draws=1, far_noise=0.1, **SCALE_FREE)
        posterior.begin()
        for index, (setting, width) in enumerate(trace):
            posterior.observe(setting, width, side if index == 0 else 1.0)
        setting, chance = posterior.final()
        finals[side] = (setting - lag - 0.5, chance)
    assert finals[1.0][1] > 0.99 and abs(finals[1.0][0]) > 0.5 * half
    assert abs(finals[0.0][0]) < 0.2 * half
    assert finals[0.0][1] < finals[1.0][1]


def test_a_reading_on_either_branch_joins_the_scale_sums_with_the_branches_spread():
    """ScaleSums.add_either: alike branches are one reading (the same sums and predictive as
    `add`); branches apart join with their mean residual and their spread added to the
    variance, and weigh each branch's predictive by its chance of a measured reading."""
    from alignrl.posterior.scale_sums import ScaleSums

    one, either = ScaleSums.empty((2,)), ScaleSums.empty((2,))
    for sums in (one, either):
        sums.add(np.array([0.1, 0.2]), np.array([0.01, 0.01]))
    residual, variance = np.array([0.3, -0.1]), np.array([0.02, 0.02])
    expected = one.predictive(residual, variance)
    one.add(residual, variance)
    density = either.add_either([residual] * 3, [variance] * 3, [np.ones(2)] * 3)
    assert np.allclose(density, expected) and np.allclose(either.sum0, one.sum0)
    assert np.allclose(either.sum1, one.sum1)
    apart = ScaleSums.empty((1,))
    apart.add(np.zeros(1), np.full(1, 0.01))
    chances = [np.ones(1), np.zeros(1)]
    density = apart.add_either([np.full(1, 0.2), np.full(1, -0.2)], [np.full(1, 0.01)] * 2, chances)
    assert np.isclose(apart.sum1[0], 0.0) and np.isclose(apart.sum0[0], 100 + 1 / 0.05)
    lone = ScaleSums.empty((1,))
    lone.add(np.zeros(1), np.full(1, 0.01))
    assert np.allclose(density, 0.5 * lone.predictive(np.full(1, 0.2), np.full(1, 0.01)))


def test_the_entropy_rule_reads_near_the_likely_focus_before_ruling_out_a_far_one():
    """Two readings on val-low-bound (focus at 0.075 of the interval) that grow upward: focus
    most likely lies below the first, less likely far above the second. The variance rule
    reads far above (two far modes weigh most in a variance); the entropy rule reads below,
    where one reading either finds focus or leaves the far mode."""
    probes = {}
    for rule in ("variance", "entropy"):
        posterior = FamilyPosterior(
            focus_box(), draws=1024, far_noise=0.1, probe_rule=rule, **SCALE_FREE
        )
        posterior.begin()
        for setting, reading in [(0.2688, 26.77), (0.4727, 36.61)]:
            posterior.observe(setting, reading)
        probes[rule] = posterior.probe()
    assert probes["variance"] > 0.6 and probes["entropy"] < 0.2688


def test_readings_levelling_off_as_a_grids_keep_steep_columns_in_the_posterior():
    """val-steep on images (100 px of blur per interval, a grid, whose edge widths level off
    at about 15 px): the champion's first readings of one alignment, none near focus. The box,
    whose readings level off from 18 px, all but rules out steep columns and is 98 % sure of a
    setting outside the column's window (+-0.5 % of the interval); levelling off from 10 px
    (Task.posterior_saturation_px, as images do) it keeps them and is not sure."""
    optimum = 0.183
    readings = [
        (-0.1352, 16.38),
        (0.1176, 15.02),
        (0.7225, math.nan),
        (-0.0377, 11.30),
        (0.0540, 11.47),
    ]
    steep, sure = {}, {}
    for saturation in (None, (10.0, 80.0)):
        posterior = FamilyPosterior(
            focus_box(saturation_px=saturation),
            draws=1024,
            far_noise=0.1,
            probe_rule="entropy",
            **SCALE_FREE,
        )
        posterior.begin()
        for error, reading in readings:
            posterior.observe(optimum + error, reading)
        weights = posterior._posterior.sum(axis=(1, 2))
        steep[saturation] = float(weights[posterior.models.gain[:, 0, 0] >= 60.0].sum())
        setting, sure[saturation] = posterior.final()
        if saturation is None:
            assert abs(setting - optimum) > 0.005 and sure[saturation] > 0.98
    assert steep[(10.0, 80.0)] > 2.0 * steep[None]
    assert sure[(10.0, 80.0)] < 0.98


def test_a_column_too_noisy_to_pass_surely_even_at_focus_still_ends():
    """Where a column's readings are so noisy that a setting at the optimum itself passes the
    verification with less than the confidence asked, no reading can make a plain chance that
    sure, and the oracle reads on to its budget; with `relative_stop` (a calibrated column's
    posterior) it stops once the final setting passes with the confidence x the chance at
    the optimum (a column fitted noisy: docs/benchmarks.md, twenty-fifth session)."""
    noisy = {**_instrument("val-mid").model_dump(), "reading_noise_rel": 0.08}
    family = FocusFamily.model_validate(noisy)
    apparatus = FamilyColumn(family, analytic=True)
    medians = {}
    for relative in (False, True):
        oracle = BayesianAutofocus(
            family, confidence=0.98, max_acquisitions=12, relative_stop=relative
        )
        oracle.begin()
        k, z, n, weight = oracle._scored(oracle._posterior, 2000)
        assert float(oracle._passes(None, k, z, n)[0] @ weight) < 0.97
        session = run_session(oracle, apparatus, get_task("focus"), scenarios=8, seed=5)
        medians[relative] = session.median_acquisitions
        assert session.successes >= 6
    assert medians[False] == 12 and medians[True] < 12
    assert 0.98 <= oracle.final()[1] <= 1.0  # how sure it ended the last alignment
