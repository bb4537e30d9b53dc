"""`alignrl align` and `alignrl export`: a trained policy at work on an instrument, every
write through the safety shield (alignrl/deploy/align.py), and an aligner exported as a
self-contained ONNX, TorchScript or safetensors policy with its card."""

from __future__ import annotations

import argparse
import sys
import time

from alignrl.apparatus.base import ApparatusError
from alignrl.cli.common import (
    CommandError,
    _add_apparatus_options,
    _add_policy_option,
    _add_shield_options,
    _emit,
    _json_object,
    _seed,
)
from alignrl.cli.gifs import add_gif_options, check_gif, write_gif
from alignrl.envs.option_table import ACTING_OPTIONS


def _count(number: int, noun: str) -> str:
    return f"{number} {noun}{'' if number == 1 else 's'}"


def _setting_text(setting: dict[str, float] | None) -> str:
    if setting is None:
        return "unknown"
    return ", ".join(f"{knob} {value:.4g}" for knob, value in setting.items())


def cmd_align(args: argparse.Namespace) -> int:
    """One alignment through the safety shield; the exit code says how it ended
    (alignrl/deploy/align.py: 0 aligned, 1 not, 2 config, 3 aborted, 4 driver failure)."""
    from alignrl.apparatus.filming import Film, FilmedApparatus
    from alignrl.apparatus.guard import declared_intervals
    from alignrl.apparatus.registry import build_apparatus
    from alignrl.apparatus.shield import JsonLinesAudit, MemoryAudit, resolve_limits
    from alignrl.deploy.align import (
        EXIT_ABORTED,
        EXIT_DRIVER,
        align,
        alignment_scene,
        operator_signals,
    )
    from alignrl.deploy.policy import load_deployable
    from alignrl.envs.task import get_task

    check_gif(args)
    film = Film() if args.gif is not None else None
    apparatus_args = _json_object(args.apparatus_args, "--apparatus-args")
    site_limits = _json_object(args.limits, "--limits")
    max_step = _json_object(args.max_step, "--max-step")
    with operator_signals():
        try:
            policies = []
            for source in args.policy:
                try:
                    policies.append(load_deployable(source))
                except ImportError as error:  # an ONNX policy without onnxruntime
                    raise CommandError(f"cannot run policy {source}: {error}") from None
            judged = get_task(args.task) if args.task is not None else None
            if len(policies) > 1 and judged is None:
                raise CommandError(
                    "several --policy run in sequence and need --task, the task the column "
                    "is judged on (e.g. --task column)"
                )
            if len(policies) == 1 and judged is not None and judged.name != policies[0].task.name:
                raise CommandError(
                    f"policy {policies[0].name!r} aligns task {policies[0].task.name!r}, "
                    f"not {args.task!r}"
                )
            try:
                # Unshielded here: align() puts its own shield (with the watchdog) around it.
                apparatus = build_apparatus(
                    args.apparatus, apparatus_args, args.seed, args.call_timeout
                )
            except ApparatusError as error:
                print(f"alignrl: apparatus error: {error}", file=sys.stderr)
                return EXIT_DRIVER
            knobs = declared_intervals(apparatus, args.apparatus, args.call_timeout)
            limits = resolve_limits(knobs, site_limits, max_step)
        except KeyboardInterrupt:
            print("\ninterrupted before the alignment started: nothing written", file=sys.stderr)
            return EXIT_ABORTED
        audit = JsonLinesAudit(args.log) if args.log else MemoryAudit()
        try:
            result = align(
                policies,
                apparatus if film is None else FilmedApparatus(apparatus, film, knobs),
                limits,
                audit,
                task=judged,
                apparatus_spec=args.apparatus,
                spec_px=args.spec_px,
                dry_run=args.dry_run,
                timeout_s=args.timeout,
                call_timeout_s=args.call_timeout,
                max_acquisitions=args.max_acquisitions,
                restore_on_abort=args.restore_on_abort,
                log_path=args.log,
            )
        except KeyboardInterrupt:  # before the alignment began: it handles its own
            print("\ninterrupted before the alignment started: nothing written", file=sys.stderr)
            return EXIT_ABORTED
        finally:
            if isinstance(audit, JsonLinesAudit):
                audit.close()
    lines = [
        f"{result.outcome}: {result.reason}",
        f"  policy {result.policy} on {result.apparatus}: "
        f"{_count(result.acquisitions, 'acquisition')}, {_count(result.writes, 'write')} "
        f"({result.clamped} clamped, {result.refused} refused)"
        + (" - dry run: nothing was written" if result.dry_run else ""),
        f"  start {_setting_text(result.start_setting)}; "
        f"left at {_setting_text(result.final_setting)}"
        + (" (start restored)" if result.restored else ""),
    ]
    if result.log:
        lines.append(f"  audit log: {result.log}")
    payload = result.to_dict()
    if film is not None:
        scene = alignment_scene(result, judged or policies[0].task, film.knobs)
        line = write_gif(film.readings, scene, args.gif, payload)
        lines += [f"  {line}"] if line else []
    _emit(payload, args.json, lines)
    return result.exit_code


def cmd_export(args: argparse.Namespace) -> int:
    from alignrl.deploy.export import (
        default_out,
        export_command,
        export_policy,
        with_acting_options,
    )
    from alignrl.deploy.graph import move_floors
    from alignrl.runs.sources import resolve_source

    started = time.perf_counter()
    learner = args.with_learner_state
    source = with_acting_options(resolve_source(args.run, args.member), args.overrides)
    out = (
        args.out
        if args.out is not None
        else default_out(source, args.run, args.format, args.runs_dir)
    )
    command = export_command(args.run, args.member, args.format, out, learner, args.overrides)
    try:
        result = export_policy(
            source,
            out,
            args.format,
            force=args.force,
            command=command,
            learner_state=learner,
            named=args.run,
        )
    except ImportError as error:  # the optional extra: its message says what to install
        raise CommandError(str(error)) from None
    card, parity = result.card, result.parity
    payload = {
        "run": args.run,
        "member": card["member"]["id"],
        "chosen_as": card["source"]["chosen_as"],
        "format": args.format,
        "out": str(result.out),
        "policy": str(result.policy_file),
        "card": str(result.out / "card.json"),
        "model_card": str(result.out / "model_card.md"),
        "learner": str(result.learner_file) if result.learner_file else None,
        "inputs": card["inputs"],
        "outputs": card["outputs"],
        "history": card["history"],
        "knobs": card["knobs"],
        "memory": card["memory"]["kind"],
        "parity_histories": parity.histories,
        "parity_max_abs_difference": parity.max_abs_difference,
        "seconds": round(time.perf_counter() - started, 2),
    }

    def shapes(side: str) -> str:
        return ", ".join(
            f"{entry['name']} {entry['dtype']} ({', '.join(map(str, entry['shape']))})"
            for entry in card[side]
        )

    floors = move_floors(source.task.move_floor, card["knobs"])
    least = [f", every move at least {floor:g}" if floor else "" for floor in floors]
    lines = [
        f"exported {payload['member']} ({payload['chosen_as']} of {args.run}) as "
        f"{args.format}: {result.policy_file}",
        f"  inputs:  {shapes('inputs')}",
        f"  outputs: {shapes('outputs')}",
        *(
            f"  knob:    {knob['name']} in [{knob['low']:g}, {knob['high']:g}], at most "
            f"{knob['max_step']:g} per action{at_least}"
            for knob, at_least in zip(card["knobs"], least, strict=True)
        ),
        f"  memory:  {card['memory']['note']}",
        f"  parity:  max |{args.format} - PyTorch| = {parity.max_abs_difference:.2g} on "
        f"{parity.histories} random histories (allowed {parity.tolerance:g})",
        f"  model card: {payload['model_card']} and {payload['card']}",
    ]
    if result.learner_file:
        lines.append(
            f"  learner: {result.learner_file} and {result.out / 'learner.json'} (critics, "
            "target critics, entropy coefficient, optimizers: adapt and init_from train on "
            "from them)"
        )
    _emit(payload, args.json, lines)
    return 0


def add_deploy_parsers(verbs: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    align = verbs.add_parser(
        "align", help="align an apparatus with a trained policy, through the safety shield"
    )
    _add_policy_option(
        align,
        "a run directory (training or league), a checkpoint .pt, an exported policy "
        "directory, or champion:NAME; give it several times (with --task) to run task "
        "champions in that order, e.g. aperture, focus, stigmation for --task column",
    )
    _add_apparatus_options(align)
    align.add_argument(
        "--task",
        default=None,
        help="the task the alignment is judged on (default: the policy's own; required with "
        "several --policy)",
    )
    align.add_argument(
        "--spec-px",
        type=float,
        default=None,
        help="success threshold, edge width in px (default: relative to the best the "
        "apparatus can reach, where it can say)",
    )
    _add_shield_options(align)
    align.add_argument(
        "--dry-run", action="store_true", help="decide and log every write, make none"
    )
    align.add_argument(
        "--timeout", type=float, default=None, metavar="S", help="watchdog: end after S seconds"
    )
    align.add_argument(
        "--max-acquisitions",
        type=int,
        default=None,
        metavar="N",
        help="watchdog: at most N images (default: the task's episode steps + 1)",
    )
    align.add_argument(
        "--restore-on-abort",
        action="store_true",
        help="after Ctrl-C, SIGTERM or the watchdog, write the starting setting back",
    )
    align.add_argument("--seed", type=_seed, default=0, help="seed of a simulated apparatus")
    add_gif_options(align, session=False)
    align.add_argument("--json", action="store_true", help="machine-readable result")
    align.set_defaults(handler=cmd_align)

    export = verbs.add_parser(
        "export",
        help="an aligner as a self-contained ONNX, TorchScript or safetensors policy with its card",
    )
    export.add_argument(
        "run",
        metavar="RUN",
        help="a league run (its champion), a training run (its best checkpoint), a member "
        ".pt file, a safetensors export, or champion:NAME (a shipped champion)",
    )
    export.add_argument("--member", metavar="ID", help="this member of a league run instead")
    export.add_argument(
        "--format",
        required=True,
        choices=("onnx", "torchscript", "safetensors"),
        help="policy.onnx (needs: pip install 'alignrl[onnx]'), policy.pt (torch.jit) or "
        "policy.safetensors (the network's weights; no extra dependencies)",
    )
    export.add_argument(
        "--out",
        metavar="DIR",
        help="folder to write (default: RUN/exports/MEMBER-FORMAT beside a run; "
        "RUNS/exports/NAME-FORMAT for a policy outside any run)",
    )
    export.add_argument(
        "--runs-dir",
        default="runs",
        metavar="RUNS",
        help="where the export of a policy outside any run goes without --out",
    )
    export.add_argument(
        "--with-learner-state",
        action="store_true",
        help="with --format safetensors: also the critics, optimizers and entropy coefficient "
        "(learner.safetensors, learner.json), so that adapt and init_from can train on from "
        "the export",
    )
    export.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="task_options.NAME=VALUE",
        help="how the exported policy acts, one of the task options that never change what it "
        f"observes ({', '.join(ACTING_OPTIONS)}), e.g. task_options.move_floor=0.02; "
        "recorded in its card (repeatable)",
    )
    export.add_argument("--force", action="store_true", help="replace a non-empty --out")
    export.add_argument("--json", action="store_true", help="machine-readable summary")
    export.set_defaults(handler=cmd_export)
