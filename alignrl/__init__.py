"""alignrl: reinforcement-learning agents that align electron microscopes."""

__version__ = "0.1.0"
