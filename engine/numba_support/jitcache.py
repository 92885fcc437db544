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

from engine.numba_support.numba_import import coverage_hidden
from engine.numba_support.numba_internals import make_fast_loading, stable_key_cache

with coverage_hidden():
    import numba

_ENGINE = Path(__file__).resolve().parent.parent


def _hash_sources() -> str:
    h = hashlib.sha1()
    for sub in ("physics", "loops", "backends", "shapes", "neighbours"):
        for f in sorted((_ENGINE / sub).rglob("*.py")):          # shape packages are sub-folders
            h.update(str(f.relative_to(_ENGINE)).encode())
            h.update(f.read_bytes())
    # kernels the backends compile in from engine/ itself
    for name in ("setup/scene.py", "setup/cell_rsa.py", "setup/counter_rng.py"):
        h.update(name.encode())
        h.update((_ENGINE / name).read_bytes())
    return h.hexdigest()[:16]


#: the digest of the engine sources as this module's import found them (source_digest)
_DIGEST = _ENGINE_DIGEST = _hash_sources()
#: package folder -> hash of its sources, for the shape packages registered from outside engine/ (include_sources)
_PLUGINS: dict = {}


def source_digest() -> str:
    """A hash of every engine source the compiled code is built from, taken once, when this module is imported
    (with the engine's own imports). It names the code this process runs: a hash taken later, after the files
    changed on disk, would file this process's machine code under sources it was not compiled from, where a new
    process would load it. (Hashing again also cost about 1 ms of Python, and up to 16 ms of waiting for the GIL
    measured on the GPU start-up thread, for every kernel set a GPU job makes.)"""
    return _DIGEST


def include_sources(package_dir) -> None:
    """Add the sources of a shape package kept outside the hashed folders (engine.shapes.register) to
    :func:`source_digest`, so that machine code compiled from it is never loaded after it changed. Hashed when the
    package is registered (the code this process compiles from then on is that source); kernels compiled later in
    this process are filed under the new digest, which depends only on the set of packages included (registering
    the same package again changes nothing)."""
    root = Path(package_dir).resolve()
    h = hashlib.sha1()
    for f in sorted(root.rglob("*.py")):
        h.update(str(f.relative_to(root)).encode())
        h.update(f.read_bytes())
    _PLUGINS[str(root)] = h.hexdigest()
    _combine()


def exclude_sources(package_dir) -> None:
    """Undo :func:`include_sources` for a package that is unregistered (engine.shapes.unregister)."""
    _PLUGINS.pop(str(Path(package_dir).resolve()), None)
    _combine()


def _combine() -> None:
    global _DIGEST
    if not _PLUGINS:
        _DIGEST = _ENGINE_DIGEST
        return
    combined = hashlib.sha1(_ENGINE_DIGEST.encode())
    for key in sorted(_PLUGINS):
        combined.update(_PLUGINS[key].encode())
    _DIGEST = combined.hexdigest()[:16]


def configure() -> None:
    if os.environ.get("NUMBA_CACHE_DIR"):
        return
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    numba.config.CACHE_DIR = str(base / "demq-numba" / source_digest())


configure()


def cache_closure(dispatcher, key: tuple):
    """Give a factory-built njit closure an on-disk cache keyed by (the engine source digest, ``key``).

    Numba keys a cached closure by a pickle of its cell contents; cells holding other dispatchers pickle
    differently in every process, so a fresh process would compile again (the same problem
    engine/loops/cuda_cache.py solves for the CUDA kernels). The digest covers every source the closure
    compiles in, so an edit never loads stale machine code. Where the cache cannot be attached (no cache locator
    for the file, e.g. a read-only install; another numba) the closure compiles as before. Returns ``dispatcher``.
    """
    stable_key_cache(dispatcher, (source_digest(),) + tuple(str(k) for k in key))
    return dispatcher


def fast_loads(namespace: dict) -> None:
    """Make every ``cache=True`` njit dispatcher in ``namespace`` (a module's ``globals()``) load its disk cache
    without refreshing numba's CPU target first; call it at the bottom of a module that defines them.

    numba refreshes the target context before every cache load "to ensure it is initialized". On the CPU target
    that installs every lowering registry and imports scipy.linalg for numba's BLAS check: 0.25-0.4 s of Python,
    once per process, under the GIL (part of a fresh process's time to result). A load needs only the symbols
    its linked machine code calls (engine/numba_support/numba_internals.py, FastLoadCache). Any compilation (a cache
    miss, a new signature) still refreshes the context itself. A dispatcher whose cache is not numba's plain
    FunctionCache is left alone.
    """
    for obj in list(namespace.values()):
        make_fast_loading(obj)
