"""Real-GPU checks of the CUDA ellipsoid backend (skipped without a GPU): compiled kernels agree with the CPU.

CPU <-> GPU agreement for ellipsoids as for spheres (tests/gpu/test_cuda_gpu.py). The compiled GPU
kernels may contract a*b + c into fused multiply-adds, so the trajectories differ from the CPU's from the
last bit on and the difference grows through the contacts; the bound is that of the sphere test, 1e-9 of
the box edge in positions after 200 steps with contacts and rebuilds.

Run on the GPU machine: ``python -m pytest tests/gpu/test_cuda_ellipsoid_gpu.py -q -s``.
"""

import dataclasses
import math

import numpy as np
import pytest

from engine.backends.base import cuda_available

pytestmark = pytest.mark.skipif(not cuda_available(), reason="needs a CUDA GPU")


def _gas(n=4096, xi=2.0, phi=0.058, precision="float64", seed=3, e_n=0.9):
    """Spec-built Rubio-Largo et al. (2015) start (bounding spheres on an fcc lattice, random orientations)."""
    from engine.setup.params import derive
    from engine.setup.scene import initial_ellipsoids
    from engine.driver.simulate import contact_params
    from engine.setup.spec import SimulationSpec

    spec = SimulationSpec(shape="ellipsoid", elongation=xi, n_particles=n, volume_fraction=phi, e_n=e_n, e_t=-1.0,
                          precision=precision, seed=seed, velocity_rms=3.5,
                          box_length=2.0 * (n / 4096) ** (1 / 3))
    p = derive(spec)
    return initial_ellipsoids(spec, p), contact_params(spec, p, thermalization=False)


def _dense(n_side=16, xi=2.0, precision="float64", seed=3, speed=1.0):
    """n_side^3 spheroids (r_eq = 0.1 m, m = 1 kg) on a cubic lattice of spacing 0.27 m < 2a with random
    orientations redrawn until every neighbour pair is apart by at least 0.5 % (Perram-Wertheim W_0 >= 1.005):
    many pairs start nearly touching, so contacts form within a few steps."""
    from engine.backends.base import ContactParams, EllipsoidSystem
    from engine.physics.ellipsoid import ellipsoid_overlap_pw

    rng = np.random.default_rng(seed)
    r_eq, spacing = 0.1, 0.27
    a, b = r_eq * xi ** (2 / 3), r_eq / xi ** (1 / 3)
    n = n_side ** 3
    g = np.arange(n_side)
    idx = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    pos = (idx + 0.5) * spacing
    box = n_side * spacing
    offsets = [o for o in np.ndindex(3, 3, 3) if o > (1, 1, 1)]  # 13 half-space neighbours
    pairs = []
    for o in offsets:
        j = (idx + np.array(o) - 1) % n_side
        pairs.append(np.stack([np.arange(n), (j[:, 0] * n_side + j[:, 1]) * n_side + j[:, 2]], 1))
    pairs = np.concatenate(pairs)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    for _ in range(200):
        bad = set()
        for i, j in pairs:
            r = pos[j] - pos[i]
            r -= box * np.round(r / box)
            if ellipsoid_overlap_pw(r[0], r[1], r[2], *q[i], a, b, b, *q[j], a, b, b, 1e-15, 0.5)[1] < 1.005:
                bad.add(int(j))
        if not bad:
            break
        bad = np.array(sorted(bad))
        qn = rng.normal(size=(len(bad), 4))
        q[bad] = qn / np.linalg.norm(qn, axis=1, keepdims=True)
    else:
        raise RuntimeError("no overlap-free orientations found")
    vel = rng.normal(size=(n, 3)) * speed
    vel -= vel.mean(0)
    m = np.ones(n)
    i_perp = 0.2 * (a * a + b * b)
    system = EllipsoidSystem(box_length=box, position=pos, velocity=vel,
                             angular_velocity=rng.normal(size=(n, 3)) * 10.0, orientation=q,
                             semi_axes=np.tile([a, b, b], (n, 1)), mass=m,
                             inertia=np.tile([0.4 * b * b, i_perp, i_perp], (n, 1)))
    k_n = 1.0e5
    c = ContactParams(k_n=k_n, gamma_n_coef=2.0 * np.sqrt(k_n) * 0.2, k_t=None, friction=None,
                      dt=np.pi * np.sqrt(0.5 / k_n) / 50, skin=0.02, precision=precision, orientation=True,
                      overlap_limit=0.2)
    return system, c


def _rel(a, b, system):
    box = system.box_length
    dx = np.abs(a["position"] - b["position"].astype(np.float64))
    dx = np.minimum(dx, box - dx)  # a wrap across the boundary is no difference
    out = {"x": float(dx.max() / box)}
    for key, name in (("velocity", "v"), ("angular_velocity", "w")):
        out[name] = float(np.abs(a[key] - b[key]).max() / np.abs(a[key]).max())
    out["q"] = float(np.abs(np.abs(np.sum(a["orientation"] * b["orientation"], 1)) - 1).max())
    return out


def test_real_gpu_ellipsoid_kernels_compile_and_device_is_named():
    from engine.backends.registry import make_backend
    from engine.backends.ensemble import make_ensemble

    system, c = _gas(n=512)
    be = make_backend("auto", system, c)
    assert be.name == "cuda" and be.device and type(be).__name__ == "CudaEllipsoidBackend"
    be.warmup()
    be.advance(5)
    ens = make_ensemble("auto", [system, system], [c, c])
    assert type(ens).__name__ == "CudaEllipsoidEnsemble"


def _lockstep(system, c, multistep):
    """The CPU and the GPU backend of one scene advanced side by side, 4 x 50 steps: (cpu, gpu, contacts after
    each 50)."""
    from engine.shapes.spheroid.cpu_backend import CpuEllipsoidBackend
    from engine.shapes.spheroid.cuda_backend import CudaEllipsoidBackend

    cpu, gpu = CpuEllipsoidBackend(system, c), CudaEllipsoidBackend(system, c)
    gpu.e.multistep = multistep
    contacts = []
    for _ in range(4):
        cpu.advance(50)
        gpu.advance(50)
        contacts.append(cpu.observe()["contacts"])
    return cpu, gpu, contacts


@pytest.mark.parametrize("xi,multistep", [(2.0, True), (2.0, False), (1.5, True)])
def test_cpu_and_gpu_agree_float64_200_steps(xi, multistep):
    """4096 ellipsoids with contacts, 200 steps, positions within 1e-9 of L."""
    system, c = _dense(xi=xi)
    cpu, gpu, contacts = _lockstep(system, c, multistep)
    a, b = cpu.state(), gpu.state()
    obs, o2 = cpu.observe(), gpu.observe()
    r = _rel(a, b, system)
    print(f"\nxi={xi} {'multistep' if multistep else 'per-phase'}: contacts {contacts}, builds cpu {cpu.builds} "
          f"gpu {gpu.builds}, late {gpu.late_rebuilds}; max rel diff x {r['x']:.2e} v {r['v']:.2e} "
          f"w {r['w']:.2e} |q.q'|-1 {r['q']:.2e}")
    assert contacts[-1] > 100 and gpu.builds > 1, (contacts, gpu.builds)
    assert gpu.late_rebuilds == 0
    assert r["x"] <= 1e-9, r
    assert r["v"] <= 1e-6 and r["w"] <= 1e-6 and r["q"] <= 1e-9, r
    assert o2["contacts"] == obs["contacts"]
    for key in ("kinetic_energy_translational", "kinetic_energy_rotational", "kinetic_energy_rotational_active"):
        assert math.isclose(o2[key], obs[key], rel_tol=1e-9), (key, o2[key], obs[key])


def test_float32_accuracy_against_float64():
    """float32 on the GPU against float64 on the GPU after 200 steps (measured, printed)."""
    from engine.shapes.spheroid.cuda_backend import CudaEllipsoidBackend

    s64, c64 = _dense(precision="float64")
    s32, c32 = _dense(precision="float32")
    g64, g32 = CudaEllipsoidBackend(s64, c64), CudaEllipsoidBackend(s32, c32)
    g64.advance(200)
    g32.advance(200)
    r = _rel(g64.state(), g32.state(), s64)
    o64, o32 = g64.observe(), g32.observe()
    e_rel = abs(o32["kinetic_energy_translational"] / o64["kinetic_energy_translational"] - 1)
    print(f"\nellipsoids float32 vs float64 after 200 steps: max |dx|/L {r['x']:.2e}, max|dv|/max|v| {r['v']:.2e}, "
          f"max|dw|/max|w| {r['w']:.2e}, rel E_tr diff {e_rel:.2e}, contacts {o64['contacts']} vs {o32['contacts']}")
    assert r["x"] < 1e-3 and e_rel < 1e-3 and r["v"] < 1e-2


def test_instability_is_reported_on_gpu():
    from engine.shapes.spheroid.cuda_backend import CudaEllipsoidBackend
    from engine.errors import InstabilityError

    system, c = _gas(n=512)
    system.velocity[7] = [1e4, 0.0, 0.0]  # far too fast for the stiffness
    be = CudaEllipsoidBackend(system, c)
    with pytest.raises(InstabilityError) as err:
        be.advance(2000)
    assert "step" in str(err.value) and err.value.particle >= 0


def test_ensemble_scenes_equal_single_runs_and_both_loops_agree():
    """Four paper-size ellipsoid scenes (own xi, seed and e_n) advanced together equal each run alone, in
    float64, after 400 steps; half of the single runs use the per-phase loop. Bound: rounding growth,
    1e-9 of L (a list built at a different step orders neighbours differently)."""
    from engine.shapes.spheroid.cuda_backend import CudaEllipsoidBackend, CudaEllipsoidEnsemble

    scenes = [_gas(n=4096, xi=xi, seed=10 + k, e_n=e) for k, (xi, e) in
              enumerate(((1.15, 0.9), (1.5, 0.95), (2.5, 0.98), (3.0, 0.9)))]
    ens = CudaEllipsoidEnsemble([s for s, _ in scenes], [c for _, c in scenes])
    assert ens.multistep
    singles = []
    for k, (s, c) in enumerate(scenes):
        b = CudaEllipsoidBackend(s, c)
        b.e.multistep = k % 2 == 0
        singles.append(b)
    for chunk in (150, 250):
        assert not ens.advance(chunk)
        for b in singles:
            b.advance(chunk)
    obs = ens.observe()
    for k, b in enumerate(singles):
        r = _rel(b.state(), ens.state(k), scenes[k][0])
        print(f"\nscene {k}: contacts {obs[k]['contacts']}, builds {b.builds}/{ens.builds}, max |dx|/L {r['x']:.2e}")
        assert r["x"] <= 1e-9, r
        assert math.isclose(obs[k]["kinetic_energy_translational"], b.observe()["kinetic_energy_translational"],
                            rel_tol=1e-9)


def test_ensemble_scene_failure_stays_local():
    """A scene with a far too large time step fails alone; the others complete their steps."""
    from engine.shapes.spheroid.cuda_backend import CudaEllipsoidEnsemble
    from engine.errors import InstabilityError

    good, c = _gas(n=512, seed=1)
    bad, cb = _gas(n=512, seed=2)
    bad.velocity[3] = [1e4, 0.0, 0.0]
    ens = CudaEllipsoidEnsemble([good, bad], [c, dataclasses.replace(cb)])
    failed = ens.advance(500)
    assert list(failed) == [1] and isinstance(failed[1], InstabilityError)
    assert ens.active[0] and not ens.active[1] and ens.observe()[0]["kinetic_energy_translational"] > 0


@pytest.mark.parametrize("friction,multistep", [(None, True), (0.2, False)])
def test_rough_cpu_and_gpu_agree_float64_200_steps(friction, multistep):
    """Rough spheroids (e_t = 0.5; with and without a Coulomb limit), 4096 with contacts, 200 steps:
    positions within 1e-9 of L, the list slots' springs and k_t alike."""
    from engine.setup.params import k_t_paper

    system, c = _dense(xi=2.0)
    c = c.with_(k_t=k_t_paper(0.5, c.k_n), friction=friction)
    cpu, gpu, contacts = _lockstep(system, c, multistep)
    a, b = cpu.state(), gpu.state()
    r = _rel(a, b, system)
    (pa, sa), (pb, sb) = cpu.contacts(), gpu.contacts()
    oa, ob = np.lexsort(pa.T[::-1]), np.lexsort(pb.T[::-1])
    spring = float(np.abs(sa[oa][:, :3] - sb[ob][:, :3]).max() / np.abs(sa[:, :3]).max()) \
        if len(sa) == len(sb) and len(sa) else float("nan")
    print(f"\nrough xi=2 friction={friction} {'multistep' if multistep else 'per-phase'}: contacts {contacts}; max "
          f"rel diff x {r['x']:.2e} v {r['v']:.2e} w {r['w']:.2e} |q.q'|-1 {r['q']:.2e} spring {spring:.2e}")
    assert contacts[-1] > 100 and sa.shape[1] == 6
    assert r["x"] <= 1e-9, r
    assert r["v"] <= 1e-6 and r["w"] <= 1e-6 and r["q"] <= 1e-9, r
    assert np.array_equal(pa[oa], pb[ob]) and spring <= 1e-6
    o1, o2 = cpu.observe(), gpu.observe()
    assert o1["rotational_dof"] == o2["rotational_dof"] == 3
    for key in ("kinetic_energy_translational", "kinetic_energy_rotational", "elastic_energy"):
        assert math.isclose(o2[key], o1[key], rel_tol=1e-8), (key, o2[key], o1[key])
