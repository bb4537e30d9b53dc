"""Alignment environments: tasks, rewards, curriculum, AlignmentEnv (Gymnasium), DuelEnv
(PettingZoo AEC) and DuelBatch (the duels the league plays, stepped together), and a
vectorized form over many microscopes. The ids under Gymnasium's registry (alignrl/Focus-v0,
...) are registered by `import alignrl` (alignrl/__init__.py, alignrl/envs/registration.py)."""

from alignrl.envs.alignment import AlignmentEnv
from alignrl.envs.curriculum import Curriculum
from alignrl.envs.duel import DuelBatch, DuelEnv
from alignrl.envs.task import TASKS, SuccessRule, Task, get_task
from alignrl.envs.vector import VectorAlignmentEnv, make_apparatus_copies

__all__ = [
    "TASKS",
    "AlignmentEnv",
    "Curriculum",
    "DuelBatch",
    "DuelEnv",
    "SuccessRule",
    "Task",
    "VectorAlignmentEnv",
    "get_task",
    "make_apparatus_copies",
]
