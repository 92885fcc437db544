"""A rebuild's scratch in memory that holds nothing needed meanwhile (engine/loops/cuda_rebuild.py ``LEND_SCRATCH``):
the permutation's rows and the cells' counts in the Verlet list's history, the compact store's index in the next
force buffer.
Under the CUDA simulator, each case run with the scratch lent and with arrays of its own: the same trajectory bit
for bit (positions, velocities, spins; the same number of list builds, at least two, so that sorts, permutations
and kept histories are exercised), and the ensemble holds less device memory by what the lent arrays took. Cases:
rough float32 with a Coulomb cap, a dense gas whose list's slots grow (the lent views made anew in the new history),
smooth float64 and rough mixed precision (positions in float64; in a history of N slots they are permuted a row at a
time), rough spheroids (one force buffer:
their own store index), a list built on the host (cpu-sequential: the index written by the compaction, read by the
attachment), two sizes of spheres (the multigrid build: the grid levels permuted through the lent rows too)."""

from __future__ import annotations

import pytest

from tests.cudasim import run_children

#: heavy: ~1-2 min of CUDA simulator (fourteen runs of tens of steps)
pytestmark = pytest.mark.heavy

SCRIPT = r'''
import sys
from tests.cudasim import fast_block_polling
fast_block_polling()
import tempfile
from pathlib import Path
import h5py, numpy as np
import engine.loops.cuda_ensemble as ens
import engine.loops.cuda_rebuild as rb
from engine import run
from engine.loops.cuda_memory import device_allocations
from engine.setup.spec import SimulationSpec

ens.MULTISTEP = False
rb.SORT_DRIFT_CELLS = 0     # every rebuild permutes: the scratch of its gathers is in use (and held at the end)
case = sys.argv[1]
if case in ("dense-grows", "mixed-thin-history"):
    rb.HIST_MARGIN = 0     # the first list holds N slots: the dense gas's rows outgrow them at the first build; in
    # the dilute mixed gas the float64 positions' rows (24 B a particle) exceed that history (5 float32 words a slot)
kept = []
init = ens.CudaEnsembleBase.__init__
def keep(self, *a, **k):
    kept.append(self)
    init(self, *a, **k)
    if case == "host-list":
        self.set_list_mode("cpu-sequential")
ens.CudaEnsembleBase.__init__ = keep

base = dict(n_particles=40, volume_fraction=0.15, e_n=0.8, thermalization=0.0, snapshots=2, backend="cuda",
            t_end=1.2e-3, output_interval=4e-4, velocity_rms=12.0, verlet_skin=0.1, seed=4)
kw = {"rough-f32": dict(precision="float32", e_t=0.8, friction=0.3),
      "dense-grows": dict(precision="float64", e_t=0.8, volume_fraction=0.35, verlet_skin=0.4, n_particles=64,
                          velocity_rms=6.0, t_end=4e-3),
      "smooth-f64": dict(precision="float64", e_t=-1.0),
      "rough-mixed": dict(precision="mixed", e_t=0.8),
      "mixed-thin-history": dict(precision="mixed", e_t=0.8, volume_fraction=0.05),
      "spheroids": dict(precision="float64", e_t=0.8, shape="ellipsoid", elongation=1.5, volume_fraction=0.1,
                        velocity_rms=10.0),
      "host-list": dict(precision="float64", e_t=0.8),
      "species": dict(precision="float64", e_t=0.8, species=[{"radius_ratio": 0.3, "number_fraction": 0.5},
                                                            {"radius_ratio": 1.0, "number_fraction": 0.5}],
                      velocity_rms=4.0, t_end=3e-3)}[case]
DATA = ("position", "velocity", "angular_velocity")
out = {}
for lend in (True, False):
    rb.LEND_SCRATCH = lend
    kept.clear()
    spec = SimulationSpec(**{**base, **kw})
    s = run(spec, Path(tempfile.mkdtemp()) / "x.h5", backend="cuda")
    (e,) = kept
    with h5py.File(s.output) as f:
        out[lend] = ([f[f"particles/all/{d}/value"][...] for d in DATA], e.builds, e.nbr.shape[0],
                     sum(device_allocations(e).values()), s.steps)
(a, builds, stride, held, steps), (b, builds_ref, stride_ref, held_ref, steps_ref) = out[True], out[False]
assert steps == steps_ref and builds == builds_ref and builds >= 2 and stride == stride_ref, out
if case == "dense-grows":
    assert stride > 64, stride    # the list's slots regrown (from N, below): the history lent from is a new one
if case == "species":
    assert e.multigrid, "the size spread is binned on grid levels (their level ids permuted too)"
for d, x, y in zip(DATA, a, b):
    assert np.array_equal(x, y), (case, d)
print("LENT-OK", case, builds, stride, held, held_ref)
'''

CASES = ("rough-f32", "dense-grows", "smooth-f64", "rough-mixed", "mixed-thin-history", "spheroids", "host-list",
         "species")


def test_lent_scratch_keeps_the_trajectory_and_holds_less():
    got = run_children({c: ["-c", SCRIPT, c] for c in CASES}, timeout=1200)
    for case, (rc, out, err) in got.items():
        assert rc == 0 and "LENT-OK" in out, (case, out[-3000:] + err[-3000:])
        _, _, builds, stride, held, held_ref = out.strip().splitlines()[-1].split()
        n = 64 if case == "dense-grows" else 40
        # lent: the permutation's rows (4 words, 3 more for 'mixed' positions), int32 and int64 rows, the cells'
        # counts; spheroids keep their store index (one force buffer), the others lend it too (8 B a particle)
        assert int(held_ref) - int(held) >= (4 * 4 + 4 + 8) * n, (case, held, held_ref)
