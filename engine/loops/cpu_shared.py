"""What the CPU backends of every shape share and none owns: the list-slot layout, checkpoint springs, the
worst-overlap reduction and the device name.

Used by engine/loops/cpu.py (spheres) and engine/shapes/spheroid/cpu_backend.py (ellipsoids), so neither
imports the other's private helpers. Everything ``cache=True`` (see engine/numba_support/jitcache.py).
"""

from __future__ import annotations

import numba
import numpy as np

from engine.numba_support.jitcache import fast_loads  # before any cache=True kernel: keys the disk cache by source

#: Per list slot: tangential spring (3, m), overlap (m) and dashpot force (N) at the previous step.
SLOT = 5


@numba.njit(cache=True)
def worst_overlap(values, idx):
    """(largest value, its particle) over per-chunk maxima ``values`` with their particles ``idx``."""
    k = 0
    for c in range(values.shape[0]):
        if values[c] > values[k]:
            k = c
    return values[k], idx[k]


@numba.njit(cache=True)
def collect_springs(pos, radius, nbr, nn, hist, box, inv_box, half):
    """(pairs (M,2) int64 ids, slots (M,SLOT)) of the list slots in contact (overlap > 0), for checkpoints."""
    n = pos.shape[0]
    total = 0
    for i in range(n):
        total += nn[i]
    pairs = np.empty((total, 2), np.int64)
    springs = np.empty((total, hist.shape[2]), hist.dtype)
    m = 0
    for i in range(n):
        for kk in range(nn[i]):
            if hist[i, kk, 3] > 0:
                pairs[m, 0] = i
                pairs[m, 1] = nbr[i, kk]
                for q in range(hist.shape[2]):
                    springs[m, q] = hist[i, kk, q]
                m += 1
    return pairs[:m].copy(), springs[:m].copy()


@numba.njit(cache=True)
def restore_springs(nbr, nn, hist, pairs, springs):
    """Write checkpointed slots ``springs`` of ``pairs`` (ids) into the matching slots of a fresh list."""
    for p in range(pairs.shape[0]):
        i = pairs[p, 0]
        for kk in range(nn[i]):
            if nbr[i, kk] == pairs[p, 1]:
                for q in range(hist.shape[2]):
                    hist[i, kk, q] = springs[p, q]
                break


def cpu_name() -> str:
    """The CPU model and the Numba thread count, for the result file's device name."""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return f"{line.split(':', 1)[1].strip()} x{numba.get_num_threads()} threads"
    except OSError:
        pass
    import platform

    return f"{platform.processor() or 'cpu'} x{numba.get_num_threads()} threads"


fast_loads(globals())  # their disk-cache loads skip numba's target refresh (engine/numba_support/jitcache.py)
