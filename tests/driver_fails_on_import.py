"""A driver module that fails as it is imported, as HOSTILE_IMPORT says: "exit" (SystemExit, as
a vendor SDK's licence check may), "raise" (RuntimeError); anything else imports cleanly."""

import os

from fake_drivers import ParabolicLens as Lens

__all__ = ["Lens"]

if os.environ.get("HOSTILE_IMPORT") == "exit":
    raise SystemExit(0)
if os.environ.get("HOSTILE_IMPORT") == "raise":
    raise RuntimeError("vendor SDK: no licence for this PC")
