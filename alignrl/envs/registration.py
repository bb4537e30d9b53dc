"""The environments under Gymnasium's registry: `import alignrl` registers the ids
(alignrl.GYMNASIUM_ENVS, alignrl/__init__.py), so that `gymnasium.make("alignrl/Focus-v0")`
builds an AlignmentEnv; `gymnasium.make("alignrl:alignrl/Focus-v0")` needs no import of
alignrl first (Gymnasium imports the module named before the colon). Keyword arguments of
`make` reach AlignmentEnv: `apparatus=`, `apparatus_args=`, `history=`, `complexity=`,
`render_mode=`.

| id | task | apparatus |
| --- | --- | --- |
| `alignrl/Focus-v0` | focus | the default (`csv:default`, the shipped recordings' simulator) |
| `alignrl/FocusFamily-v0` | focus, unit-free | `family:focus`, analytic: a new column per episode |
| `alignrl/Stigmation-v0` | stigmation | `synthetic`, analytic |
| `alignrl/Aperture-v0` | aperture | `synthetic`, analytic |
| `alignrl/Column-v0` | column | `synthetic`, analytic |

This module holds what the ids need beyond AlignmentEnv: the focus family's env, whose task
(readings relative to the episode's first) is an object no registry entry can spell.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from alignrl.envs.alignment import AlignmentEnv
from alignrl.envs.task import get_task

__all__ = ["focus_family_env"]


def focus_family_env(**kwargs: Any) -> AlignmentEnv:
    """The AlignmentEnv of `alignrl/FocusFamily-v0`: the focus task with its readings
    relative to the episode's first (`quality_reference: first`), unless `task=` is given."""
    kwargs.setdefault("task", dataclasses.replace(get_task("focus"), quality_reference="first"))
    return AlignmentEnv(**kwargs)


# What Gymnasium reads of an entry point to check a render_mode (AlignmentEnv's).
focus_family_env.metadata = AlignmentEnv.metadata  # type: ignore[attr-defined]
