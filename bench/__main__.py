"""``python -m bench <name> [--out DIR] [args]``: see bench/cli.py."""

import sys

from bench.cli import main

sys.exit(main())
