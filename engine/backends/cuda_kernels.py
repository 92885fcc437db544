"""CUDA kernels of the GPU backend, built by factories keyed on what a scene needs (DESIGN §1).

Every kernel calls the same ``@numba.njit`` physics functions as the CPU backend
(:mod:`engine.physics`); this module owns only layout, loops and launches.

Layout (device, particles in *sorted* order, structure of arrays, i fastest):
    pos, vel, omega (3, N); quat (4, N); force_a/force_b (3, N) (double buffer: the force kernel reads
    the previous step's forces for the predicted velocities of *other* particles while writing its
    own); torque (3, N); x_ref (3, N); ids (N) int32 = particle id of each device slot.
    Neighbour list: nbr (M, N) int32, nn (N) int32, hist (H, M, N) per-slot contact history
    (H = 5: tangential spring x,y,z, previous overlap, previous normal force), double-buffered for
    the rebuild (history carried over through the id permutation).
    Uniform scenes (one radius, one mass) pass scalars instead of per-particle radius / 1/m / 1/I.

Reductions (max displacement, max speed, instability flags, observables) are done per block in
shared memory and folded into a small float64 ``status`` array with one atomic per block.
"""

from __future__ import annotations

import math

import numpy as np
from numba import cuda
from numba.cuda import types as ct

from engine.physics.contact import (contact_elastic_energy, contact_end_fraction, min_image, sphere_contact,
                                    sphere_contact_end)
from engine.physics.integrate import drift_wrap, kick
from engine.physics.rotation import fincham_quat_step_space

# status slots (float64)
S_DISP2, S_V2, S_BAD_ID, S_BAD_STEP, S_OVL, S_OVL_ID, S_OVL_STEP, S_NEED_NB, S_LATE = range(9)
S_LEN = 12
HW = 5  # history words per list slot: spring x, y, z, previous overlap, previous normal force

_cache: dict = {}


def kernels(dtype, rough: bool, coulomb: bool, orient: bool, uniform: bool, tpb: int):
    """The kernel set for one specialisation (cached)."""
    key = (np.dtype(dtype).str, rough, coulomb, orient, uniform, tpb)
    if key not in _cache:
        _cache[key] = _make(np.dtype(dtype).type, rough, coulomb, orient, uniform, tpb)
    return _cache[key]


def _make(DT, ROUGH, COULOMB, ORIENT, UNIFORM, TPB):  # noqa: C901  (one closure per specialisation)
    ZERO = DT(0)
    BIG = DT(np.finfo(DT).max)
    INF = np.float64(np.inf)
    f64 = np.float64
    SH2 = 2 * TPB
    SHOBS = (8, TPB)

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

    # ---- step kernels -------------------------------------------------------------------------

    @cuda.jit
    def kick_drift(n, pos, vel, omega, quat, force, torque, inv_m, inv_i, im0, ii0, x_ref, ids,
                   hk, dt, box, inv_box, half, status, step):
        """v += F/m hk, w += tau/I hk, x += v dt (wrapped), q advanced; max |x - x_ref|^2, max |v|^2."""
        sh = cuda.shared.array(SH2, ct.float64)
        i0 = cuda.grid(1)
        stride = cuda.gridsize(1)
        md = 0.0
        mv = 0.0
        for i in range(i0, n, stride):
            im = im0 if UNIFORM else inv_m[i]
            v2 = ZERO
            dsp = ZERO
            for k in range(3):
                v = kick(vel[k, i], force[k, i], im, hk)
                vel[k, i] = v
                x = drift_wrap(pos[k, i], v, dt, box, inv_box)
                pos[k, i] = x
                d = min_image(x - x_ref[k, i], box, inv_box, half)
                dsp += d * d
                v2 += v * v
            w2 = ZERO
            if ROUGH:
                ii = ii0 if UNIFORM else inv_i[i]
                for k in range(3):
                    w = kick(omega[k, i], torque[k, i], ii, hk)
                    omega[k, i] = w
                    w2 += w * w
            if ORIENT:
                q0, q1, q2, q3 = fincham_quat_step_space(quat[0, i], quat[1, i], quat[2, i], quat[3, i],
                                                         omega[0, i], omega[1, i], omega[2, i], dt, half)
                quat[0, i] = q0
                quat[1, i] = q1
                quat[2, i] = q2
                quat[3, i] = q3
            if not (dsp < BIG) or not (v2 < BIG) or not (w2 < BIG):
                cuda.atomic.min(status, S_BAD_ID, f64(ids[i]))
                cuda.atomic.min(status, S_BAD_STEP, f64(step))
            else:
                if dsp > md:
                    md = dsp
                if v2 > mv:
                    mv = v2
        block_max2(sh, md, mv)
        if cuda.threadIdx.x == 0:
            cuda.atomic.max(status, S_DISP2, sh[0])
            cuda.atomic.max(status, S_V2, sh[TPB])

    @cuda.jit
    def forces(n, pos, vel, omega, radius, inv_m, r0, im0, f_old, f_new, torque, nbr, nn, hist, ids,
               box, inv_box, half, hp, k_n, gn_coef, k_t, mu, dt, ovl_limit, status, step):
        """Contact forces and torques from the full list; per-slot history advanced in place."""
        sh = cuda.shared.array(SH2, ct.float64)
        i0 = cuda.grid(1)
        stride = cuda.gridsize(1)
        one = half + half
        worst = 0.0
        worst_id = INF
        if i0 == 0:  # reset the per-step maxima for the next kick_drift (stream-ordered after its copy)
            status[S_DISP2] = 0.0
            status[S_V2] = 0.0
        for i in range(i0, n, stride):
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
                rx = min_image(xi - pos[0, j], box, inv_box, half)
                ry = min_image(yi - pos[1, j], box, inv_box, half)
                rz = min_image(zi - pos[2, j], box, inv_box, half)
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
                                           hist[0, kk, i], hist[1, kk, i], hist[2, kk, i], delta_prev, hist[4, kk, i], m12,
                                           k_n, gn_coef * math.sqrt(m12), k_t, mu, dt, half)
                    elif ROUGH:
                        g = sphere_contact(rx, ry, rz, d, vix - vjx, viy - vjy, viz - vjz,
                                           uix - ujx, uiy - ujy, uiz - ujz,
                                           omega[0, i], omega[1, i], omega[2, i],
                                           omega[0, j], omega[1, j], omega[2, j], ri, rj,
                                           hist[0, kk, i], hist[1, kk, i], hist[2, kk, i], delta_prev, hist[4, kk, i], m12,
                                           k_n, gn_coef * math.sqrt(m12), k_t, None, dt, half)
                    else:
                        g = sphere_contact(rx, ry, rz, d, vix - vjx, viy - vjy, viz - vjz,
                                           uix - ujx, uiy - ujy, uiz - ujz,
                                           ZERO, ZERO, ZERO, ZERO, ZERO, ZERO, ri, rj,
                                           hist[0, kk, i], hist[1, kk, i], hist[2, kk, i], delta_prev, hist[4, kk, i], m12,
                                           k_n, gn_coef * math.sqrt(m12), None, None, dt, half)
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
                                               k_t, pe, dt, half)
                    else:
                        e = sphere_contact_end(rx, ry, rz, d, vel[0, i] - vjx, vel[1, i] - vjy, vel[2, i] - vjz,
                                               ZERO, ZERO, ZERO, ZERO, ZERO, ZERO, ri, rj,
                                               hist[4, kk, i], hist[0, kk, i], hist[1, kk, i], hist[2, kk, i],
                                               None, pe, dt, half)
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
            if w64 > worst:
                worst = w64
                if w64 > ovl_limit:
                    worst_id = min(worst_id, f64(ids[i]))
        # block max of the worst overlap; offender id by atomic min
        block_max2(sh, worst, -worst_id)
        if cuda.threadIdx.x == 0 and sh[0] > ovl_limit:
            cuda.atomic.max(status, S_OVL, sh[0])
            cuda.atomic.min(status, S_OVL_ID, -sh[TPB])
            cuda.atomic.min(status, S_OVL_STEP, f64(step))

    @cuda.jit
    def half_kick(n, vel, omega, force, torque, inv_m, inv_i, im0, ii0, hk):
        for i in range(cuda.grid(1), n, cuda.gridsize(1)):
            im = im0 if UNIFORM else inv_m[i]
            for k in range(3):
                vel[k, i] = kick(vel[k, i], force[k, i], im, hk)
            if ROUGH:
                ii = ii0 if UNIFORM else inv_i[i]
                for k in range(3):
                    omega[k, i] = kick(omega[k, i], torque[k, i], ii, hk)

    # ---- neighbour list: cells, sort, permute, build ------------------------------------------

    @cuda.jit
    def fill_i32(a, value):
        for i in range(cuda.grid(1), a.shape[0], cuda.gridsize(1)):
            a[i] = value

    @cuda.jit
    def count_cells(n, pos, nc, inv_cell, count):
        for i in range(cuda.grid(1), n, cuda.gridsize(1)):
            c = _cell(pos[0, i], pos[1, i], pos[2, i], nc, inv_cell)
            cuda.atomic.add(count, c, 1)

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
    def scatter(n, pos, nc, inv_cell, cell_start, cursor, order):
        for i in range(cuda.grid(1), n, cuda.gridsize(1)):
            c = _cell(pos[0, i], pos[1, i], pos[2, i], nc, inv_cell)
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

    @cuda.jit
    def build(n, pos, radius, r0, skin, box, inv_box, half, nc, inv_cell, cell_start,
              nbr_old, nn_old, hist_old, order, inv_old, nbr, nn, hist, x_ref, status):
        """Full Verlet list in the sorted order; history of surviving pairs carried over.

        Old list rows are in the previous order: row of new i is order[i]; an old neighbour index o
        maps to the new index inv_old[o]. nn[i] gets the true count even beyond the stride.
        """
        sh = cuda.shared.array(SH2, ct.float64)
        max_nb = nbr.shape[0]
        lo = -1 if nc >= 3 else 0
        hi = 2 if nc >= 2 else 1
        need = 0.0
        for i in range(cuda.grid(1), n, cuda.gridsize(1)):
            xi = pos[0, i]
            yi = pos[1, i]
            zi = pos[2, i]
            c = _cell(xi, yi, zi, nc, inv_cell)
            cx = c // (nc * nc)
            cy = (c // nc) % nc
            cz = c % nc
            ri = r0 if UNIFORM else radius[i]
            oi = order[i]
            no = nn_old[oi]
            if no > nbr_old.shape[0]:
                no = nbr_old.shape[0]
            cnt = 0
            for ox in range(lo, hi):
                ax = (cx + ox + nc) % nc
                for oy in range(lo, hi):
                    ay = (cy + oy + nc) % nc
                    for oz in range(lo, hi):
                        az = (cz + oz + nc) % nc
                        cc = (ax * nc + ay) * nc + az
                        for j in range(cell_start[cc], cell_start[cc + 1]):
                            if j == i:
                                continue
                            dx = min_image(xi - pos[0, j], box, inv_box, half)
                            dy = min_image(yi - pos[1, j], box, inv_box, half)
                            dz = min_image(zi - pos[2, j], box, inv_box, half)
                            rj = r0 if UNIFORM else radius[j]
                            rc = ri + rj + skin
                            d2 = dx * dx + dy * dy + dz * dz
                            if d2 < rc * rc:
                                if cnt < max_nb:
                                    nbr[cnt, i] = j
                                    found = False
                                    for kk in range(no):
                                        if inv_old[nbr_old[kk, oi]] == j:
                                            for q in range(HW):
                                                hist[q, cnt, i] = hist_old[q, kk, oi]
                                            found = True
                                            break
                                    if not found:
                                        for q in range(HW):
                                            hist[q, cnt, i] = ZERO
                                        hist[3, cnt, i] = ri + rj - math.sqrt(d2)
                                cnt += 1
            nn[i] = cnt
            x_ref[0, i] = xi
            x_ref[1, i] = yi
            x_ref[2, i] = zi
            if cnt > need:
                need = f64(cnt)
        block_max2(sh, need, 0.0)
        if cuda.threadIdx.x == 0:
            cuda.atomic.max(status, S_NEED_NB, sh[0])

    # ---- observables ----------------------------------------------------------------------------

    @cuda.jit
    def observe(n, pos, vel, omega, radius, r0, mass, m0, inertia, i0_, nbr, nn, hist, box, inv_box,
                half, k_n, k_t, acc):
        """acc += (E_tr, E_rot, contacts (x2), elastic energy, P_x, P_y, P_z); acc[7] = max overlap."""
        sh = cuda.shared.array(SHOBS, ct.float64)
        t = cuda.threadIdx.x
        a = cuda.local.array(8, ct.float64)
        for q in range(8):
            a[q] = 0.0
        for i in range(cuda.grid(1), n, cuda.gridsize(1)):
            m = f64(m0) if UNIFORM else f64(mass[i])
            ii = f64(i0_) if UNIFORM else f64(inertia[i])
            vx = f64(vel[0, i])
            vy = f64(vel[1, i])
            vz = f64(vel[2, i])
            wx = f64(omega[0, i])
            wy = f64(omega[1, i])
            wz = f64(omega[2, i])
            a[0] += 0.5 * m * (vx * vx + vy * vy + vz * vz)
            a[1] += 0.5 * ii * (wx * wx + wy * wy + wz * wz)
            a[4] += m * vx
            a[5] += m * vy
            a[6] += m * vz
            ri = r0 if UNIFORM else radius[i]
            for kk in range(nn[i]):
                j = nbr[kk, i]
                rx = min_image(pos[0, i] - pos[0, j], box, inv_box, half)
                ry = min_image(pos[1, i] - pos[1, j], box, inv_box, half)
                rz = min_image(pos[2, i] - pos[2, j], box, inv_box, half)
                rj = r0 if UNIFORM else radius[j]
                s = ri + rj
                d2 = rx * rx + ry * ry + rz * rz
                if d2 < s * s:
                    a[2] += 1.0
                    delta = f64(s - math.sqrt(d2))
                    h0 = f64(hist[0, kk, i])
                    h1 = f64(hist[1, kk, i])
                    h2 = f64(hist[2, kk, i])
                    # each pair appears in both partners' lists
                    a[3] += 0.5 * contact_elastic_energy(delta, h0, h1, h2, k_n, k_t, 0.5)
                    ov = delta / f64(min(ri, rj))
                    if ov > a[7]:
                        a[7] = ov
        for q in range(8):
            sh[q, t] = a[q]
        cuda.syncthreads()
        s = TPB // 2
        while s > 0:
            if t < s:
                for q in range(7):
                    sh[q, t] += sh[q, t + s]
                if sh[7, t + s] > sh[7, t]:
                    sh[7, t] = sh[7, t + s]
            cuda.syncthreads()
            s //= 2
        if t == 0:
            for q in range(7):
                cuda.atomic.add(acc, q, sh[q, 0])
            cuda.atomic.max(acc, 7, sh[7, 0])

    return dict(kick_drift=kick_drift, forces=forces, half_kick=half_kick, fill_i32=fill_i32,
                count_cells=count_cells, tile_scan=tile_scan, add_offsets=add_offsets, scatter=scatter,
                sort_cells=sort_cells, gather_rows=gather_rows, gather_i32=gather_i32,
                inverse_perm=inverse_perm, build=build, observe=observe)


@cuda.jit(device=True)
def _cell(x, y, z, nc, inv_cell):
    """Cell index of a position, exactly as the CPU backend bins (float64 products, clamped)."""
    cx = min(max(int(np.float64(x) * inv_cell), 0), nc - 1)
    cy = min(max(int(np.float64(y) * inv_cell), 0), nc - 1)
    cz = min(max(int(np.float64(z) * inv_cell), 0), nc - 1)
    return (cx * nc + cy) * nc + cz
