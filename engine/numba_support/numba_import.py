"""numba's first import in a process without the ``coverage`` package's (part of a job's start-up).

numba (numba.misc.coverage_support) imports ``coverage`` whenever it is installed, to report compiled lines to a
running coverage measurement, which it does only when NUMBA_JIT_COVERAGE=1 (numba.core.config.JIT_COVERAGE).
That import took 70 ms of a fresh GPU job's start-up on the H200 host (``python3 -X importtime``), for nothing.
:func:`coverage_hidden` hides ``coverage`` from the imports inside it when numba will not use it (NUMBA_JIT_COVERAGE
unset or 0) and nothing has imported it yet; a later ``import coverage`` finds it as usual.
"""

from __future__ import annotations

import os
import sys
from contextlib import contextmanager


@contextmanager
def coverage_hidden():
    """Imports inside this block do not import ``coverage`` (see the module docstring)."""
    hide = "coverage" not in sys.modules and os.environ.get("NUMBA_JIT_COVERAGE", "0") in ("", "0")
    if hide:
        sys.modules["coverage"] = None          # `import coverage` raises ImportError, as if it were not installed
    try:
        yield
    finally:
        if hide and "coverage" in sys.modules and sys.modules["coverage"] is None:
            del sys.modules["coverage"]
