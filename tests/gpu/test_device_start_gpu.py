"""Real-GPU checks of the large starts drawn on the device (engine/loops/cuda_start.py): the same start as the
host's draws to rounding, and a job that draws its start on the device writes the file of one that draws it on the
host (engine.setup.start_kind.DEVICE_START = False), to rounding. Skipped without a GPU."""

from __future__ import annotations

import numpy as np
import pytest

from engine.backends.base import cuda_available
from tests.gpu.fresh import datasets, run_job

pytestmark = pytest.mark.skipif(not cuda_available(), reason="needs a CUDA GPU")

BIG = dict(n_particles=1_100_000, volume_fraction=0.058, e_n=0.9, e_t=0.5, seed=3)

# the device's log, cos, sin and pow (libdevice) differ from the host's libm by an ulp or two, and it may fuse a
# multiply and an add; Box-Muller and the rms normalisation carry that through a handful of operations: 1e-13 of
# each array's largest value is ~500 ulp, far below any difference a wrong site, draw or block sum would make
TOL = 1e-13


def _device(d, pos_dtype, dtype):
    from numba import cuda

    from engine.loops.cuda_start import draw_start

    stream = cuda.stream()
    pos = cuda.device_array((3, d.n), pos_dtype, stream=stream)
    dsts = {k: cuda.device_array((dim, d.n), dtype, stream=stream) for k, dim, _ in d.streams}
    draw_start(d, 0, pos, dsts, stream)
    stream.synchronize()
    return pos.copy_to_host().T, [dsts[k].copy_to_host().T for k, _, _ in d.streams]


def test_a_device_start_is_the_host_start_to_rounding():
    from engine.setup.params import derive
    from engine.setup.scene import StartDraw, parallel_start_streams
    from engine.setup.spec import SimulationSpec

    spec = SimulationSpec(**BIG)
    p = derive(spec)
    streams, radius = parallel_start_streams(spec, p)
    d = StartDraw.of(spec.n_particles, spec.seed, streams, spec.box_length, radius)
    assert d.n < d.n_sites          # the site selection runs
    pos_h, arrays_h = d.on_host()
    for pos_dtype, dtype in ((np.float64, np.float64), (np.float32, np.float32)):
        pos, arrays = _device(d, pos_dtype, dtype)
        # float32: the casts of values equal to rounding may fall on either side of a float32 rounding boundary
        tol = TOL if dtype is np.float64 else 2.0 ** -23
        dp = np.max(np.abs(pos - pos_h)) / spec.box_length
        assert dp <= tol, dp
        for a, h in zip(arrays, arrays_h):
            assert a.shape == h.shape
            assert np.max(np.abs(a - h)) <= tol * np.max(np.abs(h)), (dtype, np.max(np.abs(a - h)))
        print(f"\n{np.dtype(dtype).name}: positions |diff| / box {dp:.2e}; arrays |diff| / max",
              [f"{np.max(np.abs(a - h)) / np.max(np.abs(h)):.2e}" for a, h in zip(arrays, arrays_h)])


_CHILD = """
import json, sys
import engine.setup.start_kind
engine.setup.start_kind.DEVICE_START = {on}
from engine.driver.simulate import run
from engine.setup.spec import SimulationSpec
s = run(SimulationSpec(**json.loads(sys.argv[1])), sys.argv[2])
print("RUN " + json.dumps({"startup": s.extra.get("gpu_startup"), "steps": s.steps, "backend": s.backend}))
"""


def test_a_job_with_its_start_drawn_on_the_device_writes_the_host_starts_file_to_rounding(tmp_path):
    kw = dict(BIG, t_end=0.005, snapshots=2, thermalization=0)
    files, info = {}, {}
    for on in ("0", "1"):
        out = tmp_path / f"device{on}.h5"
        info[on] = run_job(_CHILD.replace("{on}", str(on == "1")), kw, out, {}, "RUN")
        files[on] = datasets(out)
    assert info["1"]["backend"] == "cuda" and info["1"]["startup"]["error"] is None, info
    assert info["1"]["steps"] == info["0"]["steps"] > 10
    from engine.setup.params import derive
    from engine.setup.scene import initial_spheres
    from engine.setup.spec import SimulationSpec

    host = initial_spheres(SimulationSpec(**kw), derive(SimulationSpec(**kw)))   # drawn on the host
    first = files["1"]["particles/all/position/value"][0]
    assert np.max(np.abs(first - host.position)) <= TOL * host.box_length
    v0 = files["1"]["particles/all/velocity/value"][0]
    assert np.max(np.abs(v0 - host.velocity)) <= TOL * np.max(np.abs(host.velocity))
    assert files["0"].keys() == files["1"].keys()
    worst = {}
    for name, a in files["0"].items():
        b = files["1"][name]
        if a.dtype.kind in "fc" and a.size:
            worst[name] = float(np.max(np.abs(a - b))) / max(float(np.max(np.abs(a))), 1e-300)
        elif not name.startswith("parameters"):
            assert np.array_equal(a, b), name
    print("\nrelative differences, device start against host start:", {k: f"{v:.1e}" for k, v in worst.items() if v})
    for name, w in worst.items():
        a, b = files["0"][name], files["1"][name]
        if name.startswith("particles/"):
            # the trajectory: rounding differences grow at contacts, so a typical particle stays at rounding while
            # the worst of a million (several stiff contacts in a row) grows by up to ~1e7 in this run (6e-9 seen)
            d = np.abs(a - b).reshape(len(a), -1) / max(float(np.max(np.abs(a))), 1e-300)
            assert float(np.median(d[-1])) <= 1e-12 and w <= 1e-6, (name, float(np.median(d[-1])), w)
        else:
            # sums over the whole gas: rounding (1e-12 seen) carried through the Sonine ratios' cancellations (2e-10
            # seen); the overlap observables are differences of centre distances (~2R) ~1e-4 R deep, which cancel
            # about four more digits (2e-9 seen)
            tol = 1e-6 if name.split("/")[1] in ("elastic_energy", "max_overlap") else 1e-8
            assert w <= tol, (name, w)


def test_a_spheroid_start_drawn_on_the_device_is_the_host_start_to_rounding():
    """A large random start of rough spheroids (engine/setup/cell_rsa.py's cell rounds with their orientations, then
    the spins and L: engine/shapes/spheroid/cuda_backend.py draw_ellipsoid_start) built into a CUDA ensemble holds the
    state of the same start drawn on the host."""
    from engine.setup.params import derive
    from engine.setup.scene import drawn_on_host, initial_ellipsoids
    from engine.setup.spec import SimulationSpec
    from engine.shapes.spheroid.cuda_backend import CudaEllipsoidEnsemble
    from tests.engine.test_cuda_ellipsoid_simulator import contact

    spec = SimulationSpec(shape="ellipsoid", elongation=2.0, n_particles=1_100_000, volume_fraction=0.05, seed=7)
    p = derive(spec)
    assert p.start == "random"
    drawn = initial_ellipsoids(spec, p, on_device=True)
    c = contact()
    dev = CudaEllipsoidEnsemble([drawn], [c]).state(0)
    host = CudaEllipsoidEnsemble([drawn_on_host(drawn)], [c]).state(0)
    # centres: integer grid points times one unit (exact on both) unless a candidate within rounding of touching were
    # decided differently (it would move many particles, far beyond this bound)
    assert np.max(np.abs(dev["position"] - host["position"])) <= TOL * spec.box_length
    for key in ("velocity", "angular_velocity", "orientation"):
        diff = np.max(np.abs(dev[key] - host[key])) / np.max(np.abs(host[key]))
        print(f"\n{key}: |diff| / max {diff:.1e}")
        assert diff <= TOL, (key, diff)
