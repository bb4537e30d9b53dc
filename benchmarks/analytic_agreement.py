"""The synthetic SEM's analytic mode against its image path (docs/physics.md).

    python -m benchmarks.analytic_agreement --states 1000 --preset synthetic

draws random misaligned states of the column (a fresh scenario each, every knob off its
optimum within the range a scenario's misalignment spans), measures each once with the image
path (render, then quality.edge_width / directional_widths / wobble_shift) and once in analytic
mode, and prints how far the readings agree. Exit status 1 if the widths disagree: the median
over the states of (analytic - image) / image must be within +/- 5 %, and so must the median
of |expected - image| / image, where `expected` is the analytic model's value of that state
without its drawn scatter (`SyntheticSEM.expected_width_px`): the value the model computes,
against what one image reads. Beside them: the median absolute difference of a noisy analytic
reading (its own scatter added to the image's), the shares of states within 5 %, and the same
for two image-path readings of one state (new noise, same specimen), the floor set by the
image path's own noise.

    python -m benchmarks.analytic_agreement --calibrate --preset synthetic-b

fits the preset's analytic calibration (`AnalyticModel`: the image path's bias and scatter
against the probe's effective width, its blur limits, the wobble's ratio and scatter) on 3000
rendered frames and prints it as the YAML block of the preset file.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from alignrl.apparatus import MeasurementError, NoEdgesError, make_apparatus
from alignrl.apparatus.quality import ORIENTATION_BINS_DEG, directional_widths, edge_width
from alignrl.apparatus.synthetic import (
    AnalyticModel,
    SEMConfig,
    SyntheticSEM,
    directional_edge_widths_px,
    mean_edge_width_px,
)

CRITERION_REL = 0.05  # |median of (analytic - image) / image| over the states
WOBBLE_AMPLITUDE_V = 5.0  # the wobble of the multi-knob tasks (alignrl/envs/task.py)
AGREEMENT_STREAM, CALIBRATION_STREAM = 0, 1  # scenario streams of misaligned_states
ORIENTATION_POWERS = (1.0, 0.5, 0.0, -0.5, -1.0, -1.5, -2.0, -3.0)  # candidates for the fit


@dataclass(frozen=True)
class State:
    """One misaligned column: the scenario's reset seed and the five knob settings."""

    seed: int
    settings: dict[str, float]


def misaligned_states(
    config: SEMConfig, count: int, seed: int = 0, stream: int = AGREEMENT_STREAM
) -> list[State]:
    """Random states within the misalignment a scenario can start with: the focus off by up
    to optimum_spread_v, each stigmator off by up to the excitation that cancels the largest
    astigmatism, the aperture off by up to aperture_offset_max_um along each axis (clipped to
    the knobs' intervals). Calibration and comparison draw their scenarios from different
    streams, so no comparison sees a specimen the calibration was fitted on."""
    rng = np.random.default_rng([stream, seed])
    sem = SyntheticSEM(config, seed=seed)
    reach = {
        "defocus": config.optimum_spread_v,
        "stigmator_x": config.astigmatism_max_v / config.stigmator_v_per_pct,
        "stigmator_y": config.astigmatism_max_v / config.stigmator_v_per_pct,
        "aperture_x": config.aperture_offset_max_um,
        "aperture_y": config.aperture_offset_max_um,
    }
    states = []
    for _ in range(count):
        scenario = int(rng.integers(2**31))
        sem.reset(scenario)
        optimum = sem.optimum()
        settings = {
            knob: float(np.clip(optimum[knob] + rng.uniform(-1, 1) * reach[knob], *sem.knobs[knob]))
            for knob in sem.knobs
        }
        states.append(State(scenario, settings))
    return states


def _reading(sem: SyntheticSEM) -> tuple[float, np.ndarray, np.ndarray]:
    """(width, directional widths, wobble shift) of one state; NaN for a measure that found
    nothing to measure."""
    try:
        width = sem.measure()
    except NoEdgesError:
        width = math.nan
    try:
        directional = sem.measure_directional()[1]
    except NoEdgesError:
        directional = np.full(len(ORIENTATION_BINS_DEG), np.nan)
    try:
        wobble = sem.measure_wobble(WOBBLE_AMPLITUDE_V)
    except MeasurementError:  # nothing to correlate
        wobble = np.full(2, np.nan)
    return width, directional, wobble


def compare(config: SEMConfig, states: Sequence[State]) -> dict[str, np.ndarray]:
    """Both modes on every state, each from a fresh reset to the state's scenario; and a second
    image-path width of each state on a later frame (new noise, same specimen and probe)."""
    modes = {"image": SyntheticSEM(config, seed=0), "analytic": SyntheticSEM(config, 0, True)}
    out: dict[str, list] = {f"{m}_{q}": [] for m in modes for q in ("width", "dir", "wobble")}
    out.update(true_width=[], expected_width=[], image_again_width=[])
    for state in states:
        for name, sem in modes.items():
            sem.reset(state.seed)
            sem.write(state.settings)
            if name == "image":
                out["true_width"].append(sem.probe_width_px())
                out["expected_width"].append(sem.expected_width_px())
            width, directional, wobble = _reading(sem)
            out[f"{name}_width"].append(width)
            out[f"{name}_dir"].append(directional)
            out[f"{name}_wobble"].append(wobble)
        image = modes["image"]
        image.reset(state.seed)
        image.write(state.settings)
        image.acquire()  # moves the noise stream on
        try:
            out["image_again_width"].append(image.measure())
        except NoEdgesError:
            out["image_again_width"].append(math.nan)
    return {key: np.asarray(values, dtype=np.float64) for key, values in out.items()}


def _relative(analytic: np.ndarray, image: np.ndarray) -> np.ndarray:
    """(analytic - image) / image where both read a width."""
    both = np.isfinite(analytic) & np.isfinite(image) & (image > 0)
    return (analytic[both] - image[both]) / image[both]


def agreement(result: dict[str, np.ndarray]) -> dict[str, float]:
    """The figures of one comparison. States where either mode found no edges are counted
    apart, not compared; `width_by_blur_*` splits the widths by the probe's true width."""
    image, analytic = result["image_width"], result["analytic_width"]
    relative = _relative(analytic, image)
    dir_rel = _relative(result["analytic_dir"].ravel(), result["image_dir"].ravel())
    repeat = _relative(result["image_again_width"], image)
    expected = _relative(result["expected_width"], image)
    wobble_error = np.hypot(*(result["analytic_wobble"] - result["image_wobble"]).T)
    figures = {
        "states": float(image.size),
        "no_edges_image": float(np.isnan(image).sum()),
        "no_edges_analytic": float(np.isnan(analytic).sum()),
        "width_median_rel": float(np.median(relative)),
        "width_median_abs_rel": float(np.median(np.abs(relative))),
        "width_within_5pct": float(np.mean(np.abs(relative) <= CRITERION_REL)),
        # The model without its drawn scatter (the median reading it predicts) against the
        # image: how well the analytic mode computes the value an image reads.
        "expected_median_rel": float(np.median(expected)),
        "expected_median_abs_rel": float(np.median(np.abs(expected))),
        "expected_within_5pct": float(np.mean(np.abs(expected) <= CRITERION_REL)),
        "image_repeat_median_abs_rel": float(np.median(np.abs(repeat))),
        "image_repeat_within_5pct": float(np.mean(np.abs(repeat) <= CRITERION_REL)),
        "dir_median_rel": float(np.median(dir_rel)),
        "dir_median_abs_rel": float(np.median(np.abs(dir_rel))),
        "dir_within_5pct": float(np.mean(np.abs(dir_rel) <= CRITERION_REL)),
        "wobble_median_error_px": float(np.nanmedian(wobble_error)),
        "wobble_median_shift_px": float(np.nanmedian(np.hypot(*result["image_wobble"].T))),
    }
    for low, high in ((0.0, 8.0), (8.0, 16.0), (16.0, math.inf)):
        inside = (result["true_width"] >= low) & (result["true_width"] < high)
        part = _relative(analytic[inside], image[inside])
        name = f"width_by_blur_{low:g}_{high:g}px"
        figures[f"{name}_states"] = float(inside.sum())
        figures[f"{name}_median_rel"] = float(np.median(part)) if part.size else math.nan
        figures[f"{name}_median_abs_rel"] = (
            float(np.median(np.abs(part))) if part.size else math.nan
        )
    return figures


def speed(config: SEMConfig, analytic: bool, calls: int = 200, seed: int = 0) -> float:
    """measure() calls per second at random misaligned states (one per call)."""
    sem = SyntheticSEM(config, seed=seed, analytic=analytic)
    states = misaligned_states(config, calls, seed)
    sem.reset(states[0].seed)
    elapsed = 0.0
    for state in states:
        sem.write(state.settings)  # the scenario stays: only measuring is timed
        start = time.perf_counter()
        try:
            sem.measure()
        except NoEdgesError:
            pass
        elapsed += time.perf_counter() - start
    return calls / elapsed


# --- calibration ------------------------------------------------------------------------


def _read_frame(sem: SyntheticSEM) -> tuple[float, np.ndarray]:
    """(edge width, directional widths) of one new frame, NaN where there are no edges. One
    detection gives both; a frame with an empty orientation bin still has its edge width."""
    image = sem.acquire()
    try:
        measured = directional_widths(image)
        return measured.width_px, measured.widths_px
    except NoEdgesError:
        empty = np.full(len(ORIENTATION_BINS_DEG), np.nan)
    try:
        return edge_width(image), empty
    except NoEdgesError:
        return math.nan, empty


def _calibration_frames(config: SEMConfig, count: int, seed: int) -> dict[str, np.ndarray]:
    """Image-path readings of probes with random astigmatism and aperture residuals (a random
    fraction of a scenario's misalignment each), blurred by the focus to a true width
    log-uniform from the in-focus width to 25 px (half of the states, where alignment happens)
    or to 160 px (the other half, beyond the blur limits). Each state is read on two frames,
    whose difference is the noise, and wobbled once."""
    wide = config.model_copy(
        update={
            "defocus_interval_v": (-1e4, 1e4),
            "hysteresis_v": 0.0,
            "drift_v_per_acquisition": 0,
        }
    )
    sem = SyntheticSEM(wide, seed=seed)
    rng = np.random.default_rng([CALIBRATION_STREAM, seed])
    best = sem.best_quality()
    rows: dict[str, list] = {
        key: [] for key in ("covariance", "width", "width_again", "bins", "bins_again", "wobble")
    }
    rows.update(wobble_exact=[], wobble_sigma=[])
    for state in misaligned_states(wide, count, seed, CALIBRATION_STREAM):
        sem.reset(state.seed)
        part, optimum = rng.uniform(0.0, 1.0), sem.optimum()
        sem.write(
            {
                knob: optimum[knob] + part * (value - optimum[knob])
                for knob, value in state.settings.items()
                if knob != "defocus"
            }
        )
        farthest = 25.0 if rng.random() < 0.5 else 160.0
        target = best * math.exp(rng.uniform(0.0, math.log(farthest / best)))
        side = 1.0 if rng.random() < 0.5 else -1.0
        low, high = 0.0, 1e4 / 2
        for _ in range(50):  # bisect the focus error that blurs to the target width
            middle = 0.5 * (low + high)
            sem.write({"defocus": optimum["defocus"] + side * middle})
            low, high = (middle, high) if sem.probe_width_px() < target else (low, middle)
        rows["covariance"].append(sem.probe_covariance_px2())
        for suffix in ("", "_again"):
            width, bins = _read_frame(sem)
            rows[f"width{suffix}"].append(width)
            rows[f"bins{suffix}"].append(bins)
        # The wobble about this setting: its exact shift and blur, then the image path's.
        setting, exact, variance = sem.read()["defocus"], np.zeros(2), 0.0
        for sign in (1.0, -1.0):
            sem.write({"defocus": setting + sign * WOBBLE_AMPLITUDE_V})
            exact += sign * sem.image_shift_px()
            variance += 0.25 * float(np.trace(sem.probe_covariance_px2()))
        sem.write({"defocus": setting})
        try:
            shift = sem.measure_wobble(WOBBLE_AMPLITUDE_V)
        except MeasurementError:
            shift = np.full(2, np.nan)
        rows["wobble_exact"].append(exact)
        rows["wobble_sigma"].append(math.sqrt(variance))
        rows["wobble"].append(shift)
    return {key: np.asarray(values, dtype=np.float64) for key, values in rows.items()}


def _robust_std(values: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(values - np.median(values))))


def _tables(
    width: np.ndarray, reading: np.ndarray, again: np.ndarray, knots: np.ndarray
) -> tuple[list[float], list[float], list[float]]:
    """Per knot, from the states whose width lies between the geometric midpoints to its
    neighbours: the median of reading / width, the noise (robust std of the log difference of
    two readings of a state, over sqrt 2) and the specimen scatter (what the robust std of the
    log ratio has beyond the noise). A knot without data takes its nearest neighbour's."""
    ok = np.isfinite(reading) & np.isfinite(again) & (reading > 0) & (again > 0)
    log_ratio, log_again, width = np.log(reading[ok] / width[ok]), np.log(again[ok]), width[ok]
    edges = np.r_[0.0, np.sqrt(knots[1:] * knots[:-1]), np.inf]
    tables = np.full((3, knots.size), np.nan)
    for index in range(knots.size):
        inside = (width >= edges[index]) & (width < edges[index + 1])
        if inside.sum() >= 10:
            total = _robust_std(log_ratio[inside])
            noise = _robust_std(log_ratio[inside] + np.log(width[inside]) - log_again[inside])
            noise /= math.sqrt(2.0)
            specimen = math.sqrt(max(total**2 - noise**2, 0.0))
            tables[:, index] = math.exp(np.median(log_ratio[inside])), noise, specimen
    filled = np.flatnonzero(np.isfinite(tables[0]))
    nearest = filled[np.abs(np.arange(knots.size)[:, None] - filled[None, :]).argmin(axis=1)]
    ratio, noise, specimen = (list(np.round(row[nearest], 3)) for row in tables)
    return ratio, noise, specimen


def _orientation_power(frames: dict[str, np.ndarray], knots: np.ndarray) -> float:
    """The power of the orientation mean under which elliptical probes read like round ones of
    the same effective width: of the candidates, the one where the median log residual of
    strongly elliptical probes (widest / narrowest bin > 1.3) is nearest that of nearly round
    ones (< 1.1), over frames up to 25 px."""
    bins = np.array([directional_edge_widths_px(c) for c in frames["covariance"]])
    elliptical = bins.max(axis=1) / bins.min(axis=1)
    best, power = math.inf, 1.0
    for candidate in ORIENTATION_POWERS:
        width = np.array([mean_edge_width_px(c, candidate) for c in frames["covariance"]])
        ratio, _, _ = _tables(width, frames["width"], frames["width_again"], knots)
        residual = np.log(frames["width"] / (width * np.interp(width, knots, ratio)))
        near = np.isfinite(residual) & (width < 25.0)
        gap = abs(
            np.median(residual[near & (elliptical > 1.3)])
            - np.median(residual[near & (elliptical < 1.1)])
        )
        if gap < best:
            best, power = gap, candidate
    return power


def _logistic_fit(size_px: np.ndarray, failed: np.ndarray) -> tuple[float, float]:
    """Logistic P(failure | size) by maximum likelihood on a grid: (midpoint px, spread px)."""
    best = (-np.inf, 0.0, 0.0)
    for middle in np.arange(1.0, 400.0, 0.5):
        for spread in np.arange(0.5, 40.0, 0.5):
            p = np.clip(0.5 * (1.0 + np.tanh(0.5 * (size_px - middle) / spread)), 1e-9, 1 - 1e-9)
            likelihood = np.sum(np.where(failed, np.log(p), np.log1p(-p)))
            if likelihood > best[0]:
                best = (likelihood, middle, spread)
    return best[1], best[2]


def _wobble_fit(frames: dict[str, np.ndarray]) -> tuple[float, float]:
    """(ratio, scatter per px of sigma) of the image path's wobble shift against the exact one:
    the median of the measured shift projected on the exact one over its length (shifts over
    1 px), and the robust std of the remaining error's components over the probe's sigma, for
    pairs with a mean sigma up to 10 px."""
    exact, measured, sigma = frames["wobble_exact"], frames["wobble"], frames["wobble_sigma"]
    ok = np.all(np.isfinite(measured), axis=1) & (sigma < 10.0)
    length = np.hypot(*exact.T)
    along = ok & (length > 1.0)
    ratio = float(np.median(np.sum(measured[along] * exact[along], axis=1) / length[along] ** 2))
    return ratio, _robust_std(((measured[ok] - ratio * exact[ok]) / sigma[ok, None]).ravel())


def fit_calibration(frames: dict[str, np.ndarray]) -> AnalyticModel:
    """The analytic calibration that reproduces these image-path frames."""
    knots = np.asarray(AnalyticModel().knots_px)
    power = _orientation_power(frames, knots)
    width = np.array([mean_edge_width_px(c, power) for c in frames["covariance"]])
    bin_width = np.array([directional_edge_widths_px(c) for c in frames["covariance"]])
    ratio, noise, specimen = _tables(width, frames["width"], frames["width_again"], knots)
    dir_ratio, dir_noise, dir_specimen = _tables(
        bin_width.ravel(), frames["bins"].ravel(), frames["bins_again"].ravel(), knots
    )
    middle, spread = _logistic_fit(width, np.isnan(frames["width"]))
    dir_middle, dir_spread = _logistic_fit(width, np.isnan(frames["bins"][:, 0]))
    wobble_failed = ~np.all(np.isfinite(frames["wobble"]), axis=1)
    wobble_middle, wobble_spread = _logistic_fit(frames["wobble_sigma"], wobble_failed)
    wobble_ratio, wobble_scatter = _wobble_fit(frames)
    return AnalyticModel(
        knots_px=tuple(knots),
        reading_ratio=tuple(ratio),
        noise_rel=tuple(noise),
        specimen_rel=tuple(specimen),
        directional_ratio=tuple(dir_ratio),
        directional_noise_rel=tuple(dir_noise),
        directional_specimen_rel=tuple(dir_specimen),
        orientation_power=power,
        no_edges_px=middle,
        no_edges_spread_px=spread,
        directional_no_edges_px=dir_middle,
        directional_no_edges_spread_px=dir_spread,
        wobble_failure_sigma_px=wobble_middle,
        wobble_failure_spread_px=wobble_spread,
        wobble_ratio=round(wobble_ratio, 3),
        wobble_scatter_px_per_px=round(wobble_scatter, 4),
    )


def _yaml_block(model: AnalyticModel) -> str:
    lines = ["analytic_calibration:"]
    for name, value in model.model_dump().items():
        text = (
            "[" + ", ".join(f"{v:g}" for v in value) + "]"
            if isinstance(value, tuple)
            else f"{value:g}"
        )
        lines.append(f"  {name}: {text}")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", default="synthetic", help="apparatus spec of a synthetic SEM")
    parser.add_argument("--states", type=int, default=1000, help="random states to compare")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--calibrate", action="store_true", help="fit the analytic calibration and print it"
    )
    parser.add_argument("--calibration-frames", type=int, default=3000)
    args = parser.parse_args(argv)
    cv2.setNumThreads(1)
    config = make_apparatus(args.preset).config  # type: ignore[attr-defined]
    if args.calibrate:
        frames = _calibration_frames(config, args.calibration_frames, args.seed)
        print(_yaml_block(fit_calibration(frames)))
        return 0
    start = time.perf_counter()
    figures = agreement(compare(config, misaligned_states(config, args.states, args.seed)))
    elapsed = time.perf_counter() - start
    figures["image_calls_per_s"] = speed(config, analytic=False)
    figures["analytic_calls_per_s"] = speed(config, analytic=True, calls=5000)
    print(f"analytic vs image path, preset {args.preset}, {args.states} states ({elapsed:.0f} s)")
    print(f"{'figure':<40} {'value':>12}")
    for name, value in figures.items():
        print(f"{name:<40} {value:>12.4g}")
    passed = (
        abs(figures["width_median_rel"]) <= CRITERION_REL
        and figures["expected_median_abs_rel"] <= CRITERION_REL
    )
    print(
        f"criterion: median relative width difference within +/- {CRITERION_REL:.0%}, and "
        f"median |model value - image| within {CRITERION_REL:.0%}: "
        f"{'PASS' if passed else 'FAIL'}"
    )
    return 0 if passed else 1


if __name__ == "__main__":
    sys.exit(main())
