"""A driver module whose import never returns (it waits for a microscope that never answers):
imported only by the test of a bounded import, never by anything else."""

import threading

threading.Event().wait()

from fake_drivers import ParabolicLens as Lens  # noqa: E402  (never reached)

__all__ = ["Lens"]
