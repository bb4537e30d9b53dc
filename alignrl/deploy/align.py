"""One alignment of an instrument by a trained policy, through the safety shield.

The loop is the environments' own (alignrl/envs/core.py, `AlignmentEpisodes.adopt` then
`step` until the policy stops or its steps run out) over a `ShieldedApparatus`, so the policy
sees the history features it was trained on; then a final image is acquired and its edge width
judged against the spec. Where the shield changed a write (clamped it, or a dry run left the
column where it was), the history is corrected to the setting the column really has.

How it ends, and the exit code of `alignrl align`:

    0  aligned          the final edge width is within the spec
    1  not aligned      the alignment ran to its end, the spec was not met (or is unknown)
    2  config error     nothing was written (also: the column started outside --limits)
    3  aborted          the operator (Ctrl-C, SIGTERM), the watchdog, or a non-finite action
    4  driver failure   the driver failed on a read or a write; the column's state is unknown

Every read, write and measurement, and the shield's decision on it, goes to the audit log
(`JsonLinesAudit`: one JSON object a line, flushed and fsynced each line).
"""

from __future__ import annotations

import dataclasses
import math
import signal
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np

from alignrl.animation import Scene
from alignrl.apparatus.audit import plain
from alignrl.apparatus.base import Apparatus, ApparatusError
from alignrl.apparatus.shield import (
    DEFAULT_CALL_TIMEOUT_S,
    OPERATOR_ABORT,
    AuditSink,
    DriverFailure,
    KnobLimits,
    ShieldedApparatus,
    ShieldStop,
    StartOutsideLimits,
    Watchdog,
)
from alignrl.deploy.policy import DeployablePolicy
from alignrl.envs.core import AlignmentEpisodes
from alignrl.envs.task import Criterion, Task
from alignrl.evaluation.session import verify_task

__all__ = [
    "EXIT_ABORTED",
    "EXIT_ALIGNED",
    "EXIT_CONFIG",
    "EXIT_DRIVER",
    "EXIT_NOT_ALIGNED",
    "AlignResult",
    "align",
    "alignment_scene",
    "operator_signals",
]

EXIT_ALIGNED = 0
EXIT_NOT_ALIGNED = 1
EXIT_CONFIG = 2
EXIT_ABORTED = 3
EXIT_DRIVER = 4
EXIT_CODES = {
    "aligned": EXIT_ALIGNED,
    "not-aligned": EXIT_NOT_ALIGNED,
    "spec-unknown": EXIT_NOT_ALIGNED,
    "config-error": EXIT_CONFIG,
    "aborted": EXIT_ABORTED,
    "driver-failure": EXIT_DRIVER,
}


# --- operator signals ---------------------------------------------------------------------


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


@contextmanager
def operator_signals() -> Iterator[None]:
    """Within: Ctrl-C (SIGINT) and SIGTERM (a `kill`, a service stop) both raise
    KeyboardInterrupt, so each ends an alignment as an operator abort. Only the main thread
    can install handlers; elsewhere the handlers stay as they are."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.signal(sig, _interrupt) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


# --- the result ---------------------------------------------------------------------------


@dataclass(frozen=True)
class AlignResult:
    """How one alignment ended. Settings in instrument units, widths in px."""

    outcome: str  # a key of EXIT_CODES
    reason: str  # why it ended, in words
    final_width_px: float | None  # the final image; None: not taken, or it had no edges
    threshold_px: float | None  # the spec; None: unknown
    acquisitions: int  # alignment images that reached the driver (not the final one)
    writes: int  # writes that reached the driver, the restore included
    clamped: int  # writes the shield clamped (in a dry run: would have)
    refused: int  # writes the shield did not make (outside a dry run's)
    start_setting: dict[str, float] | None
    final_setting: dict[str, float] | None  # where the column was left; None: unknown
    dry_run: bool
    restored: bool  # the start was written back after an abort
    log: str | None
    policy: str
    apparatus: str
    final_directional_px: list[float] | None = None  # tasks that measure them: per bin
    final_wobble_px: list[float] | None = None  # tasks that wobble: the final shift (dx, dy)

    @property
    def success(self) -> bool:
        return self.outcome == "aligned"

    @property
    def aborted(self) -> bool:
        return self.outcome == "aborted"

    @property
    def exit_code(self) -> int:
        return EXIT_CODES[self.outcome]

    def to_dict(self) -> dict[str, Any]:
        """The stable keys of `alignrl align --json` (docs/cli.md)."""
        data = dataclasses.asdict(self)
        data.update(success=self.success, aborted=self.aborted, exit_code=self.exit_code)
        return plain(data)


# --- the alignment ------------------------------------------------------------------------


def _best_width(shield: ShieldedApparatus, **fields: Any) -> float | None:
    """The apparatus's best edge width (simulated apparatus; None: it cannot tell), logged
    with `fields`."""
    try:
        best_px = shield.best_width()
    except ApparatusError as error:
        shield.log("reference", sent=True, error=str(error))
        raise DriverFailure(f"the apparatus failed to say its best edge width: {error}") from None
    if best_px is not None:
        shield.log("reference", sent=True, best_width_px=best_px, **fields)
    return best_px


def _spec_threshold(task: Task, spec_px: float | None, shield: ShieldedApparatus) -> float | None:
    """--spec-px, else the task's absolute spec, else its relative rule with the apparatus's
    best_quality() (simulated apparatus); None where none of them is possible."""
    rule = task.success
    if spec_px is not None:
        return float(spec_px)
    if rule.absolute_px is not None:
        return float(rule.absolute_px)
    best_px = _best_width(shield, relative=rule.relative)
    return None if best_px is None else rule.threshold_px(best_px)


def _check_policy_shape(policy: DeployablePolicy, episodes: AlignmentEpisodes) -> None:
    """One action on an empty history, before anything is written: a policy for another
    task or history length is a config error, not a fault halfway through."""
    empty = np.zeros((policy.history, episodes.n_features), np.float32)
    action = np.asarray(policy.act(empty))
    if action.shape != (episodes.k + 1,):
        raise ValueError(
            f"policy {policy.name!r} answers an action of shape {action.shape}; task "
            f"{policy.task.name!r} needs ({episodes.k + 1},): {episodes.k} knob change(s) and stop"
        )


class _NonFiniteAction(ShieldStop):
    """The policy answered NaN or infinity: the alignment ends before the write it asks for."""


def _run_policy(
    policy: DeployablePolicy, episodes: AlignmentEpisodes, shield: ShieldedApparatus
) -> str:
    """The alignment proper; returns why it ended. ShieldStop and KeyboardInterrupt pass."""
    slot = np.array([0])
    k = episodes.k
    episodes.adopt(slot)
    before = -1
    while episodes.active[0]:
        action = np.asarray(policy.act(episodes.observation(0)), dtype=np.float64).reshape(-1)
        stop = bool(action[k] > 0)
        if not np.all(np.isfinite(action)):
            reason = f"the policy produced a non-finite action {action.tolist()}"
            shield.log("action", action=action, decision="refused", reason=reason)
            raise _NonFiniteAction(reason)
        shield.log("action", action=action, stop=stop)
        before = int(episodes.steps[0])
        episodes.step(slot, action[None])  # the shield's applied setting goes in the history
    # A stop the posterior is unsure of is a reading instead (probe_until_sure), and a sure
    # posterior ends the episode after a reading (stop_when_sure): how it ended, from the last
    # step, whether it took a reading.
    if episodes.steps[0] == before:
        return "the policy stopped"
    if episodes.steps[0] >= policy.task.episode_steps:
        return f"the policy used all {policy.task.episode_steps} steps of its task"
    return "its posterior was sure of the best setting"


def align(
    policy: DeployablePolicy | Sequence[DeployablePolicy],
    apparatus: Apparatus,
    limits: Mapping[str, KnobLimits],
    audit: AuditSink,
    *,
    task: Task | None = None,
    apparatus_spec: str = "apparatus",
    spec_px: float | None = None,
    dry_run: bool = False,
    timeout_s: float | None = None,
    max_acquisitions: int | None = None,
    restore_on_abort: bool = False,
    call_timeout_s: float | None = DEFAULT_CALL_TIMEOUT_S,
    clock: Callable[[], float] | None = None,
    log_path: str | None = None,
) -> AlignResult:
    """Align `apparatus` once with `policy` through the shield (see the module docstring).

    `policy` may be a sequence of policies, run one after the other through the same shield
    (one watchdog, one audit log): a column aligned by task champions in an operator's order,
    e.g. aperture, focus, stigmation. The result is judged on `task` (default: the one
    policy's own task), whose knobs must include every policy's.

    `limits` come from `resolve_limits`. `max_acquisitions` defaults to everything the
    policies may ask for (each one's episode steps + 1 measurements); `clock` (monotonic
    seconds) is the watchdog's and the log's. A policy or task that does not fit the
    apparatus raises ValueError before anything is written; the driver's failures and the
    operator's Ctrl-C end in a result, never in an exception.
    """
    policies = [policy] if isinstance(policy, DeployablePolicy) else list(policy)
    if not policies:
        raise ValueError("align needs at least one policy")
    if task is None:
        if len(policies) > 1:
            raise ValueError("a sequence of policies needs the task it is judged on (--task)")
        task = policies[0].task
    for one in policies:
        missing = [knob for knob in one.task.knobs if knob not in task.knobs]
        if missing:
            raise ValueError(
                f"policy {one.name!r} moves {', '.join(missing)}, which task {task.name!r} "
                f"does not align"
            )
    if spec_px is not None and not (math.isfinite(spec_px) and spec_px > 0):
        raise ValueError(f"--spec-px must be a positive edge width in px, got {spec_px}")
    if max_acquisitions is None:
        max_acquisitions = sum(
            (one.task.episode_steps + 1) * one.task.acquisitions_per_step for one in policies
        )
    watchdog = Watchdog(timeout_s, max_acquisitions, clock or time.monotonic)
    shield = ShieldedApparatus(apparatus, limits, audit, watchdog, dry_run, call_timeout_s)
    task.check_apparatus(shield.knobs)
    stages = []
    for one in policies:
        # Checks the knobs; align verifies on its own (final_measures), not the episode.
        episodes = AlignmentEpisodes([shield], one.task.for_acting(), one.history)
        _check_policy_shape(one, episodes)
        stages.append((one, episodes))
    names = " -> ".join(one.name for one in policies)

    def result(outcome: str, reason: str, **fields: Any) -> AlignResult:
        done = AlignResult(
            outcome=outcome,
            reason=reason,
            final_width_px=fields.get("final_width_px"),
            threshold_px=fields.get("threshold_px"),
            acquisitions=shield.acquisitions,
            writes=shield.writes,
            clamped=shield.clamped,
            refused=shield.refused,
            start_setting=shield.start,
            final_setting=dict(shield.setting) if shield.setting is not None else None,
            dry_run=dry_run,
            restored=shield.restored,
            log=log_path,
            policy=names,
            apparatus=apparatus_spec,
            final_directional_px=fields.get("final_directional_px"),
            final_wobble_px=fields.get("final_wobble_px"),
        )
        shield.log("end", result=done.to_dict())
        return done

    shield.log(
        "start",
        policy=names,
        policy_source=[one.source for one in policies],
        task=task.name,
        stages=[one.task.name for one in policies],
        history=[one.history for one in policies],
        apparatus=apparatus_spec,
        knobs={name: list(interval) for name, interval in shield.knobs.items()},
        limits={name: knob.as_dict() for name, knob in limits.items()},
        dry_run=dry_run,
        timeout_s=timeout_s,
        call_timeout_s=call_timeout_s,
        max_acquisitions=max_acquisitions,
        restore_on_abort=restore_on_abort,
        spec_px=spec_px,
    )
    threshold: float | None = None
    try:
        shield.begin()
        threshold = _spec_threshold(task, spec_px, shield)
        reasons = []
        for one, episodes in stages:
            if len(stages) > 1:
                shield.log("stage", policy=one.name, task=one.task.name)
            reasons.append(_run_policy(one, episodes, shield))
        reason = (
            "; ".join(reasons)
            if len(stages) == 1
            else "; ".join(
                f"{one.task.name}: {why}" for (one, _), why in zip(stages, reasons, strict=True)
            )
        )
        with shield.final_measures():
            final_width, directional, shift = verify_task(shield, task)
        # Directional widths are judged against the best width (asked again: it may drift).
        best_px = _best_width(shield) if task.judges("directional") else None
    except StartOutsideLimits as error:
        return result("config-error", str(error))
    except DriverFailure as error:
        shield.abort(str(error))  # nothing more reaches a failing driver, not even a restore
        return result("driver-failure", str(error), threshold_px=threshold)
    except (KeyboardInterrupt, ShieldStop) as error:
        why = OPERATOR_ABORT if isinstance(error, KeyboardInterrupt) else str(error)
        shield.abort(why)
        if restore_on_abort:
            try:
                shield.restore()
            except DriverFailure as failure:
                return result("driver-failure", f"{why}; {failure}", threshold_px=threshold)
            except KeyboardInterrupt:
                why += "; the restore was interrupted"
        return result("aborted", why, threshold_px=threshold)
    except Exception as error:
        # A bug (in alignrl, the policy or the driver), not an outcome: it still surfaces as
        # a traceback, but nothing more reaches the driver and the log says how it ended.
        shield.abort(f"internal error: {type(error).__name__}: {error}")
        shield.log("end", error=f"{type(error).__name__}: {error}")
        raise
    measured = {
        "final_directional_px": None if directional is None else directional.tolist(),
        "final_wobble_px": None if shift is None else shift.tolist(),
    }
    if final_width is None or not math.isfinite(final_width):
        return result(
            "not-aligned",
            f"{reason}; the final image had no edges",
            threshold_px=threshold,
            **measured,
        )
    if threshold is None:
        return result(
            "spec-unknown",
            f"{reason}; spec unknown: the apparatus cannot say its best edge width, give "
            "--spec-px to judge",
            final_width_px=final_width,
            **measured,
        )
    criteria = _judge(task, final_width, threshold, directional, shift, best_px)
    return result(
        "aligned" if all(criterion.met[0] for criterion in criteria) else "not-aligned",
        f"{reason}; " + "; ".join(criterion.words() for criterion in criteria),
        final_width_px=final_width,
        threshold_px=threshold,
        **measured,
    )


def alignment_scene(
    result: AlignResult, task: Task, knobs: Mapping[str, tuple[float, float]]
) -> Scene:
    """What the frames of a filmed alignment (alignrl/apparatus/filming.py) share: the knobs
    of the task it was judged on with their intervals (`knobs`: the apparatus's), the spec,
    which images were the alignment's own (the rest: the final judging image), and how it
    ended."""
    return Scene(
        knobs={knob: knobs[knob] for knob in task.knobs},
        title=f"{result.policy} on {result.apparatus}" + (" (dry run)" if result.dry_run else ""),
        threshold_px=result.threshold_px,
        acquisitions=result.acquisitions,
        ending=f"{result.outcome}: {result.reason}",
    )


def _judge(
    task: Task,
    width: float,
    threshold: float,
    directional: np.ndarray | None,
    shift: np.ndarray | None,
    best_px: float | None,
) -> list[Criterion]:
    """The final measurement judged as sessions and training judge it (Task.judge); a judged
    measure that failed is not met. The directional widths are judged against `best_px`, the
    apparatus's best width (their spec is relative to it)."""
    limit = None
    if task.judges("directional"):
        limit = task.directional_threshold_px(threshold, best_px)
    return task.judge(
        np.array([width]),
        np.array([threshold]),
        None if directional is None else directional[None],
        None if limit is None else np.array([limit]),
        None if shift is None else shift[None],
    )
