"""``python -m bench <name> [--out DIR] [args]``: see bench/__init__.py."""

import sys

from bench import main

sys.exit(main())
