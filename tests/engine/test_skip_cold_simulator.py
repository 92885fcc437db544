"""The per-phase CUDA loop's skipped stores and loads of zero forces (engine/loops/cuda_loop.py ``SKIP_COLD``) under the
CUDA simulator: a force pass stores a particle's force and torque only where they are not zero (or were not at the
two passes before) and marks in ``hot`` which are; the kick-drift reads them only where ``hot`` says so. Checked:
the trajectory is the one with every store and load made, bit for bit (rough spheres with a Coulomb cap through the
two-launch step, smooth spheres through the fused step, records and rebuilds on the way); before every kick-drift
a particle whose flags say zero holds zeros in both force buffers and the torque, and some particles are cold (no
particle ever is without the flags); the kick-drift does not read a cold particle's force and torque (NaN written
there before it changes nothing); before every fused force-and-kick-drift pass a particle whose ``hot`` bit 2 is
clear holds the same velocity in both halves of the double buffer (``KEEP_VELOCITY``: that pass then stores no
velocity component its force does not kick), and some particles are so."""

from __future__ import annotations

import pytest

from tests.cudasim import run_children

#: heavy: ~1-2 min of CUDA simulator (a per-phase run of tens of steps, four times)
pytestmark = pytest.mark.heavy

SCRIPT = r'''
from tests.cudasim import fast_block_polling
fast_block_polling()
import tempfile
from pathlib import Path
import h5py, numpy as np
import engine.loops.cuda_ensemble as ens
import engine.loops.cuda_loop as loop
import engine.loops.cuda_stepping as st
from engine import run
from engine.setup.spec import SimulationSpec

ens.MULTISTEP = False                      # the one-launch-per-phase loop at this small N
checked = {"kicks": 0, "cold": 0}
orig = st.TimeLoop._kick_drift
def spy(self, first, step, n=None, grid=None, exact=1):
    if n is not None or not loop.SKIP_COLD:
        return orig(self, first, step, n=n, grid=grid, exact=exact)
    hot = self.hot.copy_to_host()
    f_cur, f_nxt = self.f_cur.copy_to_host(), self.f_nxt.copy_to_host()
    torque = self.torque.copy_to_host()
    cold_now = (hot & 1) == 0
    cold_both = (hot & 3) == 0
    # a particle whose flags say zero holds zeros: its last force and torque, and the other buffer's older force
    assert not f_cur[:, cold_now].any() and not torque[:, cold_now].any(), step
    assert not f_nxt[:, cold_both].any(), step
    checked["kicks"] += 1
    checked["cold"] += int(cold_now.sum())
    # the kick-drift must not read a cold particle's force or torque: NaN there changes nothing
    poisoned_f, poisoned_t = f_cur.copy(), torque.copy()
    poisoned_f[:, cold_now] = np.nan
    poisoned_t[:, cold_now] = np.nan
    self.f_cur.copy_to_device(poisoned_f)
    self.torque.copy_to_device(poisoned_t)
    orig(self, first, step, n=n, grid=grid, exact=exact)
    self.f_cur.copy_to_device(f_cur)
    self.torque.copy_to_device(torque)
st.TimeLoop._kick_drift = spy

import engine.loops.cuda_records as rec
checked["fused"] = checked["kept"] = 0
def same_halves(self):
    """Before a fused pass: where bit 2 is clear the other half of the velocity buffer holds this one's numbers."""
    if not (loop.SKIP_COLD and loop.KEEP_VELOCITY):
        return
    hot = self.hot.copy_to_host()
    kept = (hot & 4) == 0
    vel, other = self.vel.copy_to_host(), self._fused_out()[1].copy_to_host()
    assert np.array_equal(vel[:, kept], other[:, kept]), self.steps_done
    checked["fused"] += 1
    checked["kept"] += int(kept.sum())
orig_fused = st.TimeLoop._forces_kick_drift
def spy_fused(self, step, par, exact, n=None, grid=None):
    if n is None:
        same_halves(self)
    return orig_fused(self, step, par, exact, n=n, grid=grid)
st.TimeLoop._forces_kick_drift = spy_fused
orig_observe = rec.ObserveSums._observe_in_forces
def spy_observe(self, step, row, fused, par=0, exact=1, n=None, grid=None):
    if fused and n is None:
        same_halves(self)
    return orig_observe(self, step, row, fused, par=par, exact=exact, n=n, grid=grid)
rec.ObserveSums._observe_in_forces = spy_observe

DATA = ("position", "velocity", "angular_velocity")
out = {}
for name, kw in (("rough", dict(e_t=0.8, friction=0.3)), ("smooth", dict(e_t=-1.0))):
    for skip in (True, False):
        loop.SKIP_COLD = skip
        # a thin skin (rebuilds every ten steps or so) and several records inside each advance call
        spec = SimulationSpec(n_particles=40, volume_fraction=0.15, e_n=0.8, thermalization=0.0, snapshots=3,
                              backend="cuda", t_end=1.2e-3, output_interval=3e-4, velocity_rms=12.0,
                              verlet_skin=0.1, seed=4, **kw)
        s = run(spec, Path(tempfile.mkdtemp()) / "x.h5", backend="cuda")
        with h5py.File(s.output) as f:
            out[name, skip] = ([f[f"particles/all/{d}/value"][...] for d in DATA],
                               int(f["parameters"].attrs["neighbour_builds"]), s.steps)
    (a, builds, steps), (b, builds_ref, steps_ref) = out[name, True], out[name, False]
    assert steps == steps_ref and builds == builds_ref and builds >= 2, (name, steps, builds, builds_ref)
    for d, x, y in zip(DATA, a, b):
        assert np.array_equal(x, y), (name, d)
assert checked["kicks"] > 20 and checked["cold"] > 0, checked
assert checked["fused"] > 20 and checked["kept"] > 0, checked
print("SKIP-OK", checked)
'''


def test_skipped_stores_and_loads_of_zero_forces_keep_the_trajectory():
    rc, out, err = run_children({"run": ["-c", SCRIPT]}, timeout=900)["run"]
    assert rc == 0 and "SKIP-OK" in out, out[-3000:] + err[-3000:]
