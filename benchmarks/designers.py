"""Does the adversary earn its place? Issue 22's experiment, at equal aligner env steps:

    python -m benchmarks.designers --out runs/designers --seeds 0 1 2 --aligner-steps 15000

Three ways to train one SAC aligner on the focus family (alignrl/apparatus/families/focus.yaml,
analytic readings, unit-free observations and log-ratio rewards), each at every seed:
* uniform: trained alone, the family drawn uniformly every episode (domain randomization:
  `alignrl train`);
* improvement: a league of that aligner and a designing misaligner paid the seed's
  improvement payoff (what the aligner did not recover);
* regret: the same league, the designer paid the aligner's regret against the hyperbola fit
  on a twin of the column (alignrl.envs.design).
Checkpoints are chosen on the validation instruments (set:validation), never on the held-out
ones. Each chosen aligner is then judged on the held-out set (7 instruments x --scenarios,
seed 0, the same sessions for every aligner and for the hyperbola fit): successes with a
95 % Wilson interval, median and p90 acquisitions, the mean of the worst 10 % of final width
/ best width (a failed verification counts as the no-edges width), and exploitability: a
fresh regret-paid designer trained for --exploit-matches matches against the frozen aligner
(alignrl.league.exploit; one per --exploit-seeds), the mean regret the strongest of them reaches
in matches it did not learn from (log-ratio units: 1.0 is a final width e = 2.7 times the
hyperbola fit's).

Runs go to OUT/runs/ (OUT/configs/ the files they were made from, OUT/logs/ their output),
--jobs at a time, each niced; a run that finished (OUT/done/NAME) is not run again, and a
judged run's OUT/judged/NAME.json is read instead of judged again. OUT/designs.png shows
where the designers put their columns early and late in training (does the improvement
payoff collapse onto columns nobody can align?). The table goes to stdout and OUT/table.md.
Not a test: tens of minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from alignrl.league.exploit import DESIGNER as EXPLOIT_DESIGNER
from alignrl.league.logs import DESIGN_COLUMNS

CONDITIONS = ("uniform", "improvement", "regret")
TASK_OPTIONS = {
    "success_bonus": 5.0,
    "bonus_relative": 1.10,
    "verify_final": True,
    "quality_reference": "first",
    "final_reward_form": "log_ratio",
}
LEARNER = {
    "algorithm": "sac",
    "encoder": "mlp",
    "encoder_kwargs": {"hidden": [256]},
    "hidden": [256, 256],
    "batch_size": 256,
    "learning_starts": 1000,
    "random_steps": 2000,
    "buffer_size": 200000,
}
# The designers are those of alignrl.league.exploit: one SAC, as the default roster's.
DESIGNER = EXPLOIT_DESIGNER.model_dump(mode="json", exclude_unset=True)
COMMON = {
    "apparatus": "family:focus",
    "apparatus_args": {"analytic": True},
    "eval_apparatus": "set:validation",
    "eval_apparatus_args": {"analytic": True},
    "task": "focus",
    "task_options": TASK_OPTIONS,
    "history": 10,
    "envs": 8,
    "threads": 1,
}
EVALUATIONS = 4  # validation sessions per run, the last at the end


def run_name(condition: str, seed: int) -> str:
    return f"designers-{condition}-s{seed}"


def write_config(out: Path, condition: str, seed: int, steps: int) -> tuple[Path, str]:
    """The experiment file of one run and the verb that runs it."""
    folder = out / "configs"
    folder.mkdir(parents=True, exist_ok=True)
    name = run_name(condition, seed)
    every = max(1, steps // EVALUATIONS)
    if condition == "uniform":
        data = {
            "name": name,
            "seed": seed,
            **COMMON,
            "learner": LEARNER,
            "budget": {
                "env_steps": steps,
                "eval_every": every,
                "eval_scenarios": 100,
                "checkpoint_every": every,
            },
        }
        path = folder / f"{name}.yaml"
        path.write_text(yaml.safe_dump(data, sort_keys=False))
        return path, "train"
    for team, member, learner in (
        ("aligner", "aligner-sac", LEARNER),
        ("misaligner", "designer-sac", DESIGNER),
    ):
        roster = {"team": team, "members": [{"id": member, "learner": learner}]}
        (folder / f"{name}-{team}s.yaml").write_text(yaml.safe_dump(roster, sort_keys=False))
    matches = 32
    iterations = math.ceil(steps / (matches * 3))  # more than enough: aligner_steps stops it
    data = {
        "name": name,
        "seed": seed,
        **COMMON,
        "design": True,
        "payoff": condition,
        "reference": "hyperbola",
        "aligners": str(folder / f"{name}-aligners.yaml"),
        "misaligners": str(folder / f"{name}-misaligners.yaml"),
        "schedule": {
            "iterations": iterations,
            "aligner_steps": steps,
            "matches": matches,
            "snapshot_every": 20,
            "pbt_every": iterations + 1,  # one member a team: nothing to copy
            "evaluate_every": max(1, steps // (EVALUATIONS * matches * 5)),
            "eval_scenarios": 100,
            "checkpoint_every": 10,
            "keep_best": 1,
        },
        "pbt": {"enabled": False},
    }
    path = folder / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path, "league run"


def launch(out: Path, condition: str, seed: int, steps: int) -> tuple[str, float]:
    """Run one configuration to its end (unless it is complete); (name, seconds)."""
    path, verb = write_config(out, condition, seed, steps)
    name = run_name(condition, seed)
    run, marker = out / "runs" / name, out / "done" / name
    if marker.exists():
        return name, 0.0
    logs = out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    command = [
        "nice",
        "-n",
        "5",
        sys.executable,
        "-m",
        "alignrl.cli",
        *verb.split(),
        str(path),
        "--runs-dir",
        str(out / "runs"),
        "--quiet",
    ]
    if run.exists() and verb == "train":
        command = [*command[:5], "train", "--resume", str(run), "--quiet"]
    elif run.exists():
        command = [*command[:5], "league", "resume", str(run), "--quiet"]
    began = time.perf_counter()
    with (logs / f"{name}.log").open("a") as log:
        done = subprocess.run(
            command,
            stdout=log,
            stderr=subprocess.STDOUT,
            check=False,
            env={**os.environ, "OMP_NUM_THREADS": "1"},
        )
    if done.returncode != 0:
        raise RuntimeError(f"{name}: exit {done.returncode}; see {logs / f'{name}.log'}")
    marker.parent.mkdir(parents=True, exist_ok=True)
    marker.write_text(" ".join(command) + "\n")
    return name, time.perf_counter() - began


# --- judging ----------------------------------------------------------------------------


def wilson(successes: int, total: int, z: float = 1.96) -> tuple[float, float]:
    """The 95 % Wilson score interval of a success share."""
    share = successes / total
    centre = (share + z * z / (2 * total)) / (1 + z * z / total)
    half = z * math.sqrt(share * (1 - share) / total + z * z / (4 * total * total))
    return max(0.0, centre - half / (1 + z * z / total)), min(
        1.0, centre + half / (1 + z * z / total)
    )


def set_figures(result: Any) -> dict[str, Any]:
    """Successes, interval, acquisitions and the worst 10 % of final / best width of a set."""
    from alignrl.envs.task import get_task

    task = get_task("focus")
    ratios = []
    for session in result.sessions:
        for record in session.records:
            best = record.threshold_px / task.success.relative
            width = record.final_width_px if record.final_width_px is not None else task.no_edges_px
            ratios.append(width / best)
    ratios = np.sort(np.asarray(ratios))
    worst = ratios[-max(1, len(ratios) // 10) :]
    low, high = wilson(result.successes, result.alignments)
    return {
        "successes": result.successes,
        "alignments": result.alignments,
        "interval": [round(low, 4), round(high, 4)],
        "median_acquisitions": result.median_acquisitions,
        "p90_acquisitions": result.p90_acquisitions,
        "worst_decile_ratio": round(float(np.mean(worst)), 3),
        "per_instrument": {
            name: session.successes
            for name, session in zip(result.instruments, result.sessions, strict=True)
        },
    }


def exploit_config(seed: int) -> Any:
    from alignrl.league.config import parse_league

    return parse_league(
        {
            "name": "exploit",
            "seed": seed,
            **COMMON,
            "design": True,
            "payoff": "regret",
            "reference": "hyperbola",
        }
    )


def judge(out: Path, name: str, args: argparse.Namespace) -> dict[str, Any]:
    """One run's chosen aligner on the held-out set (cached)."""
    from alignrl.deploy.policy import load_deployable
    from alignrl.envs.task import get_task
    from alignrl.evaluation.controllers import PolicyController
    from alignrl.evaluation.instrument_sets import run_set

    cached = out / "judged" / f"{name}.json"
    if cached.exists():
        return json.loads(cached.read_text())
    run = out / "runs" / name
    policy = load_deployable(str(run))
    controller = PolicyController(
        name=name, act=policy.act, task=policy.task, history=policy.history
    )
    began = time.perf_counter()
    result = run_set(
        controller,
        "heldout",
        get_task("focus"),
        scenarios=args.scenarios,
        seed=0,
        analytic=not args.images,
    )
    figures = {"name": name, **set_figures(result)}
    figures["seconds"] = round(time.perf_counter() - began, 1)
    cached.parent.mkdir(parents=True, exist_ok=True)
    cached.write_text(json.dumps(figures, indent=1))
    print(f"{name}: {figures['successes']}/{figures['alignments']} held-out", file=sys.stderr)
    return figures


def exploitability(out: Path, name: str, seed: int, args: argparse.Namespace) -> dict[str, Any]:
    """What a fresh regret-paid designer (its own seed) finds against one run's chosen
    aligner in --exploit-matches matches (cached per budget and seed)."""
    from alignrl.league.exploit import exploit
    from alignrl.runs.sources import resolve_source

    cached = out / "exploit" / f"{name}-m{args.exploit_matches}-s{seed}.json"
    if cached.exists():
        return json.loads(cached.read_text())
    began = time.perf_counter()
    agent = resolve_source(str(out / "runs" / name)).agent
    found = exploit(
        agent, exploit_config(seed), args.exploit_matches, evaluate=args.exploit_evaluate, seed=seed
    )
    figures = {
        "name": name,
        "seed": seed,
        "matches": args.exploit_matches,
        "final_regret": round(found.mean_regret, 4),
        "curve": [[m, round(v, 4)] for m, v in found.curve],
        "seconds": round(time.perf_counter() - began, 1),
    }
    cached.parent.mkdir(parents=True, exist_ok=True)
    cached.write_text(json.dumps(figures, indent=1))
    print(
        f"{name}: exploitability {figures['final_regret']:.3f} (designer seed {seed})",
        file=sys.stderr,
    )
    return figures


def hyperbola(out: Path, args: argparse.Namespace) -> dict[str, Any]:
    from alignrl.envs.task import get_task
    from alignrl.evaluation.baselines import get_baseline
    from alignrl.evaluation.instrument_sets import run_set

    cached = out / "judged" / "hyperbola.json"
    if cached.exists():
        return json.loads(cached.read_text())
    result = run_set(
        get_baseline("hyperbola"),
        "heldout",
        get_task("focus"),
        scenarios=args.scenarios,
        seed=0,
        analytic=not args.images,
    )
    figures = {"name": "hyperbola", **set_figures(result)}
    cached.parent.mkdir(parents=True, exist_ok=True)
    cached.write_text(json.dumps(figures, indent=1))
    return figures


def aligner_steps(out: Path, name: str) -> int:
    """Steps the judged run's aligner took (its last checkpoint)."""
    from alignrl.runs.sources import resolve_source

    return int(resolve_source(str(out / "runs" / name)).agent.steps_seen)


# --- the table and the designs' histogram ---------------------------------------------


def table(rows: dict[str, list[dict[str, Any]]], reference: dict[str, Any]) -> list[str]:
    lines = [
        "| training | seeds | held-out successes (95 % interval) | median / p90 acquisitions "
        "| worst 10 % final/best width | exploitability (regret of the strongest designer) |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for condition, judged in rows.items():
        if not judged:
            continue
        successes = sum(r["successes"] for r in judged)
        total = sum(r["alignments"] for r in judged)
        low, high = wilson(successes, total)
        per_seed = ", ".join(str(r["successes"]) for r in judged)
        lines.append(
            f"| {condition} | {len(judged)} | {successes}/{total} ({100 * low:.0f}-"
            f"{100 * high:.0f} %; per seed {per_seed}/{judged[0]['alignments']}) | "
            f"{np.mean([r['median_acquisitions'] for r in judged]):.1f} / "
            f"{np.mean([r['p90_acquisitions'] for r in judged]):.1f} | "
            f"{np.mean([r['worst_decile_ratio'] for r in judged]):.2f} | "
            f"{np.mean([r['exploitability'] for r in judged]):.3f} (per seed "
            f"{', '.join(format(r['exploitability'], '.2f') for r in judged)}) |"
        )
    low, high = wilson(reference["successes"], reference["alignments"])
    lines.append(
        f"| hyperbola fit | - | {reference['successes']}/{reference['alignments']} "
        f"({100 * low:.0f}-{100 * high:.0f} %) | {reference['median_acquisitions']:g} / "
        f"{reference['p90_acquisitions']:g} | {reference['worst_decile_ratio']:.2f} | 0 (the "
        "reference) |"
    )
    return lines


def plot_designs(out: Path, names: list[str]) -> Path | None:
    """Histograms of the designers' columns: first and last fifth of each league's matches,
    per design parameter (fractions of the family's box), pooled over seeds per payoff."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import pandas as pd

    frames = {}
    for name in names:
        path = out / "runs" / name / "metrics" / "designs.csv"
        if path.exists():
            frame = pd.read_csv(path)
            frame["payoff"] = name.split("-")[1]
            frames[name] = frame
    if not frames:
        return None
    every = pd.concat(frames.values())
    parameters = [c for c in every.columns if c not in (*DESIGN_COLUMNS, "payoff")]
    columns = 5
    rows = math.ceil(len(parameters) / columns)
    figure, axes = plt.subplots(rows, columns, figsize=(3.2 * columns, 2.4 * rows), squeeze=False)
    bins = np.linspace(0, 1, 11)
    for axis, parameter in zip(axes.flat, parameters, strict=False):
        for payoff, colour in (("improvement", "tab:red"), ("regret", "tab:blue")):
            chosen = every[every.payoff == payoff]
            if chosen.empty:
                continue
            last = chosen.iteration.max()
            for share, style, label in (
                (chosen.iteration <= 0.2 * last, ":", "first fifth"),
                (chosen.iteration >= 0.8 * last, "-", "last fifth"),
            ):
                values = chosen[share][parameter]
                counts, _ = np.histogram(values, bins)
                shares = counts / max(1, counts.sum())
                axis.step(
                    bins,
                    np.append(shares, shares[-1]),
                    where="post",
                    color=colour,
                    linestyle=style,
                    label=f"{payoff}, {label}",
                )
        axis.set_title(parameter, fontsize=9)
        axis.set_xlim(0, 1)
    for axis in list(axes.flat)[len(parameters) :]:
        axis.axis("off")
    axes.flat[0].legend(fontsize=6)
    figure.suptitle("Where the designers put the column (fraction of the family's range)")
    figure.tight_layout()
    path = out / "designs.png"
    figure.savefig(path, dpi=90)
    plt.close(figure)
    return path


def design_summary(out: Path, names: list[str]) -> list[str]:
    """Per league: the aligner's success on the designer's columns early and late."""
    import pandas as pd

    lines = []
    for name in names:
        path = out / "runs" / name / "metrics" / "designs.csv"
        if not path.exists():
            continue
        frame = pd.read_csv(path)
        last = frame.iteration.max()
        early = frame[frame.iteration <= 0.2 * last]
        late = frame[frame.iteration >= 0.8 * last]
        lines.append(
            f"- {name}: the aligner met the spec on {100 * early.success.mean():.0f} % of the "
            f"designer's columns in the first fifth, {100 * late.success.mean():.0f} % in the "
            f"last; mean aligner payoff {early.aligner_payoff.mean():.2f} -> "
            f"{late.aligner_payoff.mean():.2f}"
        )
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("runs/designers"))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--conditions", nargs="+", choices=CONDITIONS, default=list(CONDITIONS))
    parser.add_argument("--aligner-steps", type=int, default=15000)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--scenarios", type=int, default=100, help="per held-out instrument")
    parser.add_argument("--images", action="store_true", help="judge on images (slow)")
    parser.add_argument("--exploit-matches", type=int, default=1024)
    parser.add_argument("--exploit-evaluate", type=int, default=256)
    parser.add_argument(
        "--exploit-seeds",
        type=int,
        nargs="+",
        default=[100],
        help="one fresh designer per seed; the strongest of them counts",
    )
    args = parser.parse_args(argv)
    pairs = [(c, s) for s in args.seeds for c in args.conditions]
    began = time.perf_counter()
    with ThreadPoolExecutor(args.jobs) as pool:
        futures = [pool.submit(launch, args.out, c, s, args.aligner_steps) for c, s in pairs]
        for done, future in enumerate(futures, 1):
            name, seconds = future.result()
            elapsed = time.perf_counter() - began
            print(
                f"[{done}/{len(pairs)}] {name} done ({seconds:.0f} s; {elapsed:.0f} s in all, "
                f"about {elapsed / done * (len(pairs) - done):.0f} s left)",
                file=sys.stderr,
            )
    rows: dict[str, list[dict[str, Any]]] = {c: [] for c in args.conditions}
    with ThreadPoolExecutor(args.jobs) as pool:
        judged = list(pool.map(lambda pair: judge(args.out, run_name(*pair), args), pairs))
        tries = [(run_name(*pair), seed) for pair in pairs for seed in args.exploit_seeds]
        found = list(pool.map(lambda t: exploitability(args.out, *t, args), tries))
    for (condition, _), figures in zip(pairs, judged, strict=True):
        mine = [f["final_regret"] for f in found if f["name"] == figures["name"]]
        rows[condition].append({**figures, "exploitability": max(mine)})
    reference = hyperbola(args.out, args)
    names = [run_name(c, s) for c, s in pairs]
    steps = {name: aligner_steps(args.out, name) for name in names}
    lines = [
        "Aligner steps per run (the kept checkpoint's): "
        + ", ".join(f"{n.removeprefix('designers-')} {v}" for n, v in steps.items()),
        "",
        *table(rows, reference),
        "",
        *design_summary(args.out, [n for n in names if "uniform" not in n]),
    ]
    figure = plot_designs(args.out, [n for n in names if "uniform" not in n])
    if figure:
        lines += ["", f"designs: {figure}"]
    text = "\n".join(lines)
    print(text)
    (args.out / "table.md").write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
