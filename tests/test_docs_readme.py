"""The README keeps true: its quick tour's commands and Python example, and `make run` with
the docs commands that read the league it trains, print what the README shows. The rules
(what runs, how output is compared, what is loose) are those of tests/test_docs_manual.py."""

from __future__ import annotations

import pytest
import test_docs_manual as manual


@pytest.fixture(scope="module")
def sessions(tmp_path_factory: pytest.TempPathFactory) -> dict[str, manual.Session]:
    return manual.make_sessions(tmp_path_factory.mktemp("readme"), manual.README_SESSIONS)


@pytest.mark.parametrize("shown", manual.output_params(readme=True))
def test_each_shown_output_is_what_the_command_prints(
    shown: manual.Shown, sessions: dict[str, manual.Session]
) -> None:
    manual.check_output(shown, sessions)


def test_the_tour_is_run() -> None:
    tour = [shown.command for shown in manual.RUN if shown.page == "README.md"]
    assert "make run" in tour
    assert any(command.startswith("alignrl record") for command in tour)
    assert any(command.startswith("alignrl align --policy champion:") for command in tour)
    assert any(shown.python for shown in manual.RUN if shown.page == "README.md")
