"""Does the Ray backend scale with microscopes? Matches per second of `RayBackend.play` with 1
worker and with 2, the same members, each worker driving its own apparatus.

    python -m benchmarks.ray_scaling [--matches 256] [--repeats 3] [--out FILE]

Measured on `synthetic`, the image-based SEM: like a real microscope it spends its time
acquiring images (rendering and measuring each frame), so matches are where the time goes;
and on `csv:default`, the recordings replayed (microseconds per image), where what remains
is the backend's own overhead. The members are two of the default rosters, untrained, acting
with their stochastic policies; learning, which happens in the driver after each batch, is
not timed. Ray is started on this machine with one CPU per worker; the figures are only
meaningful on an otherwise quiet machine with at least 2 free cores (the load average at
the start is printed with them).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import ray

from alignrl.agents.agent import Agent
from alignrl.league.config import LeagueConfig, RayConfig, load_league
from alignrl.league.ray_backend import RayBackend
from alignrl.league.warm_starts import member_spec

LEAGUE = Path(__file__).resolve().parents[1] / "experiments" / "league-default.yaml"
APPARATUS = {  # spec -> arguments
    "synthetic": {},
    "csv:default": {"noise": 0.02, "split": "train"},
}
ENVS_PER_WORKER = 8
MEMBERS = ("mlp-sac", "mlp-sac-mis")  # aligner, misaligner of the default rosters


def _league(apparatus: str, workers: int) -> tuple[LeagueConfig, Agent, Agent]:
    """The default league on `workers` Ray workers of `apparatus`, and the two members."""
    config, aligners, misaligners = load_league(LEAGUE)
    worker = {"apparatus": apparatus, "apparatus_args": APPARATUS[apparatus]}
    config = config.model_copy(
        update={
            "backend": "ray",
            "envs": ENVS_PER_WORKER,
            "ray": RayConfig(workers=[worker] * workers, num_cpus_per_worker=1),
        }
    )
    aligner = next(m for m in aligners.members if m.id == MEMBERS[0])
    misaligner = next(m for m in misaligners.members if m.id == MEMBERS[1])
    return (
        config,
        Agent(member_spec(aligner, "aligner", config), config.envs),
        Agent(member_spec(misaligner, "misaligner", config), config.envs),
    )


def matches_per_second(
    apparatus: str, workers: int, matches: int, repeats: int
) -> tuple[float, float]:
    """(matches per second, seconds) of `repeats` plays of `matches` matches, after one
    play that starts the workers."""
    config, aligner, misaligner = _league(apparatus, workers)
    backend = RayBackend(config)
    rng = np.random.default_rng(0)
    try:
        backend.play(aligner, misaligner, max(matches // 4, 1), rng, set())  # start the workers
        started = time.perf_counter()
        for _ in range(repeats):
            backend.play(aligner, misaligner, matches, rng, set())
        seconds = time.perf_counter() - started
    finally:
        backend.close()
    return matches * repeats / seconds, seconds


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--matches", type=int, default=256, help="matches per play")
    parser.add_argument("--repeats", type=int, default=3, help="plays timed per setting")
    parser.add_argument("--out", help="also write the Markdown table here")
    args = parser.parse_args(argv)

    load = os.getloadavg()[0]
    ray.init(
        address="local",
        num_cpus=max(2, os.cpu_count() or 1),
        include_dashboard=False,
        log_to_driver=False,
    )
    measured: list[tuple[str, int, float, float]] = []  # apparatus, workers, seconds, rate
    try:
        for apparatus in APPARATUS:
            for workers in (1, 2):
                rate, seconds = matches_per_second(apparatus, workers, args.matches, args.repeats)
                measured.append((apparatus, workers, seconds, rate))
    finally:
        ray.shutdown()
    arguments = argv if argv is not None else sys.argv[1:]
    command = " ".join(["python -m benchmarks.ray_scaling", *arguments])
    lines = [
        f"Ray backend scaling: `{command}` on {platform.processor() or platform.machine()} "
        f"with {os.cpu_count()} cores, "
        f"{time.strftime('%Y-%m-%d')}, Ray {ray.__version__}, load average {load:.2f} at "
        "the start.",
        f"Members {MEMBERS[0]} vs {MEMBERS[1]} (default rosters, untrained, stochastic actions; "
        "learning in the driver not timed). `synthetic` is the image-based SEM: like a real "
        "microscope it spends its time acquiring images. `csv:default` replays recordings "
        "and shows the backend's own overhead.",
        "",
        "| apparatus | workers | envs per worker | matches | seconds | matches/s | vs 1 worker |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    alone = {apparatus: rate for apparatus, workers, _, rate in measured if workers == 1}
    for apparatus, workers, seconds, rate in measured:
        ratio = f"{rate / alone[apparatus]:.2f}"
        lines.append(
            f"| {apparatus} | {workers} | {ENVS_PER_WORKER} | {args.matches * args.repeats} | "
            f"{seconds:.1f} | {rate:.1f} | {ratio if workers == 1 else f'**{ratio}**'} |"
        )
    report = "\n".join(lines) + "\n"
    print(report, end="")
    if args.out:
        Path(args.out).write_text(report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
