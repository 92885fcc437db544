"""The CUDA observe kernels' Sonine moments (spheres and spheroids) equal the CPU observe under the Numba CUDA
simulator, after a few steps with contacts (child process: the simulator must be on before numba.cuda is
imported). Tolerance 1e-10 relative: the same float64 per-particle terms summed in another order."""

import subprocess
import sys
from pathlib import Path

from tests.cudasim import child_env

ROOT = Path(__file__).resolve().parents[2]


def _close(a, b, rel=1e-10):
    return abs(a - b) <= rel * max(abs(a), abs(b)) + 1e-300


def _child() -> None:
    import numpy as np

    from engine.shapes.sphere.cpu_backend import CpuBackend
    from engine.shapes.spheroid.cpu_backend import CpuEllipsoidBackend
    from engine.backends.cuda import CudaBackend
    from engine.shapes.spheroid.cuda_backend import CudaEllipsoidBackend
    from engine.physics.sonine import sonine_observables
    from tests.engine import test_cuda_ellipsoid_simulator as E
    from tests.engine import test_cuda_simulator as S

    cases = (("spheres", CpuBackend(S.tiny_system(), S.contact()), CudaBackend(S.tiny_system(), S.contact())),
             ("spheroids", CpuEllipsoidBackend(E.tiny_ellipsoids(mixed=True), E.contact()),
              CudaEllipsoidBackend(E.tiny_ellipsoids(mixed=True), E.contact())))
    for label, cpu, gpu in cases:
        assert gpu.device == "CUDA simulator"
        cpu.advance(12)
        gpu.advance(12)
        ca, cb = cpu.observe(), gpu.observe()
        assert ca["contacts"] > 0 and ca["sonine_rotational_dof"] == cb["sonine_rotational_dof"]
        for x, y in zip(ca["energy_moments"], cb["energy_moments"]):
            assert x > 0 and _close(x, y), (label, ca["energy_moments"], cb["energy_moments"])
        n = len(cpu.state()["position"])
        ra, rb = sonine_observables(ca, n), sonine_observables(cb, n)
        for key in ra:
            assert np.isfinite(ra[key]) and abs(ra[key] - rb[key]) < 1e-9, (label, key, ra[key], rb[key])
        print(label, ra)
    print("SONINE-SIMULATOR-OK")


def test_cuda_observe_sonine_moments_match_cpu_under_simulator():
    env = child_env()
    r = subprocess.run([sys.executable, __file__, "--child"], env=env, cwd=ROOT, capture_output=True,
                       text=True, timeout=600)
    assert r.returncode == 0 and "SONINE-SIMULATOR-OK" in r.stdout, r.stdout[-4000:] + r.stderr[-4000:]


if __name__ == "__main__" and "--child" in sys.argv:
    sys.path.insert(0, str(ROOT))
    from tests.cudasim import fast_block_polling

    fast_block_polling()
    _child()
