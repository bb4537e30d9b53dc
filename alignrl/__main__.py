"""`python -m alignrl`: the `alignrl` command (alignrl.cli)."""

from alignrl.cli.main import main

raise SystemExit(main())
