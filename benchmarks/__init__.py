"""Measured figures of alignrl (`make bench`); never part of `make test`."""
