"""Host memory for a large scene's copies: pageable against page-locked in place (time to result).

    python -m bench host_memory [--particles 2097152] [--reps 3]

The arrays of one 2M-sphere state (positions, velocities, spins: N x 3 float64 each; orientations N x 4: 218 MB),
already written to (as a start or engine.backends.cuda._touched_empty leaves them). Per repetition, on the GPU's
stream: the upload of fresh arrays as they are (pageable) and registered first (cuMemHostRegister through
numba-cuda's Context.mempin, then unregistered); the download into touched host arrays as they are and registered
first, with the time until the host call returns and until the copy is done. A diagnostic of one step of
engine/backends/cuda.py's frames (CudaEnsemble._host_slot); the end-to-end figure is bench.e2e's.
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--particles", type=int, default=2_097_152)
    ap.add_argument("--reps", type=int, default=3)
    args = ap.parse_args()
    from numba import cuda

    n = args.particles
    ctx = cuda.current_context()
    s = cuda.stream()
    rng = np.random.default_rng(1)

    def arrays():
        return [rng.random((n, 3)), rng.random((n, 3)), rng.random((n, 3)), rng.random((n, 4))]

    def register(arrs):
        return [ctx.mempin(a, a.ctypes.data, a.nbytes, mapped=False) for a in arrs]

    mb = sum(a.nbytes for a in arrays()) / 2 ** 20
    name = cuda.get_current_device().name
    print(f"{name.decode() if isinstance(name, bytes) else name}: {n} particles, {mb:.0f} MiB per state")
    for rep in range(args.reps):
        for locked in (False, True):
            a = arrays()
            t0 = time.perf_counter()
            pins = register(a) if locked else []
            t1 = time.perf_counter()
            d = [cuda.to_device(x, stream=s) for x in a]
            s.synchronize()
            t2 = time.perf_counter()
            pins.clear()                    # their finalizers queue the unregistrations ...
            ctx.deallocations.clear()       # ... done now
            t3 = time.perf_counter()
            print(f"upload   {'locked  ' if locked else 'pageable'}: register {1e3 * (t1 - t0):6.1f} ms, "
                  f"copy {1e3 * (t2 - t1):6.1f} ms, unregister {1e3 * (t3 - t2):6.1f} ms")
        for locked in (False, True):
            h = [np.empty(x.shape) for x in d]
            for x in h:
                x.reshape(-1)[::512] = 0.0          # every page written once
            t0 = time.perf_counter()
            pins = register(h) if locked else []
            t1 = time.perf_counter()
            for x, y in zip(d, h):
                x.copy_to_host(y, stream=s)
            t2 = time.perf_counter()
            s.synchronize()
            t3 = time.perf_counter()
            print(f"download {'locked  ' if locked else 'pageable'}: register {1e3 * (t1 - t0):6.1f} ms, "
                  f"host call returns after {1e3 * (t2 - t1):6.1f} ms, copy done after {1e3 * (t3 - t1):6.1f} ms")
            del pins


if __name__ == "__main__":
    main()
