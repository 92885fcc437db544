"""A GPU list build's filling pass copies the rows its counting pass kept (engine/loops/cuda_rebuild.py
``BUILD_KEPT``, engine/loops/cuda_kernels.py ``build``) instead of searching their cells again.
Under the CUDA simulator, each case is run with every row searched twice (``BUILD_KEPT = 0``), with one neighbour
kept (most rows of the dense gas are longer: searched again) and with the default: every list built is the same
(its rows and their neighbours, compared after each rebuild) and so is the trajectory, bit for bit. Cases: a dense
rough gas (rows of every length around the kept number), the same with the list's slots outgrowing their first
allocation at the first build (the kept rows lay in the history that the room replaced: the filling pass must
search), smooth float32 spheres in a dilute gas (rows of at most the kept number: every row copied)."""

from __future__ import annotations

import pytest

from tests.cudasim import run_children

#: heavy: ~1 min of CUDA simulator (nine runs of tens of steps, three children)
pytestmark = pytest.mark.heavy

SCRIPT = r'''
import sys
from tests.cudasim import fast_block_polling, kept_ensembles
fast_block_polling()
import tempfile
from pathlib import Path
import h5py, numpy as np
import engine.loops.cuda_ensemble as ens
import engine.loops.cuda_rebuild as rb
from engine import run
from engine.setup.spec import SimulationSpec

ens.MULTISTEP = False
case = sys.argv[1]
if case == "dense-grows":
    rb.HIST_MARGIN = 0     # the first list holds N slots: the dense gas's rows outgrow them at the first build
lists = []
gpu_rebuild = rb.ListBuilds._gpu_rebuild
def recorded(self):
    gpu_rebuild(self)
    nn = self.nn.copy_to_host()
    lists.append((nn, self.nbr.copy_to_host()[:nn[-1]]))
rb.ListBuilds._gpu_rebuild = recorded
ensembles = kept_ensembles()

base = dict(n_particles=64, volume_fraction=0.35, e_n=0.8, e_t=0.8, thermalization=0.0, snapshots=2,
            backend="cuda", precision="float64", t_end=4e-3, output_interval=1e-3, velocity_rms=6.0,
            verlet_skin=0.4, seed=5)
kw = {"dense": {}, "dense-grows": {},
      "smooth-f32": dict(precision="float32", e_t=-1.0, volume_fraction=0.05, n_particles=40, verlet_skin=0.1,
                         velocity_rms=12.0, t_end=1.2e-3, output_interval=4e-4)}[case]
DATA = ("position", "velocity", "angular_velocity")
out = {}
for keep in (0, 1, rb.BUILD_KEPT):
    rb.BUILD_KEPT = keep if keep else 0
    lists.clear()
    ensembles.clear()
    s = run(SimulationSpec(**{**base, **kw}), Path(tempfile.mkdtemp()) / "x.h5", backend="cuda")
    (e,) = ensembles
    with h5py.File(s.output) as f:
        out[keep] = ([f[f"particles/all/{d}/value"][...] for d in DATA], list(lists), e.nbr.shape[0], s.steps)
    rb.BUILD_KEPT = 4
ref, ref_lists, _, steps = out[0]
assert len(ref_lists) >= 2, len(ref_lists)
lengths = np.concatenate([np.diff(nn) for nn, _ in ref_lists])
for keep, (data, built, stride, st) in out.items():
    assert st == steps and len(built) == len(ref_lists), (keep, st, len(built))
    for (nn, nbr), (nn_ref, nbr_ref) in zip(built, ref_lists):
        assert np.array_equal(nn, nn_ref) and np.array_equal(nbr, nbr_ref), (case, keep)
    for d, x, y in zip(DATA, data, ref):
        assert np.array_equal(x, y), (case, keep, d)
if case.startswith("dense"):
    assert (lengths > 4).any() and ((lengths > 1) & (lengths <= 4)).any(), "rows longer than each kept number"
    if case == "dense-grows":
        assert out[4][2] > 64, "the list's slots regrown at a build: its kept rows were in the history replaced"
else:
    assert lengths.max() <= 4 and lengths.max() > 0, lengths.max()
print("KEPT-OK", case, len(ref_lists), int(lengths.max()))
'''

CASES = ("dense", "dense-grows", "smooth-f32")


def test_rows_copied_from_the_counting_pass_are_the_rows_searched_again():
    got = run_children({c: ["-c", SCRIPT, c] for c in CASES}, timeout=1200)
    for case, (rc, out, err) in got.items():
        assert rc == 0 and "KEPT-OK" in out, (case, out[-3000:] + err[-3000:])
