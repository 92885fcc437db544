"""Where Numba keeps compiled kernels on disk, keyed by the physics source.

Numba's on-disk cache checks only the file of the cached function itself, so an edit to a physics
function in engine/physics/ would leave the backends running stale machine code. Importing this
module (the backends do, before defining their kernels) points Numba's cache at a folder named by a
hash of every engine source the kernels compile in, unless the user set NUMBA_CACHE_DIR.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numba

_ENGINE = Path(__file__).resolve().parent


def source_digest() -> str:
    h = hashlib.sha1()
    for sub in ("physics", "backends", "shapes"):
        for f in sorted((_ENGINE / sub).glob("*.py")):
            h.update(f.name.encode())
            h.update(f.read_bytes())
    # kernels the backends compile in from engine/ itself
    for name in ("multigrid.py", "cells.py", "scene.py"):
        h.update(name.encode())
        h.update((_ENGINE / name).read_bytes())
    return h.hexdigest()[:16]


def configure() -> None:
    if os.environ.get("NUMBA_CACHE_DIR"):
        return
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    numba.config.CACHE_DIR = str(base / "demq-numba" / source_digest())


configure()
