"""Real-GPU check of the GPU start-up thread (engine/driver/startup.py): a job in a fresh process writes the same result
file with the thread as without it (engine.driver.startup.ENABLED = False), for spheres and ellipsoids — the trajectory
bit for bit, the observables to rounding as any two GPU runs — and the thread ran without error. Skipped without a
GPU."""

from __future__ import annotations

import numpy as np
import pytest

from engine.backends.base import cuda_available
from tests.gpu.fresh import datasets, run_job

pytestmark = pytest.mark.skipif(not cuda_available(), reason="needs a CUDA GPU")


_CHILD = """
import json, sys
import engine.driver.startup
engine.driver.startup.ENABLED = {on}
from engine.driver.simulate import run
from engine.setup.spec import SimulationSpec
kw = json.loads(sys.argv[1])
s = run(SimulationSpec(**kw), sys.argv[2])
print("STARTUP " + json.dumps(s.extra.get("gpu_startup")))
"""


@pytest.mark.parametrize("kw", [
    dict(n_particles=40000, volume_fraction=0.1, e_n=0.8, e_t=0.5, t_end=0.02, snapshots=1, seed=5,
         thermalization=2),
    dict(shape="ellipsoid", elongation=2.0, n_particles=8000, volume_fraction=0.1, e_n=0.9, t_end=0.01,
         snapshots=1, seed=5, thermalization=0)])
def test_a_fresh_process_writes_the_same_file_with_and_without_the_startup_thread(tmp_path, kw):
    files, info = {}, {}
    for on in ("0", "1"):
        out = tmp_path / f"on{on}.h5"
        info[on] = run_job(_CHILD.replace("{on}", str(on == "1")), kw, out, {}, "STARTUP")
        files[on] = datasets(out)
    assert info["0"] is None
    assert info["1"] is not None and info["1"]["error"] is None, info["1"]
    assert files["0"].keys() == files["1"].keys()
    differ = {}
    for name, a in files["0"].items():
        b = files["1"][name]
        if not np.array_equal(a, b):
            differ[name] = float(np.max(np.abs(np.asarray(a, float) - np.asarray(b, float))))
    print("\ndatasets that differ (max |difference|):", differ)
    # the trajectory itself: bit for bit
    assert not [n for n in differ if not n.startswith("observables/")], differ
    # the observables' block sums end in one float atomic per block, whose order varies from run to run
    # (engine/loops/cuda_kernels.py): equal to rounding, as between any two GPU runs; a Sonine coefficient
    # cancels O(1) moment ratios against each other, so its rounding is absolute, ~1e-13
    for name in differ:
        assert np.allclose(files["0"][name], files["1"][name], rtol=1e-9, atol=1e-12), (name, differ[name])


_EXPLICIT_CUDA = """
import json, sys
from numba import cuda  # imported first, as by a script or a worker: the job's first driver call comes at once
from engine.driver.simulate import run
from engine.setup.spec import SimulationSpec
s = run(SimulationSpec(**json.loads(sys.argv[1])), sys.argv[2], backend="cuda")
print("DONE " + json.dumps(s.steps))
"""


def test_an_explicit_cuda_job_in_a_process_that_imported_numba_cuda_starts(tmp_path):
    # backend = 'cuda' skips the main thread's probe: its memory query's first driver call came beside the start-up
    # thread's probe and failed with CUDA_ERROR_NOT_INITIALIZED (in most such processes on an H200)
    kw = dict(n_particles=4096, volume_fraction=0.1, t_end=0.002, snapshots=0, seed=1, thermalization=0)
    for k in range(4):
        assert run_job(_EXPLICIT_CUDA, kw, tmp_path / f"r{k}.h5", {}, "DONE") > 0


_HOST_CALLS = """
import gc, json, sys
import numba.core.dispatcher as nd
calls = []
first_call = nd.Dispatcher._compile_for_args
def logged(self, *a, **k):
    calls.append(self.py_func.__name__)
    return first_call(self, *a, **k)
nd.Dispatcher._compile_for_args = logged
from engine.driver.simulate import run
from engine.setup.spec import SimulationSpec
s = run(SimulationSpec(**json.loads(sys.argv[1])), sys.argv[2], backend="cuda")
print("HOST " + json.dumps({"calls": calls, "frozen": gc.get_freeze_count(), "steps": s.steps}))
"""


def test_a_gpu_job_with_its_start_drawn_on_the_device_calls_no_host_compiled_function(tmp_path):
    # the first call of a host-compiled (CPU) function in a process costs numba's CPU start-up (its extension entry
    # points, the runtime's compile): 0.05-0.07 s of the start-up thread's critical path on an H200 host when the
    # random start's pass keys were made on the host
    kw = dict(n_particles=1 << 20, volume_fraction=0.1, t_end=0.002, snapshots=1, seed=1, thermalization=0)
    got = run_job(_HOST_CALLS, kw, tmp_path / "r.h5", {}, "HOST")
    assert got["steps"] > 0 and got["calls"] == [], got
    assert got["frozen"] > 10000, got     # the imports' objects left out of later collections (startup.py)
