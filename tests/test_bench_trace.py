"""benchmarks/trace.py: alignments step by step on a validation instrument, never on a
held-out one."""

from __future__ import annotations

import pytest

from benchmarks.trace import main, trace


def test_a_trace_walks_each_episode_to_its_end() -> None:
    # focus-v1: the trace is the same for any policy, and focus-v1's episodes take no
    # posterior (focus-v2's take seconds each)
    lines = trace("champion:focus-v1", "val-mid", episodes=2, seed=7)
    starts = [line for line in lines if line.startswith("episode ")]
    ends = [line for line in lines if line.startswith("  left at ")]
    assert [line.split(":")[0] for line in starts] == ["episode 7", "episode 8"]
    assert len(ends) == 2 and all(line.endswith(("aligned", "missed")) for line in ends)
    steps = [line for line in lines if line.startswith("  at ")]
    assert steps and all("-> move" in line and " fit " not in line for line in steps)


def test_a_held_out_or_unknown_instrument_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--policy", "champion:focus-v2", "--instrument", "near-bound"]) == 2
    assert "held out" in capsys.readouterr().err
    assert main(["--policy", "champion:focus-v2", "--instrument", "val-nowhere"]) == 2
    assert "no such validation instrument" in capsys.readouterr().err


def test_images_measure_rendered_frames_instead_of_the_analytic_reading() -> None:
    """focus-v1 (a task without focus-v2's posterior, seconds an episode): the same column
    and start, read two ways."""

    def first_reading(images: bool) -> tuple[str, str]:
        lines = trace("champion:focus-v1", "val-steep", episodes=1, seed=103, images=images)
        setting, reading = next(line for line in lines if line.startswith("  at ")).split(" read ")
        return setting, reading.split(" px")[0]

    (analytic_at, analytic), (imaged_at, imaged) = first_reading(False), first_reading(True)
    assert analytic_at == imaged_at and analytic != imaged
    assert float(imaged) > 0
