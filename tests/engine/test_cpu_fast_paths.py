"""The CPU loop's shortcuts for dilute scenes give the bits of the full work they skip (engine/loops/cpu.py):

- the force loop visits only the particles with list entries (``index_active``): the same forces, torques, slot
  histories, collision counts and worst overlap as the loop over every particle, whatever stale force the others
  held before the build;
- the kick-drift kicks only where a kick changes something: spheres kick the force loop's hot list (a force or
  torque now or at the last kick) and drift every particle, the same numbers as the full kick-drift of every
  particle (smooth and rough, orientations tracked, float64 and mixed precision); a spheroid with an empty list is
  kicked with compile-time zeros, the same bits as with its stored zeros, -0.0 components included;
- the list build walks the neighbour cells with nested offset loops: the same list, entry for entry, as the walk by
  engine.neighbours.cells.neighbour_cell, on grids of 1, 2, 3 and more cells per side;
- through the whole time loop (list builds inside it, and the growth of a list that overflows): the active set is
  the particles with list entries, the others' forces and torques are +0.0 after every advance, every listed
  particle that is not hot has zero force and torque and a predicted velocity equal to its velocity, and an unlisted
  particle's predicted velocity is written when a build lists it;
- engine/backends/ensemble.py ``ThreadChoice``: all threads while they are faster, one thread when it is faster.

The trajectories these changes must leave unchanged are also fingerprinted by ``python -m bench bit_identity``.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import pytest

from engine.backends.ensemble import ONE_THREAD_BELOW, ThreadChoice
from engine.driver.simulate import contact_params
from engine.loops.cpu import all_hot, bin_particles, build_list, index_active, make_forces, make_step
from engine.neighbours.cells import cell_coords_of, distance2, neighbour_cell, neighbour_cell_count
from engine.neighbours.multigrid import carry_slot
from engine.setup.params import derive
from engine.setup.scene import initial_ellipsoids
from engine.setup.spec import SimulationSpec
from engine.shapes.sphere.cpu_backend import CpuBackend
from engine.shapes.spheroid.cpu_backend import CpuEllipsoidBackend
from tests.engine.scenes import gas


def _in_contact(be):
    """Advance until a pair is in contact (lists rebuilt on the way)."""
    be.advance(100)
    for _ in range(600):
        if be.observe()["contacts"] > 0:
            return be
        be.advance(5)
    raise AssertionError("no contact")


def _sphere_backend(phi=0.1, e_t=0.8, precision="float64", orientation=True, n=128):
    system, params = gas(n=n, phi=phi, e_t=e_t, v_rms=0.3, precision=precision, orientation=orientation, seed=4)
    return _in_contact(CpuBackend(system, params))


def _ellipsoid_backend(e_t=0.8):
    spec = SimulationSpec(shape="ellipsoid", elongation=2.0, n_particles=128, volume_fraction=0.05, e_t=e_t,
                          t_end=0.05, backend="cpu", seed=2, snapshots=1, velocity_rms=0.5, stiffness=1e5,
                          box_length=0.6)
    p = derive(spec)
    return _in_contact(CpuEllipsoidBackend(initial_ellipsoids(spec, p), contact_params(spec, p, thermalization=False)))


def _backends():
    return {"rough": _sphere_backend(), "smooth": _sphere_backend(e_t=-1.0, orientation=False),
            "mixed": _sphere_backend(precision="mixed"), "ellipsoids": _ellipsoid_backend()}


@pytest.fixture(scope="module")
def backends():
    return _backends()


def _forces(be, active, n_active, hist, begun_or_ext, force, torque):
    """The backend's force loop on copies of its slot history, forces and collision counts."""
    make_forces(be.shape)(be.pos, be.vel, be.vel_p, be._spin, be._quat_arg, be._rad_list, be.inv_m, be.nbr, be.nn,
                          hist, force, torque, be.box_c, be.inv_box, be.half, be.k_n, be.gn_coef, be._law, be.dt,
                          begun_or_ext, be.chunk_a, be.chunk_b, active, n_active, np.zeros(n_active[0], np.int64),
                          np.zeros_like(be.hot_count))
    return be.chunk_a.copy(), be.chunk_b.copy()


def _copy_ext(ext):
    return tuple(a.copy() for a in ext)


@pytest.mark.parametrize("name", ["rough", "smooth", "mixed", "ellipsoids"])
def test_force_loop_over_the_listed_particles_is_the_full_loop(backends, name):
    be = backends[name]
    n = be.n
    assert 0 < int((be.nn > 0).sum()) < n, "the scene has particles with and without list entries"
    torque_of = (lambda t: None if be._torque_arg is None else t)
    # the full loop, every particle visited (the loop before index_active)
    hist_a, ext_a = be.hist.copy(), _copy_ext(be._ext)
    f_a, t_a = np.full_like(be.force, 7.0), np.full_like(be.torque, 7.0)
    everyone = np.arange(n, dtype=np.int64)
    ca, cb = _forces(be, everyone, np.array([n]), hist_a, ext_a, f_a, torque_of(t_a))
    # stale forces everywhere, then the active set of the list and the loop over it
    hist_b, ext_b = be.hist.copy(), _copy_ext(be._ext)
    f_b, t_b = np.full_like(be.force, -3.0), np.full_like(be.torque, -3.0)
    active, n_active = np.zeros(n, np.int64), np.zeros(1, np.int64)
    index_active(be.nn, active, n_active, f_b, torque_of(t_b))
    assert np.array_equal(active[:n_active[0]], np.flatnonzero(be.nn > 0))
    worst_b = _forces(be, active, n_active, hist_b, ext_b, f_b, torque_of(t_b))
    assert np.array_equal(f_a, f_b) and np.array_equal(np.signbit(f_a), np.signbit(f_b))
    if be._torque_arg is not None:
        assert np.array_equal(t_a, t_b) and np.array_equal(np.signbit(t_a), np.signbit(t_b))
    assert np.array_equal(hist_a, hist_b)
    for a, b in zip(ext_a, ext_b):
        assert np.array_equal(a, b)
    k_a, k_b = int(np.argmax(ca)), int(np.argmax(worst_b[0]))
    assert (ca[k_a], cb[k_a]) == (worst_b[0][k_b], worst_b[1][k_b])
    assert ca[k_a] > 0, "some pair in contact"


def _step_copies(be, force, torque, nn, active, n_active, hot, hot_count):
    """Three kick-drifts (opening half kick, then full kicks) of copies of the backend's state under the stored
    ``force`` and ``torque``, with -0.0 planted in some velocity and spin components: the copies, in order."""
    step = make_step(be.shape)
    pos, vel, vel_p, spin = be.pos.copy(), be.vel.copy(), be.vel_p.copy(), be._spin.copy()
    vel[::7, 1] = -0.0       # -0.0 + 0.0 is +0.0: a kick by zero gives the same number, not the same sign
    vel_p[::7, 1] = -0.0     # (and vel_p = v after a kick by zero, the state the loop leaves)
    spin[::5, 2] = -0.0
    quat = None if be._quat_arg is None else be._quat_arg.copy()
    ext = _copy_ext(be._ext)
    x_ref = be.x_ref.copy()
    ca, cb = np.zeros_like(be.chunk_a), np.zeros_like(be.chunk_b)
    for s, hk in enumerate((be.dt * be.half, be.dt, be.dt)):
        step(pos, vel, spin, quat, force, None if be._torque_arg is None else torque, be.inv_m, be._spin_inv, x_ref,
             vel_p, ext, hk, be.dt, be.box_c, be.inv_box, be.half, ca, cb, s, nn, active, n_active, hot, hot_count)
    return pos, vel, vel_p, spin, quat, ext, ca, cb


@pytest.mark.parametrize("name", ["rough", "smooth", "mixed", "ellipsoids"])
def test_kick_drift_kicks_only_where_a_kick_changes_something(backends, name):
    """Against the full kick-drift of every particle (every particle listed and hot, its stored force and torque:
    zeros for the unlisted). Spheres (FREE_DRIFT): the kicks of the hot list and a drift of all give the same
    numbers, ``vel_p`` of every listed particle included (a kept -0.0 is the number +0.0 would be). Spheroids: an
    unlisted particle kicked with compile-time zeros gives the same bits, signs of zero included."""
    be = backends[name]
    n = be.n
    everyone, hot_all, count_all = np.arange(n, dtype=np.int64), np.zeros(n, np.int64), np.zeros_like(be.hot_count)
    all_hot(everyone, np.array([n]), hot_all, count_all)
    full = _step_copies(be, be.force, be.torque, np.ones_like(be.nn), everyone, np.array([n]), hot_all, count_all)
    fast = _step_copies(be, be.force, be.torque, be.nn, be.active, be.n_active, be.hot, be.hot_count)
    free_drift = getattr(be.shape, "FREE_DRIFT", False)
    listed = be.nn > 0
    if free_drift:
        assert 0 < int(be.hot_count.sum()) < int(listed.sum()), "some listed particles are hot, not all"
    for k, (a, b) in enumerate(zip(full, fast)):
        if a is None:
            assert b is None
            continue
        for x, y in zip(a if isinstance(a, tuple) else (a,), b if isinstance(b, tuple) else (b,)):
            if free_drift and k == 2:        # vel_p: read only for list partners
                x, y = x[listed], y[listed]
            assert x.dtype == y.dtype and np.array_equal(x, y)
            if not free_drift:
                assert np.array_equal(np.signbit(x), np.signbit(y))


@numba.njit
def _reference_list(pos, radius, skin, box, inv_box, half, nc, cell_start, cell_list, cell_of, nbr_old, nn_old,
                    hist_old, nbr, nn, hist):
    """The list build as it was: neighbour cells by engine.neighbours.cells.neighbour_cell (serial)."""
    max_nb = nbr.shape[1]
    for i in range(pos.shape[0]):
        cx, cy, cz = cell_coords_of(cell_of[i], nc)
        cnt = 0
        for k in range(neighbour_cell_count(nc)):
            cc = neighbour_cell(cx, cy, cz, k, nc)
            for s in range(cell_start[cc], cell_start[cc + 1]):
                j = cell_list[s]
                if j == i:
                    continue
                d2 = distance2(pos[i, 0], pos[i, 1], pos[i, 2], pos[j, 0], pos[j, 1], pos[j, 2], box, inv_box, half)
                rc = radius[i] + radius[j] + skin
                if d2 < rc * rc:
                    if cnt < max_nb:
                        nbr[i, cnt] = j
                        if not carry_slot(i, cnt, j, nbr_old, nn_old, hist_old, hist):
                            hist[i, cnt, 3] = radius[i] + radius[j] - math.sqrt(d2)
                    cnt += 1
        nn[i] = cnt


@pytest.mark.parametrize("nc", [1, 2, 3, 4, 7])
def test_list_build_visits_the_neighbour_cells_in_neighbour_cell_order(nc):
    rng = np.random.default_rng(nc)
    n, box = 300, 1.0
    radius = rng.uniform(0.02, 0.05, n)
    skin = 0.6 * box / max(nc, 1) - 2 * radius.max() if nc > 2 else 0.3
    skin = max(skin, 0.01)
    pos = rng.random((n, 3)) * box
    cell_start, cursor = np.zeros(nc**3 + 1, np.int64), np.zeros(nc**3, np.int64)
    cell_list, cell_of = np.zeros(n, np.int64), np.zeros(n, np.int64)
    bin_particles(pos, nc, nc / box, cell_start, cell_list, cell_of, cursor)
    max_nb = 400
    # an old list to carry history from: every particle's first slots, with marked words
    nbr_old = rng.integers(0, n, (n, max_nb)).astype(np.int32)
    nn_old = rng.integers(0, 6, n).astype(np.int32)
    hist_old = rng.random((n, max_nb, 5))
    lists = []
    for build in (build_list, _reference_list):
        nbr, nn, hist = np.zeros((n, max_nb), np.int32), np.zeros(n, np.int32), np.zeros((n, max_nb, 5))
        args = (pos, radius, skin, box, 1 / box, 0.5, nc, cell_start, cell_list, cell_of, nbr_old, nn_old, hist_old,
                nbr, nn, hist)
        build(*args, np.zeros_like(pos)) if build is build_list else build(*args)
        lists.append((nbr, nn, hist))
    (nbr_a, nn_a, hist_a), (nbr_b, nn_b, hist_b) = lists
    assert np.array_equal(nn_a, nn_b) and nn_a.max() <= max_nb and nn_a.sum() > 0
    for i in range(n):
        assert np.array_equal(nbr_a[i, :nn_a[i]], nbr_b[i, :nn_b[i]]), i
        assert np.array_equal(hist_a[i, :nn_a[i]], hist_b[i, :nn_b[i]]), i


def test_active_set_and_zero_forces_hold_after_every_advance():
    """Dilute rough gas: particles enter and leave the lists at the builds inside the loop; a stride of 1 slot makes
    the first builds overflow (the host grows the list and builds again)."""
    system, params = gas(n=200, phi=0.1, v_rms=0.5, seed=7)
    be = CpuBackend(system, params)
    be._alloc_lists(1)
    be._build()
    be._forces()
    builds, seen_free, seen_hot, seen_listed_anew = be.builds, 0, 0, 0
    for _ in range(12):
        # an unlisted particle's predicted velocity is no one's business until a build lists it, which writes it
        # (engine/loops/cpu.py refresh_predicted): poisoned here, it must never reach a force or a listed particle
        was_free = be.nn == 0
        be.vel_p[was_free] = np.nan
        be.advance(150)
        seen_listed_anew += int((was_free & (be.nn > 0)).sum())
        assert np.isfinite(be.force).all() and np.isfinite(be.vel_p[be.nn > 0]).all()
        listed = np.flatnonzero(be.nn > 0)
        assert np.array_equal(be.active[:be.n_active[0]], listed) and len(listed)
        free = be.nn == 0
        seen_free += int(free.sum())
        assert np.all(be.force[free] == 0) and not np.signbit(be.force[free]).any()
        assert np.all(be.torque[free] == 0) and not np.signbit(be.torque[free]).any()
        # the kick-drift skips every listed particle that is not hot: its force and torque are zero and its
        # predicted velocity is its velocity (engine/loops/cpu.py make_step)
        hot = np.zeros(be.n, bool)
        for c in range(len(be.hot_count)):
            a0 = c * be.n_active[0] // len(be.hot_count)
            hot[be.hot[a0:a0 + be.hot_count[c]]] = True
        cold = (be.nn > 0) & ~hot
        seen_hot += int(hot.sum())
        assert np.all(be.force[cold] == 0) and np.all(be.torque[cold] == 0)
        assert np.array_equal(be.vel_p[cold], be.vel[cold])
    assert seen_hot > 0 and be.builds > builds + 2 and be.max_nb > 1 and seen_free > 0 and seen_listed_anew > 0


def test_thread_choice_takes_the_faster_count():
    def run(cost, calls=200, n=4096, free=True):
        tc = ThreadChoice(n, threads=2)
        used = []
        for _ in range(calls):
            k = tc.pick()
            used.append(k)
            tc.record(k, 100, 100 * cost[k], 100 * cost[k] * (1.0 if free else 0.6))
        return used

    idle = run({2: 0.7, 1: 1.0})
    assert idle[:2] == [1, 2] and idle.count(2) > 0.8 * len(idle) and idle.count(1) < 40    # trials of one thread
    busy = run({2: 8.0, 1: 1.0})
    assert busy[:2] == [1, 2] and busy.count(2) <= 3                                        # trial cost bounded
    assert set(run({2: 8.0, 1: 1.0}, free=False)) == {1}     # every core busy: all threads not even tried
    assert set(run({2: 0.5, 1: 1.0}, n=ONE_THREAD_BELOW - 1)) == {1}
    # a load that comes while on all threads: one thread is tried on the next advance
    tc = ThreadChoice(4096, threads=2)
    for k, c in ((1, 1.0), (2, 0.7), (2, 0.7), (2, 5.0)):
        assert tc.pick() == k
        tc.record(k, 10, 10 * c, 10 * c)
    assert tc.pick() == 1
