"""CUDA backend under the Numba CUDA simulator (CI has no GPU): same trajectory as the CPU backend.

The simulator must be switched on before numba.cuda is first imported, and other tests in the same
pytest process may import it first, so the comparison runs in child processes: two side by side (single
scenes; ensemble), one per core of the CI machine.
"""

import sys
from pathlib import Path

import numpy as np

from tests.cudasim import run_children

ROOT = Path(__file__).resolve().parents[2]


def tiny_system(n_side=3, seed=1, speed=1.0, spin=10.0):
    """27 spheres on a lattice with small gaps: contacts start within ~20 steps (speed = 0: never, the spheres
    only spin)."""
    from engine.backends.base import SphereSystem

    rng = np.random.default_rng(seed)
    a, spacing = 0.1, 0.204
    g = (np.arange(n_side) + 0.5) * spacing
    pos = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    n = len(pos)
    pos = pos + rng.uniform(-0.001, 0.001, size=pos.shape)
    vel = rng.normal(size=(n, 3)) * speed
    vel -= vel.mean(0)
    omega = rng.normal(size=(n, 3)) * spin
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


def _child(part: str) -> None:
    """One of the two independent parts of the check (the test runs them side by side): "scenes" (single
    scenes, both loops) or "ensemble"."""
    worst = {}
    if part == "scenes":
        _scenes(worst)
    else:
        assert part == "ensemble", part
        _ensemble(worst)
    for k, v in worst.items():
        print("max rel diff", k, f"{v:.2e}")
        assert v < 1e-11, (k, v)
    print("SIMULATOR-OK")


def _scenes(worst: dict) -> None:
    from engine.shapes.sphere.cpu_backend import CpuBackend
    from engine.backends.cuda import CudaBackend

    for label, c, multistep in (("rough+coulomb", contact(), True), ("rough", contact(friction=None), True),
                                ("smooth", contact(k_t=None, friction=None), True),
                                ("rough+coulomb per-phase", contact(), False)):
        cpu = CpuBackend(tiny_system(), c)
        gpu = CudaBackend(tiny_system(), c)
        gpu.e.multistep = multistep
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
        # the collision counter: every contact begun so far, the same on both backends
        assert ca["collisions"] == cb["collisions"] >= ca["contacts"], (label, ca["collisions"], cb["collisions"])
        for key in ("kinetic_energy_translational", "kinetic_energy_rotational", "elastic_energy"):
            assert abs(ca[key] - cb[key]) <= 1e-9 * abs(ca[key]) + 1e-300, (label, key, ca[key], cb[key])
        assert gpu.late_rebuilds == 0 and gpu.builds >= 2, (label, gpu.builds, gpu.late_rebuilds)
        print(label, "contacts", ca["contacts"], "builds cpu/gpu", cpu.builds, gpu.builds)
    # orientations switched on mid-run (set_contact): the steps run without them leave nothing pending
    c_off = contact(orientation=False)
    cpu = CpuBackend(tiny_system(), c_off)
    gpu = CudaBackend(tiny_system(), c_off)
    for be in (cpu, gpu):
        be.advance(17)
        be.set_contact(contact())
        be.advance(23)
    a, b = cpu.state(), gpu.state()
    assert np.abs(a["orientation"] - np.asarray(tiny_system().orientation)).max() > 1e-3
    worst[("orientation switched on", "orientation")] = float(np.max(np.abs(a["orientation"] - b["orientation"])))
    # precision 'mixed' (float64 positions, float32 state): the CUDA code against the CPU's, both loops; the
    # simulator's numpy scalar arithmetic rounds float32 intermediates differently from compiled numba, so the
    # agreement is to float32 rounding (6e-8) through ~20 contact steps, not to 1e-11
    for multistep in (True, False):
        cpu = CpuBackend(tiny_system(), contact(precision="mixed"))
        gpu = CudaBackend(tiny_system(), contact(precision="mixed"))
        gpu.e.multistep = multistep
        for be in (cpu, gpu):
            be.advance(40)
        a, b = cpu.state(), gpu.state()
        assert a["position"].dtype == b["position"].dtype == np.float64 and b["velocity"].dtype == np.float32
        assert cpu.observe()["contacts"] == gpu.observe()["contacts"] > 0
        for key in ("position", "velocity", "angular_velocity", "orientation"):
            d = float(np.max(np.abs(np.asarray(a[key], np.float64) - b[key])) / np.max(np.abs(a[key])))
            print("mixed", multistep, key, f"{d:.2e}")
            assert d < 1e-5, ("mixed", multistep, key, d)


def _ensemble(worst: dict) -> None:
    """Three different scenes advanced together equal each scene run alone on the CPU; a fourth that
    blows up (time step far too large) fails alone, at its own step, without disturbing the others."""
    from engine.shapes.sphere.cpu_backend import CpuBackend
    from engine.backends.cuda import CudaEnsemble
    from engine.errors import InstabilityError

    scenes = [(tiny_system(seed=1), contact()),
              (tiny_system(seed=2), contact(k_t=None, friction=None, gamma_n_coef=2.0 * np.sqrt(1e5) * 0.4)),
              (tiny_system(n_side=2, seed=3), contact(friction=None, skin=0.03, dt=np.pi * np.sqrt(0.5e-5) / 35)),
              (tiny_system(seed=4), contact(dt=np.pi * np.sqrt(0.5e-5) * 3, overlap_limit=0.05))]
    ens = CudaEnsemble([s for s, _ in scenes], [c for _, c in scenes])
    ens.warmup()
    cpus = [CpuBackend(s, c) for s, c in scenes[:3]]
    failed = {}
    for chunk in (17, 23):
        failed.update(ens.advance(chunk))
        for cpu in cpus:
            cpu.advance(chunk)
    assert list(failed) == [3] and isinstance(failed[3], InstabilityError), failed
    assert "overlap" in str(failed[3]) and 0 <= failed[3].step < 40, str(failed[3])
    assert not ens.active[3] and ens.active[:3].all()
    obs = ens.observe()
    assert obs[3] is None
    for k, cpu in enumerate(cpus):
        a, b = cpu.state(), ens.state(k)
        for key in ("position", "velocity", "angular_velocity", "orientation"):
            scale = np.max(np.abs(a[key])) + 1e-300
            worst[(f"ensemble scene {k}", key)] = float(np.max(np.abs(a[key] - b[key])) / scale)
        ca = cpu.observe()
        assert ca["contacts"] == obs[k]["contacts"] and ca["contacts"] > 0, (k, ca, obs[k])
        assert ca["collisions"] == obs[k]["collisions"] > 0, (k, ca["collisions"], obs[k]["collisions"])
        pa, _ = cpu.contacts()
        pb, _ = ens.contacts(k)
        assert np.array_equal(pa[np.lexsort(pa.T[::-1])], pb[np.lexsort(pb.T[::-1])]), k
    # observe reads the sums of the current step each time (one host buffer, reused): the same without steps in
    # between, new ones after steps
    now = ens.observe()
    assert ens.observe() == now
    ens.advance(7)
    later = ens.observe()
    for k in range(3):
        assert later[k]["kinetic_energy_translational"] != now[k]["kinetic_energy_translational"], k
    ens.deactivate(0)
    before = ens.state(0)["position"]
    ens.advance(5)
    assert np.array_equal(before, ens.state(0)["position"]) and ens.observe()[0] is None


def test_cuda_backend_matches_cpu_under_simulator():
    children = {part: [__file__, "--child", part] for part in ("scenes", "ensemble")}
    for part, (rc, out, err) in run_children(children, timeout=600).items():
        assert rc == 0 and "SIMULATOR-OK" in out, (part, out[-4000:] + err[-4000:])


if __name__ == "__main__" and "--child" in sys.argv:
    sys.path.insert(0, str(ROOT))
    from tests.cudasim import fast_block_polling

    fast_block_polling()
    _child(sys.argv[sys.argv.index("--child") + 1])
