"""`alignrl calibrate`: a champion adapted to one microscope by calibrating the posterior that
walks and ends its alignments (alignrl/deploy/calibrate.py)."""

from __future__ import annotations

import argparse
import shlex
import sys
from typing import Any

from alignrl.cli.common import (
    EXIT_INTERRUPTED,
    _add_apparatus_options,
    _add_shield_options,
    _at_least_one,
    _at_least_zero,
    _emit,
    _json_object,
    _message,
    _seed,
    _share,
    _shield_options,
)

# The alignments ran, but their readings support no calibration (a driver whose widths do not
# follow the setting, or limits that keep focus out of reach): nothing written, as `alignrl
# align` exits 1 for "not aligned".
EXIT_NOT_CALIBRATED = 1


def column_lines(column: dict[str, float]) -> list[str]:
    """The calibrated column in words, one line per aspect."""
    return [
        f"  focus:    {column['blur_px_per_interval']:.3g} px of blur per interval, in focus "
        f"sigma {column['floor_sigma_px']:.3g} px, curve power {column['curve_power']:.3g}, "
        f"flat {100 * column['flat_fraction']:.2g} % of the interval, over/under-focus "
        f"{column['asymmetry']:.3g}",
        f"  readings: noise {100 * column['reading_noise_rel']:.2g} % + "
        f"{column['reading_noise_px']:.2g} px, specimen {100 * column['specimen_rel']:.2g} %, "
        f"level off at {column['saturation_px']:.3g} px, no edges beyond "
        f"{column['no_edges_px']:.3g} px",
        f"  column:   drift {100 * column['drift_fraction']:.2g} % of the interval per image, "
        f"backlash {100 * column['hysteresis_fraction']:.2g} %",
    ]


def _interrupted(out: Any) -> int:
    print(
        f"\ninterrupted: no calibrated policy written ({out} left as it was: a calibration "
        "counts only when complete)",
        file=sys.stderr,
    )
    return EXIT_INTERRUPTED


def cmd_calibrate(args: argparse.Namespace) -> int:
    from alignrl.deploy.align import operator_signals

    try:
        with operator_signals():  # SIGTERM ends it as Ctrl-C does
            return _calibrate(args)
    except KeyboardInterrupt:
        return _interrupted(args.out)


def _calibrate(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from alignrl.apparatus.registry import make_apparatus
    from alignrl.deploy.calibrate import CALIBRATION_FILE, plan_calibration, run_calibration
    from alignrl.posterior.calibration import UncalibratedError

    # Everything that can be checked without the apparatus, before it is opened
    plan = plan_calibration(
        args.policy,
        args.out,
        alignments=args.alignments,
        population=args.population,
        rounds=args.rounds,
        from_above=args.from_above,
        far_noise=args.far_noise,
        force=args.force,
    )
    apparatus = make_apparatus(
        args.apparatus,
        _json_object(args.apparatus_args, "--apparatus-args"),
        shield=_shield_options(args),
    )
    bars: dict[str, Any] = {}

    def bar(total: int, unit: str, desc: str) -> Any:
        return tqdm(total=total, unit=unit, desc=desc, disable=args.quiet, file=sys.stderr)

    done = []

    def alignment(_record: Any) -> None:
        if "session" not in bars:
            bars["session"] = bar(args.alignments, "alignment", "aligning")
        bars["session"].update(1)
        done.append(1)
        if len(done) == args.alignments:  # the search starts: its own bar
            bars["session"].close()
            bars["fit"] = bar(args.rounds, "round", "calibrating")

    def calibrated_round(_done: int, steps: int, best: float) -> None:
        bars["fit"].total = steps  # the rounds, and the far noise's where it is searched
        bars["fit"].set_postfix_str(f"log evidence {best:.1f}", refresh=False)
        bars["fit"].update(1)

    command = shlex.join(["alignrl", *args.argv])
    try:
        result = run_calibration(
            plan,
            apparatus,
            seed=args.seed,
            spec_px=args.spec_px,
            budget=args.budget,
            command=command,
            on_alignment=alignment,
            on_round=calibrated_round,
        )
    except UncalibratedError as error:
        print(f"alignrl: not calibrated: {_message(error)}", file=sys.stderr)
        return EXIT_NOT_CALIBRATED
    finally:
        for bar in bars.values():
            bar.close()
    session, calibration = result.session, result.calibration
    payload = {
        "policy": args.policy,
        "apparatus": args.apparatus,
        "out": str(result.out),
        "alignments": session.scenarios,
        "successes": session.successes,
        "median_acquisitions": session.median_acquisitions,
        "readings": calibration.readings,
        "log_evidence": calibration.log_evidence,
        "column": calibration.column,
        "far_noise": calibration.far_noise,
        "seconds": round(result.seconds, 1),
    }
    lines = [
        f"calibrated {args.policy} on {args.apparatus} from {session.scenarios} alignments "
        f"({session.successes}/{session.scenarios} aligned at a median of "
        f"{session.median_acquisitions:g} acquisitions; {calibration.readings} readings"
        f"{f', {args.from_above} per alignment from above' if args.from_above else ''})",
        *column_lines(calibration.column),
        f"  far from focus: a reading's spread {100 * calibration.far_noise:.2g} % of it more "
        f"per e-fold of its width over the in-focus one"
        f"{' (given)' if args.far_noise is not None else ' (fitted)'}",
        f"  log evidence {calibration.log_evidence:.1f} ({calibration.per_reading():.2f} per "
        f"reading) after {args.rounds} rounds, {result.seconds:.0f} s",
        f"  written: {result.out} (the policy with this column, {CALIBRATION_FILE})",
        f"  next: alignrl evaluate --policy {result.out} --apparatus {args.apparatus}",
    ]
    _emit(payload, args.json, lines)
    return 0


def add_calibrate_parser(verbs: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    calibrate = verbs.add_parser(
        "calibrate",
        help="adapt a champion to one microscope: calibrate its posterior on alignments there",
    )
    calibrate.add_argument(
        "--policy",
        required=True,
        help="a policy whose alignments end at its focus posterior and approach from below, "
        "e.g. champion:focus-v2 (an export or run of that task too)",
    )
    _add_apparatus_options(calibrate)
    calibrate.add_argument(
        "--alignments",
        type=_at_least_one,
        default=10,  # alignrl.posterior.calibration.ALIGNMENTS, left unimported (scipy)
        help="alignments run to calibrate on (default: 10)",
    )
    calibrate.add_argument(
        "--seed", type=_seed, default=0, help="seed of the alignments' starts and of the search"
    )
    calibrate.add_argument(
        "--spec-px",
        type=float,
        default=None,
        help="success threshold of the alignments, edge width in px (default: relative to "
        "the best the apparatus can reach; required where it cannot say)",
    )
    calibrate.add_argument(
        "--budget", type=int, default=None, help="most acquisitions per alignment (default: 50)"
    )
    calibrate.add_argument(
        "--population",
        type=_at_least_one,
        default=256,
        help="columns the search weighs per round (default: 256; at least 8, at most what "
        "4 GiB holds: about 4,400, 0.96 MB each)",
    )
    calibrate.add_argument(
        "--rounds", type=_at_least_one, default=8, help="rounds of the search (default: 8)"
    )
    calibrate.add_argument(
        "--from-above",
        type=_at_least_zero,
        default=2,  # alignrl.posterior.calibration.FROM_ABOVE, left unimported (scipy)
        metavar="N",
        help="images approached from above after each alignment, which tell the column's "
        "backlash (default: 2; 0: none)",
    )
    calibrate.add_argument(
        "--far-noise",
        type=_share,
        default=None,
        metavar="SHARE",
        help="how much less a reading far from focus is trusted, per e-fold of its width "
        "over the in-focus one (default: fitted with the column, between 0.05 and 0.3)",
    )
    calibrate.add_argument(
        "--out", required=True, metavar="DIR", help="folder the calibrated policy goes to"
    )
    calibrate.add_argument("--force", action="store_true", help="replace a non-empty --out")
    calibrate.add_argument("--quiet", action="store_true", help="no progress bars")
    calibrate.add_argument("--json", action="store_true", help="machine-readable summary")
    _add_shield_options(calibrate)
    calibrate.set_defaults(handler=cmd_calibrate)
