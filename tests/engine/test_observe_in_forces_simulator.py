"""Records summed in the last force pass of an advance call (engine/loops/cuda_stepping.py ``OBSERVE_IN_FORCES``,
cuda_loop ``forces_observe``), under the CUDA simulator, for a lone sphere scene in the per-phase loop, smooth (its
force and kick-drift passes fused) and rough (two passes a step; the spins, half a step behind too, brought level
with the torques the force pass stored):

- the observables equal those of the closing half kick and the observe kernel at the same state;
- calls split at records, and one call observing at the same steps in its fused force passes
  (``advance_observing``), give the trajectory of one long call bit for bit (the velocities stay half a step behind
  between calls, so no half kicks are added), and the state read between calls is level with the positions;
- a whole run (thermalisation, records, snapshots) writes the records and frames of the closing path to rounding.
"""

from __future__ import annotations

import pytest

from tests.cudasim import run_children

PRELUDE = r'''
from tests.cudasim import fast_block_polling
fast_block_polling()
import tempfile
from pathlib import Path
import h5py, numpy as np
import engine.loops.cuda_ensemble as ens_mod
import engine.loops.cuda_stepping as st
from engine.loops.cuda_records import ObserveSums
from engine import run
from engine.backends.cuda import CudaBackend
from engine.setup.params import derive
from engine.setup.scene import initial_spheres
from engine.driver.simulate import contact_params
from engine.setup.spec import SimulationSpec

ens_mod.MULTISTEP = False          # the per-phase loop at this small N
launches = []
orig = ObserveSums._observe_in_forces
def spy(self, step, row, fused, par=0, exact=1, n=None, grid=None):
    if n is None:
        launches.append((step, row, fused))
    return orig(self, step, row, fused, par, exact, n=n, grid=grid)
ObserveSums._observe_in_forces = spy

import sys
E_T = float(sys.argv[1]) if len(sys.argv) > 1 else -1.0
FUSED = E_T < 0                    # smooth spheres fuse a step's forces with the next kick-drift; rough ones do not
spec = SimulationSpec(n_particles=32, volume_fraction=0.1, e_n=0.8, e_t=E_T, velocity_rms=2.0, seed=3,
                      thermalization=0.0)
p = derive(spec)
system, contact = initial_spheres(spec, p), contact_params(spec, p, thermalization=False)

def backend(open_records, scene=None):
    st.OBSERVE_IN_FORCES = open_records
    return CudaBackend(*(scene or (system, contact)))

# the same gas with spheres 0 and 1 placed overlapping by 1 % of a radius and approaching: a contact at every
# record below (the dilute start has none so early)
import dataclasses
pos, vel = system.position.copy(), system.velocity.copy()
pos[1] = (pos[0] + [1.99 * p.radius, 0.0, 0.0]) % spec.box_length
vel[0], vel[1] = [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]
touching = dataclasses.replace(system, position=pos, velocity=vel), contact
'''

BACKEND = r'''
# 1. the force pass's observables (its overlaps from the slots' history) against the observe kernel's (from the
# positions) at the same state, with contacts in every record
b = backend(True, touching)
for _ in range(3):
    b.advance(4)
    o_pass = b.observe()
    assert b.e._open and b.e._observed_at == b.steps_done
    st_open = b.state()                 # closes: the velocities level with the positions
    assert not b.e._open
    b.e._observed_at = None             # the next observe() runs the observe kernel on the closed state
    o_kernel = b.observe()
    for key, v in o_kernel.items():
        np.testing.assert_allclose(np.asarray(o_pass[key], float), np.asarray(v, float), rtol=1e-13, atol=1e-300,
                                   err_msg=key)   # the same velocities and sums; only the block sums' order may differ
    assert o_kernel["contacts"] > 0 and o_kernel["elastic_energy"] > 0.0 and o_kernel["max_overlap"] > 0.0, o_kernel
assert len(launches) == 3 and all(r == 0 and not f for _, r, f in launches), launches
if not FUSED:
    assert o_kernel["kinetic_energy_rotational"] > 0.0, o_kernel

# 2. calls split at records give one long call's trajectory bit for bit, and so does one call observing at the same
# steps inside its fused force passes; the closing path differs by rounding only
split = backend(True)
seen = []
for _ in range(5):
    split.advance(4)
    seen.append(split.observe())
one = backend(True)
one.advance(20)
batched = backend(True)
launches.clear()
failed, rows = batched.e.advance_observing(20, [4, 8, 12, 16, 20])
assert not failed and len(rows) == 5
assert [(st_, r, f) for st_, r, f in launches] == [(3, 0, FUSED), (7, 1, FUSED), (11, 2, FUSED), (15, 3, FUSED),
                                                    (19, 4, False)], launches
assert batched.observe() == rows[-1][0]
closed = backend(False)
for _ in range(5):
    closed.advance(4)
    closed.observe()
assert split.builds == one.builds == batched.builds == closed.builds, (split.builds, one.builds, closed.builds)
s_split, s_one, s_batched, s_closed = split.state(), one.state(), batched.state(), closed.state()
for key in ("position", "velocity", "angular_velocity"):
    assert np.array_equal(s_split[key], s_one[key]), key
    assert np.array_equal(s_split[key], s_batched[key]), key
    np.testing.assert_allclose(s_split[key], s_closed[key], rtol=1e-12, atol=1e-12, err_msg=key)  # rounding of
    # the closing path's two half kicks per record against one whole kick
for a, b in zip(seen, rows):
    for key, v in a.items():
        np.testing.assert_allclose(np.asarray(b[0][key], float), np.asarray(v, float), rtol=1e-13, atol=1e-300,
                                   err_msg=key)   # the same sums but for the block sums' order
for key in ("kinetic_energy_translational", "kinetic_energy_rotational"):
    np.testing.assert_allclose(split.observe()[key], closed.observe()[key], rtol=1e-12, atol=1e-300)
print("OBSERVE-OK", len(launches))
'''

RUNS = r'''
import engine.driver.simulate as simulate
simulate.RECORDS_CALL_S = 1e9      # the simulator's steps are slow: let one call run through every record ahead
batches = []
orig_ao = st.TimeLoop.advance_observing
def spy_ao(self, nsteps, at):
    batches.append(list(at))
    return orig_ao(self, nsteps, at)
st.TimeLoop.advance_observing = spy_ao
# 3. whole runs: thermalisation then cooling (a contact switch while the velocities are half a step behind),
# records and snapshots, smooth and rough (records inside one call: fused passes for smooth, two passes for rough)
for e_t in (-1.0, 0.8):
    files = {}
    for open_records in (True, False):
        st.OBSERVE_IN_FORCES = open_records
        launches.clear()
        run_spec = SimulationSpec(n_particles=32, volume_fraction=0.1, e_n=0.8, e_t=e_t, velocity_rms=2.0,
                                  seed=4, thermalization=0.05, snapshots=3, backend="cuda", t_end=1.2e-3,
                                  output_interval=2e-4)
        d = tempfile.mkdtemp()
        s = run(run_spec, Path(d) / "x.h5", backend="cuda")
        with h5py.File(s.output) as f:
            files[open_records] = {k: f[k][()] for k in ("observables/kinetic_energy_translational/value",
                                                            "observables/elastic_energy/value",
                                                            "particles/all/position/value",
                                                            "particles/all/velocity/value")}
        if open_records:
            assert any(len(b) > 2 for b in batches), batches     # records passed inside one call
            # ... by the fused observing kernel (smooth), the observing force pass (rough)
            assert sum(f == (e_t < 0) for _, _, f in launches) >= 3, launches
        else:
            assert not batches, batches
        batches.clear()
    for k, v in files[True].items():
        assert v.shape == files[False][k].shape, k
        np.testing.assert_allclose(v, files[False][k], rtol=1e-9, atol=1e-12, err_msg=f"{e_t} {k}")  # rounding,
        # grown over a few hundred steps of a gas with collisions
print("OBSERVE-OK", len(launches))
'''


@pytest.mark.parametrize("e_t", [-1.0, 0.8], ids=["smooth", "rough"])
def test_records_from_the_force_pass_match_the_observe_kernel_and_keep_the_trajectory(e_t):
    rc, out, err = run_children({"run": ["-c", PRELUDE + BACKEND, str(e_t)]}, timeout=900)["run"]
    assert rc == 0 and "OBSERVE-OK" in out, out[-3000:] + err[-3000:]


@pytest.mark.heavy  # ~40 s of CUDA simulator: four whole runs
def test_whole_runs_write_the_closing_paths_records_and_frames():
    rc, out, err = run_children({"run": ["-c", PRELUDE + RUNS]}, timeout=900)["run"]
    assert rc == 0 and "OBSERVE-OK" in out, out[-3000:] + err[-3000:]
