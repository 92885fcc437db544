"""CUDA backend under the Numba CUDA simulator (CI has no GPU): same trajectory as the CPU backend.

The simulator must be switched on before numba.cuda is first imported, and other tests in the same
pytest process may import it first, so the comparison runs in a child process.
"""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]


def tiny_system(n_side=3, seed=1):
    """27 spheres on a lattice with small gaps: contacts start within ~20 steps."""
    from engine.backends.base import SphereSystem

    rng = np.random.default_rng(seed)
    a, spacing = 0.1, 0.204
    g = (np.arange(n_side) + 0.5) * spacing
    pos = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    n = len(pos)
    pos = pos + rng.uniform(-0.001, 0.001, size=pos.shape)
    vel = rng.normal(size=(n, 3))
    vel -= vel.mean(0)
    omega = rng.normal(size=(n, 3)) * 10.0
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    m = np.full(n, 1.0)
    return SphereSystem(box_length=n_side * spacing, position=pos % (n_side * spacing), velocity=vel,
                        angular_velocity=omega, orientation=q, radius=np.full(n, a), mass=m,
                        inertia=0.4 * m * a * a)


def contact(**kw):
    from engine.backends.base import ContactParams

    k_n = 1.0e5
    t_c = np.pi * np.sqrt(0.5 / k_n)
    base = dict(k_n=k_n, gamma_n_coef=2.0 * np.sqrt(k_n) * 0.2, k_t=k_n * 2 / 7 * 0.5, friction=0.3,
                dt=t_c / 50, skin=0.02, precision="float64", orientation=True, overlap_limit=0.2)
    base.update(kw)
    return ContactParams(**base)


def _child() -> None:
    from engine.backends.cpu import CpuBackend
    from engine.backends.cuda import CudaBackend

    worst = {}
    for label, c in (("rough+coulomb", contact()), ("rough", contact(friction=None)),
                     ("smooth", contact(k_t=None, friction=None))):
        cpu = CpuBackend(tiny_system(), c)
        gpu = CudaBackend(tiny_system(), c)
        assert gpu.device == "CUDA simulator"
        gpu.warmup()
        for chunk in (17, 23):
            cpu.advance(chunk)
            gpu.advance(chunk)
        a, b = cpu.state(), gpu.state()
        for key in ("position", "velocity", "angular_velocity", "orientation"):
            scale = np.max(np.abs(a[key])) + 1e-300
            worst[(label, key)] = float(np.max(np.abs(a[key] - b[key])) / scale)
        pa, sa = cpu.contacts()
        pb, sb = gpu.contacts()
        oa, ob = np.lexsort(pa.T[::-1]), np.lexsort(pb.T[::-1])
        assert np.array_equal(pa[oa], pb[ob]), (label, pa, pb)
        if len(sa):
            worst[(label, "springs")] = float(np.max(np.abs(sa[oa] - sb[ob])) / np.max(np.abs(sa)))
        ca, cb = cpu.observe(), gpu.observe()
        assert ca["contacts"] == cb["contacts"] and ca["contacts"] > 0, (label, ca, cb)
        for key in ("kinetic_energy_translational", "kinetic_energy_rotational", "elastic_energy"):
            assert abs(ca[key] - cb[key]) <= 1e-9 * abs(ca[key]) + 1e-300, (label, key, ca[key], cb[key])
        assert gpu.late_rebuilds == 0 and gpu.builds >= 2, (label, gpu.builds, gpu.late_rebuilds)
        print(label, "contacts", ca["contacts"], "builds cpu/gpu", cpu.builds, gpu.builds)
    for k, v in worst.items():
        print("max rel diff", k, f"{v:.2e}")
        assert v < 1e-11, (k, v)
    print("SIMULATOR-OK")


def test_cuda_backend_matches_cpu_under_simulator():
    env = {**os.environ, "NUMBA_ENABLE_CUDASIM": "1", "PYTHONPATH": str(ROOT)}
    r = subprocess.run([sys.executable, __file__, "--child"], env=env, cwd=ROOT, capture_output=True,
                       text=True, timeout=600)
    assert r.returncode == 0 and "SIMULATOR-OK" in r.stdout, r.stdout[-4000:] + r.stderr[-4000:]


if __name__ == "__main__" and "--child" in sys.argv:
    _child()
