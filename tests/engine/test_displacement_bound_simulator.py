"""The per-phase CUDA loop's displacement bound (engine/loops/cuda_stepping.py), under the CUDA simulator: the
kick-drift skips the x_ref read on most steps, and the lists are rebuilt no later than with the exact
measurement every step, so the trajectory is the same bit for bit."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

#: heavy: ~30 s of CUDA simulator (a thin-skin scene needs tens of one-launch-per-phase steps to show the bound
#: at work); the light run already sits near its time budget
pytestmark = pytest.mark.heavy

SCRIPT = r'''
import tempfile
from pathlib import Path
import h5py, numpy as np
import engine.loops.cuda_ensemble as ens
import engine.loops.cuda_stepping as st
from engine import run
from engine.spec import SimulationSpec

ens.MULTISTEP = False                      # the one-launch-per-phase loop at this small N
exact_flags = []
orig = st.TimeLoop._kick_drift
def spy(self, first, step, n=None, grid=None, exact=1):
    if n is None:
        exact_flags.append(exact)
    return orig(self, first, step, n=n, grid=grid, exact=exact)
st.TimeLoop._kick_drift = spy

out = {}
for bound in (True, False):
    st.DISPLACEMENT_BOUND = bound
    exact_flags.clear()
    # a thin skin (a rebuild every ten steps or so: the bound decides several) and two records (long advance calls)
    spec = SimulationSpec(n_particles=32, volume_fraction=0.1, e_n=0.8, e_t=0.8, thermalization=0.0, snapshots=1,
                          backend="cuda", t_end=1.3e-3, output_interval=6.5e-4, velocity_rms=12.0,
                          verlet_skin=0.1)
    d = tempfile.mkdtemp()
    s = run(spec, Path(d) / "x.h5", backend="cuda")
    with h5py.File(s.output) as f:
        out[bound] = (f["particles/all/position/value"][-1], f["particles/all/velocity/value"][-1],
                      int(f["parameters"].attrs["neighbour_builds"]), s.steps, list(exact_flags))
pos_b, vel_b, builds_b, steps, flags_b = out[True]
pos_e, vel_e, builds_e, _, flags_e = out[False]
assert all(flags_e), "with the bound off every kick_drift measures exactly"
assert 0 in flags_b, f"the bound never let a step skip x_ref: {flags_b}"
assert builds_b >= 3, builds_b              # the bound really decided rebuilds in this run
assert builds_b == builds_e, (builds_b, builds_e)
assert np.array_equal(pos_b, pos_e) and np.array_equal(vel_b, vel_e)
print("BOUND-OK", steps, builds_b, flags_b.count(0), len(flags_b))
'''


def test_the_bound_skips_x_ref_and_rebuilds_as_the_exact_rule():
    env = dict(os.environ, NUMBA_ENABLE_CUDASIM="1")
    root = Path(__file__).resolve().parents[2]
    r = subprocess.run([sys.executable, "-c", SCRIPT], cwd=root, env=env, capture_output=True, text=True,
                       timeout=900)
    assert r.returncode == 0 and "BOUND-OK" in r.stdout, r.stdout[-3000:] + r.stderr[-3000:]
