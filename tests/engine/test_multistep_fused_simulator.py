"""The fused many-steps CUDA kernel (engine/loops/cuda_loop.py ``run_steps_fused``: a step's forces and the next
kick-drift in one pass, one grid sync a step, positions, velocities and spins double-buffered) under the CUDA
simulator: the trajectory of the two-pass kernel ``run_steps`` bit for bit, through launches that end at records
and at list rebuilds in either half of the double buffer."""

from __future__ import annotations

import pytest

from tests.cudasim import run_children

SCRIPT = r'''
import sys
from tests.cudasim import fast_block_polling
fast_block_polling()
import tempfile
from pathlib import Path
import h5py, numpy as np
import engine.loops.cuda_stepping as st
from engine import run
from engine.shapes.sphere.cuda_backend import CudaEnsemble
from engine.setup.spec import SimulationSpec

swaps = []
orig = CudaEnsemble._swap_multistep
def spy(self):
    swaps.append(self.steps_done)
    return orig(self)
CudaEnsemble._swap_multistep = spy
launches = []
orig_run = st.TimeLoop._run_steps
def spy_run(self, nmax, first, step0, grid=None, n=None, thr=None, status=None):
    if n is None:
        launches.append(self._multistep_fused())
    return orig_run(self, nmax, first, step0, grid=grid, n=n, thr=thr, status=status)
st.TimeLoop._run_steps = spy_run

e_t, friction = float(sys.argv[1]), (None if sys.argv[2] == "none" else float(sys.argv[2]))
out = {}
for fused in (True, False):
    st.MULTISTEP_FUSED = fused
    swaps.clear()
    launches.clear()
    # a thin skin (a rebuild every few tens of steps) and three records: launches end at both
    spec = SimulationSpec(n_particles=32, volume_fraction=0.1, e_n=0.7, e_t=e_t, friction=friction,
                          thermalization=0.0, snapshots=1, backend="cuda", t_end=1.5e-3, output_interval=5e-4,
                          velocity_rms=8.0, verlet_skin=0.1)
    s = run(spec, Path(tempfile.mkdtemp()) / "x.h5", backend="cuda")
    with h5py.File(s.output) as f:
        p = "particles/all/"
        out[fused] = ([f[p + e + "/value"][-1] for e in ("position", "velocity", "angular_velocity", "orientation")],
                      [f["observables/" + o + "/value"][:] for o in ("kinetic_energy_translational",
                                                                     "kinetic_energy_rotational", "contacts")],
                      int(f["parameters"].attrs["neighbour_builds"]), list(swaps), list(launches))
state, obs, builds, swaps_f, launches_f = out[True]
state0, obs0, builds0, swaps0, launches0 = out[False]
assert launches_f and all(launches_f) and not any(launches0), (launches_f, launches0)
assert swaps0 == [] and len(swaps_f) >= 2, swaps_f
assert builds == builds0 and builds >= 3, (builds, builds0)
assert all(np.array_equal(a, b) for a, b in zip(state, state0)), "the fused kernel changed the trajectory"
assert all(np.array_equal(a, b) for a, b in zip(obs, obs0)), "the fused kernel changed the observables"
print("FUSED-OK", len(launches_f), builds, len(swaps_f))
'''


@pytest.mark.parametrize("e_t, friction", [(0.5, "0.3"), (-1.0, "none")], ids=["rough-coulomb", "smooth"])
def test_the_fused_many_steps_kernel_keeps_the_two_pass_trajectory(e_t, friction):
    rc, out, err = run_children({"run": ["-c", SCRIPT, str(e_t), friction]}, timeout=900)["run"]
    assert rc == 0 and "FUSED-OK" in out, out[-3000:] + err[-3000:]
