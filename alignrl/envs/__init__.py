"""Alignment environments: tasks, rewards, curriculum, AlignmentEnv (Gymnasium), DuelEnv
(PettingZoo AEC) and DuelBatch (the duels the league plays, stepped together), and a
vectorized form over many microscopes; the envs registered with Gymnasium (alignrl/Focus-v0,
...)."""

from alignrl.envs.alignment import AlignmentEnv
from alignrl.envs.curriculum import Curriculum
from alignrl.envs.duel import DuelBatch, DuelEnv
from alignrl.envs.registration import register_envs
from alignrl.envs.task import TASKS, SuccessRule, Task, get_task
from alignrl.envs.vector import VectorAlignmentEnv, make_apparatus_copies

register_envs()  # gymnasium.make("alignrl/Focus-v0") and the rest: alignrl/envs/registration.py

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
