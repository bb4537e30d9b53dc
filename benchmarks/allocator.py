"""One `alignrl` command timed with glibc's allocator as alignrl tunes it (alignrl/memory.py)
and as glibc leaves it (ALIGNRL_MALLOC=system), the two alternating, each run a fresh process.

    python -m benchmarks.allocator [--repeats 2] -- evaluate --policy champion:focus-v2 \
        --apparatus instrument:val-mid --scenarios 4 --seed 3 --json

Prints a row per run (wall seconds, user and system CPU seconds, peak resident MB, whether its
standard output is the first run's, durations aside) and the medians of each mode. Not a
test: compare on one machine, nothing else running; what the tuning saves is the time the
machine spends faulting pages in, which differs from machine to machine.
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time

from alignrl.memory import without_malloc_choices

MODES = {"tuned": {}, "system": {"ALIGNRL_MALLOC": "system"}}
_DURATION = re.compile(r'"seconds": [0-9.]+|\b[0-9.]+ s\b')  # what differs between two runs


def run_once(argv: list[str], mode: str) -> tuple[float, float, float, float, str]:
    """(wall s, user s, system s, peak resident MB, output without durations) of one run."""
    environment = {**without_malloc_choices(os.environ), **MODES[mode]}
    command = [sys.executable, "-m", "alignrl", *argv]
    with tempfile.TemporaryFile() as output, tempfile.TemporaryFile() as errors:
        started = time.perf_counter()
        process = subprocess.Popen(command, stdout=output, stderr=errors, env=environment)
        _, status, usage = os.wait4(process.pid, 0)  # its own CPU times, not the children's
        wall = time.perf_counter() - started
        output.seek(0)
        errors.seek(0)
        text, said = output.read().decode(errors="replace"), errors.read().decode(errors="replace")
    code = os.waitstatus_to_exitcode(status)
    if code:
        raise SystemExit(f"`alignrl {' '.join(argv)}` exited {code}:\n{said}")
    return wall, usage.ru_utime, usage.ru_stime, usage.ru_maxrss / 1024, _DURATION.sub("#", text)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("command", nargs=argparse.REMAINDER, help="after --: alignrl's arguments")
    args = parser.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        parser.error("give the alignrl command after --")
    rows: dict[str, list[tuple[float, ...]]] = {mode: [] for mode in MODES}
    first = None
    print(f"alignrl {' '.join(command)}")
    print("mode     wall s   user s    sys s   peak MB  same output")
    for _ in range(args.repeats):
        for mode in MODES:
            wall, user, system, peak, text = run_once(command, mode)
            first = text if first is None else first
            rows[mode].append((wall, user, system, peak))
            same = "yes" if text == first else "NO"
            print(
                f"{mode:7s} {wall:7.1f} {user:8.1f} {system:8.1f} {peak:9.0f}  {same}", flush=True
            )
    for mode, values in rows.items():
        medians = [statistics.median(column) for column in zip(*values, strict=True)]
        print(f"median {mode}: wall {medians[0]:.1f} s, user {medians[1]:.1f} s, "
              f"system {medians[2]:.1f} s, peak {medians[3]:.0f} MB")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
