"""Measured figures of alignrl, written to docs/benchmarks.md by `make bench`.

Each benchmark runs on one core (OpenCV threads off) and reports a median over repeats, next
to the target its issue set. Nothing here is a test: a slow machine gives slow numbers.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

import alignrl
from alignrl.apparatus import NoEdgesError, ScenarioSimulator, edge_width, make_apparatus
from alignrl.apparatus.quality import TEN_NINETY_PER_SIGMA
from alignrl.apparatus.recorder import sweep_many, sweep_plan
from alignrl.envs.task import get_task
from alignrl.envs.vector import VectorAlignmentEnv, make_apparatus_copies
from benchmarks.baselines import bench_baselines


@dataclass(frozen=True)
class Figure:
    name: str
    value: str
    target: str
    note: str = ""


def _median_seconds(action: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        action()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def bench_render(repeats: int) -> Figure:
    sem = make_apparatus("synthetic", seed=0)
    sem.acquire()  # warm caches
    seconds = _median_seconds(sem.acquire, repeats)
    return Figure(
        "synthetic SEM: render one 256x256 frame (blur, shift, shot + detector noise)",
        f"{seconds * 1e3:.2f} ms",
        "a few ms on one core",
    )


def bench_edge_width(repeats: int) -> list[Figure]:
    sem = make_apparatus("synthetic", {"drift_v_per_acquisition": 0.0}, seed=0)
    optimum = sem.optimum()["defocus"]
    figures = []
    for label, error_v in (("in focus", 0.0), ("10 V off", 10.0), ("30 V off", 30.0)):
        sem.write({"defocus": float(np.clip(optimum + error_v, 0, 100))})
        frame = sem.acquire()
        seconds = _median_seconds(lambda frame=frame: edge_width(frame), repeats)
        figures.append(
            Figure(
                f"edge_width on a 256x256 synthetic frame, {label}", f"{seconds * 1e3:.2f} ms", ""
            )
        )
    return figures


def bench_query(million: int) -> Figure:
    simulator = ScenarioSimulator()
    rng = np.random.default_rng(0)
    n = million * 1_000_000
    rows = rng.integers(0, len(simulator.scenarios), n)
    low, high = simulator.knobs[simulator.knob]
    volts = rng.uniform(low, high, n)
    simulator.query(rows[:1000], volts[:1000])
    seconds = _median_seconds(lambda: simulator.query(rows, volts), 5)
    return Figure(
        f"scenario simulator: batched query of {n:,} (scenario, voltage) pairs",
        f"{n / seconds / 1e6:.2f} M queries/s",
        ">= 1 M queries/s on one core",
    )


def bench_vector_env(num_envs: int, steps: int) -> Figure:
    """Env steps per second of the vectorized env on the scenario simulator, random actions."""
    env = VectorAlignmentEnv(make_apparatus_copies("csv:default", {"noise": 0.02}, num_envs))
    env.reset(seed=0)
    actions = np.random.default_rng(0).uniform(-1.0, 1.0, (steps, num_envs, 2))
    start = time.perf_counter()
    for action in actions:
        env.step(action)
    seconds = time.perf_counter() - start
    return Figure(
        f"VectorAlignmentEnv, {num_envs} x `csv:default` (2 % noise), random actions",
        f"{steps * num_envs / seconds / 1e3:.0f} k env steps/s",
        ">= 50 k env steps/s on one core",
        "episodes end and reset inside the loop, as in training",
    )


def bench_task_envs(num_envs: int, steps: int) -> list[Figure]:
    """Env steps per second of each task on the analytic synthetic column (the pre-training
    simulator of the multi-knob tasks), random actions that never stop early."""
    figures = []
    for task in ("focus", "stigmation", "aperture", "column"):
        units = make_apparatus_copies("synthetic", {"analytic": True}, num_envs)
        env = VectorAlignmentEnv(units, get_task(task))
        env.reset(seed=0)
        actions = np.random.default_rng(0).uniform(-1.0, 1.0, (steps, num_envs, env.episodes.k + 1))
        actions[..., -1] = -1.0
        start = time.perf_counter()
        for action in actions:
            env.step(action)
        seconds = time.perf_counter() - start
        figures.append(
            Figure(
                f"VectorAlignmentEnv, {num_envs} x analytic `synthetic`, task `{task}`",
                f"{steps * num_envs / seconds / 1e3:.1f} k env steps/s",
                ">= 0.2 k env steps/s (SAC trains at ~0.05-0.1 k env steps/s)",
                f"{env.episodes.task.acquisitions_per_step} acquisition(s) per step",
            )
        )
    return figures


def bench_record(scenarios: int, workers: int) -> Figure:
    factory = _SyntheticFactory()
    plan = sweep_plan(factory().knobs)
    start = time.perf_counter()
    rows = list(sweep_many(factory, plan, range(scenarios), 0, workers))
    seconds = time.perf_counter() - start
    per_scenario = seconds / scenarios
    pairs = statistics.median(len(r.voltages) for _, r in rows if r is not None)
    return Figure(
        f"recorder: {scenarios} adaptive sweeps of `synthetic`, {workers} worker(s)",
        f"{per_scenario:.3f} s per scenario",
        "",
        f"median {pairs:.0f} stored points + 9 pre-scan acquisitions per sweep; "
        f"2000 scenarios at this rate: {2000 * per_scenario / 60:.1f} min",
    )


def bench_fidelity(preset: str, frames: int) -> list[str]:
    """How the edge-width reading follows the true probe width across the focus range.

    Random voltages over the whole interval, a new specimen area every 10 frames. The true
    10-90 % width of the probe is 2.563 sigma; the reading saturates once the blur exceeds
    the particles, and must never pass a blurred frame off as a sharp one.
    """
    sem = make_apparatus(preset, seed=0)
    rng = np.random.default_rng(0)
    low, high = sem.knobs["defocus"]
    in_focus = TEN_NINETY_PER_SIGMA * sem.config.probe_sigma0_px
    pairs, no_edges, sharp_lies = [], 0, 0
    for index in range(frames):
        if index % 10 == 0:
            sem.reset(int(rng.integers(2**31)))
        sem.write({"defocus": float(rng.uniform(low, high))})
        true_width = TEN_NINETY_PER_SIGMA * sem.probe_sigmas_px()[0]
        try:
            reading = sem.measure()
        except NoEdgesError:
            no_edges += 1
            continue
        pairs.append((true_width, reading))
        if true_width > 4 * in_focus and reading < 2 * in_focus:
            sharp_lies += 1
    table = np.array(pairs)
    lines = [
        f"### Edge-width fidelity on `{preset}` ({frames} frames)",
        "",
        f"{no_edges} frames had no measurable edge (NoEdgesError); {sharp_lies} frames blurred "
        f"beyond 4x the in-focus width ({in_focus:.2f} px) read below 2x it.",
        "",
        "| true 10-90 % width (px) | frames | reading / true, median | min | max |",
        "| --- | --- | --- | --- | --- |",
    ]
    for lower, upper in ((0, 4), (4, 8), (8, 15), (15, 25), (25, 200)):
        chosen = (table[:, 0] >= lower) & (table[:, 0] < upper)
        if chosen.any():
            ratio = table[chosen, 1] / table[chosen, 0]
            lines.append(
                f"| {lower}-{upper} | {int(chosen.sum())} | {np.median(ratio):.2f} | "
                f"{ratio.min():.2f} | {ratio.max():.2f} |"
            )
    return [*lines, ""]


class _SyntheticFactory:
    """Picklable factory for worker processes."""

    def __call__(self):
        return make_apparatus("synthetic")


def machine() -> list[str]:
    cpu = platform.processor() or "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return [
        f"- CPU: {cpu}, {os.cpu_count()} logical cores visible",
        f"- Python {platform.python_version()}, numpy {np.__version__}, "
        f"OpenCV {cv2.__version__}, alignrl {alignrl.__version__}",
        f"- OS: {platform.platform()}",
    ]


MEASURED_BY_HAND = "## Measured by hand"
DOCS = Path(__file__).resolve().parent.parent / "docs" / "benchmarks.md"


def measured_by_hand(out: Path) -> str:
    """The part of the benchmarks page that `make bench` does not measure (runs of minutes to
    hours, each with its command): kept as `out` has it, or else as docs/benchmarks.md has it,
    so that the page has one copy of it and a new run of the figures above never drops it."""
    for page in (out, DOCS):
        if page.exists():
            text = page.read_text()
            if MEASURED_BY_HAND in text:
                return text[text.index(MEASURED_BY_HAND) :].rstrip()
    raise SystemExit(f"neither {out} nor {DOCS} has a '{MEASURED_BY_HAND}' part to keep")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default="docs/benchmarks.md")
    parser.add_argument("--quick", action="store_true", help="fewer repeats (smoke run)")
    args = parser.parse_args(argv)
    cv2.setNumThreads(1)
    repeats = 20 if args.quick else 200
    figures = [bench_render(repeats), *bench_edge_width(repeats // 2)]
    figures.append(bench_query(1 if args.quick else 2))
    figures.append(bench_vector_env(64, 300 if args.quick else 3000))
    figures += bench_task_envs(8, 100 if args.quick else 1000)
    figures.append(bench_record(4 if args.quick else 20, 1))
    figures.append(bench_record(4 if args.quick else 20, 2))

    lines = [
        "# Benchmarks",
        "",
        "Written by `make bench` (`python -m benchmarks.run --out docs/benchmarks.md`); "
        "every figure below was measured by that command on this machine:",
        "",
        *machine(),
        f"- Date: {datetime.date.today().isoformat()}",
        "",
        "| what | measured | target |",
        "| --- | --- | --- |",
    ]
    for figure in figures:
        note = f" ({figure.note})" if figure.note else ""
        lines.append(f"| {figure.name}{note} | {figure.value} | {figure.target} |")
    lines.append("")
    for preset in ("synthetic", "synthetic-b"):
        lines += bench_fidelity(preset, 200 if args.quick else 1500)
    lines += bench_baselines(20 if args.quick else 100)
    out = Path(args.out)
    lines += ["", measured_by_hand(out), ""]
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile("w", dir=out.parent, delete=False, suffix=".tmp") as handle:
        handle.write("\n".join(lines))
    os.replace(handle.name, out)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
