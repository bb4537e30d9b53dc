"""Whether an aligner's "sure" means what it says: after every reading, the chance its
ending posterior gives the setting it would end at (alignrl/envs/ending.py,
`finish_at_posterior`), against whether the verification there passes (issue 21).

    python -m benchmarks.reliability --policy champion:focus-v2 --apparatus family:focus \
        --episodes 100 --seed 100 --images --out runs/reliability

The champion stops once that chance reaches its `stop_when_sure` (0.98): if the chance is
calibrated, 98 % of the settings it is that sure of pass, and a lower stop would lose
columns in proportion; if it is too modest, the champion reads more images than it needs.
Each episode is driven step by step as benchmarks/trace.py drives one (seeds SEED,
SEED + 1, ...: the column's draw and a start uniform over the interval). After each reading
a twin of the column (the same column, drift and noise stream, alignrl/envs/design.py) is
written to the setting the posterior holds likeliest to pass, approached from below as the
ending approaches it, and verified as a session verifies; the episode itself goes on
untouched. The readings are binned by the chance stated; each bin shows how many passed.

Writes OUT/reliability.json (every reading: episode, readings so far, chance, whether it
passed, whether the episode stopped there) and OUT/reliability.png (stated against found).
The held-out instruments are refused, as benchmarks/trace.py refuses them: this looks into
how the aligner decides. Not a test: seconds per episode on images.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from alignrl.apparatus.base import Apparatus
from alignrl.apparatus.instruments import diagnosis_problem
from alignrl.envs.design import twin_of
from alignrl.envs.task import Task
from alignrl.evaluation.session import verify_task
from benchmarks.trace import SLOT, begin_episode, one_slot

# Stated chances are binned at these edges (the last bin holds the stops at 0.98)
EDGES = (0.0, 0.5, 0.8, 0.9, 0.95, 0.98, 1.0)
# Stops shown beside the policy's own: each episode ended at its first reading that sure
STOPS = (0.9, 0.95, 0.98)
FROM_BELOW = 0.05  # x the interval: where the twin's knob comes up from to the setting


@dataclass(frozen=True)
class Stated:
    """One reading of an episode: the chance stated after it, and what the verification
    found at that setting."""

    episode: int
    readings: int  # readings the aligner had taken
    chance: float  # the posterior's chance that its likeliest setting passes
    passed: bool  # whether the verification at that setting passed
    stopped: bool  # whether the episode ended on this reading


@dataclass(frozen=True)
class Bin:
    """The readings whose stated chance lies in [low, high)."""

    low: float
    high: float
    count: int
    stated: float  # their mean stated chance (NaN where empty)
    found: float  # the share of them that passed (NaN where empty)


def verified_at(column: Apparatus, fraction: float, task: Task, threshold_px: float) -> bool:
    """Whether a twin of `column` verifies within `threshold_px` at `fraction` of its
    interval, the knob coming up to it from below."""
    twin = twin_of(column)
    knob = task.knobs[0]
    low, high = twin.knobs[knob]
    target = low + fraction * (high - low)
    for setting in (max(low, target - FROM_BELOW * (high - low)), target):
        twin.write({knob: setting})
    width, _, _ = verify_task(twin, task)
    return width is not None and width <= threshold_px


def stated_chances(
    policy_spec: str, apparatus_spec: str, episodes: int, seed: int, images: bool = False
) -> list[Stated]:
    """Every reading of `episodes` episodes of the policy on `apparatus_spec` (its ending
    posterior must be on: `finish_at_posterior`)."""
    policy, task, column, engine = one_slot(policy_spec, apparatus_spec, images)
    if task.ending.at != "posterior":
        raise ValueError(f"{policy_spec} ends without a posterior: it states no chance")
    rows: list[Stated] = []
    for episode in range(episodes):
        begin_episode(engine, seed + episode)
        while engine.active[0]:
            taken = int(engine.acquisitions[0])
            engine.step(SLOT, np.asarray(policy.act(engine.observation(0)), float)[None])
            stopped = not engine.active[0]
            if int(engine.acquisitions[0]) == taken:  # a stop without a reading
                if stopped and rows and rows[-1].episode == episode:
                    rows[-1] = replace(rows[-1], stopped=True)
                continue
            if not engine.ends.readings[0]:
                continue  # nothing measured yet: the posterior states nothing
            fraction, chance = engine.ends.best(0)
            passed = verified_at(column, fraction, task, float(engine.threshold[0]))
            rows.append(Stated(episode, int(engine.acquisitions[0]), chance, passed, stopped))
    return rows


def binned(rows: list[Stated], edges: tuple[float, ...] = EDGES) -> list[Bin]:
    """The readings binned by stated chance (the last bin closed at 1)."""
    chance = np.array([row.chance for row in rows], float)
    passed = np.array([row.passed for row in rows], float)
    bins = []
    for index, (low, high) in enumerate(itertools.pairwise(edges)):
        last = index == len(edges) - 2
        inside = (chance >= low) & ((chance <= high) if last else (chance < high))
        count = int(inside.sum())
        stated = float(chance[inside].mean()) if count else float("nan")
        found = float(passed[inside].mean()) if count else float("nan")
        bins.append(Bin(low, high, count, stated, found))
    return bins


@dataclass(frozen=True)
class Stop:
    """Had every episode stopped at its first reading stating at least `level` (else where
    it stopped): the readings it would have taken and whether that setting passed. The walk
    up to that reading is the policy's own, so this is what that stop would have done."""

    level: float
    episodes: int
    median_readings: float
    passed: float  # share


def stopped_at(rows: list[Stated], level: float) -> Stop:
    """The episodes of `rows` stopped at `level` (Stop)."""
    ends = []
    for episode in sorted({row.episode for row in rows}):
        mine = [row for row in rows if row.episode == episode]
        ends.append(next((row for row in mine if row.chance >= level), mine[-1]))
    return Stop(
        level,
        len(ends),
        float(np.median([row.readings for row in ends])),
        float(np.mean([row.passed for row in ends])),
    )


def table(bins: list[Bin], rows: list[Stated], stops: list[Stop]) -> str:
    """The bins as a markdown table, the line of the policy's own stops, and `stops`."""
    lines = [
        "| chance stated | readings | mean stated | passed |",
        "| --- | --- | --- | --- |",
    ]
    for each in bins:
        shown = "-" if not each.count else f"{each.stated:.3f} | {each.found:.3f}"
        lines.append(f"| {each.low:.2f}-{each.high:.2f} | {each.count} | {shown} |")
    ends = [row for row in rows if row.stopped]
    if ends:
        lines.append("")
        lines.append(
            f"the last reading of each of {len(ends)} episodes: mean stated "
            f"{np.mean([row.chance for row in ends]):.3f}, passed "
            f"{np.mean([row.passed for row in ends]):.3f}; readings per episode, median "
            f"{np.median([row.readings for row in ends]):g}"
        )
        lines.append("")
        lines.append("| had it stopped once as sure as | readings, median | passed |")
        lines.append("| --- | --- | --- |")
        for stop in stops:
            lines.append(f"| {stop.level:.2f} | {stop.median_readings:g} | {stop.passed:.3f} |")
    return "\n".join(lines)


def plot(bins: list[Bin], path: Path, title: str) -> None:
    """Stated against found, one point per bin sized by its readings."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    filled = [each for each in bins if each.count]
    figure, axes = plt.subplots(figsize=(4.8, 4.4))
    axes.plot([0, 1], [0, 1], color="0.6", linestyle="--", label="calibrated")
    axes.scatter(
        [each.stated for each in filled],
        [each.found for each in filled],
        s=[20 + 3 * each.count for each in filled],
        label="readings binned by chance",
    )
    for each in filled:
        axes.annotate(
            str(each.count),
            (each.stated, each.found),
            fontsize=7,
            xytext=(4, -10),
            textcoords="offset points",
        )
    axes.set(
        xlabel="chance stated after a reading",
        ylabel="share that passed there",
        xlim=(0, 1.02),
        ylim=(0, 1.02),
        title=title,
    )
    axes.legend(loc="upper left", fontsize=8, markerscale=0.4)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--policy", default="champion:focus-v2")
    parser.add_argument(
        "--apparatus",
        default="family:focus",
        help="family:focus (the training box) or instrument:NAME (a validation instrument)",
    )
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=100)
    parser.add_argument("--images", action="store_true", help="rendered frames, not analytic")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    if args.apparatus.startswith("instrument:"):
        problem = diagnosis_problem(args.apparatus.split(":", 1)[1], "reliabilities")
        if problem is not None:
            print(problem, file=sys.stderr)
            return 2
    try:
        rows = stated_chances(args.policy, args.apparatus, args.episodes, args.seed, args.images)
    except ValueError as error:
        print(f"benchmarks.reliability: {error}", file=sys.stderr)
        return 2
    bins = binned(rows)
    stops = [stopped_at(rows, level) for level in STOPS]
    args.out.mkdir(parents=True, exist_ok=True)
    written = {
        "args": {key: str(value) for key, value in vars(args).items()},
        "bins": [asdict(each) for each in bins],
        "stops": [asdict(stop) for stop in stops],
        "readings": [asdict(row) for row in rows],
    }
    (args.out / "reliability.json").write_text(json.dumps(written, indent=1))
    reading = "images" if args.images else "analytic"
    plot(bins, args.out / "reliability.png", f"{args.policy} on {args.apparatus} ({reading})")
    print(
        f"{args.policy} on {args.apparatus}, {args.episodes} episodes from seed {args.seed} "
        f"({reading})\n"
    )
    print(table(bins, rows, stops))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
