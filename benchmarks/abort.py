"""How long an `alignrl` command takes to end after Ctrl-C or SIGTERM while a driver call hangs
(issue 60: within a second, nothing more sent to the driver).

    python -m benchmarks.abort [--repeats 5] [--signal TERM|INT] [--verbs align evaluate baselines]

Each run is a fresh process of the command on `HungLens` (below), a lens whose third
acquisition never returns; once it hangs, the signal is sent, and the seconds from the signal
to the process's exit are timed. `align` runs champion:focus-v1 with --restore-on-abort: the
restore must not be sent to a driver whose call has not returned. Prints a row per run (exit
code, seconds, what the driver received after it hung) and each verb's median and largest
time. Not a test: the time includes the interpreter's exit, which differs between machines.
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Mapping
from pathlib import Path

from alignrl.apparatus import check_write

SIGNALS = {"TERM": signal.SIGTERM, "INT": signal.SIGINT}
EXPECTED_EXIT = {"align": 3, "evaluate": 130, "baselines": 130}  # aborted / interrupted
HANG_AFTER = 2  # acquisitions that return before one hangs


class HungLens:
    """A noiseless lens (the Gaussian-probe focus curve, best width 2.563 px at 42 V) whose
    acquisition number HANG_AFTER + 1 never returns. It creates the file `marker` as it hangs
    and appends every write it receives afterwards to `marker` + ".after", one JSON line each."""

    def __init__(self, marker: str) -> None:
        self.knobs: Mapping[str, tuple[float, float]] = {"defocus": (0.0, 100.0)}
        self.marker = Path(marker)
        self.voltage, self.acquisitions = 50.0, 0

    def reset(self, seed: int | None = None) -> None:
        self.voltage = 50.0

    def read(self) -> dict[str, float]:
        return {"defocus": self.voltage}

    def write(self, values: Mapping[str, float]) -> None:
        check_write(self.knobs, values)
        if self.marker.exists():
            with open(f"{self.marker}.after", "a") as after:
                after.write(json.dumps(dict(values)) + "\n")
        self.voltage = float(values["defocus"])

    def measure(self) -> float:
        self.acquisitions += 1
        if self.acquisitions > HANG_AFTER:
            self.marker.touch()
            threading.Event().wait()  # the driver waits for a microscope that never answers
        return 2.563 * math.hypot(1.0, 0.2 * (self.voltage - 42.0))

    def image(self) -> None:
        return None


def _command(verb: str, marker: Path) -> list[str]:
    driver = ["--apparatus", "benchmarks.abort:HungLens"]
    driver += ["--apparatus-args", json.dumps({"marker": str(marker)}), "--spec-px", "3"]
    if verb == "align":
        return ["align", "--policy", "champion:focus-v1", *driver, "--restore-on-abort"]
    if verb == "evaluate":
        return ["evaluate", "--policy", "hyperbola", *driver, "--scenarios", "2", "--quiet"]
    return ["baselines", *driver, "--scenarios", "2", "--quiet"]


def run_once(verb: str, sent: signal.Signals) -> tuple[int, float, int]:
    """(exit code, seconds from the signal to the exit, writes the driver received after it
    hung) of one run of `verb`."""
    with tempfile.TemporaryDirectory() as folder:
        marker = Path(folder) / "hung"
        process = subprocess.Popen(
            [sys.executable, "-m", "alignrl", *_command(verb, marker)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        while not marker.exists():
            if process.poll() is not None:
                raise SystemExit(f"alignrl {verb} ended before the driver hung:\n{process.stderr}")
            time.sleep(0.01)
        signalled = time.perf_counter()
        process.send_signal(sent)
        code = process.wait(timeout=120)
        seconds = time.perf_counter() - signalled
        after = Path(f"{marker}.after")
        received = len(after.read_text().splitlines()) if after.exists() else 0
    return code, seconds, received


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--signal", choices=sorted(SIGNALS), default="TERM")
    parser.add_argument(
        "--verbs", nargs="+", choices=sorted(EXPECTED_EXIT), default=list(EXPECTED_EXIT)
    )
    args = parser.parse_args(argv)
    print(f"SIG{args.signal} while the driver's measure() hangs, {args.repeats} runs a verb")
    print("verb       exit  expected  seconds  writes after the hang")
    times: dict[str, list[float]] = {verb: [] for verb in args.verbs}
    for verb in args.verbs:
        for _ in range(args.repeats):
            code, seconds, received = run_once(verb, SIGNALS[args.signal])
            times[verb].append(seconds)
            row = f"{verb:10s} {code:4d}  {EXPECTED_EXIT[verb]:8d}  {seconds:7.2f}  {received}"
            print(row, flush=True)
    for verb, values in times.items():
        print(f"{verb}: median {statistics.median(values):.2f} s, largest {max(values):.2f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
