"""engine/backends/ensemble.py ``scene_threads``: a CPU scene below ONE_THREAD_BELOW particles runs on one Numba
thread, a larger one on all of them, and the count is restored afterwards (tests run Numba on one thread, so the
check runs in a child with two)."""

from __future__ import annotations

import os
import subprocess
import sys

SCRIPT = r'''
import numba
from engine.backends.ensemble import ONE_THREAD_BELOW, scene_threads
assert numba.get_num_threads() == 2
with scene_threads(ONE_THREAD_BELOW - 1) as k:
    assert k == 1 and numba.get_num_threads() == 1
assert numba.get_num_threads() == 2
with scene_threads(ONE_THREAD_BELOW) as k:
    assert k == 2 and numba.get_num_threads() == 2
try:
    with scene_threads(64):
        raise RuntimeError("a failing step")
except RuntimeError:
    pass
assert numba.get_num_threads() == 2
print("THREADS-OK")
'''


def test_small_scenes_run_on_one_thread_and_the_count_is_restored():
    env = dict(os.environ, NUMBA_NUM_THREADS="2")
    r = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and "THREADS-OK" in r.stdout, r.stdout[-2000:] + r.stderr[-2000:]
