"""The per-phase CUDA loop (engine/loops/cuda_stepping.py) under the CUDA simulator: with the displacement bound
the kick-drift skips the x_ref read on most steps, and the lists are rebuilt no later than with the exact
measurement every step; the fused step (a step's forces and the next kick-drift in one launch, positions and
velocities double-buffered) gives the two-launch step's trajectory. Each bit for bit."""

from __future__ import annotations

import pytest

from tests.cudasim import run_children

#: heavy: ~45 s of CUDA simulator (a thin-skin scene needs tens of one-launch-per-phase steps to show the bound
#: at work); the light run already sits near its time budget
pytestmark = pytest.mark.heavy

SCRIPT = r'''
from tests.cudasim import fast_block_polling
fast_block_polling()
import tempfile
from pathlib import Path
import h5py, numpy as np
import engine.loops.cuda_ensemble as ens
import engine.loops.cuda_stepping as st
from engine import run
from engine.setup.spec import SimulationSpec

ens.MULTISTEP = False                      # the one-launch-per-phase loop at this small N
exact_flags = []
orig = st.TimeLoop._kick_drift
def spy(self, first, step, n=None, grid=None, exact=1):
    if n is None:
        exact_flags.append(exact)
    return orig(self, first, step, n=n, grid=grid, exact=exact)
st.TimeLoop._kick_drift = spy
orig_fused = st.TimeLoop._forces_kick_drift
fused_launches = []
def spy_fused(self, step, par, exact, n=None, grid=None):
    if n is None:
        exact_flags.append(exact)
        fused_launches.append(step)
    return orig_fused(self, step, par, exact, n=n, grid=grid)
st.TimeLoop._forces_kick_drift = spy_fused

out = {}
for bound, fused in ((True, True), (False, True), (True, False)):
    st.DISPLACEMENT_BOUND = bound
    st.FUSED = fused
    exact_flags.clear()
    fused_launches.clear()
    # a thin skin (a rebuild every ten steps or so: the bound decides several) and two records (long advance calls)
    # smooth spheres with a dashpot (e_t = -1: the fused step is the smooth sphere's; the dashpot and the
    # predicted velocities read the neighbours' velocities and previous forces, which that step double-buffers)
    spec = SimulationSpec(n_particles=32, volume_fraction=0.1, e_n=0.8, e_t=-1.0, thermalization=0.0, snapshots=1,
                          backend="cuda", t_end=1.3e-3, output_interval=6.5e-4, velocity_rms=12.0,
                          verlet_skin=0.1)
    d = tempfile.mkdtemp()
    s = run(spec, Path(d) / "x.h5", backend="cuda")
    with h5py.File(s.output) as f:
        out[bound, fused] = (f["particles/all/position/value"][-1], f["particles/all/velocity/value"][-1],
                             int(f["parameters"].attrs["neighbour_builds"]), s.steps, list(exact_flags),
                             len(fused_launches))
pos_b, vel_b, builds_b, steps, flags_b, nf = out[True, True]
assert nf > steps // 2, (nf, steps)          # the fused launches ran most steps
assert out[True, False][5] == 0
assert all(out[False, True][4]), "with the bound off every kick-drift measures exactly"
assert 0 in flags_b, f"the bound never let a step skip x_ref: {flags_b}"
assert 0 in out[True, False][4]
assert builds_b >= 3, builds_b              # the bound really decided rebuilds in this run
for key in ((False, True), (True, False)):
    pos, vel, builds = out[key][:3]
    assert builds == builds_b, (key, builds, builds_b)
    assert np.array_equal(pos, pos_b) and np.array_equal(vel, vel_b), key
print("BOUND-OK", steps, builds_b, flags_b.count(0), len(flags_b), nf)
'''


def test_the_bound_and_the_fused_step_keep_the_trajectory():
    rc, out, err = run_children({"run": ["-c", SCRIPT]}, timeout=900)["run"]
    assert rc == 0 and "BOUND-OK" in out, out[-3000:] + err[-3000:]
