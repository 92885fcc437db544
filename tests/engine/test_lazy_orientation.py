"""Lazy sphere orientations on the CPU (issue 15 item 1): a sphere's quaternion is brought up to date only when a
torque is about to change its spin, and when the time loop returns (engine/shapes/sphere/kernels.py ``rotate``,
``settle``; the closed form engine.physics.rotation.fincham_quat_steps_space). The result must be the per-step
Fincham scheme to rounding, however the steps fall between contacts and calls."""

import numba
import numpy as np
import pytest

from engine.backends.base import ContactParams
from engine.physics.rotation import fincham_quat_step_space, fincham_quat_steps_space
from engine.shapes.sphere.cpu_backend import CpuBackend
from tests.engine.test_cuda_simulator import tiny_system as lattice_gas

K_N = 1.0e5
T_C = np.pi * np.sqrt(0.5 / K_N)       # unit masses: m12 = 1/2


def contact(**kw):
    base = dict(k_n=K_N, gamma_n_coef=2.0 * np.sqrt(K_N) * 0.2, k_t=K_N * 2 / 7 * 0.5, friction=None,
                dt=T_C / 50, skin=0.02, precision="float64", orientation=True, overlap_limit=0.2)
    base.update(kw)
    return ContactParams(**base)


@numba.njit
def _per_step(q, w, dt, steps):
    out = q.copy()
    for i in range(q.shape[0]):
        q0, q1, q2, q3 = q[i, 0], q[i, 1], q[i, 2], q[i, 3]
        for _ in range(steps):
            q0, q1, q2, q3 = fincham_quat_step_space(q0, q1, q2, q3, w[i, 0], w[i, 1], w[i, 2], dt, 0.5)
        out[i, 0], out[i, 1], out[i, 2], out[i, 3] = q0, q1, q2, q3
    return out


def test_closed_form_is_k_fincham_steps_to_rounding():
    rng = np.random.default_rng(3)
    q = rng.normal(size=(6, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w = rng.normal(size=(6, 3)) * 200.0
    dt = 1.0e-4
    for k in (0, 1, 2, 37, 5000):
        ref = _per_step(q, w, dt, k)
        got = np.array([fincham_quat_steps_space(*q[i], *w[i], dt, k, 0.5) for i in range(6)])
        # k renormalised products against one closed form: rounding of k steps, ~1e-16 each
        assert np.abs(got - ref).max() < 1e-15 * (k + 1), k
    # and not the identity: the quaternions turned by k theta (theta ~ |w| dt / 2 = 1e-2 per step)
    assert np.abs(_per_step(q, w, dt, 37) - q).max() > 0.1


@pytest.mark.parametrize("rough", [True, False])
def test_free_spheres_after_a_million_steps_equal_the_per_step_scheme(rough):
    """No contact ever: the loop defers every quaternion step to its four returns (chunks of 250 000)."""
    system = lattice_gas(speed=0.0, spin=30.0)
    be = CpuBackend(system, contact(k_t=None if not rough else K_N / 7))
    for _ in range(4):
        be.advance(250_000)
    assert be.observe()["contacts"] == 0
    ref = _per_step(np.asarray(system.orientation, float), np.asarray(system.angular_velocity, float), be.dt,
                    1_000_000)
    got = be.state()["orientation"]
    # 1e6 renormalised per-step products (the reference) carry ~1e6 roundings of 1e-16: 1e-9 bounds them
    assert np.abs(got - ref).max() < 1e-9
    assert np.abs(np.linalg.norm(got, axis=1) - 1).max() < 1e-14
    assert not be._lag.any()                          # nothing pending once the loop has returned


def test_colliding_gas_orientation_does_not_depend_on_where_the_loop_returns():
    """A rough gas with contacts from the first steps: one call of 400 steps (orientations caught up at contact
    steps and at the end) against 400 calls of one step (caught up every step, i.e. the per-step scheme)."""
    a = CpuBackend(lattice_gas(), contact(friction=0.3))
    b = CpuBackend(lattice_gas(), contact(friction=0.3))
    a.advance(400)
    for _ in range(400):
        b.advance(1)
    assert a.observe()["contacts"] > 0
    sa, sb = a.state(), b.state()
    # the one-step calls split each fused kick into two half kicks: the same trajectory to rounding
    for key in ("position", "velocity", "angular_velocity"):
        assert np.abs(sa[key] - sb[key]).max() < 1e-12 * np.abs(sa[key]).max(), key
    assert np.abs(sa["orientation"] - sb["orientation"]).max() < 1e-12
    # the spins did change in contacts (the lazy path had something to catch up with)
    assert np.abs(sa["angular_velocity"] - np.asarray(lattice_gas().angular_velocity)).max() > 1e-3
