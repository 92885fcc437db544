"""On-disk cache of the factory-built CUDA kernels (a job's time to result includes compilation).

The kernels are closures over compile-time constants (precision, rough/smooth, Coulomb, orientation, ...), built
by factories in cuda_kernels.py, cuda_loop.py (with a shape's engine/shapes/<shape>/device.py) and cuda_lists.py.
numba-cuda can cache closures, but it keys them by a pickle of the closure's cell contents, which here holds
other dispatchers whose pickles are not stable across processes, so a fresh process would compile again.
:func:`cache_kernels` gives every kernel of a set a cache keyed instead by (the hash of every engine source the
kernels compile in, engine.jitcache.source_digest; the factory's specialisation key; the kernel's name), stored in Numba's cache
folder (engine/jitcache.py). An edit to any engine source changes the key, so stale machine code is never
loaded. Under the CUDA simulator nothing is cached.
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
    try:
        import numba_cuda
        from numba.cuda.dispatcher import CUDACache, CUDADispatcher
        from numba.cuda.utils import numba_target_override
    except ImportError:  # another numba-cuda layout: compile in every process, as before
        return kernels
    from engine.jitcache import source_digest

    class StableKeyCache(CUDACache):
        def __init__(self, py_func, stable):
            self._stable = stable
            super().__init__(py_func)

        def _index_key(self, sig, codegen):
            k = (sig, codegen.magic_tuple(), numba_cuda.__version__, self._stable)
            return k if self._launch_config_key is None else k + (("launch_config", self._launch_config_key),)

        def load_overload(self, sig, target_context):
            # numba-cuda refreshes the CUDA target (every lowering and typing registry: about 0.3 s of Python
            # under the GIL, once per process) before a load; a kernel is rebuilt from its linked code without
            # the context (_Kernel._rebuild), and any compilation refreshes the context itself
            # (engine/jitcache.py, fast_loads, says the same of the CPU target)
            with numba_target_override(), self._guard_against_spurious_io_errors():
                return self._load_overload(sig, target_context)

    digest = source_digest()
    for name, disp in kernels.items():
        if isinstance(disp, CUDADispatcher) and not disp.targetoptions.get("device", False):
            try:
                disp._cache = StableKeyCache(disp.py_func, (digest, name) + tuple(str(x) for x in key))
            except Exception:  # no cache locator for this file: compile as before
                pass
    return kernels
