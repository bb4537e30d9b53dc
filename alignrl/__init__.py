"""alignrl: reinforcement-learning agents that align electron microscopes.

From Python: `alignrl.api` (train, evaluate, align without YAML; docs/python.md). Importing
alignrl registers the environments with Gymnasium, so that `gymnasium.make("alignrl/Focus-v0")`
builds one; with only gymnasium imported, `gymnasium.make("alignrl:alignrl/Focus-v0")` imports
alignrl itself first (docs/environments.md). Registering imports gymnasium, not the
environments: Gymnasium imports alignrl.envs when an id is first made."""

from __future__ import annotations

import copy
from typing import Any

__version__ = "0.1.0"

# The ids under Gymnasium's registry: id -> (entry point, keyword arguments of its env). The
# entry points are strings, which Gymnasium imports at `make`: nothing of alignrl.envs (a
# layer above this package's own modules) is imported here.
_ANALYTIC_SEM = {"apparatus": "synthetic", "apparatus_args": {"analytic": True}}
GYMNASIUM_ENVS: dict[str, tuple[str, dict[str, Any]]] = {
    "alignrl/Focus-v0": ("alignrl.envs.alignment:AlignmentEnv", {"task": "focus"}),
    "alignrl/FocusFamily-v0": (
        "alignrl.envs.registration:focus_family_env",
        {"apparatus": "family:focus", "apparatus_args": {"analytic": True}, "history": 10},
    ),
    "alignrl/Stigmation-v0": (
        "alignrl.envs.alignment:AlignmentEnv",
        {"task": "stigmation", **_ANALYTIC_SEM},
    ),
    "alignrl/Aperture-v0": (
        "alignrl.envs.alignment:AlignmentEnv",
        {"task": "aperture", **_ANALYTIC_SEM},
    ),
    "alignrl/Column-v0": (
        "alignrl.envs.alignment:AlignmentEnv",
        {"task": "column", **_ANALYTIC_SEM},
    ),
}


def register_gymnasium_envs() -> None:
    """Register every id of GYMNASIUM_ENVS with Gymnasium that is not registered yet."""
    import gymnasium

    for env_id, (entry_point, kwargs) in GYMNASIUM_ENVS.items():
        if env_id not in gymnasium.registry:
            gymnasium.register(id=env_id, entry_point=entry_point, kwargs=copy.deepcopy(kwargs))


register_gymnasium_envs()
