"""The spheroid shape's CUDA parts (prolate ellipsoids, Rubio-Largo et al. 2015; frictionless or rough): what
an ellipsoid adds to the one CUDA time loop (engine/loops/cuda_loop.py; the interface is in
engine/shapes/sphere/device.py).

The device functions call the same ``@numba.njit`` functions as the CPU plug-in (engine/shapes/spheroid/kernels.py)
and keep only the gather from and scatter into this backend's layout: the spheroid's pair evaluator
:func:`engine.shapes.spheroid.law.spheroid_pair` (exact disjointness screens, Perram-Wertheim contact function,
contact point and normal, overlap, normal force with the contact start/end corrections, the rough law's tangential
spring, torques), :func:`~engine.shapes.spheroid.law.spheroid_gap` for the previous step's gap of a contact that
starts right after a screened step, :func:`~engine.shapes.spheroid.law.mid_step_omega` (the rough spring's
mid-step spins) and :func:`~engine.shapes.spheroid.law.spheroid_rotation` (Euler's equations in the body frame
through the space-frame angular momentum L, Fincham's leap-frog for the quaternion, Rubio-Largo et al. (2015)
Eqs. 13-21, renormalised every step); observe reads :func:`engine.physics.rotation.body_omega`.

Layout (device, particle index fastest; engine/shapes/spheroid/cuda_backend.py allocates it):
    ``spin`` = angm (3, N): space-frame angular momentum L (kg m^2/s), kicked by the torque with unit factor;
    ``spin_inv`` = inv_i (3, N): principal 1/I about the body axes; ``rad`` = the bounding radius a (largest
    semi-axis: the broad phase is the bounding-sphere list of engine/loops/cuda_kernels.py);
    ``ext`` = (axes (3, N), vel_p (3, N), omega_p (3, N), pos_prev (3, N), quat_prev (4, N), inv_i (3, N)):
    semi-axes, the predicted end-of-step velocities v + F/m dt/2 and angular velocities R I^-1 R^T (L + tau dt/2)
    written by the kick-drift (so the force phase reads no force of another particle: one force buffer), the
    positions and orientations before the current step (read when a contact starts right after a screened step,
    and by the rough spring's mid-step angular velocity), and the principal 1/I again (the rough law's
    tangential mass; a (3, 1) dummy for uniform scenes, which read spd).
    hist (5 or 6, M, N): slots 3 and 4 hold the previous overlap (m; negative: the gap; -inf: screened) and the
    previous dashpot force (N); rough contacts (flag ROUGH, 6 words): the tangential spring in 0-2 (m) and the
    contact's k_t in 5 (N/m; engine.physics.rough_spheroid.rough_spheroid_pair); frictionless: 0-2 unused.
Per-scene constants: the common tables, D_R0 = a, with :data:`NCOL` spheroid columns appended to spd after the
backend's ND (:data:`C_A` ... :data:`C_FT` are offsets from ND): semi-axes, principal 1/I, Perram-Wertheim
tolerance, smallest semi-axis (overlap guard), margin of the exact screens, the rough law's factor f_t.
Each pair is evaluated with the lower particle id as "A" in both partners' loops (CPU: the lower index), so
F_ji = -F_ij to the last bit without atomics and the GPU repeats the CPU's arithmetic exactly.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
from numba import cuda

from engine.physics.contact import contact_elastic_energy, min_image
from engine.physics.ellipsoid import PAIR_DONE, PAIR_NEEDS_PREV
from engine.physics.integrate import kick
from engine.physics.rotation import body_omega
from engine.shapes.spheroid.law import (S_DELTA, S_FD, S_KT, S_STATUS, S_XI_X, S_XI_Y, S_XI_Z, mid_step_omega,
                                        spheroid_gap, spheroid_pair, spheroid_rotation)

#: the compile-time flags of make_cuda, in order: rough contacts (tangential spring, 6 history words), Coulomb
#: limit (orientation is always tracked)
FLAGS = ("rough", "coulomb")
#: spheroid columns of spd, offsets from the backend's ND (working precision); C_FT: the rough law's factor
#: (arccos(-e_t)/pi)^2 (engine.shapes.spheroid.cpu_backend.tangential_factor_of); mu is the common D_MU
C_A, C_B, C_C, C_II1, C_II2, C_II3, C_TOL, C_BMIN, C_SCR, C_FT = range(10)
NCOL = 10
#: observe accumulators per scene: E_tr, E_rot, E_rot perpendicular to body x, contacts (x2), elastic
#: energy, P_x, P_y, P_z, largest overlap (m), then the Sonine moments sum e_tr^2, sum e_perp^2, sum e_tr e_perp
A_TR, A_ROT, A_PERP, A_CON, A_EL, A_PX, A_PY, A_PZ, A_OVL, A_TR2, A_ROT2, A_X = range(12)
NACC = 12


def make_cuda(L, DT, UNIFORM, TPB, ROUGH, COULOMB):  # noqa: C901  (one closure per specialisation)
    """The spheroid's device functions and its own kernel (clamp_history) for one specialisation."""
    ZERO = DT(0)
    HALF = DT(0.5)
    SCREENED_GAP = DT(-np.inf)
    ONE = DT(1)
    BIG = DT(np.finfo(DT).max)
    f64 = np.float64
    D_BOX, D_INVBOX, D_DT, D_KN, D_GN, D_R0, D_M0, D_IM0 = L.D_BOX, L.D_INVBOX, L.D_DT, L.D_KN, L.D_GN, L.D_R0, \
        L.D_M0, L.D_IM0
    F_KN = L.F_KN
    D_MU = L.D_MU
    E_A, E_B, E_C, E_II1, E_II2, E_II3, E_TOL, E_BMIN, E_SCR, E_FT = (L.ND + c for c in range(NCOL))

    @cuda.jit(device=True)
    def translated(k, i, x_old, v, f, im, hp, ext):
        """Keep the position before the step; predicted end-of-step velocity v + F/m dt/2."""
        ext[3][k, i] = x_old
        ext[1][k, i] = kick(v, f, im, hp)

    @cuda.jit(device=True)
    def rotate(i, s, spin, quat, torque, torqued, spin_inv, ext, spd, spi, hk, hp, dt, step):
        """The orientation before the step into quat_prev, then the gather from and scatter into this backend's
        layout of the spheroid's one rotation step (law.spheroid_rotation: L += tau hk, q by Fincham's leap-frog,
        the predicted space-frame w at t + dt into omega_p). True when L and q are finite. ``torqued`` False: the
        torque is zero (+0.0, as the force pass sums it) and is not read."""
        angm = spin
        omega_p = ext[2]
        quat_prev = ext[4]
        for k in range(4):
            quat_prev[k, i] = quat[k, i]
        if UNIFORM:
            ii1 = spd[s, E_II1]
            ii2 = spd[s, E_II2]
            ii3 = spd[s, E_II3]
        else:
            ii1 = spin_inv[0, i]
            ii2 = spin_inv[1, i]
            ii3 = spin_inv[2, i]
        tx = ty = tz = ZERO
        if torqued:
            tx = torque[0, i]
            ty = torque[1, i]
            tz = torque[2, i]
        lx, ly, lz, q0, q1, q2, q3, wx, wy, wz = spheroid_rotation(
            quat[0, i], quat[1, i], quat[2, i], quat[3, i], angm[0, i], angm[1, i], angm[2, i],
            tx, ty, tz, ii1, ii2, ii3, hk, hp, dt, HALF)
        angm[0, i] = lx
        angm[1, i] = ly
        angm[2, i] = lz
        quat[0, i] = q0
        quat[1, i] = q1
        quat[2, i] = q2
        quat[3, i] = q3
        omega_p[0, i] = wx
        omega_p[1, i] = wy
        omega_p[2, i] = wz
        l1 = abs(lx) + abs(ly) + abs(lz)
        return (l1 < BIG) and (abs(q0) <= ONE + HALF)

    @cuda.jit(device=True)
    def spin_kick(i, s, spin, torque, spin_inv, spd, hk):
        """L += tau dt/2 (unit factor: the torque is dL/dt)."""
        for k in range(3):
            spin[k, i] = kick(spin[k, i], torque[k, i], ONE, hk)

    @cuda.jit(device=True)
    def particle(i, s, pos, rad, inv_m, ids, spd):
        """The id of i (the lower id of a pair is "A") and the scene's constants, read once per particle."""
        return (ids[i], spd[s, D_BOX], spd[s, D_INVBOX], spd[s, D_DT], spd[s, D_KN], spd[s, D_GN], spd[s, E_TOL],
                spd[s, E_SCR], spd[s, D_R0], spd[s, D_IM0])

    if COULOMB:
        @cuda.jit(device=True)
        def friction_of(spd, s):
            """The scene's Coulomb coefficient (inf: no cap in a Coulomb-compiled ensemble)."""
            return spd[s, D_MU]
    else:
        @cuda.jit(device=True)
        def friction_of(spd, s):
            """No Coulomb limit compiled: None prunes the cap (engine.physics.contact.tangential_spring_step)."""
            return None

    @cuda.jit(device=True)
    def pair(i, q, j, s, p, acc, pos, vel, spin, quat, rad, inv_m, f_old, hist, ids, ext, spd):
        """A list slot of particle i (neighbour j, its history hist[:, q]), evaluated when the bounding spheres
        overlap or the pair was in contact at the previous step: the gather from and scatter into this backend's
        layout of the spheroid's one pair evaluator (law.spheroid_pair, with (A, B) = (lower id, higher id)); a
        contact starting after a screened step gets that step's gap from pos_prev/quat_prev (law.spheroid_gap);
        overlap, dashpot (and rough: spring) history advanced in place."""
        idi, box, inv_box, dt, k_n, gn_coef, tol, margin, r0, im0 = p
        fx, fy, fz, tx, ty, tz, worst = acc
        axes = ext[0]
        vel_p = ext[1]
        omega_p = ext[2]
        pos_prev = ext[3]
        quat_prev = ext[4]
        if idi < ids[j]:
            a = i
            b = j
        else:
            a = j
            b = i
        rx = min_image(pos[0, b] - pos[0, a], box, inv_box, HALF)
        ry = min_image(pos[1, b] - pos[1, a], box, inv_box, HALF)
        rz = min_image(pos[2, b] - pos[2, a], box, inv_box, HALF)
        rc = (r0 + r0) if UNIFORM else (rad[a] + rad[b])
        d2 = rx * rx + ry * ry + rz * rz
        if d2 >= rc * rc and hist[3, q] <= ZERO:
            hist[3, q] = rc - math.sqrt(d2)  # negative: no contact possible
            hist[4, q] = ZERO
            return acc
        if UNIFORM:
            m12 = ONE / (im0 + im0)
            aa = spd[s, E_A]
            ba = spd[s, E_B]
            ca = spd[s, E_C]
            ab = aa
            bb = ba
            cb = ca
        else:
            m12 = ONE / (inv_m[a] + inv_m[b])
            aa, ba, ca = axes[0, a], axes[1, a], axes[2, a]
            ab, bb, cb = axes[0, b], axes[1, b], axes[2, b]
        sa = (aa, ba, ca)
        sb = (ab, bb, cb)
        qa = (quat[0, a], quat[1, a], quat[2, a], quat[3, a])
        qb = (quat[0, b], quat[1, b], quat[2, b], quat[3, b])
        if ROUGH:
            if UNIFORM:
                ia = (spd[s, E_II1], spd[s, E_II2], spd[s, E_II3])
                ib = ia
            else:
                inv_i = ext[5]
                ia = (inv_i[0, a], inv_i[1, a], inv_i[2, a])
                ib = (inv_i[0, b], inv_i[1, b], inv_i[2, b])
            rough = ((vel[0, b] - vel[0, a], vel[1, b] - vel[1, a], vel[2, b] - vel[2, a]),
                     mid_step_omega((quat_prev[0, a], quat_prev[1, a], quat_prev[2, a], quat_prev[3, a]), qa,
                                    (spin[0, a], spin[1, a], spin[2, a]), ia, HALF),
                     mid_step_omega((quat_prev[0, b], quat_prev[1, b], quat_prev[2, b], quat_prev[3, b]), qb,
                                    (spin[0, b], spin[1, b], spin[2, b]), ib, HALF),
                     ia, ib, (hist[0, q], hist[1, q], hist[2, q], hist[5, q]), spd[s, E_FT],
                     friction_of(spd, s))
        else:
            rough = None
        d_prev = hist[3, q]
        for _ in range(2):
            g = spheroid_pair(rx, ry, rz, qa, qb, sa, sb,
                              (vel_p[0, b] - vel_p[0, a], vel_p[1, b] - vel_p[1, a], vel_p[2, b] - vel_p[2, a]),
                              (omega_p[0, a], omega_p[1, a], omega_p[2, a]),
                              (omega_p[0, b], omega_p[1, b], omega_p[2, b]),
                              d_prev, hist[4, q], m12, (k_n, gn_coef, tol, margin, SCREENED_GAP), rough, dt, HALF)
            status = g[S_STATUS]
            if status != PAIR_NEEDS_PREV:
                break
            # a contact starts after a screened step: the gap of that step, from its state
            d_prev = spheroid_gap(min_image(pos_prev[0, b] - pos_prev[0, a], box, inv_box, HALF),
                                  min_image(pos_prev[1, b] - pos_prev[1, a], box, inv_box, HALF),
                                  min_image(pos_prev[2, b] - pos_prev[2, a], box, inv_box, HALF),
                                  (quat_prev[0, a], quat_prev[1, a], quat_prev[2, a], quat_prev[3, a]),
                                  (quat_prev[0, b], quat_prev[1, b], quat_prev[2, b], quat_prev[3, b]), sa, sb, tol,
                                  HALF)
        if i == a:
            fx += g[0]
            fy += g[1]
            fz += g[2]
            tx += g[3]
            ty += g[4]
            tz += g[5]
        else:
            fx -= g[0]
            fy -= g[1]
            fz -= g[2]
            tx += g[6]
            ty += g[7]
            tz += g[8]
        delta = g[S_DELTA]
        hist[3, q] = delta
        hist[4, q] = g[S_FD]
        if ROUGH and status == PAIR_DONE:
            hist[0, q] = g[S_XI_X]
            hist[1, q] = g[S_XI_Y]
            hist[2, q] = g[S_XI_Z]
            hist[5, q] = g[S_KT]
        if delta > ZERO:
            bmin = spd[s, E_BMIN] if UNIFORM else min(min(ba, ca), min(bb, cb))
            ov = delta / bmin
            if ov > worst:
                worst = ov
        return fx, fy, fz, tx, ty, tz, worst

    @cuda.jit(device=True)
    def observe_one(i, s, vals, v0, v1, v2, pos, spin, quat, rad, mass, inertia, nbr, nn, hist, spd, spf, ext):
        """Particle i's share of the sums of engine.shapes.spheroid.kernels.observe (``inertia`` is 1/I here):
        E_tr = m v^2/2; E_rot = sum_k I_k w_b,k^2/2 with the body-frame w_b = I^-1 R^T L; E_rot,perp the part about the
        two axes perpendicular to body x (the 2 active dof of Rubio-Largo et al. 2015, Eq. 25b as corrected in
        docs/physics.md §2.7); contacts (each pair counted twice, previous overlap > 0); elastic energy k_n delta^2/2
        (half per list slot); momentum; largest delta; the Sonine moments sum e_tr^2, sum e_perp^2, sum e_tr e_perp."""
        angm = spin
        if UNIFORM:
            m = f64(spd[s, D_M0])
            ii1 = spd[s, E_II1]
            ii2 = spd[s, E_II2]
            ii3 = spd[s, E_II3]
        else:
            m = f64(mass[0, i])
            ii1 = inertia[0, i]
            ii2 = inertia[1, i]
            ii3 = inertia[2, i]
        vx = f64(v0)
        vy = f64(v1)
        vz = f64(v2)
        wb0, wb1, wb2 = body_omega(quat[0, i], quat[1, i], quat[2, i], quat[3, i], angm[0, i], angm[1, i],
                                   angm[2, i], ii1, ii2, ii3, HALF)
        w0 = f64(wb0)
        w1 = f64(wb1)
        w2 = f64(wb2)
        ep = 0.5 * (w1 * w1 / f64(ii2) + w2 * w2 / f64(ii3))
        vals[A_TR] += 0.5 * m * (vx * vx + vy * vy + vz * vz)
        vals[A_ROT] += 0.5 * w0 * w0 / f64(ii1) + ep
        if ROUGH and spd[s, E_FT] > ZERO:
            ep = 0.5 * w0 * w0 / f64(ii1) + ep      # rough contacts exchange energy with all three dof
        vals[A_PERP] += ep
        vals[A_PX] += m * vx
        vals[A_PY] += m * vy
        vals[A_PZ] += m * vz
        et_i = 0.5 * m * (vx * vx + vy * vy + vz * vz)
        vals[A_TR2] += et_i * et_i
        vals[A_ROT2] += ep * ep
        vals[A_X] += et_i * ep
        for q in range(nn[i], nn[i + 1]):
            d = f64(hist[3, q])
            if d > 0.0:
                vals[A_CON] += 1.0
                if ROUGH:
                    vals[A_EL] += 0.5 * contact_elastic_energy(d, f64(hist[0, q]), f64(hist[1, q]),
                                                               f64(hist[2, q]), spf[s, F_KN],
                                                               f64(hist[5, q]), 0.5)
                else:
                    vals[A_EL] += 0.5 * contact_elastic_energy(d, 0.0, 0.0, 0.0, spf[s, F_KN], 0.0, 0.5)
                vals[A_OVL] = max(vals[A_OVL], d)

    @cuda.jit
    def clamp_history(n, nn, hist):
        """A fresh list holds bounding-sphere overlaps in slot 3: no contact history at t = 0 (CPU _prime)."""
        for i in range(cuda.grid(1), n, cuda.gridsize(1)):
            for q in range(nn[i], nn[i + 1]):
                if hist[3, q] > ZERO:
                    hist[3, q] = ZERO

    # not FUSABLE: the pair evaluator reads the neighbours' orientations, which the rotation step rewrites
    return SimpleNamespace(PREDICTS=True, TORQUE=True, FUSABLE=False, MULTISTEP_FUSABLE=False, NOBS=NACC,
                           OBS_MAX=A_OVL, translated=translated, rotate=rotate, settle_one=None,
                           spin_kick=spin_kick, particle=particle, pair=pair,
                           observe_one=observe_one, kernels=dict(clamp_history=clamp_history))
