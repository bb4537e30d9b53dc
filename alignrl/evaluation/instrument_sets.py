"""A controller judged over a whole instrument set: one evaluation session per instrument of
the set (alignrl/apparatus/instruments/<set>/*.yaml), one row each, and the total.

The contract (what `alignrl evaluate --set` and `alignrl baselines --set` print):

* every instrument of the set runs one `run_session` on `instrument:NAME`, in the set's order
  (file-name order), each with the same `seed`: scenario i of every instrument is reset with
  the same scenario seed, and two controllers evaluated with one seed meet the same columns,
  optima and starts on each instrument;
* `analytic` chooses the readings: the probe's analytic edge widths (fast, no images) or
  rendered frames measured as images are (the default, as on a microscope);
* every instrument keeps its own success threshold (relative to the best width that
  instrument reaches, unless `spec_px` gives one absolute width for all of them);
* the totals pool the alignments of all instruments: successes out of all alignments, the
  median and 90th percentile of the acquisitions of every alignment, and the worst
  instrument (the lowest share of successes; the first in set order on a tie), since one
  column a policy cannot align is what a microscopist meets, whatever the mean says;
* every success count carries its 95 % Wilson interval (alignrl.intervals);
* the same set at several seeds (`--seeds`): each seed's SetResult as above, and
  `set_seeds_aggregate`, the aggregate of the per-seed totals (alignrl.evaluation.report's
  `seeds_aggregate`) with each instrument's alignments pooled over the seeds.

Acquisitions count every image a controller took (the verification image not counted), as in
alignrl.evaluation.session. Pure logic apart from the apparatus it opens: no printing.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from alignrl.apparatus.instruments import load_set, set_names, task_kind, task_set
from alignrl.apparatus.limits import ShieldOptions
from alignrl.apparatus.registry import make_apparatus
from alignrl.envs.task import Task
from alignrl.evaluation.controllers import Controller, TaskController
from alignrl.evaluation.report import seeds_aggregate, session_summary
from alignrl.evaluation.session import (
    AcquisitionStatistics,
    ScenarioResult,
    SessionResult,
    run_session,
)
from alignrl.intervals import success_interval, success_text

__all__ = [
    "SetResult",
    "instrument_spec",
    "pooled_over_seeds",
    "run_set",
    "set_heading",
    "set_notes",
    "set_seeds_aggregate",
    "set_summary",
    "set_table",
]


def instrument_spec(name: str) -> str:
    """The apparatus spec of one instrument of a set."""
    return f"instrument:{name}"


@dataclass(frozen=True)
class SetResult(AcquisitionStatistics):
    """The sessions of one controller on every instrument of a set, in set order, and their
    totals (module docstring)."""

    set_name: str
    controller: str
    task: Task
    seed: int
    analytic: bool
    instruments: tuple[str, ...]
    sessions: tuple[SessionResult, ...]
    seconds: float  # wall time of all sessions

    def __post_init__(self) -> None:
        if not self.instruments:
            raise ValueError(f"set {self.set_name!r}: a set result needs at least one instrument")
        if len(self.instruments) != len(self.sessions):
            raise ValueError(
                f"set {self.set_name!r}: {len(self.instruments)} instruments but "
                f"{len(self.sessions)} sessions; need one session per instrument"
            )

    def session(self, instrument: str) -> SessionResult:
        """The session on `instrument`; ValueError naming the set's instruments otherwise."""
        if instrument not in self.instruments:
            raise ValueError(
                f"set {self.set_name!r} has no instrument {instrument!r}; its instruments "
                f"are: {', '.join(self.instruments)}"
            )
        return self.sessions[self.instruments.index(instrument)]

    @property
    def scenarios(self) -> int:
        """Alignments per instrument (the same for every instrument of a run_set)."""
        return self.sessions[0].scenarios

    @property
    def alignments(self) -> int:
        """Alignments over all instruments."""
        return sum(session.scenarios for session in self.sessions)

    @property
    def successes(self) -> int:
        return sum(session.successes for session in self.sessions)

    def acquisitions(self) -> np.ndarray:
        """The acquisitions of every alignment, instrument after instrument."""
        return np.concatenate([session.acquisitions() for session in self.sessions])

    @property
    def budget_exhausted(self) -> int:
        return sum(session.budget_exhausted for session in self.sessions)

    @property
    def unmeasured(self) -> int:
        """Verifications without edges, over all instruments."""
        return sum(session.unmeasured for session in self.sessions)

    @property
    def worst(self) -> str:
        """The instrument with the lowest share of successes (the first of a tie)."""
        shares = [session.successes / session.scenarios for session in self.sessions]
        return self.instruments[int(np.argmin(shares))]

    @property
    def worst_successes(self) -> int:
        """Successes on the worst instrument."""
        return self.session(self.worst).successes

    def to_dict(self, session: str = "test") -> dict[str, Any]:
        """The JSON object of `alignrl evaluate --set --json` (keys in docs/cli.md): the set,
        what the sessions were for (`session`), one session object per instrument in set
        order (`instruments`, each as `alignrl evaluate --json` prints it, with `instrument`
        its name) and the pooled `total`."""
        return {
            "set": self.set_name,
            "controller": self.controller,
            "session": session,
            "task": self.task.name,
            "analytic": self.analytic,
            "seed": self.seed,
            "scenarios": self.scenarios,
            "instruments": [
                {**session_summary(result, instrument_spec(name), session), "instrument": name}
                for name, result in zip(self.instruments, self.sessions, strict=True)
            ],
            "total": {
                "instruments": len(self.instruments),
                "alignments": self.alignments,
                "successes": self.successes,
                "success_interval": success_interval(self.successes, self.alignments),
                "median_acquisitions": self.median_acquisitions,
                "p90_acquisitions": round(self.p90_acquisitions, 2),
                "budget_exhausted": self.budget_exhausted,
                "unmeasured": self.unmeasured,
                "worst_instrument": self.worst,
                "worst_successes": self.worst_successes,
            },
            "seconds": round(self.seconds, 3),
        }


def run_set(
    controller: Controller | TaskController,
    set_name: str,
    task: Task,
    scenarios: int = 100,
    seed: int = 0,
    analytic: bool = False,
    budget: int | None = None,
    spec_px: float | None = None,
    on_scenario: Callable[[ScenarioResult], None] | None = None,
    on_instrument: Callable[[str], None] | None = None,
    shield: ShieldOptions | None = None,
) -> SetResult:
    """One session of `controller` on every instrument of set `set_name` (module docstring).

    `on_instrument(name)` is called as each instrument's session starts and `on_scenario`
    after every alignment (progress). Every instrument is opened before the first session,
    so that an unreadable instrument file is refused before any alignment. ValueError for an
    unknown set (naming the sets), and whatever run_session refuses.
    """
    set_name = task_set(set_name, task.name)  # heldout + stigmation: heldout-stigmation
    if set_name not in set_names():
        raise ValueError(f"no instrument set {set_name!r}; the sets are: {', '.join(set_names())}")
    instruments = load_set(set_name)
    names = tuple(name for name, _ in instruments)
    if not names:
        raise ValueError(f"instrument set {set_name!r} has no instruments (no YAML files)")
    kind = task_kind(task.name)
    wrong = [name for name, family in instruments if family.kind != kind]
    if wrong:
        raise ValueError(
            f"task {task.name!r} is judged on {kind} instruments; set {set_name!r} holds "
            f"others ({', '.join(wrong)})"
        )
    apparatuses = [
        make_apparatus(instrument_spec(name), {"analytic": bool(analytic)}, shield=shield)
        for name in names
    ]
    started = time.perf_counter()
    sessions = []
    for name, apparatus in zip(names, apparatuses, strict=True):
        if on_instrument is not None:
            on_instrument(name)
        sessions.append(
            run_session(
                controller,
                apparatus,
                task,
                scenarios=scenarios,
                seed=seed,
                spec_px=spec_px,
                budget=budget,
                on_scenario=on_scenario,
            )
        )
    return SetResult(
        set_name=set_name,
        controller=controller.name,
        task=task,
        seed=seed,
        analytic=bool(analytic),
        instruments=names,
        sessions=tuple(sessions),
        seconds=time.perf_counter() - started,
    )


def _cell(successes: int, alignments: int, median: float) -> str:
    return f"{success_text(successes, alignments)} at {median:g}"


def set_seeds_aggregate(results: Sequence[SetResult]) -> dict[str, Any]:
    """One controller's set at several seeds (one SetResult per seed): the aggregate of the
    per-seed totals (`seeds_aggregate`: the IQM of the per-seed success rates over all
    instruments with its bootstrap interval, the pooled successes with their Wilson
    interval, the median acquisitions), `instruments`, each instrument's alignments pooled
    over the seeds (`instrument`, `alignments`, `successes`, `success_interval`,
    `median_acquisitions`), and the worst of them (`worst_instrument`, `worst_successes`:
    the lowest share, the first in set order on a tie). ValueError where the seeds ran
    different instruments."""
    pooled = pooled_over_seeds(results, results[0].controller if results else "")
    instruments = [
        {
            "instrument": entry["instrument"],
            "alignments": entry["scenarios"],
            "successes": entry["successes"],
            "success_interval": success_interval(entry["successes"], entry["scenarios"]),
            "median_acquisitions": entry["median_acquisitions"],
        }
        for entry in pooled["instruments"]
    ]
    worst = min(instruments, key=lambda entry: entry["successes"] / entry["alignments"])
    return {
        **seeds_aggregate(results),
        "instruments": instruments,
        "worst_instrument": worst["instrument"],
        "worst_successes": worst["successes"],
    }


def pooled_over_seeds(results: Sequence[SetResult], label: str) -> dict[str, Any]:
    """A column of `set_table` (named `label`) that pools each instrument's alignments over
    the seeds of `results` (one SetResult per seed of one controller): per instrument and in
    total, the successes out of all its alignments and their median acquisitions."""
    if not results:
        raise ValueError("pooled_over_seeds needs at least one seed's set result")
    for result in results[1:]:
        if result.instruments != results[0].instruments:
            raise ValueError(
                f"seed {result.seed} ran {', '.join(result.instruments)}, seed "
                f"{results[0].seed} {', '.join(results[0].instruments)}: pooling needs the "
                "same instruments at every seed"
            )
    instruments = []
    for index, name in enumerate(results[0].instruments):
        sessions = [result.sessions[index] for result in results]
        acquisitions = np.concatenate([session.acquisitions() for session in sessions])
        instruments.append(
            {
                "instrument": name,
                "scenarios": sum(session.scenarios for session in sessions),
                "successes": sum(session.successes for session in sessions),
                "median_acquisitions": float(np.median(acquisitions)),
            }
        )
    every = np.concatenate([result.acquisitions() for result in results])
    return {
        "controller": label,
        "instruments": instruments,
        "total": {
            "alignments": sum(result.alignments for result in results),
            "successes": sum(result.successes for result in results),
            "median_acquisitions": float(np.median(every)),
        },
    }


def set_table(results: Sequence[SetResult | Mapping[str, Any]]) -> list[str]:
    """A Markdown table, padded for the terminal: one row per instrument and a final
    **total** row, one column per controller with `successes/N at median acquisitions`.
    A result is a SetResult or its `to_dict()` (as benchmarks read them back from JSON).
    Every result must cover the same instruments in the same order (ValueError otherwise)."""
    if not results:
        raise ValueError("set_table needs at least one set result")
    data = [r.to_dict() if isinstance(r, SetResult) else r for r in results]
    names = [[entry["instrument"] for entry in d["instruments"]] for d in data]
    for result, instruments in zip(data[1:], names[1:], strict=True):
        if instruments != names[0]:
            raise ValueError(
                f"set_table: {result['controller']} ran on {', '.join(instruments)}, "
                f"{data[0]['controller']} on {', '.join(names[0])}; a table needs the "
                "same instruments for every controller"
            )
    rows = [["instrument", *(d["controller"] for d in data)]]
    for index, name in enumerate(names[0]):
        cells = [d["instruments"][index] for d in data]
        rows.append(
            [
                name,
                *(_cell(c["successes"], c["scenarios"], c["median_acquisitions"]) for c in cells),
            ]
        )
    totals = [d["total"] for d in data]
    rows.append(
        [
            "**total**",
            *(_cell(t["successes"], t["alignments"], t["median_acquisitions"]) for t in totals),
        ]
    )
    sizes = [max(len(row[column]) for row in rows) for column in range(len(rows[0]))]

    def line(cells: Sequence[str]) -> str:
        padded = [cells[0].ljust(sizes[0])] + [
            cell.rjust(size) for cell, size in zip(cells[1:], sizes[1:], strict=True)
        ]
        return "| " + " | ".join(padded) + " |"

    rule = "| " + " | ".join(["-" * sizes[0]] + ["-" * (size - 1) + ":" for size in sizes[1:]])
    return [line(rows[0]), rule + " |", *(line(row) for row in rows[1:])]


def set_heading(result: SetResult, seeds: Sequence[int] | None = None) -> str:
    """What ran where: the set, its size, the readings, the scenarios and the seed (or the
    `seeds`, where the set ran at several)."""
    readings = "analytic readings" if result.analytic else "images"
    seed = f"seed {result.seed}" if seeds is None else f"seeds {', '.join(map(str, seeds))}"
    return (
        f"on set:{result.set_name} ({len(result.instruments)} instruments, {readings}): "
        f"{result.scenarios} scenarios each, {seed}"
    )


def set_summary(result: SetResult) -> str:
    """One line per controller: pooled successes (95 % Wilson interval) and acquisitions,
    and the worst instrument."""
    worst = result.session(result.worst)
    return (
        f"{result.controller}: {success_text(result.successes, result.alignments)} aligned, "
        f"acquisitions median {result.median_acquisitions:g} (p90 "
        f"{result.p90_acquisitions:.1f}), worst {result.worst} "
        f"{success_text(worst.successes, worst.scenarios)}"
    )


def set_notes(results: Sequence[SetResult], seeded: bool = False) -> list[str]:
    """What the table does not show, per controller and instrument (and seed, where
    `seeded`): alignments stopped by the budget, verification images without edges."""
    notes = []
    for result in results:
        for name, session in zip(result.instruments, result.sessions, strict=True):
            where = f"{result.controller} on {name}" + (f", seed {result.seed}" if seeded else "")
            if session.budget_exhausted:
                notes.append(
                    f"{where}: {session.budget_exhausted} alignments spent their whole budget "
                    f"of {session.budget} acquisitions and were stopped"
                )
            if session.unmeasured:
                notes.append(
                    f"{where}: {session.unmeasured} verification images had no edges "
                    "(counted as failures)"
                )
    return notes
