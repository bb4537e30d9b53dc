"""Matches per second of a league: the first iterations of an experiment, timed.

    python -m benchmarks.league_throughput [experiments/league-default.yaml] \
        [--iterations 40] [--repeats 3]

Each repeat builds the league afresh in a temporary folder (same seed: the same matches,
the same updates) and times `League.step` over `--iterations` iterations: pairing, the
matches (misaligner's starts, aligner's steps, every member's `observe` and `learn`),
ratings and logs; no evaluation sessions or checkpoints fall inside the window unless the
schedule puts them there. Prints the median matches/s over the repeats and each repeat's.
Not a test: a loaded machine gives low numbers; compare two versions on one machine, one
after the other.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")


def matches_per_second(config_path: str, iterations: int) -> float:
    from alignrl.league.config import load_league
    from alignrl.league.loop import League

    config, aligners, misaligners = load_league(config_path)
    schedule = config.schedule.model_copy(update={"iterations": iterations})
    config = config.model_copy(update={"schedule": schedule})
    with tempfile.TemporaryDirectory() as folder:
        league = League.create(config, aligners, misaligners, Path(folder))
        try:
            matches, started = 0, time.perf_counter()
            for _ in range(iterations):
                matches += int(league.step()["matches"])
            return matches / (time.perf_counter() - started)
        finally:
            league.close()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", nargs="?", default="experiments/league-default.yaml")
    parser.add_argument("--iterations", type=int, default=40)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    rates = [matches_per_second(args.config, args.iterations) for _ in range(args.repeats)]
    shown = ", ".join(f"{rate:.1f}" for rate in rates)
    print(
        f"{args.config}: {statistics.median(rates):.1f} matches/s (median of {args.repeats}; "
        f"each: {shown}) over the first {args.iterations} iterations"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
