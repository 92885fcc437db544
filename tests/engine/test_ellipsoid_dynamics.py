"""Ellipsoid dynamics on the CPU (docs/physics.md §2.4, §3.3): xi = 1 reproduces smooth spheres, conservation laws,
Euler's equations (torque-free symmetric top), restitution of a central collision."""

from __future__ import annotations

import math

import numpy as np

from engine.backends.base import ContactParams, EllipsoidSystem
from engine.shapes.sphere.cpu_backend import CpuBackend
from engine.shapes.spheroid.cpu_backend import CpuEllipsoidBackend
from engine.setup.params import gamma_n_from_restitution
from engine.physics.rotation import body_omega, fincham_quat_step_body
from engine.setup.scene import maxwellian, place_spheres, random_quaternions
from tests.engine.scenes import K_N, MASS, RADIUS, gas


def as_ellipsoids(system):
    n = system.n
    return EllipsoidSystem(system.box_length, system.position, system.velocity, system.angular_velocity,
                           system.orientation, np.full((n, 3), RADIUS), system.mass,
                           np.tile(np.asarray(system.inertia)[:, None], (1, 3)))


def spheroid_gas(n=32, phi=0.04, xi=2.5, e_n=0.8, v_rms=1.0, seed=2, precision="float64"):
    """Periodic gas of prolate spheroids with the volume of a sphere of radius RADIUS."""
    rng = np.random.default_rng(seed)
    b = RADIUS / xi ** (1 / 3)
    a = xi * b
    box = (n * 4 / 3 * math.pi * RADIUS**3 / phi) ** (1 / 3)
    pos = place_spheres(n, box, a, rng)
    vel = maxwellian(n, v_rms, rng)
    i_perp = MASS * (a * a + b * b) / 5
    inertia = np.tile([2 * MASS * b * b / 5, i_perp, i_perp], (n, 1))
    q = random_quaternions(n, rng)
    omega = maxwellian(n, v_rms * math.sqrt(MASS / i_perp), rng)
    m12 = MASS / 2
    tc = math.pi * math.sqrt(m12 / K_N)
    params = ContactParams(k_n=K_N, gamma_n_coef=gamma_n_from_restitution(e_n, K_N, m12) / math.sqrt(m12),
                           k_t=None, friction=None, dt=tc / 50, skin=0.4 * b, precision=precision,
                           orientation=True, overlap_limit=0.3)
    return EllipsoidSystem(box, pos, vel, omega, q, np.tile([a, b, b], (n, 1)), np.full(n, MASS), inertia), params


def test_xi_one_reproduces_smooth_spheres():
    system, params = gas(n=64, phi=0.2, e_n=0.8, e_t=-1, v_rms=1.0)
    a = CpuBackend(system, params)
    b = CpuEllipsoidBackend(as_ellipsoids(system), params)
    a.advance(1000)
    b.advance(1000)
    oa, ob = a.observe(), b.observe()
    assert oa["kinetic_energy_translational"] < 0.95 * 0.32          # collisions happened
    assert np.abs(a.pos - b.pos).max() < 1e-13
    assert np.abs(a.vel - b.vel).max() < 1e-11
    assert np.abs(a.omega - b.omega()).max() < 1e-10
    assert math.isclose(oa["kinetic_energy_translational"], ob["kinetic_energy_translational"], rel_tol=1e-11)


def test_momenta_conserved_in_dissipative_spheroid_gas():
    system, params = spheroid_gas(e_n=0.7)
    be = CpuEllipsoidBackend(system, params)
    p0 = MASS * be.vel.sum(axis=0)
    be.advance(2000)
    o = be.observe()
    assert o["kinetic_energy_translational"] < 0.99 * 0.5 * MASS * system.n   # it did collide
    # F_ji = -F_ij to the last bit (same evaluation for both partners)
    assert np.abs(MASS * be.vel.sum(axis=0) - p0).max() < 1e-13 * MASS * np.abs(be.vel).sum()


def test_angular_momentum_conserved_in_isolated_cluster():
    rng = np.random.default_rng(4)
    system, params = spheroid_gas(n=8, phi=0.005, xi=2.0)
    a = system.semi_axes[0, 0]
    grid = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], float)
    pos = 0.5 + (grid - 0.5) * 2.05 * a
    vel = -(pos - 0.5) * 60.0 + rng.normal(scale=0.3, size=(8, 3))
    sysc = EllipsoidSystem(1.0, pos, vel, rng.normal(scale=20.0, size=(8, 3)), random_quaternions(8, rng),
                           system.semi_axes[:8], system.mass[:8], system.inertia[:8])
    be = CpuEllipsoidBackend(sysc, params)

    def ang():
        return (MASS * np.cross(be.pos, be.vel)).sum(axis=0) + be.angm.sum(axis=0)

    l0 = ang()
    be.advance(3000)
    scale = MASS * np.abs(np.cross(be.pos, be.vel)).sum() + np.abs(be.angm).sum()
    assert be.observe()["kinetic_energy_translational"] < 0.9 * 0.5 * MASS * (vel**2).sum()
    assert np.abs(ang() - l0).max() < 1e-12 * scale


def test_elastic_spheroid_gas_conserves_energy():
    system, params = spheroid_gas(e_n=1.0, v_rms=0.5)
    be = CpuEllipsoidBackend(system, params)

    def energy():
        o = be.observe()
        return o["kinetic_energy_translational"] + o["kinetic_energy_rotational"] + o["elastic_energy"]

    e0 = energy()
    worst = 0.0
    for _ in range(5):
        be.advance(1000)
        worst = max(worst, abs(energy() - e0) / e0)
    assert worst < 2e-3, worst
    assert be.observe()["kinetic_energy_rotational_active"] <= be.observe()["kinetic_energy_rotational"]


def test_torque_free_symmetric_top_precesses_as_euler_predicts():
    """Body frame: w_1 const, (w_2, w_3) rotates at Omega = (I_1 - I_perp)/I_perp w_1 (Euler's equations)."""
    i1, ip = 0.4, 1.3
    wb0 = np.array([2.0, 0.7, 0.0])
    q = np.array([1.0, 0.0, 0.0, 0.0])
    L = np.array([i1 * wb0[0], ip * wb0[1], ip * wb0[2]])        # q = 1: body = space
    dt, steps = 1e-3, 5000
    for _ in range(steps):
        q = np.array(fincham_quat_step_body(*q, *L, *L, 1 / i1, 1 / ip, 1 / ip, dt, 0.5))
    wb = np.array(body_omega(*q, *L, 1 / i1, 1 / ip, 1 / ip, 0.5))
    om = (i1 - ip) / ip * wb0[0]
    t = dt * steps
    exact = [wb0[0], 0.7 * math.cos(om * t), 0.7 * math.sin(om * t)]
    assert abs(np.linalg.norm(q) - 1) < 1e-14
    assert np.allclose(wb, exact, atol=2e-5)


def test_central_collision_restitution():
    """Tip-to-tip head-on collision of aligned spheroids: no torque, e = e_n (contact-time corrections)."""
    system, params = spheroid_gas(n=2, phi=0.001, xi=3.0, e_n=0.6)
    a = system.semi_axes[0, 0]
    pos = np.array([[0.5 - a - 1e-4, 0.5, 0.5], [0.5 + a + 1e-4, 0.5, 0.5]])
    vel = np.array([[0.5, 0, 0], [-0.5, 0, 0]])
    q = np.tile([1.0, 0, 0, 0], (2, 1))
    sysc = EllipsoidSystem(1.0, pos, vel, np.zeros((2, 3)), q, system.semi_axes[:2], system.mass[:2],
                           system.inertia[:2])
    be = CpuEllipsoidBackend(sysc, params)
    be.advance(400)
    assert be.observe()["contacts"] == 0
    e = (be.vel[1, 0] - be.vel[0, 0]) / 1.0
    assert abs(e - 0.6) < 2e-3, e
    assert np.abs(be.angm).max() < 1e-15


def test_end_to_end_ellipsoid_run_writes_h5md(tmp_path):
    import h5py

    from engine.driver.simulate import run

    spec = {"shape": "ellipsoid", "elongation": 2.0, "n_particles": 32, "volume_fraction": 0.05, "e_n": 0.9,
            "e_t": -1.0, "t_end": 0.01, "thermalization": 0.1, "snapshots": 2, "backend": "cpu", "seed": 3}
    summary = run(spec, tmp_path / "e.h5")
    with h5py.File(summary.output) as f:
        part = f["particles/all"]
        axes = part["semi_axes"][...]
        assert axes.shape == (32, 3) and np.allclose(axes[:, 1], axes[:, 2])
        assert np.allclose(axes[:, 0] / axes[:, 1], 2.0) and "radius" not in part
        assert np.allclose(axes[:, 0] * axes[:, 1] ** 2, f["parameters"].attrs["radius"] ** 3)
        q = part["orientation/value"][...]
        assert q.shape == (2, 32, 4) and np.allclose(np.linalg.norm(q, axis=2), 1, atol=1e-12)
        assert not np.allclose(q[0], q[1])                           # orientations were integrated
        t_tr = f["observables/temperature_translational/value"][...]
        t_rot = f["observables/temperature_rotational/value"][...]
        e_rot = f["observables/kinetic_energy_rotational/value"][...]
        assert np.all(np.isfinite(t_tr)) and np.all(t_rot > 0)
        # 2 active rotational dof, no spin about the symmetry axis: T_rot = E_rot / N
        assert np.allclose(t_rot, e_rot / 32, rtol=1e-9)
        assert f["h5md/modules/dem"].attrs["shape_data"] == "semi_axes"
