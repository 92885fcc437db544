"""CUDA ellipsoid backend under the Numba CUDA simulator (CI has no GPU): the CPU ellipsoid backend's trajectory.

The GPU kernels call the same njit physics as engine/shapes/spheroid/cpu_backend.py, evaluate each pair with the
lower id as "A" and sum the forces in the same list order, and the many-steps-per-launch loop rebuilds the
list at the same step as the CPU; so in float64 the GPU run under the simulator (whose arithmetic is the
host's IEEE double arithmetic, and whose physics calls are the very CPU-compiled njit functions) is expected
to equal the CPU run bit for bit. The one-launch-per-phase loop decides rebuilds one step ahead (it may
rebuild earlier than the CPU, which reorders neighbours), so there only rounding differences are allowed.
The comparison runs in child processes because the simulator must be switched on before numba.cuda is first
imported; two of them side by side (single scenes; ensemble), one per core of the CI machine.

The light test (:func:`test_both_loops_run_the_one_spheroid_law`) runs the spheroid's one pair evaluator and
rotation step (engine/shapes/spheroid/law.py) through both loops on 8 spheroids: the CPU and simulator
trajectories agree bit for bit, and both backends' ``pair`` and ``rotate`` are seen calling law.py's functions.
"""

import sys
from pathlib import Path

import numpy as np
import pytest

from tests.cudasim import run_children


ROOT = Path(__file__).resolve().parents[2]


def tiny_ellipsoids(xi=1.5, n_side=3, seed=1, mixed=False, speed=1.5):
    """n_side^3 prolate spheroids (volume of a sphere of radius 0.1 m) on a cubic lattice with random
    orientations, scaled so that the closest pair is 1 % short of touching (W_0 = 1.01): contacts start
    within a few steps. mixed: every other particle has elongation 1 + (xi - 1) / 2 (non-uniform scene)."""
    from engine.backends.base import EllipsoidSystem
    from engine.physics.ellipsoid import ellipsoid_overlap_pw

    rng = np.random.default_rng(seed)
    r_eq = 0.1
    n = n_side ** 3
    xis = np.full(n, float(xi))
    if mixed:
        xis[1::2] = 1.0 + (xi - 1.0) / 2.0
    a = r_eq * xis ** (2.0 / 3.0)
    b = r_eq / xis ** (1.0 / 3.0)
    axes = np.stack([a, b, b], 1)
    spacing = 1.0
    g = (np.arange(n_side) + 0.5) * spacing
    pos = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    pos = pos + rng.uniform(-0.05, 0.05, size=pos.shape) * spacing
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    box = n_side * spacing
    w0 = np.inf
    for i in range(n):
        for j in range(i + 1, n):
            r = pos[j] - pos[i]
            r -= box * np.round(r / box)
            if np.linalg.norm(r) < 2.0 * spacing:
                w0 = min(w0, ellipsoid_overlap_pw(r[0], r[1], r[2], *q[i], *axes[i], *q[j], *axes[j], 1e-15, 0.5)[1])
    f = 1.01 / w0  # W_0 scales with the centre distances
    pos, box = pos * f, box * f
    vel = rng.normal(size=(n, 3)) * speed
    vel -= vel.mean(0)
    m = np.full(n, 1.0)
    inertia = np.stack([0.4 * m * b * b, 0.2 * m * (a * a + b * b), 0.2 * m * (a * a + b * b)], 1)
    omega = rng.normal(size=(n, 3)) * 10.0
    return EllipsoidSystem(box_length=box, position=pos % box, velocity=vel, angular_velocity=omega,
                           orientation=q, semi_axes=axes, mass=m, inertia=inertia)


def contact(**kw):
    from engine.backends.base import ContactParams

    k_n = 1.0e5
    t_c = np.pi * np.sqrt(0.5 / k_n)
    base = dict(k_n=k_n, gamma_n_coef=2.0 * np.sqrt(k_n) * 0.2, k_t=None, friction=None, dt=t_c / 50,
                skin=0.01, precision="float64", orientation=True, overlap_limit=0.2)
    base.update(kw)
    return ContactParams(**base)


KEYS = ("position", "velocity", "angular_velocity", "orientation")


def _compare(label, cpu, gpu, worst, exact):
    a, b = cpu.state(), gpu.state()
    for key in KEYS:
        scale = np.max(np.abs(a[key])) + 1e-300
        worst[(label, key, exact)] = float(np.max(np.abs(a[key] - b[key])) / scale)
    pa, sa = cpu.contacts()
    pb, sb = gpu.contacts()
    oa, ob = np.lexsort(pa.T[::-1]), np.lexsort(pb.T[::-1])
    assert np.array_equal(pa[oa], pb[ob]), (label, pa, pb)
    if len(sa):
        worst[(label, "contact slots", exact)] = float(np.max(np.abs(sa[oa] - sb[ob])) / np.max(np.abs(sa)))
    ca, cb = cpu.observe(), gpu.observe()
    assert ca["contacts"] == cb["contacts"] and ca["contacts"] > 0, (label, ca, cb)
    assert cb["rotational_dof"] == ca["rotational_dof"] == (3 if cpu_rough(cpu) else 2)
    for key in ("kinetic_energy_translational", "kinetic_energy_rotational", "kinetic_energy_rotational_active",
                "elastic_energy", "max_overlap"):
        assert abs(ca[key] - cb[key]) <= 1e-12 * abs(ca[key]) + 1e-300, (label, key, ca[key], cb[key])
    assert np.allclose(ca["momentum"], cb["momentum"], rtol=0, atol=1e-12 * np.abs(a["velocity"]).sum())
    return ca


def cpu_rough(be) -> bool:
    return bool(getattr(be, "rough", False) or getattr(getattr(be, "ens", None), "rough", False))


def _rough(e_t=0.5, **kw):
    from engine.setup.params import k_t_paper

    return contact(k_t=k_t_paper(e_t, 1.0e5), **kw)


def _child(part: str) -> None:
    """One of the two independent parts of the check (the test runs them side by side): "scenes" (single
    scenes, both loops, float64 and float32) or "ensemble"; or the light check "law"."""
    worst = {}
    if part == "law":
        _law(worst)
    elif part == "scenes":
        _scenes(worst)
        _float32(worst)
    else:
        assert part == "ensemble", part
        _ensemble(worst)
    for (label, key, exact), v in worst.items():
        print("max rel diff", label, key, f"{v:.2e}", "(expected 0)" if exact else "(rounding allowed)")
    for (label, key, exact), v in worst.items():
        assert v == 0.0 if exact else v < 1e-11, (label, key, v)
    print("SIMULATOR-OK")


def _scenes(worst: dict) -> None:
    from engine.shapes.spheroid.cpu_backend import CpuEllipsoidBackend
    from engine.shapes.spheroid.cuda_backend import CudaEllipsoidBackend

    for label, system, c, multistep in (
            ("xi=1.5 multistep", tiny_ellipsoids(1.5, seed=1), contact(), True),
            ("xi=2.5 multistep", tiny_ellipsoids(2.5, seed=2), contact(), True),
            ("xi=2.5 per-phase", tiny_ellipsoids(2.5, seed=2), contact(), False),
            ("mixed xi 1.5/2.5 multistep", tiny_ellipsoids(2.5, seed=3, mixed=True), contact(), True),
            # rough contacts: the spring and the contact's k_t in the list slots
            ("rough xi=2.0 multistep", tiny_ellipsoids(2.0, seed=8), _rough(), True),
            ("rough Coulomb mixed xi per-phase", tiny_ellipsoids(2.5, seed=7, mixed=True), _rough(0.8, friction=0.1),
             False)):
        cpu = CpuEllipsoidBackend(system, c)
        gpu = CudaEllipsoidBackend(system, c)
        gpu.e.multistep = multistep
        assert gpu.device == "CUDA simulator" and gpu.e.uniform == ("mixed" not in label)
        gpu.warmup()
        for chunk in (17, 23):
            cpu.advance(chunk)
            gpu.advance(chunk)
        obs = _compare(label, cpu, gpu, worst, exact=multistep)
        assert gpu.late_rebuilds == 0 and gpu.builds >= 2 and cpu.builds >= 2, (label, cpu.builds, gpu.builds)
        print(label, "contacts", obs["contacts"], "max overlap / b", f"{obs['max_overlap']:.3g}",
              "builds cpu/gpu", cpu.builds, gpu.builds)


def _float32(worst: dict) -> None:
    """float32 on the GPU kernels against float64 on the CPU (the float32 path runs and stays close; the
    CPU float32 loop promotes m12 to float64, the GPU one does not, so no bitwise comparison)."""
    from engine.shapes.spheroid.cpu_backend import CpuEllipsoidBackend
    from engine.shapes.spheroid.cuda_backend import CudaEllipsoidBackend

    system = tiny_ellipsoids(2.5, seed=2)
    cpu = CpuEllipsoidBackend(system, contact())
    gpu = CudaEllipsoidBackend(system, contact(precision="float32"))
    assert gpu.state()["position"].dtype == np.float32
    cpu.advance(40)
    gpu.advance(40)
    a, b = cpu.state(), gpu.state()
    dx = float(np.max(np.abs(a["position"] - b["position"])) / system.box_length)
    ca, cb = cpu.observe(), gpu.observe()
    print(f"float32 GPU vs float64 CPU after 40 steps: max |dx|/L {dx:.2e}, "
          f"contacts {ca['contacts']} / {cb['contacts']}")
    assert dx < 1e-5 and cb["contacts"] > 0
    assert abs(cb["kinetic_energy_translational"] / ca["kinetic_energy_translational"] - 1) < 1e-3


def _ensemble(worst: dict) -> None:
    """Four different ellipsoid scenes (one rough) advanced together equal each scene run alone on the CPU (both
    GPU loops); a fifth that blows up (time step far too large) fails alone without disturbing the others."""
    from engine.shapes.spheroid.cpu_backend import CpuEllipsoidBackend
    from engine.shapes.spheroid.cuda_backend import CudaEllipsoidEnsemble
    from engine.errors import InstabilityError

    t_c = np.pi * np.sqrt(0.5e-5)
    # a rough scene packed with frictionless ones (the worker packs them together): the ensemble compiles the
    # rough law, the frictionless scenes run it with f_t = 0 and must still equal their lone runs
    scenes = [(tiny_ellipsoids(1.5, seed=4), contact()),
              (tiny_ellipsoids(2.5, seed=8), contact(gamma_n_coef=2.0 * np.sqrt(1e5) * 0.4)),
              (tiny_ellipsoids(2.0, n_side=2, seed=9), contact(skin=0.015, dt=t_c / 35)),
              (tiny_ellipsoids(2.0, seed=8), _rough()),
              (tiny_ellipsoids(2.0, seed=7, speed=3.0), contact(dt=t_c * 3, overlap_limit=0.05))]
    for multistep in (True, False):
        ens = CudaEllipsoidEnsemble([s for s, _ in scenes], [c for _, c in scenes])
        ens.multistep = multistep
        ens.warmup()
        cpus = [CpuEllipsoidBackend(s, c) for s, c in scenes[:4]]
        failed = {}
        for chunk in (17, 23):
            failed.update(ens.advance(chunk))
            for cpu in cpus:
                cpu.advance(chunk)
        assert list(failed) == [4] and isinstance(failed[4], InstabilityError), failed
        assert 0 <= failed[4].step < 40, str(failed[4])
        assert not ens.active[4] and ens.active[:4].all()
        obs = ens.observe()
        assert obs[4] is None
        loop = "multistep" if multistep else "per-phase"
        for k, cpu in enumerate(cpus):
            view = _SceneOf(ens, k)
            _compare(f"ensemble {loop} scene {k}", cpu, view, worst, exact=multistep)
        ens.deactivate(0)
        before = ens.state(0)["position"]
        ens.advance(5)
        assert np.array_equal(before, ens.state(0)["position"]) and ens.observe()[0] is None


class _SceneOf:
    """Scene k of an ensemble with a single backend's state/contacts/observe."""

    def __init__(self, ens, k):
        self.ens, self.k = ens, k

    def state(self):
        return self.ens.state(self.k)

    def contacts(self):
        return self.ens.contacts(self.k)

    def observe(self):
        return self.ens.observe()[self.k]


class _Spy:
    """Stands for an njit function under a module's name: counts the calls and passes them on."""

    def __init__(self, fn):
        self.fn, self.calls = fn, 0

    def __call__(self, *args):
        self.calls += 1
        return self.fn(*args)


def _spy(module, name: str) -> _Spy:
    spy = _Spy(getattr(module, name))
    setattr(module, name, spy)
    return spy


def _cpu_slots_through_law(cpu) -> int:
    """Every list slot of the CPU backend's present state through the compiled ``pair`` and through its
    plain-Python source with law.spheroid_pair spied on: the same results and history, bit for bit, and the law
    called for every slot past the bounding-sphere test. Returns the slots in contact."""
    from engine.shapes.spheroid import kernels, law

    args = (cpu.pos, cpu.vel, cpu.vel_p, cpu._spin, cpu._quat_arg, cpu._rad_list, cpu.inv_m)
    tail = (cpu.box_c, cpu.inv_box, cpu.half, cpu.k_n, cpu.gn_coef, cpu._law, cpu.dt, cpu._ext)
    in_contact = 0
    for i in range(cpu.n):
        for kk in range(cpu.nn[i]):
            j = cpu.nbr[i, kk]
            h_py, h_jit = cpu.hist.copy(), cpu.hist.copy()
            g_jit = kernels.pair(i, kk, j, *args, h_jit, *tail)
            spy = _spy(kernels, "spheroid_pair")
            try:
                g_py = kernels.pair.py_func(i, kk, j, *args, h_py, *tail)
            finally:
                kernels.spheroid_pair = law.spheroid_pair
            assert tuple(map(float, g_py)) == tuple(map(float, g_jit)), (i, kk, g_py, g_jit)
            assert np.array_equal(h_py, h_jit), (i, kk)
            d = cpu.pos[j] - cpu.pos[i]
            d -= cpu.box * np.round(d / cpu.box)
            reached = np.dot(d, d) < (cpu._rad_list[i] + cpu._rad_list[j]) ** 2 or cpu.hist[i, kk, 3] > 0
            assert (spy.calls > 0) == reached, (i, kk, spy.calls)
            in_contact += g_py[6] > 0
    return in_contact


def _cpu_rotation_through_law(cpu) -> None:
    """Particle 0's CPU rotation step through the compiled ``rotate`` and through its plain-Python source with
    law.spheroid_rotation spied on: the same angular momentum, orientation and predicted spin, bit for bit."""
    from engine.shapes.spheroid import kernels, law

    out = []
    for python in (False, True):
        spin, quat, ext = cpu._spin.copy(), cpu.quat.copy(), tuple(a.copy() for a in cpu._ext)
        torque = np.full_like(cpu.torque, 1e-3)
        spy = _spy(kernels, "spheroid_rotation") if python else None
        try:
            (kernels.rotate.py_func if python else kernels.rotate)(
                0, 0.0, cpu.pos, cpu.vel, spin, quat, torque, (torque[0, 0], torque[0, 1], torque[0, 2]),
                cpu._spin_inv, cpu.x_ref, ext, cpu.dt, cpu.dt * 0.5, cpu.dt, cpu.box_c, cpu.inv_box, cpu.half, 0)
        finally:
            kernels.spheroid_rotation = law.spheroid_rotation
        out.append((spin, quat, ext[2]))
    assert spy.calls == 1
    for a, b in zip(*out):
        assert np.array_equal(a, b)
    assert not np.array_equal(out[0][1][0], cpu.quat[0]) and not np.array_equal(out[0][0][0], cpu._spin[0])


def _law(worst: dict) -> None:
    """8 spheroids, frictionless and rough, 2 x 12 steps in both loops (the CUDA one under the simulator, many
    steps per launch: bit for bit the CPU's) through contacts, with law.py's functions spied on in device.py: the
    device pair and rotate ran them (the rough spins only when rough; spheroid_gap: contacts that started after a
    screened step); the CPU's pair and rotate run them too (:func:`_cpu_slots_through_law`,
    :func:`_cpu_rotation_through_law`)."""
    from engine.shapes.spheroid import device
    from engine.shapes.spheroid.cpu_backend import CpuEllipsoidBackend
    from engine.shapes.spheroid.cuda_backend import CudaEllipsoidBackend

    spies = {name: _spy(device, name)
             for name in ("spheroid_pair", "spheroid_gap", "spheroid_rotation", "mid_step_omega")}
    for label, system, c in (("law smooth xi=2", tiny_ellipsoids(2.0, n_side=2, seed=8), contact()),
                             ("law rough xi=2", tiny_ellipsoids(2.0, n_side=2, seed=8), _rough())):
        calls = {name: spy.calls for name, spy in spies.items()}
        cpu = CpuEllipsoidBackend(system, c)
        gpu = CudaEllipsoidBackend(system, c)
        gpu.e.multistep = True
        assert gpu.device == "CUDA simulator"
        slots = 0
        for chunk in (12, 12):
            cpu.advance(chunk)
            gpu.advance(chunk)
            slots += _cpu_slots_through_law(cpu)
        _cpu_rotation_through_law(cpu)
        obs = _compare(label, cpu, gpu, worst, exact=True)
        new = {name: spy.calls - calls[name] for name, spy in spies.items()}
        # the gap of a contact that starts after a screened step: the retry path of both loops' pair ran too
        assert new["spheroid_pair"] > 0 and new["spheroid_gap"] > 0, (label, new)
        assert new["spheroid_rotation"] >= 24 * cpu.n, (label, new)
        assert (new["mid_step_omega"] > 0) == ("rough" in label), (label, new)
        assert slots > 0, label
        print(label, "contacts", obs["contacts"], "device law calls", new, "CPU slots in contact", slots)


def test_both_loops_run_the_one_spheroid_law():
    (rc, out, err), = run_children({"law": [__file__, "--child", "law"]}, timeout=300).values()
    assert rc == 0 and "SIMULATOR-OK" in out, out[-4000:] + err[-4000:]


@pytest.mark.heavy   # the CUDA simulator on whole spheroid scenes: about 1.5 min of CPU
def test_cuda_ellipsoid_backend_matches_cpu_under_simulator():
    children = {part: [__file__, "--child", part] for part in ("scenes", "ensemble")}
    for part, (rc, out, err) in run_children(children, timeout=900).items():
        assert rc == 0 and "SIMULATOR-OK" in out, (part, out[-4000:] + err[-4000:])


if __name__ == "__main__" and "--child" in sys.argv:
    sys.path.insert(0, str(ROOT))
    from tests.cudasim import fast_block_polling

    fast_block_polling()
    _child(sys.argv[sys.argv.index("--child") + 1])
