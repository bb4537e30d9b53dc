"""How a trained focus aligner's alignments end, compared on one instrument set: as it was
trained, at its narrowest reading (straight back, or taking up backlash), and at a fit of its
readings (`finish_at_fit`) for several fit windows, and where the posterior over the training
box puts the best setting (`finish_at_posterior`). docs/benchmarks.md, "Ending at a fit of
the readings" (issue 21).

    python -m benchmarks.endings --policy champion:focus-v2 --set validation --analytic \
        --scenarios 200 --seed 3000000 --windows 2 3 5 10 20 1000

With --floors, rows where every move goes at least that share of the interval further (the
task option move_floor), with --below also every reading from below (approach_from_below);
--floors-only runs those rows alone (docs/benchmarks.md, "A floor under every move"):

    python -m benchmarks.endings --policy champion:focus-v2 --set validation --analytic \
        --scenarios 200 --seed 3000000 --floors 0 0.01 0.02 0.035 --floors-only [--below]

The policy acts exactly as trained (the same observations and actions); only what happens
once it stops changes (the task options stop_at_best, backlash_overshoot, finish_at_fit,
finish_at_posterior and finish_window of alignrl/envs/task.py), and in the last two rows how
it reaches each setting (approach_from_below: every reading from below, the backlash taken up
before it). Every ending runs one session per instrument of the set on the same seeded
columns and starts (alignrl.evaluation.instrument_sets). The held-out set is refused: this
chooses a setting, and choices are made on validation only.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

from alignrl.apparatus.instruments import HELD_OUT_SET
from alignrl.deploy.policy import load_deployable
from alignrl.envs.endings import POSTERIOR_OPTIONS, with_ending
from alignrl.envs.option_table import MAX_MOVE_FLOOR
from alignrl.envs.task import Task, get_task
from alignrl.evaluation.controllers import PolicyController
from alignrl.evaluation.instrument_sets import run_set, set_summary, set_table


def floors(task: Task, values: list[float], below: bool = False) -> list[tuple[str, Task]]:
    """(label, the policy's task with every move at least that share of the interval, and
    with `below` every reading approached from below; without it, a task that ends at the
    posterior (whose reading model needs them from below) ends at the fit instead)."""
    label = ", every reading from below" if below else ""
    if not below and task.ending.at == "posterior":
        task = with_ending(without_posterior(task), finish_at_fit=True)
    return [
        (
            f"moves at least {v:g}{label}",
            with_ending(dataclasses.replace(task, move_floor=v), approach_from_below=below),
        )
        for v in values
    ]


def without_posterior(task: Task) -> Task:
    """`task` ending anywhere but at the posterior: finish_at_posterior and the options that
    ask that posterior (alignrl/envs/endings.py, POSTERIOR_OPTIONS) at their defaults."""
    return with_ending(task, finish_at_posterior=False, **POSTERIOR_OPTIONS)


def endings(task: Task, windows: list[float]) -> list[tuple[str, Task]]:
    """(label, the policy's task with that ending) for every ending compared; the ending at
    the posterior takes every stop as the policy asks (no probe_until_sure)."""
    plain = with_ending(without_posterior(task), finish_at_fit=False, stop_at_best=True)
    fitted = with_ending(plain, finish_at_fit=True)
    return [
        ("as trained", task),
        ("narrowest, straight back", with_ending(plain, backlash_overshoot=0.0)),
        ("narrowest", plain),
        *((f"fit within {w:g}x", with_ending(fitted, finish_window=w)) for w in windows),
        (
            "as trained, every reading from below",
            with_ending(task, approach_from_below=True),
        ),
        (
            "at the posterior, every reading from below",
            with_ending(plain, approach_from_below=True, finish_at_posterior=True),
        ),
    ]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--policy", required=True, help="a run, an export or champion:NAME")
    parser.add_argument("--set", default="validation", help="an instrument set (not heldout)")
    parser.add_argument("--analytic", action="store_true", help="analytic readings, no images")
    parser.add_argument("--scenarios", type=int, default=200)
    parser.add_argument("--seed", type=int, default=3_000_000)
    parser.add_argument("--windows", type=float, nargs="+", default=[3.0, 10.0])
    parser.add_argument("--floors", type=float, nargs="+", default=[], help="move_floor values")
    parser.add_argument("--below", action="store_true", help="floor rows: readings from below")
    parser.add_argument("--floors-only", action="store_true", help="the floor rows alone")
    args = parser.parse_args(argv)
    if args.set == HELD_OUT_SET:
        print(f"{HELD_OUT_SET} is held out: settings are chosen on validation", file=sys.stderr)
        return 2
    if any(not window > 1 for window in args.windows):
        print("--windows: every window must be above 1 (x the narrowest reading)", file=sys.stderr)
        return 2
    if any(not 0 <= value <= MAX_MOVE_FLOOR for value in args.floors):
        print(f"--floors: every floor must be in [0, {MAX_MOVE_FLOOR:g}]", file=sys.stderr)
        return 2
    policy = load_deployable(args.policy)
    if policy.task.measures != ("width",) or len(policy.task.knobs) != 1:
        print(f"{args.policy}: endings are compared for one-knob focus aligners", file=sys.stderr)
        return 2
    judged = get_task(policy.task.name)
    results = []
    compared = [] if args.floors_only else endings(policy.task, args.windows)
    for label, task in [*compared, *floors(policy.task, args.floors, args.below)]:
        controller = PolicyController(label, policy.act, task, policy.history)
        result = run_set(controller, args.set, judged, args.scenarios, args.seed, args.analytic)
        print(set_summary(result), file=sys.stderr, flush=True)
        results.append(result)
    print(
        f"{policy.name} on set:{args.set} ({'analytic' if args.analytic else 'images'}), "
        f"{args.scenarios} scenarios each, seed {args.seed}"
    )
    print("\n".join(set_table(results)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
