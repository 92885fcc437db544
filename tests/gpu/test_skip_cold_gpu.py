"""Real-GPU check of the skipped stores and loads of zero forces (engine/loops/cuda_loop.py ``SKIP_COLD``, and
``KEEP_VELOCITY`` with it): rough spheres (float64; float32 with a Coulomb cap at phi = 0.2), rough spheroids and
smooth elastic float32 spheres (the fused step) through the per-phase loop write the same positions, velocities, spins
and orientations, bit for bit, with the flags and with every store and load made.
(The observables are left out: their block sums end in float atomics, whose order varies from run to run.) Skipped
without a GPU."""

from __future__ import annotations

import numpy as np
import pytest

from engine.backends.base import cuda_available
from tests.gpu.fresh import datasets, run_job

pytestmark = pytest.mark.skipif(not cuda_available(), reason="needs a CUDA GPU")

_CHILD = """
import json, sys
import engine.loops.cuda_ensemble as ens
import engine.loops.cuda_loop as loop
ens.MULTISTEP = False                       # the per-phase loop (kick_drift reads the flags) at this N
loop.SKIP_COLD = {skip}
from engine.driver.simulate import run
from engine.setup.spec import SimulationSpec
s = run(SimulationSpec(**json.loads(sys.argv[1])), sys.argv[2], backend="cuda")
print("DONE " + json.dumps(s.steps))
"""


@pytest.mark.parametrize("kw", [
    dict(n_particles=65536, volume_fraction=0.058, e_t=0.8, precision="float64"),
    dict(n_particles=65536, volume_fraction=0.2, e_t=0.8, friction=0.2, precision="float32"),
    dict(shape="ellipsoid", elongation=2.0, n_particles=16384, volume_fraction=0.05, e_t=0.8, precision="float64"),
    dict(n_particles=65536, volume_fraction=0.058, e_n=1.0, e_t=-1.0, precision="float32")])
def test_the_flags_keep_the_trajectory_bit_for_bit(tmp_path, kw):
    kw = dict(kw, t_end=0.01, snapshots=2, seed=1, thermalization=0)
    files = {}
    for skip in (True, False):
        out = tmp_path / f"skip{skip}.h5"
        assert run_job(_CHILD.replace("{skip}", str(skip)), kw, out, {}, "DONE") > 0
        files[skip] = datasets(out)
    particles = [n for n in files[True] if n.startswith("particles/")]
    assert particles
    for name in particles:
        assert np.array_equal(files[True][name], files[False][name]), name
