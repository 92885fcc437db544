"""On-disk cache of the factory-built CUDA kernels (a job's time to result includes compilation).

The kernels are closures over compile-time constants (precision, rough/smooth, Coulomb, orientation, ...), built
by factories in cuda_kernels.py, cuda_loop.py (with a shape's engine/shapes/<shape>/device.py) and cuda_lists.py.
numba-cuda can cache closures, but it keys them by a pickle of the closure's cell contents, which here holds
other dispatchers whose pickles are not stable across processes, so a fresh process would compile again.
:func:`cache_kernels` gives every kernel of a set a cache keyed instead by (the hash of every engine source the
kernels compile in, engine.numba_support.jitcache.source_digest; the factory's specialisation key; the kernel's name),
stored in Numba's cache folder (engine/numba_support/jitcache.py). An edit to any engine source changes the key, so
stale machine code is never loaded. The cache class and its contact with numba-cuda's internals live in
engine/numba_support/numba_internals.py. Under the CUDA simulator nothing is cached.
"""

from __future__ import annotations

import os

SIM = os.environ.get("NUMBA_ENABLE_CUDASIM") == "1"
#: False: no disk cache, every process compiles (bench/e2e.py ``--off kernel_cache`` sets it, for A/B timings)
ENABLED = True


def cache_kernels(kernels: dict, key: tuple) -> dict:
    """Attach the stable-key disk cache to every (non-device) kernel dispatcher of ``kernels``; returns it."""
    if SIM or not ENABLED:
        return kernels
    from engine.numba_support.jitcache import source_digest
    from engine.numba_support.numba_internals import cuda_stable_key_cache, cuda_stable_key_cache_class

    if cuda_stable_key_cache_class() is None:  # another numba-cuda layout: compile in every process, as before
        return kernels
    digest = source_digest()
    for name, disp in kernels.items():
        cuda_stable_key_cache(disp, (digest, name) + tuple(str(x) for x in key))
    return kernels
