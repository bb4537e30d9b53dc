"""model_card.md: a policy's card for a person, rendered from card.json's values (written by
alignrl.deploy.card, keys in docs/deploy.md): what the policy is, how to feed it, its knobs
and limits, how it was trained, its evaluation sessions as tables, parity and lineage.

Every success count of the evaluations is shown with its 95 % Wilson interval, and the
section says what the sessions were: validation sessions, the run's own, one of which chose
the exported checkpoint (so its figure flatters it), not a test of the policy. A card written
before the label existed (a shipped champion's) is read the same way: its sessions are a
run's.

Knob values and steps are in the apparatus's units (volts for a lens); edge widths in pixels.
"""

from __future__ import annotations

import json
from typing import Any

from alignrl.intervals import success_text

__all__ = ["render_model_card"]

INTERVAL_COLUMNS = ("success_low", "success_high")  # shown inside the successes cell


def _cell(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:g}"
    return str(value).replace("|", "\\|")


def _table(rows: list[dict[str, Any]], columns: list[str]) -> list[str]:
    return [
        "| " + " | ".join(columns) + " |",
        "| " + " | ".join("---" for _ in columns) + " |",
        *("| " + " | ".join(_cell(row.get(c)) for c in columns) + " |" for row in rows),
    ]


def _counted(row: dict[str, Any]) -> dict[str, Any]:
    """A session's row for the table: successes with their interval ("83/100 (74-89 %)"),
    where the row counts them out of its scenarios."""
    successes, scenarios = row.get("successes"), row.get("scenarios")
    shown = {key: value for key, value in row.items() if key not in INTERVAL_COLUMNS}
    if isinstance(successes, int) and isinstance(scenarios, int) and 0 <= successes <= scenarios:
        shown["successes"] = success_text(successes, scenarios) if scenarios else successes
    return shown


def _session_at(row: dict[str, Any]) -> str:
    """When a run's session was held: its league iteration or training env steps."""
    if row.get("iteration") is not None:
        return f"iteration {row['iteration']}"
    if row.get("env_steps") is not None:
        return f"{row['env_steps']} env steps"
    return "an unrecorded time"


def _evaluations(evaluations: dict[str, Any], chosen_as: str) -> list[str]:
    """The Evaluations section: what the sessions are, the one the checkpoint was chosen
    on, the table of them all with intervals, and the command that runs one again."""
    lines = ["## Evaluations", ""]
    if not evaluations["rows"]:
        return [*lines, "No evaluation session recorded for this member."]
    session = evaluations.get("session", "validation")
    chosen = evaluations.get("chosen_on")
    lines.append(
        f"These are **{session}** sessions"
        + (
            ": the run's own sessions, on which it chooses its best checkpoint and its "
            "champion. The best of several sessions flatters what it chose; for a test "
            "figure, run a session that chooses nothing (`alignrl evaluate --seeds 0 1 2` "
            "on instruments the run never saw)."
            if session == "validation"
            else "."
        )
    )
    if chosen:
        figure = f"{_counted(chosen)['successes']} aligned"
        lines += [
            "",
            f"The exported checkpoint was kept as the run's best on the {session} session "
            f"at {_session_at(chosen)}: {figure}.",
        ]
    else:
        lines += [
            "",
            f"The exported checkpoint ({chosen_as}) is not one a session of the run kept as "
            "its best.",
        ]
    rows = [_counted(row) for row in evaluations["rows"]]
    lines += [
        "",
        f"From `{evaluations['source']}`, written by {evaluations['produced_by']}. Successes "
        "with their 95 % Wilson interval.",
        "",
        *_table(rows, list(rows[0])),
        "",
        "The same session on the exported weights:",
        "",
        "```",
        evaluations["command"],
        "```",
    ]
    if evaluations["note"]:
        lines += ["", f"Note: {evaluations['note']}."]
    return lines


def _shape(entry: dict[str, Any]) -> str:
    return "(" + ", ".join(str(size) for size in entry["shape"]) + ")"


def render_model_card(card: dict[str, Any]) -> str:
    """model_card.md: the card for a person, from card.json's values."""
    member, training, task = card["member"], card["training"], card["task"]
    evaluations, parity, lineage = card["evaluations"], card["parity"], card["lineage"]
    lines = [
        f"# Model card: {member['id']}",
        "",
        f"An aligner of task `{task['name']}` (knobs: {', '.join(task['knobs'])}): "
        f"{member['algorithm'].upper()} with a {member['architecture']} history encoder, "
        f"exported as {card['export_format']} (`{card['policy_file']}`) on {card['created']} "
        f"by alignrl {card['alignrl_version']} (torch {card['torch_version']}).",
        "",
        f"- source: {card['source']['kind']} `{card['source']['member_file']}` "
        f"({card['source']['chosen_as']})",
        f"- exported with: `{card['command']}`" if card["command"] else "- exported from Python",
        "",
        "## Inputs and outputs",
        "",
        "| name | direction | dtype | shape |",
        "| --- | --- | --- | --- |",
        *(
            f"| `{entry['name']}` | {side} | {entry['dtype']} | {_shape(entry)} |"
            for side in ("inputs", "outputs")
            for entry in card[side]
        ),
        "",
        f"`history` is the env's history, oldest row first, zero padding in front; each row "
        f"is {card['features']} features laid out as "
        + ", ".join(f"{name} [{a}:{b}]" for name, (a, b) in card["feature_layout"].items())
        + f". `action` is in [-1, 1]: one value per knob, then the stop component "
        f"({card['action']['stop_when']} stops). `knob_step` is the knob change asked for, "
        "in the apparatus's units.",
        "",
        f"Normalisation: {card['normalisation']}.",
        "",
        f"Memory: {card['memory']['note']}.",
        "",
        "## Knobs and limits",
        "",
        *_table(card["knobs"], ["name", "low", "high", "max_step"]),
        "",
        f"Episodes last at most {task['episode_steps']} steps; an alignment succeeds at "
        + (
            f"an edge width of {task['success']['absolute_px']:g} px or less."
            if task["success"]["absolute_px"]
            else f"{task['success']['relative']:g} x the best edge width the apparatus reaches."
        ),
        "",
        "## Training",
        "",
        f"- apparatus: `{training['apparatus']}` {json.dumps(training['apparatus_args'])}",
        f"- evaluated on: `{training['eval_apparatus']}` "
        f"{json.dumps(training['eval_apparatus_args'])}",
        f"- settings: {training['settings']}"
        + (f" (`{card['source']['config_file']}`)" if card["source"]["config_file"] else ""),
        f"- task options: {json.dumps(task['options']) if task['options'] else 'none'}",
        f"- transitions seen: {training['steps_seen']}, learner updates: {training['updates']}",
    ]
    if training["env_steps"] is not None:
        lines.append(f"- env steps at the exported checkpoint: {training['env_steps']}")
    if training["league_iteration"] is not None:
        lines.append(f"- league iteration of its best evaluation: {training['league_iteration']}")
    adapted = training["adapted_on"]
    lines += [f"- adapted on: {json.dumps(adapted) if adapted else 'nothing yet'}", ""]
    lines += _evaluations(evaluations, card["source"]["chosen_as"])
    lines += [
        "",
        "## Parity",
        "",
        f"The written file, run by {parity['runtime']}, against {parity['reference']} on "
        f"{parity['histories']} random histories: max |difference| "
        f"{parity['max_abs_difference']:.3g} (action), "
        f"{parity['knob_step_max_abs_difference']:.3g} (knob_step); "
        f"allowed {parity['tolerance']:g} (action) and {parity['knob_step_tolerance']:g} "
        "(knob_step: the same allowance times the largest max_step).",
        "",
        "## Lineage",
        "",
        f"Parent: {lineage['parent'] or 'none (a starting member)'}.",
    ]
    if lineage["copies"]:
        lines += ["", *_table(lineage["copies"], list(lineage["copies"][0]))]
    return "\n".join(lines) + "\n"
