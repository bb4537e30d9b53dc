"""`python -m alignrl.cli ...`: the `alignrl` command."""

import sys

from alignrl.cli.main import main

sys.exit(main())
