"""Sphere orientations (docs/physics.md §3.2): a sphere's quaternion is turned by the exact rotation of the spin it had
(engine.physics.rotation.sphere_quat_turn), lazily: only when a torque is about to change that spin, and when the
time loop returns (engine/shapes/sphere/kernels.py ``rotate``, ``settle``; the GPU's twin is checked against the
CPU in test_cuda_simulator.py). Free spheres are exact to rounding over any number of steps; in a colliding gas the
orientations are closer to a t_c/1000 reference than the per-step Fincham update of
Hidalgo et al. (2013)."""

import numba
import numpy as np
import pytest

from engine.backends.base import ContactParams
from engine.physics.rotation import fincham_quat_step_space, sphere_quat_turn
from engine.shapes.sphere.cpu_backend import CpuBackend
from tests.engine.test_cuda_simulator import tiny_system as lattice_gas

K_N = 1.0e5
T_C = np.pi * np.sqrt(0.5 / K_N)       # unit masses: m12 = 1/2


def contact(**kw):
    base = dict(k_n=K_N, gamma_n_coef=2.0 * np.sqrt(K_N) * 0.2, k_t=K_N * 2 / 7 * 0.5, friction=None,
                dt=T_C / 50, skin=0.02, precision="float64", orientation=True, overlap_limit=0.2)
    base.update(kw)
    return ContactParams(**base)


def exact(q, w, t):
    """exp(t/2 (0, w)) q, rows of q and w, written out independently of the engine (numpy, float64)."""
    wn = np.linalg.norm(w, axis=1)
    a = 0.5 * wn * t
    u = w / wn[:, None]
    r0, r = np.cos(a), np.sin(a)[:, None] * u              # the rotation quaternion (r0, r)
    p0, p = q[:, 0], q[:, 1:]
    return np.column_stack([r0 * p0 - (r * p).sum(1), r0[:, None] * p + p0[:, None] * r + np.cross(r, p)])


@numba.njit
def fincham_path(q, wmid, dt, sub):
    """The per-step Fincham update of Hidalgo et al. (2013) through a spin history wmid (steps, N, 3) of mid-step spins:
    one step per step (sub = 1), or sub steps of dt/sub through the piecewise-linear spin joining the mid-step values
    (the reference: the same spin history, integrated at dt/sub)."""
    n = wmid.shape[0]
    out = q.copy()
    for i in range(q.shape[0]):
        q0, q1, q2, q3 = q[i, 0], q[i, 1], q[i, 2], q[i, 3]
        for s in range(n):
            for j in range(sub):
                w = wmid[s, i]
                if sub > 1:
                    t = (j + 0.5) / sub - 0.5          # from the step's midpoint, in steps
                    if t < 0 and s > 0:
                        w = wmid[s, i] + (wmid[s, i] - wmid[s - 1, i]) * t
                    elif t > 0 and s + 1 < n:
                        w = wmid[s, i] + (wmid[s + 1, i] - wmid[s, i]) * t
                q0, q1, q2, q3 = fincham_quat_step_space(q0, q1, q2, q3, w[0], w[1], w[2], dt / sub, 0.5)
        out[i, 0], out[i, 1], out[i, 2], out[i, 3] = q0, q1, q2, q3
    return out


def test_turn_is_the_exact_rotation():
    rng = np.random.default_rng(3)
    q = rng.normal(size=(6, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w = rng.normal(size=(6, 3)) * 200.0
    dt = 1.0e-4
    for k in (0, 1, 2, 37, 5000):
        got = np.array([sphere_quat_turn(*q[i], *w[i], dt, k, 0.5) for i in range(6)])
        ref = exact(q, w, k * dt) if k else q
        # the phase a = k dt |w| / 2 (up to 30 rad) is rounded to ~1e-16 a; the products to a few 1e-16
        assert np.abs(got - ref).max() < 1e-15 * (4 + k * dt * np.abs(w).max()), k
    # k steps then m steps = k + m steps (the lazy catch-up may fall anywhere)
    a = np.array([sphere_quat_turn(*sphere_quat_turn(*q[i], *w[i], dt, 37, 0.5), *w[i], dt, 63, 0.5)
                  for i in range(6)])
    b = np.array([sphere_quat_turn(*q[i], *w[i], dt, 100, 0.5) for i in range(6)])
    assert np.abs(a - b).max() < 1e-14
    # no spin: unchanged
    assert np.array_equal(sphere_quat_turn(*q[0], 0.0, 0.0, 0.0, dt, 10, 0.5), tuple(q[0]))


@pytest.mark.parametrize("rough", [True, False])
def test_free_spheres_are_exact_after_a_million_steps(rough):
    """No contact ever: the loop defers every turn to its four returns (chunks of 250 000 steps); the result is
    the exact rotation to rounding, where the per-step Fincham update of Hidalgo et al. (2013) has drifted by its
    phase error."""
    system = lattice_gas(speed=0.0, spin=30.0)
    be = CpuBackend(system, contact(k_t=None if not rough else K_N / 7))
    for _ in range(4):
        be.advance(250_000)
    assert be.observe()["contacts"] == 0
    q0 = np.asarray(system.orientation, float)
    w = np.asarray(system.angular_velocity, float)
    t = 1_000_000 * be.dt
    got = be.state()["orientation"]
    # four turns by phases of up to ~2e3 rad, each rounded to ~1e-16 of the phase
    assert np.abs(got - exact(q0, w, t)).max() < 2e-12
    assert np.abs(np.linalg.norm(got, axis=1) - 1).max() < 1e-14
    assert not be._lag.any()                          # nothing pending once the loop has returned
    fincham = fincham_path(q0, np.broadcast_to(w, (1_000_000,) + w.shape), be.dt, 1)
    # the per-step scheme: (dt |w| / 2)^3 / 6 ~ 1e-9 rad per step, ~1e-3 after a million steps
    assert np.abs(fincham - exact(q0, w, t)).max() > 1e-5


def test_colliding_gas_orientation_does_not_depend_on_where_the_loop_returns():
    """A rough gas with contacts from the first steps: one call of 400 steps (orientations caught up at contact
    steps and at the end) against 400 calls of one step (caught up every step)."""
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


@pytest.mark.parametrize("spin", [10.0, 300.0])
def test_colliding_gas_orientation_against_a_tc_over_1000_reference(spin):
    """400 steps (8 t_c) of the rough lattice gas at dt = t_c/50. The reference is the run's own spin history
    (the mid-step spins, joined piecewise linearly) integrated by Fincham's update at dt/20 = t_c/1000: it
    isolates the orientation integrator from the contact's own O(dt^2) error, which a separate t_c/1000 run
    would add to both (and which is larger: a rerun at t_c/1000 differs in spin by 2e-3 of |w| after 8 t_c).
    The lazy exact turns must be closer to it than the per-step Fincham update of the same spins."""
    system = lattice_gas(spin=spin, speed=1.0)
    lazy = CpuBackend(system, contact(friction=0.3))
    n = 400
    lazy.advance(n)
    steps = CpuBackend(system, contact(friction=0.3))
    wmid = np.empty((n, steps.n, 3))
    for s in range(n):
        steps.advance(1)
        # the spin of step s's turn: the closing half kick undone (w(t) = w(t + dt/2) + tau/I dt/2)
        wmid[s] = steps.omega - steps.torque * steps.inv_i[:, None] * (steps.dt / 2)
    assert lazy.observe()["contacts"] > 0 and np.ptp(wmid[:, :, 0], axis=0).max() > 1e-2 * spin
    q0 = np.asarray(system.orientation, float)
    ref = fincham_path(q0, wmid, steps.dt, 20)
    err_lazy = np.abs(lazy.state()["orientation"] - ref).max()
    err_fincham = np.abs(fincham_path(q0, wmid, steps.dt, 1) - ref).max()
    # measured: 7.7e-8 vs 3.1e-7 at spin 10, 3.6e-5 vs 1.4e-2 at spin 300 (the per-step phase error grows as w^3)
    assert err_lazy < err_fincham / 2, (err_lazy, err_fincham)


def test_free_turns_stay_pending_across_returns_and_a_read_changes_nothing():
    """The CPU loop settles only the spheres under a torque when it returns (engine/loops/cpu.py make_run_steps); a
    free sphere's turns stay pending across returns, and reading the orientations brings a copy up to date without
    settling the loop's own: a rough gas with contacts, advanced in calls of 7 steps and read at every return,
    ends with the same bits in every array as the same gas read only at the end (so a snapshot or a checkpoint
    taken on the wall clock cannot change a trajectory)."""
    read = CpuBackend(lattice_gas(spin=30.0), contact(friction=0.3))
    deferred = CpuBackend(lattice_gas(spin=30.0), contact(friction=0.3))
    for _ in range(60):
        read.advance(7)
        read.state()
        deferred.advance(7)
        deferred.observe()
    assert read.pending_turns[0] == deferred.pending_turns[0] == 420      # reads left the turns pending
    assert deferred.observe()["contacts"] > 0
    sa, sb = read.state(), deferred.state()
    for key in ("position", "velocity", "angular_velocity", "orientation"):
        assert np.array_equal(sa[key], sb[key]), key
    assert np.abs(sa["orientation"] - np.asarray(lattice_gas(spin=30.0).orientation)).max() > 1e-2
    deferred.settle_orientations()                                       # what the read returned, settled in place
    assert deferred.pending_turns[0] == 0 and np.array_equal(deferred._quat, sb["orientation"])
