"""The CUDA simulator's shared arrays are one per launch in the simulator children (tests/cudasim.py
``atomic_shared_arrays``, called by ``fast_block_polling``).

The stock simulator looks a ``cuda.shared.array`` line up and, when it has no array yet, makes one (``np.empty``) and
stores it: a thread that runs between the two keeps an uninitialised array of its own. The child widens that window
(the simulator's ``np.empty`` sleeps 20 ms, so the block's next threads reach the line meanwhile) and runs the list
build's exclusive scan (engine/loops/cuda_kernels.py ``tile_scan``: its block sums in a shared int64 array) first
with the stock simulator, which must go wrong (else the widening no longer reaches the race and this check proves
nothing), then after ``fast_block_polling()``: every tile's scan and total exact. Without the patch the scan read
another thread's count from its own array and stored a heap address as an int32 offset, as once in CI (the children
of tests/engine/test_lent_scratch_simulator.py: "OverflowError: tid=[7,0,0] ctaid=[0,0,0]: Python integer
140434626053834 out of bounds for int32")."""

from __future__ import annotations

from tests.cudasim import run_children

SCRIPT = r'''
import time, types
import numpy as np
from numba import cuda
from numba.cuda.simulator import kernelapi as KA

class SlowEmpty(types.ModuleType):
    """numpy whose empty() sleeps 20 ms (the simulator's module global ``np``)"""
    def __getattr__(self, name):
        return getattr(np, name)
    @staticmethod
    def empty(*a, **k):
        time.sleep(0.02)
        return np.empty(*a, **k)

KA.np = SlowEmpty("numpy")
from engine.loops.cuda_kernels import grid_kernels

tpb, items, m = 32, 16, 1000
scan = grid_kernels(np.float64, True, tpb)["tile_scan"]
src = np.random.default_rng(3).integers(0, 10, m).astype(np.int32)
tile = tpb * items
nb = (m + tile - 1) // tile
want = np.concatenate([np.cumsum(src[a:a + tile]) - src[a:a + tile] for a in range(0, m, tile)])
sums = np.array([src[a:a + tile].sum() for a in range(0, m, tile)])

def right():
    d_src, dst, bsum = cuda.to_device(src), cuda.device_array(m, np.int32), cuda.device_array(nb, np.int32)
    try:
        scan[nb, tpb](d_src, dst, m, bsum, items)
    except OverflowError:
        return False
    return bool(np.array_equal(dst.copy_to_host(), want) and np.array_equal(bsum.copy_to_host(), sums))

stock = right()
from tests.cudasim import atomic_shared_arrays, fast_block_polling
fast_block_polling()
patched = atomic_shared_arrays()
print("SHARED", stock, patched, all(right() for _ in range(3)))
'''


def test_every_thread_of_a_launch_gets_the_same_shared_array():
    (rc, out, err), = run_children({"shared": ["-c", SCRIPT]}, timeout=300).values()
    assert rc == 0 and "SHARED" in out, out[-3000:] + err[-3000:]
    _, stock, patched, right = out.strip().splitlines()[-1].split()
    assert right == "True", "a thread of a launch kept a shared array of its own"
    if patched == "True":
        assert stock == "False", "the widened window no longer exposes the stock simulator's race"
