"""CPU backend: Numba ``parallel=True`` loops over particles, the whole time loop compiled; one machinery for
every particle shape.

What lives here, shared by every shape: the cells and the Verlet list build (engine/neighbours/cells.py,
engine/neighbours/multigrid.py), the list-slot history store (engine/loops/cpu_shared.py), the time loop
(:func:`make_run_steps`, specialised at compile time by a shape plug-in of engine/shapes/: its kick-drift
``step`` and its ``forces``), the closing half kick, and the host class :class:`CpuLoop` (list growth,
overflow recovery, instability errors). Each shape's host class (a :class:`CpuLoop` subclass holding its state
arrays and observables) lives in its plug-in package: engine/shapes/sphere/cpu_backend.py,
engine/shapes/spheroid/cpu_backend.py.

Layout: arrays of shape (N, 3) (and (N, 4) for quaternions) in the working precision; a full Verlet
neighbour list (each pair stored for both partners) of fixed stride ``max_nb`` per particle with one
slot of contact history per list entry (tangential spring, previous overlap and dashpot force), so every
thread writes only its own particle (no atomics) and the spring of (j, i) is exactly minus the spring of
(i, j). The list is built from linked cells of edge >= 2 a_max + L_v (or, when the radii span more than one
level, from the multigrid cells of Skorych & Dosta (2022) Algorithm 1, engine/neighbours/multigrid.py) and rebuilt when
any particle has moved more than L_v/2 since the last build (Skorych & Dosta 2022); the history of surviving pairs is
carried into the new list. No allocation in the time loop: the scratch list is preallocated and grown (rarely) from
Python when a build overflows it.

Dilute scenes: most particles have an empty list (the default job: 0.06 entries per particle). Every build indexes
the particles that have entries (:func:`index_active`) and zeroes the others' forces; the force loop visits only the
indexed ones, and the kick-drift kicks the others with compile-time zeros. Both skip work whose result is known to
the bit (+0.0 forces and torques), so the trajectories are those of the full loops
(tests/engine/test_cpu_fast_paths.py).

Compile-time specialisation: the shape (one loop per shape, closures over its njit functions, cached on
disk per shape by engine.numba_support.jitcache.cache_closure); for spheres ``k_t``/``torque`` = None (smooth spheres:
no spring, no torque, no spin update), ``mu`` = None (no Coulomb limit) and ``quat`` = None (orientation not
needed) are pruned by Numba when the functions are compiled for those argument types. Everything is cached
on disk, so a new process (a job's child, a test run) loads the compiled code.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import prange

from engine.numba_support.jitcache import fast_loads  # before any cache=True kernel: keys the disk cache by source
from engine.numba_support.jitcache import cache_closure

from engine.loops.system import ContactParams, cell_grid
from engine.loops.cpu_shared import SLOT, cpu_name, worst_overlap
from engine.backends.protocol import Backend
from engine.loops.status import BAD_VALUE, OK, OVERFLOW, OVERLAP, instability_error
from engine.neighbours.cells import cell_coords_of, cell_index_of, distance2, neighbour_row, neighbour_z, offset_span
from engine.neighbours.multigrid import (bin_levels, build_levels_carry, carry_slot, grid_levels, level_arrays,
                                         main_level)
from engine.physics.contact import min_image
from engine.physics.integrate import drift_wrap, kick


@numba.njit(parallel=True, cache=True)
def max_displacement2(pos, x_ref, box, inv_box, half, chunk):
    """Largest squared displacement (minimum image) since the last list build."""
    n = pos.shape[0]
    nch = chunk.shape[0]
    for c in prange(nch):
        m = 0.0
        for i in range(c * n // nch, (c + 1) * n // nch):
            dx = min_image(pos[i, 0] - x_ref[i, 0], box, inv_box, half)
            dy = min_image(pos[i, 1] - x_ref[i, 1], box, inv_box, half)
            dz = min_image(pos[i, 2] - x_ref[i, 2], box, inv_box, half)
            d2 = dx * dx + dy * dy + dz * dz
            if d2 > m:
                m = d2
        chunk[c] = m
    m = 0.0
    for c in range(nch):
        if chunk[c] > m:
            m = chunk[c]
    return m


@numba.njit(parallel=True, cache=True)
def half_kick(vel, omega, force, torque, inv_m, inv_i, hk):
    """Closing half kick that makes velocities synchronous with positions."""
    for i in prange(vel.shape[0]):
        for k in range(3):
            vel[i, k] = kick(vel[i, k], force[i, k], inv_m[i], hk)
        if torque is not None:
            for k in range(3):
                omega[i, k] = kick(omega[i, k], torque[i, k], inv_i[i], hk)


@numba.njit(cache=True)
def bin_particles(pos, nc, inv_cell, cell_start, cell_list, cell_of, cursor):
    """Counting sort of the particles into nc^3 cells (cell_start has nc^3 + 1 entries)."""
    n = pos.shape[0]
    ncell = nc * nc * nc
    for c in range(ncell + 1):
        cell_start[c] = 0
    for i in range(n):
        c = cell_index_of(pos[i, 0], pos[i, 1], pos[i, 2], inv_cell, nc)
        cell_of[i] = c
        cell_start[c + 1] += 1
    for c in range(ncell):
        cell_start[c + 1] += cell_start[c]
    for c in range(ncell):
        cursor[c] = cell_start[c]
    for i in range(n):
        c = cell_of[i]
        cell_list[cursor[c]] = i
        cursor[c] += 1


@numba.njit(parallel=True, cache=True)
def build_list(pos, radius, skin, box, inv_box, half, nc, cell_start, cell_list, cell_of,
               nbr_old, nn_old, hist_old, nbr, nn, hist, x_ref):
    """Full Verlet list: j is a neighbour of i when |r_ij| < a_i + a_j + L_v; springs carried over.

    nn[i] receives the true neighbour count even when it exceeds the stride (the caller then grows
    the list and builds again); slots beyond the stride are not written.

    The neighbour cells are those of engine.neighbours.cells.neighbour_cell, in its order k (offsets ox outermost, oy,
    oz innermost, each ascending; 3, 2 or 1 per axis), so the candidates and the list come in the same order; they
    are walked as three nested offset loops whose wrap is a comparison, not a ``%``: neighbour_cell's three
    integer divisions and modulos by nc per cell (81 per particle) took most of a build (2.6 ms of the default
    job's 4096 spheres on one thread; about 200 builds per job).
    """
    n = pos.shape[0]
    max_nb = nbr.shape[1]
    span = offset_span(nc)
    for i in prange(n):
        cx, cy, cz = cell_coords_of(cell_of[i], nc)
        xi = pos[i, 0]
        yi = pos[i, 1]
        zi = pos[i, 2]
        ri = radius[i]
        cnt = 0
        for ox in range(span):
            for oy in range(span):
                row = neighbour_row(cx, cy, ox, oy, nc)
                for oz in range(span):
                    cc = row + neighbour_z(cz, oz, nc)
                    for s in range(cell_start[cc], cell_start[cc + 1]):
                        j = cell_list[s]
                        if j == i:
                            continue
                        d2 = distance2(xi, yi, zi, pos[j, 0], pos[j, 1], pos[j, 2], box, inv_box, half)
                        rc = ri + radius[j] + skin
                        if d2 < rc * rc:
                            if cnt < max_nb:
                                nbr[i, cnt] = j
                                if not carry_slot(i, cnt, j, nbr_old, nn_old, hist_old, hist):
                                    hist[i, cnt, 3] = ri + radius[j] - math.sqrt(d2)
                            cnt += 1
        nn[i] = cnt
        x_ref[i, 0] = xi
        x_ref[i, 1] = yi
        x_ref[i, 2] = zi


@numba.njit(parallel=True, cache=True)
def copy_list(nbr_src, nn_src, hist_src, nbr_dst, nn_dst, hist_dst):
    for i in prange(nn_src.shape[0]):
        m = nn_src[i]
        nn_dst[i] = m
        for k in range(m):
            nbr_dst[i, k] = nbr_src[i, k]
            for q in range(hist_src.shape[2]):
                hist_dst[i, k, q] = hist_src[i, k, q]


@numba.njit(cache=True)
def index_active(nn, active, n_active, force, torque):
    """After a list build: the particles with at least one list entry, in increasing id order, into
    ``active[:n_active[0]]``, and the force (and torque) of every other particle set to zero.

    Why: the force loop visits only the listed particles. A particle with an empty list gets the force of an
    empty sum, +0.0 in every component, from the full loop; zeroing it here once per build gives the same bits,
    and the loop then skips it until the next build. In a dilute gas (the default job: phi = 0.008, 0.06 list
    entries per particle) that is nearly every particle, and the full loop's per-particle visit (read nn, write
    six zeros) was a third of the single-thread step time. The visiting order and the chunks' contiguous id
    ranges are unchanged, so the per-particle sums and the worst-overlap particle (lowest id among ties) are too.
    """
    m = 0
    for i in range(nn.shape[0]):
        if nn[i] > 0:
            active[m] = i
            m += 1
        else:
            for k in range(3):
                force[i, k] = 0.0
                if torque is not None:
                    torque[i, k] = 0.0
    n_active[0] = m


@numba.njit(cache=True)
def all_hot(active, n_active, hot, hot_count):
    """Every particle with list entries kicked at the next kick-drift (after forces computed outside the time loop,
    whose hot list cannot tell which forces the last kick used; make_forces)."""
    na = n_active[0]
    nch = hot_count.shape[0]
    for c in range(nch):
        a0 = c * na // nch
        a1 = (c + 1) * na // nch
        for a in range(a0, a1):
            hot[a] = active[a]
        hot_count[c] = a1 - a0


@numba.njit(cache=True)
def refresh_predicted(nn_old, nn_new, vel, vel_p, force, inv_m, hp):
    """After a list build in the time loop: the predicted end-of-step velocity v + F/m dt/2 (``hp`` = dt/2) of every
    particle that had no list entries (``nn_old``) and has some now (``nn_new``), whose kick-drift left ``vel_p``
    unwritten (a shape with ``FREE_DRIFT``, :func:`make_step`); its force is the zero of the build that emptied its
    list, so this writes what the full kick-drift would have written, bit for bit."""
    for i in range(nn_old.shape[0]):
        if nn_old[i] == 0 and nn_new[i] > 0:
            im = inv_m[i]
            for k in range(3):
                vel_p[i, k] = kick(vel[i, k], force[i, k], im, hp)


def _free_drift(shape) -> bool:
    """Whether a particle of ``shape`` under no force and no torque only drifts (its ``FREE_DRIFT``: spheres)."""
    return bool(getattr(shape, "FREE_DRIFT", False))


#: A scene of fewer particles than this advances in the time loop compiled without parallel regions
#: (:func:`make_run_steps` with ``parallel=False``); it runs on one Numba thread anyway
#: (engine.backends.ensemble.ONE_THREAD_BELOW, the same size). Why: each ``parallel=True`` region enters Numba's
#: thread pool and meets its threads at its end even on one thread, two regions a step (kick-drift, forces); for a
#: small scene that was most of the step: 64 spheres took 73 ns a particle-step in regions, 28 ns without (2-core
#: VM, one thread, 2026-11-28, one-off study bench/cpu_small_scenes.py, in git history). From about a thousand particles
#: on, the regions' loops are the faster ones (1024: 21.4 against 21.0 ns; 4096: 12.9 against 14.3 ns): numba compiles a
#: region's body with its arrays marked as not aliased, which plain njit does not offer. The numbers are the same bits
#: either way (tests/engine/test_threads.py).
SERIAL_LOOP_BELOW = 1024

_loops: dict = {}
_force_loops: dict = {}
_step_loops: dict = {}
_serial_twins: dict = {}


def _serial_jit(py_func):
    """njit of a loop written with ``prange``, as a plain loop with the error model of a parallel region's body
    (numba compiles a ``prange`` body with ``error_model="numpy"``: a division by zero gives inf or nan instead of
    a test and a Python exception at every division). With Python's model the force loop of 4096 spheres took 27 us
    a call against 17 us with numpy's (2-core VM); the quotients are the same IEEE ones either way."""
    return numba.njit(error_model="numpy")(py_func)


def serial_twin(kernel):
    """``kernel`` (a ``parallel=True`` njit dispatcher) compiled again without parallel regions (its ``prange``
    loops run as plain loops; :func:`_serial_jit`), cached on disk under its own key: a building block of the
    small scenes' loop (:data:`SERIAL_LOOP_BELOW`)."""
    if not kernel.targetoptions.get("parallel"):
        return kernel
    twin = _serial_twins.get(kernel)
    if twin is None:
        name = f"{kernel.py_func.__module__}.{kernel.py_func.__qualname__}"
        twin = _serial_twins[kernel] = cache_closure(_serial_jit(kernel.py_func), ("serial", name))
    return twin


def make_step(shape, parallel: bool = True):
    """The one CPU kick-drift (``parallel``: in one parallel region; else compiled as a plain loop, for the small
    scenes' loop), specialised by a shape's ``pre_step`` and ``rotate`` (cached on disk per shape):

    ``step(pos, vel, spin, quat, force, torque, inv_m, spin_inv, x_ref, vel_p, ext, hk, dt, box, inv_box, half,
    chunk_a, chunk_b, s, nn, active, n_active, hot, hot_count)`` (s: the step's index counted from the last full
    ``settle`` of the orientations, :func:`make_run_steps`): per particle, the shape's ``pre_step``, then the shared
    translation v += F/m hk, predicted end-of-step velocity v + F/m dt/2 (the normal
    dashpot's), x += v dt wrapped into the box, then the shape's ``rotate`` with the particle's torque, which
    returns the particle's displacement measure (module docstring of engine/shapes/sphere/kernels.py: |v|^2 or the
    exact squared displacement) and whether its state is finite. Per chunk: the largest measure into ``chunk_a``,
    the first non-finite particle into ``chunk_b`` (-1: none).

    A particle with an empty list (``nn[i] == 0``) has had zero force and torque since the last build
    (:func:`index_active`): it is kicked with a zero of the working precision instead of its six stored zeros, the
    same arithmetic on the same values, so the same bits. The zero is a compile-time constant, so the inlined
    ``rotate`` drops what only a torque does (a sphere's pending orientation turn). In a dilute gas that is nearly
    every particle, and the default job's step went from about 6.0 to 4.8 ns per particle on one thread.

    With the shape's ``FREE_DRIFT`` (spheres) the kick is skipped wherever it would add zero: a kick by zero
    leaves v and the spin as they are (v + 0 = v; the one exception, -0.0 becoming +0.0, is the same number) and
    sets the predicted velocity ``vel_p`` to v. The step then kicks only the ``hot`` particles, those the force
    loop found under a force or torque now or at the last kick (``hot[a0:a0 + hot_count[c]]`` for its chunk c,
    a0 = c n_active / chunks: :func:`make_forces`), and drifts every particle in one branch-free pass. Every other
    particle keeps v, spin and ``vel_p`` = v bit for bit: its last kick was by zero. A particle with an empty list
    is no one's list partner, so its ``vel_p`` (read only by the pair evaluator, for partners) may lag until a build
    gives it entries and writes it (:func:`refresh_predicted`). Forces computed outside the loop make every listed
    particle hot (:func:`all_hot`). At 32 768 spheres, phi = 0.058 (a third listed, a few in contact) one thread's
    kick-drift went from 11.0 to ~4 ns a particle (2-core VM).
    """
    if (shape.NAME, parallel) in _step_loops:
        return _step_loops[shape.NAME, parallel]
    pre_step = shape.pre_step
    rotate = shape.rotate
    free_drift = _free_drift(shape)

    def drift_only(i, pos, vel, dt, box, inv_box):
        # a free particle's step when the shape's FREE_DRIFT holds: (|v|^2, finite)
        v2 = 0.0
        for k in range(3):
            v = vel[i, k]
            pos[i, k] = drift_wrap(pos[i, k], v, dt, box, inv_box)
            v2 += v * v
        return v2, v2 < 1e300

    drift_only = numba.njit(inline="always")(drift_only)

    def kick_drift_of(drift: bool):
        def kick_drift(i, fx, fy, fz, tq, pos, vel, spin, quat, torque, inv_m, spin_inv, x_ref, vel_p, ext, hk, hp,
                       dt, box, inv_box, half, s):
            # the kick-drift of particle i under force (fx, fy, fz) and torque tq: (displacement measure, finite);
            # without `drift` (a compile-time constant) its kick alone, for FREE_DRIFT shapes, whose rotate neither
            # reads nor writes the position: the drift follows in its own pass
            pre_step(i, pos, quat, ext)
            im = inv_m[i]
            v2 = 0.0
            for k in range(3):
                f = fx if k == 0 else (fy if k == 1 else fz)
                v = kick(vel[i, k], f, im, hk)
                vel[i, k] = v
                vel_p[i, k] = kick(v, f, im, hp)
                if drift:
                    pos[i, k] = drift_wrap(pos[i, k], v, dt, box, inv_box)
                v2 += v * v
            return rotate(i, v2, pos, vel, spin, quat, torque, tq, spin_inv, x_ref, ext, hk, hp, dt, box, inv_box,
                          half, s)

        return numba.njit(inline="always")(kick_drift)

    one = kick_drift_of(True)
    kick_only = kick_drift_of(False)

    def step_free_drift(pos, vel, spin, quat, force, torque, inv_m, spin_inv, x_ref, vel_p, ext, hk, dt, box,
                        inv_box, half, chunk_a, chunk_b, s, nn, active, n_active, hot, hot_count):
        # FREE_DRIFT shapes: the kicks of the hot particles (the force loop's list, by its chunks), then one
        # branch-free drift of every particle (by chunks of ids)
        n = pos.shape[0]
        nch = chunk_a.shape[0]
        na = n_active[0]
        hp = dt * half
        for c in prange(nch):
            a0 = c * na // nch
            bad = -1
            for h in range(a0, a0 + hot_count[c]):
                i = hot[h]
                tq = (force.dtype.type(0), force.dtype.type(0), force.dtype.type(0))
                if torque is not None:
                    tq = (torque[i, 0], torque[i, 1], torque[i, 2])
                _, ok = kick_only(i, force[i, 0], force[i, 1], force[i, 2], tq, pos, vel, spin, quat, torque, inv_m,
                                  spin_inv, x_ref, vel_p, ext, hk, hp, dt, box, inv_box, half, s)
                if not ok and bad < 0:
                    bad = i
            chunk_b[c] = bad
        kick_bad = -1
        for c in range(nch):
            if chunk_b[c] >= 0 and (kick_bad < 0 or chunk_b[c] < kick_bad):
                kick_bad = chunk_b[c]
        for c in prange(nch):
            i0 = c * n // nch
            i1 = (c + 1) * n // nch
            bad = -1
            m = 0.0
            for i in range(i0, i1):
                measure, ok = drift_only(i, pos, vel, dt, box, inv_box)
                if not ok:
                    if bad < 0:
                        bad = i
                elif measure > m:
                    m = measure
            if i0 <= kick_bad < i1 and (bad < 0 or kick_bad < bad):
                bad = kick_bad
            chunk_a[c] = m
            chunk_b[c] = bad

    def step(pos, vel, spin, quat, force, torque, inv_m, spin_inv, x_ref, vel_p, ext, hk, dt, box, inv_box, half,
             chunk_a, chunk_b, s, nn, active, n_active, hot, hot_count):
        n = pos.shape[0]
        nch = chunk_a.shape[0]
        hp = dt * half
        for c in prange(nch):
            i0 = c * n // nch
            i1 = (c + 1) * n // nch
            m = 0.0
            bad = -1
            zero = force.dtype.type(0)  # 0 of the force's precision, a compile-time constant inside the loop
            for i in range(i0, i1):
                if nn[i] == 0:
                    measure, ok = one(i, zero, zero, zero, (zero, zero, zero), pos, vel, spin, quat, torque, inv_m,
                                      spin_inv, x_ref, vel_p, ext, hk, hp, dt, box, inv_box, half, s)
                else:
                    tq = (zero, zero, zero)
                    if torque is not None:  # pruned when there are no torques (then tq is not read)
                        tq = (torque[i, 0], torque[i, 1], torque[i, 2])
                    measure, ok = one(i, force[i, 0], force[i, 1], force[i, 2], tq, pos, vel, spin, quat, torque,
                                      inv_m, spin_inv, x_ref, vel_p, ext, hk, hp, dt, box, inv_box, half, s)
                if not ok:
                    if bad < 0:
                        bad = i
                elif measure > m:
                    m = measure
            chunk_a[c] = m
            chunk_b[c] = bad

    loop = cache_closure((numba.njit(parallel=True) if parallel else _serial_jit)(
        step_free_drift if free_drift else step), ("cpu.step", shape.NAME, parallel))
    _step_loops[shape.NAME, parallel] = loop
    return loop


def make_forces(shape, parallel: bool = True):
    """The one CPU force loop, specialised by a shape's pair evaluator ``shape.pair`` (cached on disk per shape;
    ``parallel`` as in :func:`make_step`):

    ``compute_forces(pos, vel, vel_p, spin, quat, rad, inv_m, nbr, nn, hist, force, torque, box, inv_box, half,
    k_n, gn_coef, law, dt, ext, chunk_ovl, chunk_ovl_idx, active, n_active)`` sums the forces and torques of every
    list slot of every particle of ``active[:n_active[0]]`` (the particles with list entries, :func:`index_active`:
    the others' forces are zero since the build) (each thread owns its particles: no atomics; the full list holds
    each pair twice), lets the evaluator advance the slot's history in place, and records per chunk (contiguous
    ranges of ``active``) the largest relative overlap and its particle (the stability guard). ``torque = None``
    (smooth spheres): torques are neither summed nor written. With the shape's ``FREE_DRIFT``, chunk c also lists
    in ``hot[a0:a0 + hot_count[c]]`` (a0 its first index into ``active``) the particles under a force or torque
    now or before this call (the values it overwrites: those of the last kick), which the next kick-drift kicks
    (:func:`make_step`); NaN counts as a force.
    """
    if (shape.NAME, parallel) in _force_loops:
        return _force_loops[shape.NAME, parallel]
    pair = shape.pair
    free_drift = _free_drift(shape)

    def compute_forces(pos, vel, vel_p, spin, quat, rad, inv_m, nbr, nn, hist, force, torque, box, inv_box, half,
                       k_n, gn_coef, law, dt, ext, chunk_ovl, chunk_ovl_idx, active, n_active, hot, hot_count):
        n = n_active[0]
        nch = chunk_ovl.shape[0]
        for c in prange(nch):
            a0 = c * n // nch
            a1 = (c + 1) * n // nch
            worst = 0.0
            worst_i = -1
            h = a0
            for a in range(a0, a1):
                i = active[a]
                fx = 0.0
                fy = 0.0
                fz = 0.0
                tx = 0.0
                ty = 0.0
                tz = 0.0
                for kk in range(nn[i]):
                    g = pair(i, kk, nbr[i, kk], pos, vel, vel_p, spin, quat, rad, inv_m, hist, box, inv_box, half,
                             k_n, gn_coef, law, dt, ext)
                    fx += g[0]
                    fy += g[1]
                    fz += g[2]
                    if torque is not None:
                        tx += g[3]
                        ty += g[4]
                        tz += g[5]
                    if g[6] > worst:
                        worst = g[6]
                        worst_i = i
                if free_drift:   # hot: a force or torque now or at the last kick (NaN included)
                    if fx != 0 or fy != 0 or fz != 0 or force[i, 0] != 0 or force[i, 1] != 0 or force[i, 2] != 0 or (
                            torque is not None and (tx != 0 or ty != 0 or tz != 0 or torque[i, 0] != 0
                                                    or torque[i, 1] != 0 or torque[i, 2] != 0)):
                        hot[h] = i
                        h += 1
                force[i, 0] = fx
                force[i, 1] = fy
                force[i, 2] = fz
                if torque is not None:
                    torque[i, 0] = tx
                    torque[i, 1] = ty
                    torque[i, 2] = tz
            hot_count[c] = h - a0
            chunk_ovl[c] = worst
            chunk_ovl_idx[c] = worst_i

    loop = cache_closure((numba.njit(parallel=True) if parallel else _serial_jit)(compute_forces),
                         ("cpu.compute_forces", shape.NAME, parallel))
    _force_loops[shape.NAME, parallel] = loop
    return loop


def make_run_steps(shape, parallel: bool = True):
    """The compiled time loop of a shape plug-in (engine/shapes/): one loop for every shape, specialised by the
    shape's ``step`` and ``forces`` (closure constants) and cached on disk per shape (engine.numba_support.jitcache).
    With ``parallel`` False every kernel it calls is its :func:`serial_twin`: the loop of the scenes below
    :data:`SERIAL_LOOP_BELOW` particles.

    ``run_steps(nsteps, pos, vel, spin, quat, force, torque, inv_m, spin_inv, rad, x_ref, vel_p, disp_bound,
    ext, nbr, nn, hist, nbr_new, nn_new, hist_new, nc, inv_cell, cell_start, cell_list, cell_of, cursor, box,
    inv_box, half, dt, skin, k_n, gn_coef, law, overlap_limit, chunk_a, chunk_b, mg, active, n_active, hot,
    hot_count, pending, settle_all)`` advances up to nsteps velocity-Verlet steps; velocities (and ``spin``) are
    synchronous on entry and on exit.

    Orientations (``quat`` not None): the shape's ``settle`` brings them up to date. ``settle_all`` (or an exit other
    than OK): every one, and nothing is left pending; otherwise only those the closing half kick is about to turn
    differently (spheres: those under a torque), and the others' turns stay pending across the return:
    ``pending[0]`` (int64) counts the kick-drifts since the last full settle, the origin of the steps the loop hands
    the shape. Why: a full settle turns every sphere's orientation (engine.physics.rotation.sphere_quat_turn), ~55 ns
    a sphere; the driver returns from the loop at every record (200 a run), and at N = 32 768 and a record every
    15 steps that was a fifth of the loop's time. The host settles fully (``nsteps`` = 0, ``settle_all``) before it
    switches the orientations (:meth:`CpuLoop.settle_orientations`); a read settles a copy and leaves the
    turns pending (engine/shapes/sphere/cpu_backend.py ``quat``), so reads never change a trajectory. Positions,
    velocities and spins are the same bits either way; an orientation turned over a span that crosses a return is
    turned in one piece instead of one per call (a difference at rounding level, and the turns no longer depend on
    the record cadence).

    Returns (status, steps_completed, particle, value, builds). On OVERFLOW the positions of the
    current step have been drifted but its forces not computed: the caller grows the list, rebuilds,
    computes the forces and closes the step. On BAD_VALUE / OVERLAP the state is left as it is.

    The L_v/2 rule (Skorych & Dosta 2022): with ``shape.EXACT_DISPLACEMENT`` the step measures the exact largest
    displacement since the build; otherwise disp_bound[0] accumulates max|v| dt, an upper bound of any
    particle's displacement since the build, and only when it passes L_v/2 is the exact largest displacement
    computed, and the list rebuilt if that passes too.

    mg = None: the single linked-cell grid; else the multigrid arrays (level, nc, inv_cell, start_off,
    list_off, cell_start, cell_list) of engine/neighbours/multigrid.py (scenes with more than one grid level).
    """
    if (shape.NAME, parallel) in _loops:
        return _loops[shape.NAME, parallel]
    step = make_step(shape, parallel)
    forces = make_forces(shape, parallel)
    kernel = (lambda k: k) if parallel else serial_twin
    settle = kernel(shape.settle)
    largest_displacement2 = kernel(max_displacement2)
    build = kernel(build_list)
    copy = kernel(copy_list)
    bin_multigrid = kernel(bin_levels)
    build_multigrid = kernel(build_levels_carry)
    close_kick = kernel(half_kick)
    exact = bool(shape.EXACT_DISPLACEMENT)
    free_drift = _free_drift(shape)

    def steps(nsteps, pos, vel, spin, quat, force, torque, inv_m, spin_inv, rad, x_ref, vel_p, disp_bound,
              ext, nbr, nn, hist, nbr_new, nn_new, hist_new, nc, inv_cell, cell_start, cell_list, cell_of,
              cursor, box, inv_box, half, dt, skin, k_n, gn_coef, law, overlap_limit, chunk_a, chunk_b, mg, active,
              n_active, hot, hot_count, base):
        # the steps themselves (step s of the call is step base + s since the orientations' last full settle);
        # run_steps settles the orientations as far as needed and closes the last step, on every exit
        builds = 0
        if nsteps <= 0:
            return OK, 0, -1, 0.0, builds
        limit2 = (skin * half) * (skin * half)
        for s in range(nsteps):
            hk = dt * half if s == 0 else dt
            step(pos, vel, spin, quat, force, torque, inv_m, spin_inv, x_ref, vel_p, ext, hk, dt, box, inv_box,
                 half, chunk_a, chunk_b, base + s, nn, active, n_active, hot, hot_count)
            for c in range(chunk_b.shape[0]):
                if chunk_b[c] >= 0:
                    return BAD_VALUE, s, chunk_b[c], 0.0, builds
            m2 = 0.0
            for c in range(chunk_a.shape[0]):
                if chunk_a[c] > m2:
                    m2 = chunk_a[c]
            if exact:
                rebuild = m2 > limit2
            else:
                disp_bound[0] += math.sqrt(m2) * dt
                rebuild = False
                if disp_bound[0] * disp_bound[0] > limit2:
                    exact2 = largest_displacement2(pos, x_ref, box, inv_box, half, chunk_a)
                    rebuild = exact2 > limit2
                    disp_bound[0] = math.sqrt(exact2)
            if rebuild:
                disp_bound[0] = 0.0
                if mg is None:
                    bin_particles(pos, nc, inv_cell, cell_start, cell_list, cell_of, cursor)
                    build(pos, rad, skin, box, inv_box, half, nc, cell_start, cell_list, cell_of,
                               nbr, nn, hist, nbr_new, nn_new, hist_new, x_ref)
                else:
                    bin_multigrid(pos, mg[0], mg[1], mg[2], mg[3], mg[4], mg[5], mg[6])
                    build_multigrid(pos, rad, mg[0], skin, box, inv_box, half, mg[1], mg[2], mg[3], mg[4],
                                       mg[5], mg[6], nbr, nn, hist, nbr_new, nn_new, hist_new, x_ref)
                builds += 1
                if free_drift:
                    refresh_predicted(nn, nn_new, vel, vel_p, force, inv_m, dt * half)
                need = 0
                for i in range(nn_new.shape[0]):
                    if nn_new[i] > need:
                        need = nn_new[i]
                if need > nbr_new.shape[1]:
                    return OVERFLOW, s, -1, float(need), builds
                copy(nbr_new, nn_new, hist_new, nbr, nn, hist)
                index_active(nn, active, n_active, force, torque)
            forces(pos, vel, vel_p, spin, quat, rad, inv_m, nbr, nn, hist, force, torque, box, inv_box, half,
                   k_n, gn_coef, law, dt, ext, chunk_a, chunk_b, active, n_active, hot, hot_count)
            worst, who = worst_overlap(chunk_a, chunk_b)
            if worst > overlap_limit:
                return OVERLAP, s, who, worst, builds
        return OK, nsteps, -1, 0.0, builds

    steps = numba.njit(steps)

    def run_steps(nsteps, pos, vel, spin, quat, force, torque, inv_m, spin_inv, rad, x_ref, vel_p, disp_bound,
                  ext, nbr, nn, hist, nbr_new, nn_new, hist_new, nc, inv_cell, cell_start, cell_list, cell_of,
                  cursor, box, inv_box, half, dt, skin, k_n, gn_coef, law, overlap_limit, chunk_a, chunk_b, mg,
                  active, n_active, hot, hot_count, pending, settle_all):
        status, done, who, value, builds = steps(
            nsteps, pos, vel, spin, quat, force, torque, inv_m, spin_inv, rad, x_ref, vel_p, disp_bound, ext, nbr,
            nn, hist, nbr_new, nn_new, hist_new, nc, inv_cell, cell_start, cell_list, cell_of, cursor, box, inv_box,
            half, dt, skin, k_n, gn_coef, law, overlap_limit, chunk_a, chunk_b, mg, active, n_active, hot, hot_count,
            pending[0])
        if quat is not None:
            if nsteps > 0:
                pending[0] += nsteps if status == OK else done + 1   # a step that stopped early had drifted
            if settle_all or status != OK:
                settle(spin, quat, torque, ext, pending[0], dt, half, True)
                pending[0] = 0
            elif nsteps > 0:     # only what the closing half kick is about to change
                settle(spin, quat, torque, ext, pending[0], dt, half, False)
        if nsteps > 0 and status == OK:
            close_kick(vel, spin, force, torque, inv_m, spin_inv, dt * half)
        return status, done, who, value, builds

    loop = cache_closure(numba.njit(run_steps), ("cpu.run_steps", shape.NAME, parallel))
    _loops[shape.NAME, parallel] = loop
    return loop


class CpuLoop(Backend):
    """What every CPU shape backend shares: cells, the Verlet list and its slot store, the list build, the
    time loop (``make_run_steps`` of the subclass's ``shape``) and its error handling.

    A subclass sets ``shape`` (an engine/shapes/ module) and, before ``_init_loop``, the state arrays ``pos``,
    ``vel``, ``force``, ``inv_m``, ``x_ref``, ``vel_p`` and ``_rad_list`` (list radius); ``set_contact`` then
    sets the constants and the loop arguments ``_spin``, ``_spin_inv``, ``_quat_arg``, ``_torque_arg``,
    ``_ext``, ``_law``. It implements ``_prime`` and ``_forces`` (forces at a list build outside the loop).
    """

    name = "cpu"
    shape = None
    #: history words per list slot (cpu_shared.SLOT; a shape whose pair law keeps more sets its own)
    slot_words = SLOT

    def _init_loop(self, n: int, rmax: float, rmin: float, skin: float) -> None:
        self.disp_bound = np.zeros(1)     # upper bound of the displacement since the last build (m)
        # kick-drifts since the orientations were last settled in full (make_run_steps)
        self.pending_turns = np.zeros(1, np.int64)
        self.parallel_loop = n >= SERIAL_LOOP_BELOW   # the time loop in parallel regions (SERIAL_LOOP_BELOW)
        self.device = cpu_name()
        self.steps_done = 0
        self.builds = 0
        threads = numba.get_num_threads()
        nch = max(1, min(n, 8 * threads))
        self.chunk_a = np.zeros(nch, np.float64)
        self.chunk_b = np.zeros(nch, np.int64)
        # the particles with list entries (index_active), rewritten at every build
        self.active = np.zeros(n, np.int64)
        self.n_active = np.zeros(1, np.int64)
        # the particles the next kick-drift kicks (FREE_DRIFT shapes; make_forces), by the force loop's chunks
        self.hot = np.zeros(n, np.int64)
        self.hot_count = np.zeros(nch, np.int64)
        self._setup_cells(rmax, skin, rmin)
        self._alloc_lists(8)

    # ---- set-up -----------------------------------------------------------------------------------

    def _setup_cells(self, rmax: float, skin: float, rmin: float) -> None:
        """The single linked-cell grid, and the multigrid cells (Skorych & Dosta 2022, Algorithm 1,
        engine/neighbours/multigrid.py) when the size distribution spans more than one grid level (``self.mg``; None
        otherwise)."""
        self.nc = nc = cell_grid(self.box, self.n, rmax, skin)
        self.inv_cell = nc / self.box
        self.mg = None
        self.levels = None
        if self.n and rmin < rmax:
            levels = grid_levels(self.box, self.n, rmin, rmax, float(skin))
            if levels.n_levels > 1:
                self.levels = levels
                level = main_level(self._rad_list, levels)
                self.mg = (level,) + level_arrays(self.box, level, levels)
                nc = 1                      # the single grid is not used
        self.cell_start = np.zeros(nc**3 + 1, np.int64)
        self.cursor = np.zeros(nc**3, np.int64)
        self.cell_list = np.zeros(self.n, np.int64)
        self.cell_of = np.zeros(self.n, np.int64)

    def _alloc_lists(self, max_nb: int) -> None:
        n, dt_ = self.n, self.dtype
        self.max_nb = max_nb
        self.nbr = np.zeros((n, max_nb), np.int32)
        self.nn = np.zeros(n, np.int32)
        self.hist = np.zeros((n, max_nb, self.slot_words), dt_)
        self.nbr_new = np.zeros_like(self.nbr)
        self.nn_new = np.zeros_like(self.nn)
        self.hist_new = np.zeros_like(self.hist)

    def _grow_lists(self, need: int) -> None:
        old = (self.nbr, self.nn, self.hist)
        self._alloc_lists(int(math.ceil(max(need, 2 * self.max_nb) / 4.0)) * 4)
        copy_list(old[0], old[1], old[2], self.nbr, self.nn, self.hist)

    def _set_common(self, contact: ContactParams) -> None:
        """The contact constants every shape has."""
        self.contact = contact
        c = self.dtype
        self.k_n = c(contact.k_n)
        self.gn_coef = c(contact.gamma_n_coef)
        self.dt = c(contact.dt)
        self.skin = c(contact.skin)
        self.half = c(0.5)
        self.box_c = c(self.box)
        self.inv_box = c(1.0 / self.box)
        self.overlap_limit = float(contact.overlap_limit)

    def _build(self) -> None:
        mg = self.mg
        while True:
            if mg is None:
                bin_particles(self.pos, self.nc, self.inv_cell, self.cell_start, self.cell_list, self.cell_of,
                              self.cursor)
                build_list(self.pos, self._rad_list, self.skin, self.box_c, self.inv_box, self.half, self.nc,
                           self.cell_start, self.cell_list, self.cell_of, self.nbr, self.nn, self.hist,
                           self.nbr_new, self.nn_new, self.hist_new, self.x_ref)
            else:
                bin_levels(self.pos, *mg)
                build_levels_carry(self.pos, self._rad_list, mg[0], self.skin, self.box_c, self.inv_box,
                                   self.half, *mg[1:], self.nbr, self.nn, self.hist, self.nbr_new, self.nn_new,
                                   self.hist_new, self.x_ref)
            need = int(self.nn_new.max()) if self.n else 0
            if need <= self.max_nb:
                break
            self._grow_lists(need)
        copy_list(self.nbr_new, self.nn_new, self.hist_new, self.nbr, self.nn, self.hist)
        index_active(self.nn, self.active, self.n_active, self.force, self._torque_arg)
        self.disp_bound[0] = 0.0
        self.builds += 1

    def _forces(self) -> None:
        """Forces and torques at the current positions (after a build outside the loop)."""
        make_forces(self.shape)(self.pos, self.vel, self.vel_p, self._spin, self._quat_arg, self._rad_list,
                                self.inv_m, self.nbr, self.nn, self.hist, self.force, self._torque_arg, self.box_c,
                                self.inv_box, self.half, self.k_n, self.gn_coef, self._law, self.dt, self._ext,
                                self.chunk_a, self.chunk_b, self.active, self.n_active, self.hot, self.hot_count)
        all_hot(self.active, self.n_active, self.hot, self.hot_count)
        if self._torque_arg is None:
            self.torque[:] = 0

    # ---- time loop ---------------------------------------------------------------------------------

    def warmup(self) -> None:
        """Compile (or load from the disk cache) the time loop for the current contact parameters."""
        self.advance(0, _compile_only=True)

    def advance(self, nsteps: int, _compile_only: bool = False) -> None:
        """Advance nsteps steps; raises InstabilityError naming the step, the particle and the cause."""
        left = int(nsteps)
        while left > 0 or _compile_only:
            _compile_only = False
            status, done, who, value, builds = self._run_steps(left, False)
            self.builds += builds
            if status == OK:
                self.steps_done += done
                return
            step = self.steps_done + done
            if status == OVERFLOW:
                # finish the interrupted step with a larger list, then continue
                self._grow_lists(int(value))
                self._build()
                self._forces()
                half_kick(self.vel, self._spin, self.force, self._torque_arg, self.inv_m, self._spin_inv,
                          self.dt * self.half)
                self.steps_done += done + 1
                left -= done + 1
                continue
            self.steps_done = step
            raise instability_error(status, step, int(who), value, self)

    def settle_orientations(self) -> None:
        """Bring every orientation up to date (the time loop leaves a free sphere's turns pending across its
        returns: make_run_steps); called before the orientations are read or switched."""
        if self.pending_turns[0] > 0 and self._quat_arg is not None:
            self._run_steps(0, True)

    def _run_steps(self, nsteps: int, settle_all: bool) -> tuple:
        """One call of the compiled time loop on this backend's arrays: (status, done, particle, value, builds)."""
        run_steps = make_run_steps(self.shape, self.parallel_loop)
        return run_steps(
            nsteps, self.pos, self.vel, self._spin, self._quat_arg, self.force, self._torque_arg,
            self.inv_m, self._spin_inv, self._rad_list, self.x_ref, self.vel_p, self.disp_bound, self._ext,
            self.nbr, self.nn, self.hist, self.nbr_new, self.nn_new, self.hist_new, self.nc, self.inv_cell,
            self.cell_start, self.cell_list, self.cell_of, self.cursor, self.box_c, self.inv_box, self.half,
            self.dt, self.skin, self.k_n, self.gn_coef, self._law, self.overlap_limit,
            self.chunk_a, self.chunk_b, self.mg, self.active, self.n_active, self.hot, self.hot_count,
            self.pending_turns, settle_all)


fast_loads(globals())  # their disk-cache loads skip numba's target refresh (engine/numba_support/jitcache.py)
