"""Measured figures of alignrl (`make bench`); never part of `make test`."""

from alignrl.memory import keep_freed_memory

keep_freed_memory()  # as `alignrl` does: the figures are what the commands would take
