"""CUDA kernels of the GPU backend: K independent scenes advanced together (K = 1 for one run).

Every kernel calls the same ``@numba.njit`` physics functions as the CPU backend
(:mod:`engine.physics`); this module owns only layout, loops and launches. The kernels are built by
factories keyed on what the scenes need (DESIGN §1): precision, rough or smooth, Coulomb limit,
orientation, uniform particles.

Layout (device, structure of arrays, particle index fastest). The scenes lie back to back: scene s owns
the slots [start_s, start_s + n_s) and keeps them (its cells come before the next scene's, so the cell
sort never moves a particle into another scene's range); ``sc[i]`` is the scene of slot i.
    pos, vel, omega (3, N); quat (4, N); f0/f1 (3, N) (double buffer: the force kernel reads the previous
    step's forces for the predicted velocities of *other* particles while writing its own); torque (3, N);
    x_ref (3, N); ids (N) int32 = ensemble-wide particle id (start_s + id within the scene).
    Neighbour list: nbr (M, N) int32, nn (N) int32, hist (H, M, N) per-slot contact history (H = 5:
    tangential spring x, y, z, previous overlap, previous dashpot force).
    Compact history store (rebuilds only): the slots whose history matters across a rebuild (in contact
    at the previous step or overlapping now) are copied to cj/chist before the list is rebuilt in place;
    every other slot restarts from zero history with the current gap as its previous overlap, which gives
    the same forces bit for bit (a pair apart at the previous step has zero spring, and its previous
    dashpot force is never read). This keeps one list buffer instead of two (issue 3's memory target).
Per-scene constants: spd (K, ND) in the working precision, spf (K, NF) float64, spi (K, NI) int32; a
scene whose ``spi[s, I_ACTIVE]`` is 0 is skipped by every kernel (finished, cancelled or failed: a blow-up
clears it on the device so a failing scene cannot disturb the others).

Status (float64): global slots S_* (rebuild decision, list stride, compaction count, multi-step exit)
then NSS words per scene at SS0 + NSS s (first bad value, worst overlap beyond the limit).
"""

from __future__ import annotations

import math

import numpy as np
from numba import cuda
from numba.cuda import types as ct

from engine.backends.cuda_cache import cache_kernels
from engine.cells import cell_coords, cell_index_of, distance2, neighbour_cell, neighbour_cell_count
from engine.physics.contact import (contact_elastic_energy, contact_end_fraction, min_image, sphere_contact,
                                    sphere_contact_end)
from engine.physics.integrate import drift_wrap, kick
from engine.physics.rotation import fincham_quat_step_space

# per-scene constants: spd (working precision)
D_BOX, D_INVBOX, D_DT, D_HP, D_KN, D_GN, D_KT, D_MU, D_R0, D_M0, D_I0, D_IM0, D_II0, D_SKIN = range(14)
ND = 14
# spf (float64)
F_OVL, F_INVCELL, F_LIM2INV, F_V2F, F_KN, F_KT = range(6)
NF = 6
# spi (int32)
I_NC, I_COFF, I_ACTIVE, I_START, I_N, I_ORIENT = range(6)
NI = 6

# global status slots; S_D2 (+1): max over particles of (displacement since the build / (L_v/2))^2 (two
# slots: the multi-step kernel alternates them by step parity); S_V2: max (2 |v| dt / (L_v/2))^2
# S_CHECK: max (displacement from a list's snapshot / (L_v/2))^2, the a-posteriori check of a CPU-built list
S_D2, S_D2B, S_V2, S_NEED_NB, S_NCOMP, S_RUN_DONE, S_RUN_REBUILD, S_CHECK = range(8)
SS0 = 8
# per-scene status words
SS_BAD_ID, SS_BAD_STEP, SS_OVL, SS_OVL_ID, SS_OVL_STEP = range(5)
NSS = 5
HW = 5  # history words per list slot: spring x, y, z, previous overlap, previous dashpot force
# observe sums per scene: E_tr, E_rot, contacts x 2, elastic energy, P_x, P_y, P_z, max overlap (slot 7, a max),
# then the Sonine moments sum e_tr^2, sum e_rot^2, sum e_tr e_rot (J^2; engine/physics/sonine.py)
NOBS = 11
O_TR2, O_ROT2, O_X = 8, 9, 10

_cache: dict = {}


def status_len(k: int) -> int:
    return SS0 + NSS * k


def kernels(dtype, rough: bool, coulomb: bool, orient: bool, uniform: bool, tpb: int):
    """The kernel set for one specialisation (cached)."""
    key = (np.dtype(dtype).str, rough, coulomb, orient, uniform, tpb)
    if key not in _cache:
        _cache[key] = cache_kernels(_make(np.dtype(dtype).type, rough, coulomb, orient, uniform, tpb),
                                    ("spheres",) + key)
    return _cache[key]


def device_helpers(tpb: int):
    """(block_max2, fail): the block reduction and the per-scene blow-up record shared by the sphere and
    ellipsoid kernel sets (cached per block size)."""
    key = ("helpers", tpb)
    if key not in _cache:
        _cache[key] = _make_helpers(tpb)
    return _cache[key]


def observe_reducer(tpb: int, nv: int, max_slot: int):
    """Device function ``block_accumulate(sh, vals, acc, s)``: the block-wide reduction of the nv float64
    values ``vals`` of every thread (sums, except slot ``max_slot``: a maximum) into ``acc[s, :]`` with one
    atomic per value per block (cached). ``sh`` is a shared float64 array of nv * tpb; every thread of the
    block must call it, and all of them must add to the same scene s (observe grids are one block row per
    scene)."""
    key = ("reducer", tpb, nv, max_slot)
    if key not in _cache:
        _cache[key] = _make_reducer(tpb, nv, max_slot)
    return _cache[key]


def _make_reducer(TPB, NV, MAXSLOT):
    @cuda.jit(device=True)
    def block_accumulate(sh, vals, acc, s):
        t = cuda.threadIdx.x
        for q in range(NV):
            sh[q * TPB + t] = vals[q]
        cuda.syncthreads()
        st = TPB // 2
        while st > 0:
            if t < st:
                for q in range(NV):
                    a = sh[q * TPB + t]
                    b = sh[q * TPB + t + st]
                    if q == MAXSLOT:
                        if b > a:
                            sh[q * TPB + t] = b
                    else:
                        sh[q * TPB + t] = a + b
            cuda.syncthreads()
            st //= 2
        if t < NV:
            v = sh[t * TPB]
            if t == MAXSLOT:
                cuda.atomic.max(acc, (s, t), v)
            elif v != 0.0:
                cuda.atomic.add(acc, (s, t), v)

    return block_accumulate


def _make_helpers(TPB):
    f64 = np.float64

    @cuda.jit(device=True)
    def block_max2(sh, a, b):
        """Block-wide max of (a, b) into sh[0], sh[TPB] (all threads must call)."""
        t = cuda.threadIdx.x
        sh[t] = a
        sh[t + TPB] = b
        cuda.syncthreads()
        s = TPB // 2
        while s > 0:
            if t < s:
                if sh[t + s] > sh[t]:
                    sh[t] = sh[t + s]
                if sh[t + TPB + s] > sh[t + TPB]:
                    sh[t + TPB] = sh[t + TPB + s]
            cuda.syncthreads()
            s //= 2

    @cuda.jit(device=True)
    def fail(status, spi, s, word, value, step):
        """Record a blow-up of scene s (first offender, first step) and stop the scene on the device."""
        b = SS0 + NSS * s
        cuda.atomic.min(status, b + word, f64(value))
        cuda.atomic.min(status, b + word + 1, f64(step))
        spi[s, I_ACTIVE] = 0

    return block_max2, fail


def _make(DT, ROUGH, COULOMB, ORIENT, UNIFORM, TPB):  # noqa: C901  (one closure per specialisation)
    ZERO = DT(0)
    HALF = DT(0.5)
    BIG = DT(np.finfo(DT).max)
    f64 = np.float64
    SH2 = 2 * TPB

    block_max2, fail = device_helpers(TPB)

    # ---- step phases (device functions shared by the one-step kernels and the multi-step kernel) ------

    @cuda.jit(device=True)
    def kick_drift_one(i, first, pos, vel, omega, quat, force, torque, inv_m, inv_i, x_ref, ids, sc, spd,
                       spf, spi, status, step):
        """v += F/m hk, w += tau/I hk (hk = dt/2 on the first step of a call, else dt), x += v dt wrapped,
        q advanced; returns the normalised squared displacement and speed (0, 0 for a skipped scene)."""
        s = sc[i]
        if spi[s, I_ACTIVE] == 0:
            return 0.0, 0.0
        dt = spd[s, D_DT]
        hk = spd[s, D_HP] if first else dt
        box = spd[s, D_BOX]
        inv_box = spd[s, D_INVBOX]
        im = spd[s, D_IM0] if UNIFORM else inv_m[i]
        v2 = ZERO
        dsp = ZERO
        for k in range(3):
            v = kick(vel[k, i], force[k, i], im, hk)
            vel[k, i] = v
            x = drift_wrap(pos[k, i], v, dt, box, inv_box)
            pos[k, i] = x
            d = min_image(x - x_ref[k, i], box, inv_box, HALF)
            dsp += d * d
            v2 += v * v
        w2 = ZERO
        if ROUGH:
            ii = spd[s, D_II0] if UNIFORM else inv_i[i]
            for k in range(3):
                w = kick(omega[k, i], torque[k, i], ii, hk)
                omega[k, i] = w
                w2 += w * w
        if ORIENT:
            if spi[s, I_ORIENT] != 0:
                q0, q1, q2, q3 = fincham_quat_step_space(quat[0, i], quat[1, i], quat[2, i], quat[3, i],
                                                         omega[0, i], omega[1, i], omega[2, i], dt, HALF)
                quat[0, i] = q0
                quat[1, i] = q1
                quat[2, i] = q2
                quat[3, i] = q3
        if not (dsp < BIG) or not (v2 < BIG) or not (w2 < BIG):
            fail(status, spi, s, SS_BAD_ID, ids[i], step)
            return 0.0, 0.0
        return f64(dsp) * spf[s, F_LIM2INV], f64(v2) * spf[s, F_V2F]

    @cuda.jit(device=True)
    def forces_one(i, pos, vel, omega, radius, inv_m, f_old, f_new, torque, nbr, nn, hist, ids, sc, spd,
                   spf, spi, status, step):
        """Contact forces and torque on particle i from its list; per-slot history advanced in place."""
        s = sc[i]
        if spi[s, I_ACTIVE] == 0:
            return
        box = spd[s, D_BOX]
        inv_box = spd[s, D_INVBOX]
        hp = spd[s, D_HP]
        dt = spd[s, D_DT]
        k_n = spd[s, D_KN]
        gn_coef = spd[s, D_GN]
        k_t = spd[s, D_KT]
        mu = spd[s, D_MU]
        r0 = spd[s, D_R0]
        im0 = spd[s, D_IM0]
        one = HALF + HALF
        fx = ZERO
        fy = ZERO
        fz = ZERO
        tx = ZERO
        ty = ZERO
        tz = ZERO
        xi = pos[0, i]
        yi = pos[1, i]
        zi = pos[2, i]
        ri = r0 if UNIFORM else radius[i]
        imi = im0 if UNIFORM else inv_m[i]
        wsi = ZERO
        for kk in range(nn[i]):
            j = nbr[kk, i]
            rx = min_image(xi - pos[0, j], box, inv_box, HALF)
            ry = min_image(yi - pos[1, j], box, inv_box, HALF)
            rz = min_image(zi - pos[2, j], box, inv_box, HALF)
            d = math.sqrt(rx * rx + ry * ry + rz * rz)
            rj = r0 if UNIFORM else radius[j]
            delta = ri + rj - d
            delta_prev = hist[3, kk, i]
            if delta > ZERO:
                imj = im0 if UNIFORM else inv_m[j]
                m12 = one / (imi + imj)
                vix = vel[0, i]
                viy = vel[1, i]
                viz = vel[2, i]
                vjx = vel[0, j]
                vjy = vel[1, j]
                vjz = vel[2, j]
                # predicted end-of-step velocities v + F/m dt/2 (CPU: vel_p in kick_drift)
                uix = kick(vix, f_old[0, i], imi, hp)
                uiy = kick(viy, f_old[1, i], imi, hp)
                uiz = kick(viz, f_old[2, i], imi, hp)
                ujx = kick(vjx, f_old[0, j], imj, hp)
                ujy = kick(vjy, f_old[1, j], imj, hp)
                ujz = kick(vjz, f_old[2, j], imj, hp)
                if ROUGH and COULOMB:
                    g = sphere_contact(rx, ry, rz, d, vix - vjx, viy - vjy, viz - vjz,
                                       uix - ujx, uiy - ujy, uiz - ujz,
                                       omega[0, i], omega[1, i], omega[2, i],
                                       omega[0, j], omega[1, j], omega[2, j], ri, rj,
                                       hist[0, kk, i], hist[1, kk, i], hist[2, kk, i], delta_prev,
                                       hist[4, kk, i], m12, k_n, gn_coef * math.sqrt(m12), k_t, mu, dt, HALF)
                elif ROUGH:
                    g = sphere_contact(rx, ry, rz, d, vix - vjx, viy - vjy, viz - vjz,
                                       uix - ujx, uiy - ujy, uiz - ujz,
                                       omega[0, i], omega[1, i], omega[2, i],
                                       omega[0, j], omega[1, j], omega[2, j], ri, rj,
                                       hist[0, kk, i], hist[1, kk, i], hist[2, kk, i], delta_prev,
                                       hist[4, kk, i], m12, k_n, gn_coef * math.sqrt(m12), k_t, None, dt, HALF)
                else:
                    g = sphere_contact(rx, ry, rz, d, vix - vjx, viy - vjy, viz - vjz,
                                       uix - ujx, uiy - ujy, uiz - ujz,
                                       ZERO, ZERO, ZERO, ZERO, ZERO, ZERO, ri, rj,
                                       hist[0, kk, i], hist[1, kk, i], hist[2, kk, i], delta_prev,
                                       hist[4, kk, i], m12, k_n, gn_coef * math.sqrt(m12), None, None, dt, HALF)
                fx += g[0]
                fy += g[1]
                fz += g[2]
                if ROUGH:
                    tx += g[3]
                    ty += g[4]
                    tz += g[5]
                    hist[0, kk, i] = g[6]
                    hist[1, kk, i] = g[7]
                    hist[2, kk, i] = g[8]
                hist[4, kk, i] = g[10]
                ov = delta / min(ri, rj)
                if ov > wsi:
                    wsi = ov
            elif delta_prev > ZERO:
                pe = contact_end_fraction(delta_prev, delta)
                vjx = vel[0, j]
                vjy = vel[1, j]
                vjz = vel[2, j]
                if ROUGH:
                    e = sphere_contact_end(rx, ry, rz, d, vel[0, i] - vjx, vel[1, i] - vjy, vel[2, i] - vjz,
                                           omega[0, i], omega[1, i], omega[2, i],
                                           omega[0, j], omega[1, j], omega[2, j], ri, rj,
                                           hist[4, kk, i], hist[0, kk, i], hist[1, kk, i], hist[2, kk, i],
                                           k_t, pe, dt, HALF)
                else:
                    e = sphere_contact_end(rx, ry, rz, d, vel[0, i] - vjx, vel[1, i] - vjy, vel[2, i] - vjz,
                                           ZERO, ZERO, ZERO, ZERO, ZERO, ZERO, ri, rj,
                                           hist[4, kk, i], hist[0, kk, i], hist[1, kk, i], hist[2, kk, i],
                                           None, pe, dt, HALF)
                fx += e[0]
                fy += e[1]
                fz += e[2]
                if ROUGH:
                    tx += e[3]
                    ty += e[4]
                    tz += e[5]
                    hist[0, kk, i] = ZERO
                    hist[1, kk, i] = ZERO
                    hist[2, kk, i] = ZERO
            hist[3, kk, i] = delta
        f_new[0, i] = fx
        f_new[1, i] = fy
        f_new[2, i] = fz
        if ROUGH:
            torque[0, i] = tx
            torque[1, i] = ty
            torque[2, i] = tz
        w64 = f64(wsi)
        if w64 > spf[s, F_OVL]:
            b = SS0 + NSS * s
            cuda.atomic.max(status, b + SS_OVL, w64)
            fail(status, spi, s, SS_OVL_ID, ids[i], step)

    # ---- one-step kernels (large scenes: launch overhead is negligible) ---------------------------------

    @cuda.jit
    def kick_drift(n, first, pos, vel, omega, quat, force, torque, inv_m, inv_i, x_ref, ids, sc, spd, spf,
                   spi, status, step):
        sh = cuda.shared.array(SH2, ct.float64)
        md = 0.0
        mv = 0.0
        for i in range(cuda.grid(1), n, cuda.gridsize(1)):
            d2, v2 = kick_drift_one(i, first, pos, vel, omega, quat, force, torque, inv_m, inv_i, x_ref, ids,
                                    sc, spd, spf, spi, status, step)
            md = max(md, d2)
            mv = max(mv, v2)
        block_max2(sh, md, mv)
        if cuda.threadIdx.x == 0:
            cuda.atomic.max(status, S_D2, sh[0])
            cuda.atomic.max(status, S_V2, sh[TPB])

    @cuda.jit
    def forces(n, pos, vel, omega, radius, inv_m, f_old, f_new, torque, nbr, nn, hist, ids, sc, spd, spf,
               spi, status, step):
        i0 = cuda.grid(1)
        if i0 == 0:  # reset the per-step maxima for the next kick_drift (stream-ordered after its copy)
            status[S_D2] = 0.0
            status[S_V2] = 0.0
        for i in range(i0, n, cuda.gridsize(1)):
            forces_one(i, pos, vel, omega, radius, inv_m, f_old, f_new, torque, nbr, nn, hist, ids, sc, spd,
                       spf, spi, status, step)

    @cuda.jit
    def half_kick(n, vel, omega, force, torque, inv_m, inv_i, sc, spd, spi):
        for i in range(cuda.grid(1), n, cuda.gridsize(1)):
            s = sc[i]
            if spi[s, I_ACTIVE] == 0:
                continue
            hk = spd[s, D_HP]
            im = spd[s, D_IM0] if UNIFORM else inv_m[i]
            for k in range(3):
                vel[k, i] = kick(vel[k, i], force[k, i], im, hk)
            if ROUGH:
                ii = spd[s, D_II0] if UNIFORM else inv_i[i]
                for k in range(3):
                    omega[k, i] = kick(omega[k, i], torque[k, i], ii, hk)

    # ---- many steps per launch (small scenes and ensembles: launch overhead paid once per chunk) -------

    @cuda.jit
    def run_steps(n, nmax, first, skip_kick, thr, pos, vel, omega, quat, f0, f1, torque, inv_m, inv_i, radius,
                  x_ref, nbr, nn, hist, ids, sc, spd, spf, spi, status, step0):
        """Up to nmax whole steps in one cooperative launch, the phases separated by grid syncs.

        Stops early, after the drift of a step and before its forces, when a particle has moved more than
        sqrt(thr) L_v/2 since the list build (thr = 1: the rebuild rule; thr = 1/4: the L_v/4 signal of the
        pipelined CPU-list mode): status[S_RUN_REBUILD] = 1 and status[S_RUN_DONE] = the whole steps
        completed (the host rebuilds or starts a CPU build, computes that step's forces and relaunches). Step st reads forces
        from f0 when st is even (f1 when odd) and writes the other buffer. skip_kick = 1: the drift of
        step 0 is already done (the host computes its forces first).
        """
        g = cuda.cg.this_grid()
        sh = cuda.shared.array(SH2, ct.float64)
        i0 = cuda.grid(1)
        stride = cuda.gridsize(1)
        if i0 == 0:
            status[S_D2] = 0.0
            status[S_D2B] = 0.0
            status[S_RUN_DONE] = 0.0
            status[S_RUN_REBUILD] = 0.0
        g.sync()
        done = 0
        for st in range(nmax):
            even = (st & 1) == 0
            slot = S_D2 if even else S_D2B
            if even:
                fa = f0
                fb = f1
            else:
                fa = f1
                fb = f0
            step = step0 + st
            if not (st == 0 and skip_kick != 0):
                if i0 == 0:
                    status[S_D2B if even else S_D2] = 0.0  # the other parity's slot, free until next step
                md = 0.0
                for i in range(i0, n, stride):
                    d2, v2 = kick_drift_one(i, first if st == 0 else 0, pos, vel, omega, quat, fa, torque,
                                            inv_m, inv_i, x_ref, ids, sc, spd, spf, spi, status, step)
                    md = max(md, d2)
                block_max2(sh, md, 0.0)
                if cuda.threadIdx.x == 0:
                    cuda.atomic.max(status, slot, sh[0])
                g.sync()
                if status[slot] > thr:
                    break
            for i in range(i0, n, stride):
                forces_one(i, pos, vel, omega, radius, inv_m, fa, fb, torque, nbr, nn, hist, ids, sc, spd,
                           spf, spi, status, step)
            done += 1
            g.sync()
        if i0 == 0:
            status[S_RUN_DONE] = f64(done)
            status[S_RUN_REBUILD] = 1.0 if done < nmax else 0.0

    # ---- neighbour list: cells, sort, permute, compact history, build -----------------------------------

    @cuda.jit(device=True)
    def cell_of(i, pos, sc, spf, spi):
        s = sc[i]
        return spi[s, I_COFF] + cell_index_of(pos[0, i], pos[1, i], pos[2, i], spf[s, F_INVCELL], spi[s, I_NC])

    @cuda.jit
    def fill_i32(a, value):
        for i in range(cuda.grid(1), a.shape[0], cuda.gridsize(1)):
            a[i] = value

    @cuda.jit
    def count_cells(n, pos, sc, spf, spi, count):
        for i in range(cuda.grid(1), n, cuda.gridsize(1)):
            cuda.atomic.add(count, cell_of(i, pos, sc, spf, spi), 1)

    @cuda.jit
    def tile_scan(src, dst, n, bsum, items):
        """Exclusive scan of src[0:n] per tile of TPB*items elements; tile totals into bsum."""
        sh = cuda.shared.array(TPB, ct.int64)
        t = cuda.threadIdx.x
        base = cuda.blockIdx.x * TPB * items + t * items
        s = 0
        for k in range(items):
            if base + k < n:
                s += src[base + k]
        sh[t] = s
        cuda.syncthreads()
        off = 1
        while off < TPB:
            v = 0
            if t >= off:
                v = sh[t - off]
            cuda.syncthreads()
            sh[t] += v
            cuda.syncthreads()
            off *= 2
        run = sh[t] - s
        for k in range(items):
            if base + k < n:
                x = src[base + k]
                dst[base + k] = run
                run += x
        if t == TPB - 1:
            bsum[cuda.blockIdx.x] = sh[t]

    @cuda.jit
    def add_offsets(dst, n, offs, tile):
        for i in range(cuda.grid(1), n, cuda.gridsize(1)):
            dst[i] += offs[i // tile]

    @cuda.jit
    def scatter(n, pos, sc, spf, spi, cell_start, cursor, order):
        for i in range(cuda.grid(1), n, cuda.gridsize(1)):
            c = cell_of(i, pos, sc, spf, spi)
            order[cell_start[c] + cuda.atomic.add(cursor, c, 1)] = i

    @cuda.jit
    def sort_cells(ncell, cell_start, order, ids):
        """Insertion sort of each cell's particles by id: a deterministic order (cell, id)."""
        for c in range(cuda.grid(1), ncell, cuda.gridsize(1)):
            a = cell_start[c]
            b = cell_start[c + 1]
            for p in range(a + 1, b):
                v = order[p]
                key = ids[v]
                q = p - 1
                while q >= a and ids[order[q]] > key:
                    order[q + 1] = order[q]
                    q -= 1
                order[q + 1] = v

    @cuda.jit
    def gather_rows(n, src, dst, order):
        """dst[:, k] = src[:, order[k]] (also for 1-row arrays given as (1, N))."""
        for k in range(cuda.grid(1), n, cuda.gridsize(1)):
            o = order[k]
            for r in range(src.shape[0]):
                dst[r, k] = src[r, o]

    @cuda.jit
    def gather_i32(n, src, dst, order):
        for k in range(cuda.grid(1), n, cuda.gridsize(1)):
            dst[k] = src[order[k]]

    @cuda.jit
    def inverse_perm(n, order, inv):
        for k in range(cuda.grid(1), n, cuda.gridsize(1)):
            inv[order[k]] = k

    @cuda.jit(device=True)
    def keeps_history(i, kk, j, pos, radius, hist, s, spd):
        """A slot whose history must survive a rebuild: in contact at the previous step or now."""
        if hist[3, kk, i] > ZERO:
            return True
        box = spd[s, D_BOX]
        inv_box = spd[s, D_INVBOX]
        r0 = spd[s, D_R0]
        rx = min_image(pos[0, i] - pos[0, j], box, inv_box, HALF)
        ry = min_image(pos[1, i] - pos[1, j], box, inv_box, HALF)
        rz = min_image(pos[2, i] - pos[2, j], box, inv_box, HALF)
        rs = (r0 + r0) if UNIFORM else (radius[i] + radius[j])
        return rx * rx + ry * ry + rz * rz < rs * rs

    @cuda.jit
    def compact(n, pos, radius, nbr, nn, hist, sc, spd, spi, c_off, c_cnt, cj, chist, status):
        """Copy the slots that keep history into the compact store (old slot order); the total goes to
        status[S_NCOMP]; nothing is written past the store's capacity (the host grows it and reruns)."""
        cap = cj.shape[0]
        m = nbr.shape[0]
        for i in range(cuda.grid(1), n, cuda.gridsize(1)):
            s = sc[i]
            cnt = 0
            no = min(nn[i], m)
            if spi[s, I_ACTIVE] != 0:
                for kk in range(no):
                    if keeps_history(i, kk, nbr[kk, i], pos, radius, hist, s, spd):
                        cnt += 1
            off = 0
            if cnt > 0:
                off = int(cuda.atomic.add(status, S_NCOMP, f64(cnt)))
            c_off[i] = off
            c_cnt[i] = cnt
            if cnt > 0 and off + cnt <= cap:
                q = off
                for kk in range(no):
                    j = nbr[kk, i]
                    if keeps_history(i, kk, j, pos, radius, hist, s, spd):
                        cj[q] = j
                        for w in range(HW):
                            chist[w, q] = hist[w, kk, i]
                        q += 1

    @cuda.jit
    def build(n, pos, radius, cell_start, c_off, c_cnt, cj, chist, order, inv_old, nbr, nn, hist, x_ref, sc,
              spd, spf, spi, status):
        """Full Verlet list in the sorted order; kept history found in the compact store.

        The compact store is indexed by the previous order: the old slot of new i is order[i]; an old
        neighbour index o maps to the new index inv_old[o]. nn[i] gets the true count even beyond the
        stride (the host grows the list and reruns when it does not fit).
        """
        sh = cuda.shared.array(SH2, ct.float64)
        max_nb = nbr.shape[0]
        need = 0.0
        for i in range(cuda.grid(1), n, cuda.gridsize(1)):
            xi = pos[0, i]
            yi = pos[1, i]
            zi = pos[2, i]
            x_ref[0, i] = xi
            x_ref[1, i] = yi
            x_ref[2, i] = zi
            s = sc[i]
            if spi[s, I_ACTIVE] == 0:
                nn[i] = 0
                continue
            nc = spi[s, I_NC]
            coff = spi[s, I_COFF]
            box = spd[s, D_BOX]
            inv_box = spd[s, D_INVBOX]
            skin = spd[s, D_SKIN]
            r0 = spd[s, D_R0]
            cx, cy, cz = cell_coords(xi, yi, zi, spf[s, F_INVCELL], nc)
            ri = r0 if UNIFORM else radius[i]
            oi = order[i]
            k0 = c_off[oi]
            k1 = k0 + c_cnt[oi]
            cnt = 0
            for k in range(neighbour_cell_count(nc)):
                cc = coff + neighbour_cell(cx, cy, cz, k, nc)
                for j in range(cell_start[cc], cell_start[cc + 1]):
                    if j == i:
                        continue
                    d2 = distance2(xi, yi, zi, pos[0, j], pos[1, j], pos[2, j], box, inv_box, HALF)
                    rj = r0 if UNIFORM else radius[j]
                    rc = ri + rj + skin
                    if d2 < rc * rc:
                        if cnt < max_nb:
                            nbr[cnt, i] = j
                            init_slot(i, cnt, j, ri + rj - math.sqrt(d2), k0, k1, cj, chist, inv_old, hist)
                        cnt += 1
            nn[i] = cnt
            if cnt > need:
                need = f64(cnt)
        block_max2(sh, need, 0.0)
        if cuda.threadIdx.x == 0:
            cuda.atomic.max(status, S_NEED_NB, sh[0])

    # ---- observables ----------------------------------------------------------------------------------

    block_accumulate = observe_reducer(TPB, NOBS, 7)
    SH_OBS = NOBS * TPB

    @cuda.jit
    def observe(pos, vel, omega, radius, mass, inertia, nbr, nn, hist, spd, spf, spi, acc):
        """acc[s] += (E_tr, E_rot, contacts (x2), elastic energy, P_x, P_y, P_z); acc[s, 7] = max overlap;
        acc[s, 8:11] += (sum e_tr^2, sum e_rot^2, sum e_tr e_rot), the Sonine moments (cpu.observe_kernel).

        One block row per scene (blockIdx.y = s); per particle in float64, reduced per block
        (observe_reducer): O(blocks) atomics, not O(N) on K x 8 addresses (issue 14)."""
        s = cuda.blockIdx.y
        sh = cuda.shared.array(SH_OBS, ct.float64)
        vals = cuda.local.array(NOBS, ct.float64)
        for q in range(NOBS):
            vals[q] = 0.0
        if spi[s, I_ACTIVE] != 0:
            a0 = spi[s, I_START]
            box = spd[s, D_BOX]
            inv_box = spd[s, D_INVBOX]
            r0 = spd[s, D_R0]
            for li in range(cuda.blockIdx.x * TPB + cuda.threadIdx.x, spi[s, I_N], cuda.gridDim.x * TPB):
                i = a0 + li
                m = f64(spd[s, D_M0]) if UNIFORM else f64(mass[i])
                ii = f64(spd[s, D_I0]) if UNIFORM else f64(inertia[i])
                vx = f64(vel[0, i])
                vy = f64(vel[1, i])
                vz = f64(vel[2, i])
                wx = f64(omega[0, i])
                wy = f64(omega[1, i])
                wz = f64(omega[2, i])
                vals[0] += 0.5 * m * (vx * vx + vy * vy + vz * vz)
                vals[1] += 0.5 * ii * (wx * wx + wy * wy + wz * wz)
                vals[4] += m * vx
                vals[5] += m * vy
                vals[6] += m * vz
                et_i = 0.5 * m * (vx * vx + vy * vy + vz * vz)
                er_i = 0.5 * ii * (wx * wx + wy * wy + wz * wz)
                vals[O_TR2] += et_i * et_i
                vals[O_ROT2] += er_i * er_i
                vals[O_X] += et_i * er_i
                ri = r0 if UNIFORM else radius[i]
                for kk in range(nn[i]):
                    j = nbr[kk, i]
                    rx = min_image(pos[0, i] - pos[0, j], box, inv_box, HALF)
                    ry = min_image(pos[1, i] - pos[1, j], box, inv_box, HALF)
                    rz = min_image(pos[2, i] - pos[2, j], box, inv_box, HALF)
                    rj = r0 if UNIFORM else radius[j]
                    rs = ri + rj
                    d2 = rx * rx + ry * ry + rz * rz
                    if d2 < rs * rs:
                        vals[2] += 1.0
                        delta = f64(rs - math.sqrt(d2))
                        # each pair appears in both partners' lists
                        vals[3] += 0.5 * contact_elastic_energy(delta, f64(hist[0, kk, i]), f64(hist[1, kk, i]),
                                                                f64(hist[2, kk, i]), spf[s, F_KN], spf[s, F_KT], 0.5)
                        vals[7] = max(vals[7], delta / f64(min(ri, rj)))
        block_accumulate(sh, vals, acc, s)

    return dict(kick_drift=kick_drift, forces=forces, half_kick=half_kick, run_steps=run_steps,
                fill_i32=fill_i32, count_cells=count_cells, tile_scan=tile_scan, add_offsets=add_offsets,
                scatter=scatter, sort_cells=sort_cells, gather_rows=gather_rows, gather_i32=gather_i32,
                inverse_perm=inverse_perm, compact=compact, build=build, observe=observe)


@cuda.jit
def gather_scene(src, ids, a0, n_k, dst):
    """dst[ids[a0 + l] - a0, r] = src[r, a0 + l] for l < n_k: one scene's rows of a (rows, N) state array in
    particle-id order, particle-major, for the host copy of a snapshot or checkpoint."""
    for li in range(cuda.grid(1), n_k, cuda.gridsize(1)):
        i = a0 + li
        o = ids[i] - a0
        for r in range(src.shape[0]):
            dst[o, r] = src[r, i]


cache_kernels({"gather_scene": gather_scene}, ("gather",))


@cuda.jit(device=True)
def init_slot(i, kk, j, gap, k0, k1, cj, chist, inv_old, hist):
    """History of list slot kk of particle i (neighbour j) after a rebuild: the kept history from the
    compact store entries k0..k1 of i (old indices o map to new ones by inv_old[o]), else a fresh slot
    (zero spring, zero dashpot force, previous overlap = the current gap, m)."""
    for q in range(k0, k1):
        if inv_old[cj[q]] == j:
            for w in range(HW):
                hist[w, kk, i] = chist[w, q]
            return
    for w in range(HW):
        hist[w, kk, i] = 0
    hist[3, kk, i] = gap
