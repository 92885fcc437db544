"""The per-phase CUDA loop's carried bound (engine/loops/cuda_stepping.py ``_close_call``), under the CUDA
simulator: an advance call's first rebuild is decided from the displacement bound the previous call ended with,
not from a wait for the GPU; that bound is never below the particles' true largest displacement since the list
build, and no rebuild comes late. Two packed scenes (where no host-built list
machinery is attached), smooth (fused step) and rough (two launches), a thin skin, calls of an odd number of steps
(the last kick-drift's status then sits in the pinned slot that a wait-now status read must not overwrite)."""

from __future__ import annotations

import pytest

from tests.cudasim import run_children

#: heavy: ~40 s of CUDA simulator (two contacts x 12 calls of 5 steps of two packed scenes)
pytestmark = pytest.mark.heavy

SCRIPT = r'''
from tests.cudasim import fast_block_polling
fast_block_polling()
import numpy as np
import engine.loops.cuda_stepping as st
from engine.loops import cuda_kernels as K
from engine.backends.cuda import CudaEnsemble
from engine.setup.params import derive
from engine.setup.scene import initial_spheres
from engine.driver.simulate import contact_params
from engine.setup.spec import SimulationSpec

def scene(seed, e_t):
    spec = SimulationSpec(n_particles=32, volume_fraction=0.1, e_n=0.8, e_t=e_t, velocity_rms=12.0,
                          verlet_skin=0.1, seed=seed, thermalization=0.0)
    p = derive(spec)
    return initial_spheres(spec, p), contact_params(spec, p, thermalization=False)

carried = []
orig = st.TimeLoop._advance_per_phase
def spy(self, nsteps, failed, *args):
    carried.append(self._carry is not None and self._carry[:2] == (self.steps_done, self.builds))
    return orig(self, nsteps, failed, *args)
st.TimeLoop._advance_per_phase = spy

for e_t in (-1.0, 0.8):
    scenes = [scene(1, e_t), scene(2, e_t)]
    ens = CudaEnsemble([s for s, _ in scenes], [c for _, c in scenes])
    ens.multistep = False
    assert ens.lists is None
    carried.clear()
    for _ in range(12):
        failed = ens.advance(5)
        assert not failed, failed
        # the carried bound bounds every particle's displacement since the list build (in units of L_v/2)
        pos, xr, sc = ens.pos.copy_to_host(), ens.x_ref.copy_to_host(), ens.sc.copy_to_host()
        box = ens.spd_h[sc, K.D_BOX]
        d = pos - xr
        d -= box * np.round(d / box)
        true = float(np.sqrt(((d * d).sum(axis=0) * ens.spf_h[sc, K.F_LIM2INV]).max()))
        assert ens._carry[2] >= true * (1 - 1e-9), (e_t, ens.steps_done, ens._carry, true)  # 1e-9: the device's
        # and numpy's rounding of the same float64 sum
    print(e_t, "builds", ens.builds, "late", ens.late_rebuilds, "carried", sum(carried), "of", len(carried))
    assert ens.builds >= 4, ens.builds
    assert sum(carried) >= 6, carried
    assert ens.late_rebuilds == 0, ens.late_rebuilds
print("CARRY-OK")
'''


def test_a_call_starts_from_the_previous_calls_bound_and_rebuilds_in_time():
    rc, out, err = run_children({"run": ["-c", SCRIPT]}, timeout=900)["run"]
    assert rc == 0 and "CARRY-OK" in out, out[-3000:] + err[-3000:]
