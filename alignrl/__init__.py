"""alignrl: reinforcement-learning agents that align electron microscopes.

From Python: `alignrl.api` (train, evaluate, align without YAML; docs/python.md); the
environments: `gymnasium.make("alignrl/Focus-v0")` once `alignrl.envs` is imported."""

__version__ = "0.1.0"
