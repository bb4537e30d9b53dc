"""An example Apparatus driver, written the way you would write one for your own microscope.

`MyMicroscope` drives a fictional SEM through its vendor's Python client. The vendor client
here is a stand-in, `_VendorClient`, that renders frames with alignrl's synthetic SEM (preset
`synthetic`), so this file runs offline; on a real instrument you replace `_VendorClient`
with the vendor's SDK and keep the rest. docs/apparatus.md walks through it step by step.

The vendor speaks its own units: lens voltages in whole millivolts, stage positions in
micrometres, frames as 16-bit detector counts. alignrl speaks volts and edge widths in pixels.
The driver converts between the two, refuses unsafe writes and turns vendor errors into
alignrl's exceptions.

Use it with docs/examples on the Python path:

    make_apparatus("my_microscope:MyMicroscope", {"timeout_s": 2.0})
    PYTHONPATH=docs/examples alignrl record --apparatus my_microscope:MyMicroscope ...
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import TypeVar

import numpy as np

from alignrl.apparatus import ApparatusError, check_write, edge_width
from alignrl.apparatus.synthetic import PRESET_DIR, SyntheticSEM, load_sem_config

# --- the vendor's side (replace with the real SDK) ---------------------------------------

# The stand-in's two "microscopes": the host names it answers to, and the synthetic SEM preset
# behind each (`simulated-b` is a visibly different column: the target of `alignrl adapt`).
_SIMULATED_COLUMNS = {"simulated": "synthetic", "simulated-b": "synthetic-b"}
_DWELL_US = 10.0  # pixel dwell time, microseconds: a 256x256 frame takes 0.66 s
_COUNTS_PER_YIELD = 4000.0  # detector gain: counts per unit of secondary-electron yield
_DARK_COUNTS = 1000.0  # detector offset, counts


class _VendorTimeout(TimeoutError):
    """What the vendor SDK raises when the instrument does not answer in time."""


class _VendorClient:
    """A fake of the vendor's client library: same calls, same units, no hardware.

    Behind it sits alignrl's synthetic SEM, so frames look like a real column's: sharp gold
    particles when in focus, blurred ones when not, with shot noise.
    """

    def __init__(self, host: str, seed: int | None = None) -> None:
        if host not in _SIMULATED_COLUMNS:
            raise ConnectionError(f"no microscope answers at {host!r}")
        config = load_sem_config(PRESET_DIR / f"{_SIMULATED_COLUMNS[host]}.yaml")
        self._column = SyntheticSEM(config, seed=seed)
        self._frame_pixels = config.image_size_px**2
        low_v, high_v = config.defocus_interval_v
        self._limits_mv = (round(low_v * 1000), round(high_v * 1000))

    def lens_limits(self, lens: str) -> tuple[int, int]:
        return self._limits_mv

    def get_lens(self, lens: str) -> int:
        return round(self._column.read()["defocus"] * 1000.0)

    def set_lens(self, lens: str, millivolts: int) -> None:
        self._column.write({"defocus": millivolts / 1000.0})

    def move_stage(self, x_um: float, y_um: float) -> None:
        # A new stage position shows a new specimen area: the synthetic SEM draws a new one.
        area_seed = (round(x_um * 1000) * 1_000_003 + round(y_um * 1000)) % 2**32
        lens_v = self._column.read()["defocus"]
        self._column.reset(area_seed)
        self._column.write({"defocus": lens_v})  # moving the stage leaves the lens alone

    def grab_frame(self, timeout_s: float) -> np.ndarray:
        frame_time_s = self._frame_pixels * _DWELL_US * 1e-6
        if frame_time_s > timeout_s:
            raise _VendorTimeout(f"frame not ready after {timeout_s} s")
        frame = self._column.acquire() * _COUNTS_PER_YIELD + _DARK_COUNTS
        return np.clip(np.round(frame), 0, 65535).astype(np.uint16)


# --- the driver: what alignrl loads --------------------------------------------------------

LENS = "OBJ_FOCUS"  # the vendor's name for the lens behind the `defocus` knob
MILLIVOLTS_PER_VOLT = 1000.0
STAGE_FIELD_UM = 2000.0  # specimen areas are picked inside a 2 mm square around the centre

Result = TypeVar("Result")


class MyMicroscope:
    """The objective focus of my microscope as an alignrl Apparatus: one knob, `defocus` (V).

    Parameters
    ----------
    host: where the microscope PC answers; "simulated" uses the built-in stand-in, and
        "simulated-b" a second, different one.
    timeout_s: how long to wait for a frame before giving up, seconds.
    seed: picks the specimen areas that `reset(None)` visits, for reproducible sessions.
    """

    def __init__(
        self, host: str = "simulated", timeout_s: float = 5.0, seed: int | None = None
    ) -> None:
        if timeout_s <= 0:
            raise ValueError(f"timeout_s must be positive, got {timeout_s}")
        self.timeout_s = float(timeout_s)
        try:
            self._client = _VendorClient(host, seed=seed)
            low_mv, high_mv = self._client.lens_limits(LENS)
        except (ConnectionError, TimeoutError) as error:
            raise ApparatusError(f"cannot connect to the microscope at {host!r}: {error}") from None
        # alignrl works in volts: the knob's interval is the vendor's limits, converted.
        self.knobs: Mapping[str, tuple[float, float]] = {
            "defocus": (low_mv / MILLIVOLTS_PER_VOLT, high_mv / MILLIVOLTS_PER_VOLT)
        }
        self._areas = np.random.default_rng(seed)
        self._last_image: np.ndarray | None = None

    def reset(self, seed: int | None = None) -> None:
        """Move the stage to a fresh specimen area; the same seed gives the same area.

        The lenses are left as they are: misaligning them is the agents' business.
        """
        rng = np.random.default_rng(seed) if seed is not None else self._areas
        x_um, y_um = rng.uniform(-STAGE_FIELD_UM / 2, STAGE_FIELD_UM / 2, size=2)
        self._call(self._client.move_stage, float(x_um), float(y_um))
        self._last_image = None

    def read(self) -> dict[str, float]:
        """The lens voltage as the instrument reports it (whole millivolts), in volts."""
        millivolts = self._call(self._client.get_lens, LENS)
        return {"defocus": millivolts / MILLIVOLTS_PER_VOLT}

    def write(self, values: Mapping[str, float]) -> None:
        """Set the lens. Refuses an unknown knob or a value outside `knobs` before sending
        anything to the instrument (ValueError), so a refused write changes nothing."""
        check_write(self.knobs, values)
        if "defocus" in values:
            millivolts = round(float(values["defocus"]) * MILLIVOLTS_PER_VOLT)
            self._call(self._client.set_lens, LENS, millivolts)

    def measure(self) -> float:
        """Acquire a frame and return its average edge width in pixels.

        Raises NoEdgesError (from edge_width) when the frame shows no edges, and
        ApparatusError when the instrument does not deliver a frame.
        """
        counts = self._call(self._client.grab_frame, self.timeout_s)
        self._last_image = counts.astype(np.float32)
        return edge_width(self._last_image)

    def image(self) -> np.ndarray | None:
        """The last acquired frame in detector counts (float32), or None before the first."""
        return self._last_image

    def _call(self, function: Callable[..., Result], *args: object) -> Result:
        """Call the vendor SDK; its timeouts and connection losses become ApparatusError,
        which alignrl retries or reports instead of crashing."""
        try:
            return function(*args)
        except TimeoutError as error:
            raise ApparatusError(f"microscope timed out: {error}") from None
        except ConnectionError as error:
            raise ApparatusError(f"lost the connection to the microscope: {error}") from None


if __name__ == "__main__":
    # A quick look without alignrl's command line: a focus series around the lens centre.
    microscope = MyMicroscope(seed=0)
    microscope.reset(1)
    for volts in (20.0, 35.0, 50.0, 65.0, 80.0):
        microscope.write({"defocus": volts})
        print(f"defocus {volts:5.1f} V -> edge width {microscope.measure():5.2f} px")
