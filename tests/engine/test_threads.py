"""The CPU engine's result does not depend on Numba's thread count or on the loop: each thread owns its particles and
sums their pairs in list order, so a run writes the same numbers on one thread in the loop without parallel regions
(this process, tests/conftest.py; the small scenes' loop, engine/loops/cpu.py SERIAL_LOOP_BELOW) and on two threads
in the parallel loop (a child process), bit for bit."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]

_RUN = """
import json, sys
import numba
import engine.backends.ensemble as ensemble
import engine.loops.cpu as cpu
from engine.driver.simulate import run
assert numba.get_num_threads() == 2, numba.get_num_threads()
cpu.SERIAL_LOOP_BELOW = 0                                      # every scene in the parallel loop ...
ensemble.ONE_THREAD_BELOW = 0
ensemble.ThreadChoice.pick = lambda self: max(self.counts)     # ... on both threads
spec = json.loads(sys.argv[1])
run(spec, sys.argv[2])
assert list(cpu._loops) == [(spec.get("shape", "sphere"), True)], list(cpu._loops)
"""


def _datasets(path) -> dict:
    out = {}
    with h5py.File(path) as f:
        f.visititems(lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    return out


@pytest.mark.parametrize("spec", [
    # rough spheres with contacts from the start (phi = 0.1, a thermalisation), three frames
    {"n_particles": 512, "volume_fraction": 0.1, "t_end": 0.01, "thermalization": 0.2, "snapshots": 3,
     "backend": "cpu", "seed": 3},
    {"shape": "ellipsoid", "elongation": 2.0, "n_particles": 256, "volume_fraction": 0.1, "t_end": 0.05,
     "thermalization": 0.1, "snapshots": 3, "backend": "cpu", "seed": 3},
], ids=["spheres", "spheroids"])
def test_one_and_two_threads_write_the_same_numbers(tmp_path, spec):
    import numba

    from engine.loops import cpu
    from engine.driver.simulate import run

    assert numba.get_num_threads() == 1
    run(spec, tmp_path / "one.h5")      # compiles or loads the kernels, which the child then loads from disk
    assert (spec.get("shape", "sphere"), False) in cpu._loops          # a small scene: the loop without regions
    p = subprocess.run([sys.executable, "-c", _RUN, json.dumps(spec), str(tmp_path / "two.h5")], cwd=str(tmp_path),
                       capture_output=True, text=True, timeout=600,
                       env={**os.environ, "NUMBA_NUM_THREADS": "2", "PYTHONPATH": str(ROOT)})
    assert p.returncode == 0, p.stderr[-3000:]
    one, two = _datasets(tmp_path / "one.h5"), _datasets(tmp_path / "two.h5")
    assert one.keys() == two.keys()
    assert "particles/all/position/value" in one
    energy = one["observables/kinetic_energy_translational/value"]
    assert len(energy) > 1 and energy[-1] < 0.99 * energy[0]                 # inelastic collisions took place
    for name, value in one.items():
        assert np.array_equal(value, two[name]), name
