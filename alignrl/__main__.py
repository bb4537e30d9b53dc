"""`python -m alignrl`: the `alignrl` command (alignrl.cli).

Run from a folder that holds another folder named `alignrl` (the parent of a checkout cloned
as `alignrl/`, say), Python finds that folder first on its path, where the working directory
comes before the installed package, and imports it as a namespace package in this one's
place: the command would then fail on its first import ("cannot import name '__version__'
from 'alignrl' (unknown location)"). This file is the installed package's, so it sets that
right before anything else is imported: the package it belongs to is the `alignrl` the
command runs, as `alignrl` itself (the console script) would run it.
"""

import sys
from pathlib import Path

_PACKAGE = Path(__file__).resolve().parent


def _this_package() -> None:
    """Make `alignrl` the package this file belongs to where a folder of that name (no
    package: no __init__.py) was imported in its place."""
    imported = sys.modules.get("alignrl")
    found = getattr(imported, "__file__", None)
    if found is not None and Path(found).resolve().parent == _PACKAGE:
        return
    for name in [name for name in sys.modules if name == "alignrl" or name.startswith("alignrl.")]:
        del sys.modules[name]
    sys.path.insert(0, str(_PACKAGE.parent))


_this_package()

from alignrl.cli.main import main  # noqa: E402 (after the package is the right one)

raise SystemExit(main())
