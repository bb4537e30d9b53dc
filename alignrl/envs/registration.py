"""The environments under Gymnasium's registry, so that `gymnasium.make("alignrl/Focus-v0")`
builds an AlignmentEnv once alignrl is imported (`import alignrl.envs`, or anything that
imports it). Keyword arguments of `make` reach AlignmentEnv: `apparatus=`, `apparatus_args=`,
`history=`, `complexity=`.

| id | task | apparatus |
| --- | --- | --- |
| `alignrl/Focus-v0` | focus | the default (the shipped recordings' simulator) |
| `alignrl/FocusFamily-v0` | focus, unit-free | `family:focus`, analytic: a new column per episode |
| `alignrl/Stigmation-v0` | stigmation | the default |
| `alignrl/Aperture-v0` | aperture | the default |
| `alignrl/Column-v0` | column | the default |
"""

from __future__ import annotations

import copy
import dataclasses
from typing import Any

import gymnasium

from alignrl.envs.task import get_task

__all__ = ["ENV_IDS", "register_envs"]

ENTRY_POINT = "alignrl.envs.alignment:AlignmentEnv"


def _family_task() -> Any:
    return dataclasses.replace(get_task("focus"), quality_reference="first")


ANALYTIC_SEM = {"apparatus": "synthetic", "apparatus_args": {"analytic": True}}
ENV_IDS: dict[str, dict[str, Any]] = {
    "alignrl/Focus-v0": {"task": "focus"},
    "alignrl/Stigmation-v0": {"task": "stigmation", **ANALYTIC_SEM},
    "alignrl/Aperture-v0": {"task": "aperture", **ANALYTIC_SEM},
    "alignrl/Column-v0": {"task": "column", **ANALYTIC_SEM},
}


def register_envs() -> None:
    """Register every id of ENV_IDS (and the family's) with Gymnasium, once."""
    for env_id, kwargs in ENV_IDS.items():
        if env_id not in gymnasium.registry:
            gymnasium.register(id=env_id, entry_point=ENTRY_POINT, kwargs=copy.deepcopy(kwargs))
    family = "alignrl/FocusFamily-v0"
    if family not in gymnasium.registry:
        gymnasium.register(
            id=family,
            entry_point=ENTRY_POINT,
            kwargs={
                "task": _family_task(),
                "apparatus": "family:focus",
                "apparatus_args": {"analytic": True},
                "history": 10,
            },
        )
