"""The quality measures of the multi-knob tasks, on any apparatus.

An apparatus that can compute them itself (the synthetic SEM, which also has an analytic mode
without images) offers `measure_directional()` and `measure_wobble(amplitude_v)` (the
capabilities MeasuresDirectional and MeasuresWobble of alignrl/apparatus/base.py); these
functions call them where present. Any other apparatus, a user's microscope driver included,
gets them through the Apparatus protocol alone, the way an operator does it: acquire, take the
last image, measure it (alignrl/apparatus/directional.py, alignrl/apparatus/wobble.py). A
wobble is two acquisitions at defocus +d and -d, through `write`, so that a safety shield
wrapped around the driver sees and clamps both, and the defocus is written back afterwards.

Failures are the apparatus's own exceptions: `NoEdgesError` where an image has nothing to
measure, `MeasurementError` where the apparatus gives no images or the wobble pair does not
correlate, `ApparatusError` for a driver fault.
"""

from __future__ import annotations

import numpy as np

from alignrl.apparatus.base import (
    Apparatus,
    MeasurementError,
    offers_directional,
    offers_wobble,
)

__all__ = ["WOBBLE_KNOB", "measure_directional", "measure_wobble", "wobble_by_frames"]

WOBBLE_KNOB = "defocus"  # the lens a wobble swings


def measure_directional(apparatus: Apparatus) -> tuple[float, np.ndarray]:
    """(mean edge width px, edge widths of the four normal-orientation bins px), one image."""
    if offers_directional(apparatus):
        width, widths = apparatus.measure_directional()
        return float(width), np.asarray(widths, dtype=np.float64)
    from alignrl.apparatus.directional import directional_widths

    apparatus.measure()
    measured = directional_widths(_last_image(apparatus, "directional edge widths"))
    return float(measured.width_px), np.asarray(measured.widths_px, dtype=np.float64)


def measure_wobble(apparatus: Apparatus, amplitude_v: float) -> np.ndarray:
    """Shift (dx, dy) px of the frame at defocus + amplitude against the one at - amplitude:
    the apparatus's own wobble where it has one, else `wobble_by_frames`. Two acquisitions."""
    if offers_wobble(apparatus):
        return np.asarray(apparatus.measure_wobble(float(amplitude_v)), dtype=np.float64).reshape(2)
    return wobble_by_frames(apparatus, amplitude_v)


def wobble_by_frames(apparatus: Apparatus, amplitude_v: float) -> np.ndarray:
    """A wobble through the protocol: write defocus + amplitude, acquire, write - amplitude,
    acquire, phase-correlate the two frames. The swing is clipped into the defocus interval;
    the defocus is written back to where it was, also when an acquisition fails."""
    from alignrl.apparatus.wobble import wobble_shift

    if WOBBLE_KNOB not in apparatus.knobs:
        raise MeasurementError(f"a wobble swings {WOBBLE_KNOB!r}, which this apparatus lacks")
    low, high = apparatus.knobs[WOBBLE_KNOB]
    centre = float(apparatus.read()[WOBBLE_KNOB])
    frames = []
    try:
        for sign in (1.0, -1.0):
            apparatus.write({WOBBLE_KNOB: float(np.clip(centre + sign * amplitude_v, low, high))})
            _acquire(apparatus)
            frames.append(_last_image(apparatus, "a wobble"))
    finally:
        apparatus.write({WOBBLE_KNOB: centre})
    plus, minus = frames
    return np.asarray(wobble_shift(minus, plus), dtype=np.float64)


def _acquire(apparatus: Apparatus) -> None:
    """Acquire one frame; a frame without edges still serves a wobble (phase correlation
    needs structure, not edges)."""
    from alignrl.apparatus.base import NoEdgesError

    try:
        apparatus.measure()
    except NoEdgesError:
        pass


def _last_image(apparatus: Apparatus, purpose: str) -> np.ndarray:
    image = apparatus.image()
    if image is None:
        raise MeasurementError(
            f"{purpose} needs the acquired image, and this apparatus returns none from image()"
        )
    return np.asarray(image)
