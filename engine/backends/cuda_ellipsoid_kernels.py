"""CUDA kernels of the GPU ellipsoid backend (paper 003): K scenes of frictionless spheroids, K = 1 for one run.

One physics source: every kernel calls the same ``@numba.njit`` functions as the CPU ellipsoid backend
(engine/backends/cpu_ellipsoid.py):

- :func:`engine.physics.ellipsoid.ellipsoid_pair_screened`: exact disjointness screens (plane normal to the
  centre line; Perram-Wertheim iterate with F > 1 + margin), Perram-Wertheim contact function
  (W_0 = sqrt(F_max), paper 003 §3.2 / PHYSICS-NOTES §4.3), contact point C and normal n (paper 003 Eq. 22),
  overlap delta along n (Eqs. 23-24), force F = k_n delta - gamma_n v_n with the contact start/end
  corrections, torques (C - c) x F about each centre; :func:`~engine.physics.ellipsoid.ellipsoid_contact` for
  the previous step's gap of a contact that starts right after a screened step;
- :func:`engine.physics.rotation.fincham_quat_step_body`, :func:`~engine.physics.rotation.space_omega`,
  :func:`~engine.physics.rotation.body_omega`: Euler's equations in the body frame with the principal
  moments of a spheroid through the space-frame angular momentum L (dL/dt = tau), Fincham's leap-frog for
  the quaternion (paper 003 Eqs. 13-21), renormalised every step;
- :func:`engine.physics.integrate.kick` / :func:`~engine.physics.integrate.drift_wrap` (velocity Verlet),
  :func:`engine.physics.contact.min_image`, :func:`~engine.physics.contact.contact_elastic_energy`.

This module owns only layout, loops and launches. The neighbour-list kernels (cells, scan, scatter, sort,
permute, compact history store, build) are the sphere module's (:mod:`engine.backends.cuda_kernels`): the
broad phase of an ellipsoid is its bounding sphere of radius a (largest semi-axis), which is exactly a
sphere list with radius = a, and the history rules of that module hold here too (a slot whose previous
overlap is <= 0 and whose bounding spheres are apart is rewritten by the force kernel before it is read).

Layout (device, particle index fastest) as in the sphere module, with ellipsoid state:
    pos, vel (3, N) m, m/s; angm (3, N) space-frame angular momentum L (kg m^2/s); quat (4, N) (w, x, y, z)
    body -> space; force, torque (3, N) N, N m (one buffer: the predicted end-of-step velocities
    vel_p = v + F/m dt/2 and angular velocities omega_p = R I^-1 R^T (L + tau dt/2) (3, N) are written by
    the kick-drift phase, as the CPU backend does, so the force phase reads no force of another particle);
    x_ref (3, N); pos_prev (3, N), quat_prev (4, N): positions and orientations before the current step
    (written by the kick-drift phase, read only when a contact starts right after a screened step; permuted
    with the other particle arrays at a rebuild); hist (5, M, N): slots 3 and 4 hold the previous overlap
    delta (m; negative: the gap; -inf: screened, i.e. proven apart without computing the gap) and the previous
    dashpot force (N), slots 0-2 unused (frictionless). Non-uniform scenes: bound (1, N) = a
    (the sphere list's ``radius``), axes (3, N) m, inv_m (1, N), inv_i (3, N) (principal 1/I about the body
    axes), mass (1, N).
Per-scene constants: the sphere tables spd/spf/spi (D_R0 = a, the bounding radius; D_M0, D_IM0 the mass
and 1/m) with ellipsoid columns appended to spd (semi-axes, principal 1/I, Perram-Wertheim
tolerance, smallest semi-axis for the overlap guard, margin of the exact screens).
Each pair is evaluated with the lower particle id as "A" in both partners' loops (CPU: the lower index),
so F_ji = -F_ij to the last bit without atomics and the GPU repeats the CPU's arithmetic exactly.
"""

from __future__ import annotations

import math

import numpy as np
from numba import cuda
from numba.cuda import types as ct

from engine.backends import cuda_kernels as SK
from engine.backends.cuda_cache import cache_kernels
from engine.backends.cuda_kernels import (D_BOX, D_DT, D_GN, D_HP, D_IM0, D_INVBOX, D_KN, D_M0, D_R0, F_KN,
                                          F_LIM2INV, F_OVL, I_ACTIVE, I_N, I_START, ND, NSS, S_D2, S_D2B, S_RUN_DONE,
                                          S_RUN_REBUILD, S_V2, SS0, SS_BAD_ID, SS_OVL, SS_OVL_ID, F_V2F)
from engine.physics.contact import contact_elastic_energy, min_image
from engine.physics.ellipsoid import PAIR_NEEDS_PREV, ellipsoid_contact, ellipsoid_pair_screened
from engine.physics.integrate import drift_wrap, kick
from engine.physics.rotation import body_omega, fincham_quat_step_body, space_omega

# ellipsoid columns of spd (after the sphere module's ND columns), working precision
E_A, E_B, E_C, E_II1, E_II2, E_II3, E_TOL, E_BMIN, E_SCR = range(ND, ND + 9)
NDE = ND + 9
#: observe accumulators per scene: E_tr, E_rot, E_rot perpendicular to body x, contacts (x2), elastic
#: energy, P_x, P_y, P_z, largest overlap (m)
A_TR, A_ROT, A_PERP, A_CON, A_EL, A_PX, A_PY, A_PZ, A_OVL = range(9)
# the Sonine moments sum e_tr^2, sum e_perp^2, sum e_tr e_perp (J^2; engine/physics/sonine.py)
A_TR2, A_ROT2, A_X = 9, 10, 11
NACC = 12

#: sphere-module kernels reused unchanged (the list of bounding spheres)
LIST_KERNELS = ("fill_i32", "count_cells", "tile_scan", "add_offsets", "scatter", "sort_cells", "gather_rows",
                "gather_i32", "inverse_perm", "compact", "build")

_cache: dict = {}


def kernels(dtype, uniform: bool, tpb: int) -> dict:
    """The ellipsoid kernel set (cached per precision, uniform particles, threads per block), merged with
    the sphere module's list kernels of the same precision and uniformity."""
    key = (np.dtype(dtype).str, uniform, tpb)
    if key not in _cache:
        lists = SK.kernels(dtype, False, False, False, uniform, tpb)
        k = {name: lists[name] for name in LIST_KERNELS}
        k.update(cache_kernels(_make(np.dtype(dtype).type, uniform, tpb), ("ellipsoids",) + key))
        _cache[key] = k
    return _cache[key]


def _make(DT, UNIFORM, TPB):  # noqa: C901  (one closure per specialisation)
    ZERO = DT(0)
    HALF = DT(0.5)
    SCREENED_GAP = DT(-np.inf)
    ONE = DT(1)
    BIG = DT(np.finfo(DT).max)
    f64 = np.float64
    SH2 = 2 * TPB

    block_max2, fail = SK.device_helpers(TPB)

    # ---- step phases (device functions shared by the one-step kernels and the multi-step kernel) --------

    @cuda.jit(device=True)
    def kick_drift_one(i, first, pos, vel, angm, quat, force, torque, inv_m, inv_i, x_ref, vel_p, omega_p,
                       pos_prev, quat_prev, ids, sc, spd, spf, spi, status, step):
        """One particle's kick + drift (cpu_ellipsoid.kick_drift_ell): v += F/m hk, L += tau hk (hk = dt/2
        on the first step of a call, else dt), x += v dt wrapped, q by Fincham's leap-frog with
        L(t) = L - tau dt/2 and L(t + dt/2) = L; predicted v and w at t + dt stored for the force phase.
        The positions and orientations before the step go to pos_prev, quat_prev (a contact that starts
        after a screened step needs the gap of that step). Returns the normalised squared displacement since
        the build and speed (0, 0 for a skipped scene)."""
        s = sc[i]
        if spi[s, I_ACTIVE] == 0:
            return 0.0, 0.0
        dt = spd[s, D_DT]
        hp = spd[s, D_HP]
        hk = hp if first else dt
        box = spd[s, D_BOX]
        inv_box = spd[s, D_INVBOX]
        im = spd[s, D_IM0] if UNIFORM else inv_m[i]
        v2 = ZERO
        dsp = ZERO
        for k in range(4):
            quat_prev[k, i] = quat[k, i]
        for k in range(3):
            pos_prev[k, i] = pos[k, i]
            v = kick(vel[k, i], force[k, i], im, hk)
            vel[k, i] = v
            vel_p[k, i] = kick(v, force[k, i], im, hp)
            x = drift_wrap(pos[k, i], v, dt, box, inv_box)
            pos[k, i] = x
            d = min_image(x - x_ref[k, i], box, inv_box, HALF)
            dsp += d * d
            v2 += v * v
        tx = torque[0, i]
        ty = torque[1, i]
        tz = torque[2, i]
        lx = angm[0, i] + tx * hk
        ly = angm[1, i] + ty * hk
        lz = angm[2, i] + tz * hk
        angm[0, i] = lx
        angm[1, i] = ly
        angm[2, i] = lz
        if UNIFORM:
            ii1 = spd[s, E_II1]
            ii2 = spd[s, E_II2]
            ii3 = spd[s, E_II3]
        else:
            ii1 = inv_i[0, i]
            ii2 = inv_i[1, i]
            ii3 = inv_i[2, i]
        q0, q1, q2, q3 = fincham_quat_step_body(quat[0, i], quat[1, i], quat[2, i], quat[3, i],
                                                lx - tx * hp, ly - ty * hp, lz - tz * hp, lx, ly, lz,
                                                ii1, ii2, ii3, dt, HALF)
        quat[0, i] = q0
        quat[1, i] = q1
        quat[2, i] = q2
        quat[3, i] = q3
        wx, wy, wz = space_omega(q0, q1, q2, q3, lx + tx * hp, ly + ty * hp, lz + tz * hp, ii1, ii2, ii3, HALF)
        omega_p[0, i] = wx
        omega_p[1, i] = wy
        omega_p[2, i] = wz
        l1 = abs(lx) + abs(ly) + abs(lz)
        if not (dsp < BIG) or not (v2 < BIG) or not (l1 < BIG) or not (abs(q0) <= ONE + HALF):
            fail(status, spi, s, SS_BAD_ID, ids[i], step)
            return 0.0, 0.0
        return f64(dsp) * spf[s, F_LIM2INV], f64(v2) * spf[s, F_V2F]

    @cuda.jit(device=True)
    def forces_one(i, pos, vel_p, omega_p, quat, axes, bound, inv_m, force, torque, nbr, nn, hist, pos_prev,
                   quat_prev, ids, sc, spd, spf, spi, status, step):
        """Contact forces and torque on particle i from its list (cpu_ellipsoid.compute_forces_ell): the
        Perram-Wertheim contact (behind the exact screens) only for pairs whose bounding spheres overlap or
        that were in contact at the previous step; a contact starting after a screened step gets that
        step's gap from pos_prev/quat_prev; overlap and dashpot history advanced in place; a scene whose
        overlap exceeds its limit (relative to the smaller semi-axis b) is stopped."""
        s = sc[i]
        if spi[s, I_ACTIVE] == 0:
            return
        box = spd[s, D_BOX]
        inv_box = spd[s, D_INVBOX]
        dt = spd[s, D_DT]
        k_n = spd[s, D_KN]
        gn_coef = spd[s, D_GN]
        tol = spd[s, E_TOL]
        margin = spd[s, E_SCR]
        r0 = spd[s, D_R0]
        im0 = spd[s, D_IM0]
        fx = ZERO
        fy = ZERO
        fz = ZERO
        tx = ZERO
        ty = ZERO
        tz = ZERO
        worst = ZERO
        idi = ids[i]
        for kk in range(nn[i]):
            j = nbr[kk, i]
            if idi < ids[j]:
                a = i
                b = j
            else:
                a = j
                b = i
            rx = min_image(pos[0, b] - pos[0, a], box, inv_box, HALF)
            ry = min_image(pos[1, b] - pos[1, a], box, inv_box, HALF)
            rz = min_image(pos[2, b] - pos[2, a], box, inv_box, HALF)
            rc = (r0 + r0) if UNIFORM else (bound[a] + bound[b])
            d2 = rx * rx + ry * ry + rz * rz
            if d2 >= rc * rc and hist[3, kk, i] <= ZERO:
                hist[3, kk, i] = rc - math.sqrt(d2)  # negative: no contact possible
                hist[4, kk, i] = ZERO
                continue
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
                aa = axes[0, a]
                ba = axes[1, a]
                ca = axes[2, a]
                ab = axes[0, b]
                bb = axes[1, b]
                cb = axes[2, b]
            d_prev = hist[3, kk, i]
            for _ in range(2):
                g = ellipsoid_pair_screened(
                    rx, ry, rz, quat[0, a], quat[1, a], quat[2, a], quat[3, a], aa, ba, ca,
                    quat[0, b], quat[1, b], quat[2, b], quat[3, b], ab, bb, cb,
                    vel_p[0, b] - vel_p[0, a], vel_p[1, b] - vel_p[1, a], vel_p[2, b] - vel_p[2, a],
                    omega_p[0, a], omega_p[1, a], omega_p[2, a],
                    omega_p[0, b], omega_p[1, b], omega_p[2, b],
                    d_prev, hist[4, kk, i], m12, k_n, gn_coef * math.sqrt(m12), dt, tol, margin, SCREENED_GAP,
                    HALF)
                if g[11] != PAIR_NEEDS_PREV:
                    break
                # a contact starts after a screened step: the gap of that step, from its state
                d_prev = ellipsoid_contact(
                    min_image(pos_prev[0, b] - pos_prev[0, a], box, inv_box, HALF),
                    min_image(pos_prev[1, b] - pos_prev[1, a], box, inv_box, HALF),
                    min_image(pos_prev[2, b] - pos_prev[2, a], box, inv_box, HALF),
                    quat_prev[0, a], quat_prev[1, a], quat_prev[2, a], quat_prev[3, a], aa, ba, ca,
                    quat_prev[0, b], quat_prev[1, b], quat_prev[2, b], quat_prev[3, b], ab, bb, cb, tol, HALF)[2]
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
            delta = g[9]
            hist[3, kk, i] = delta
            hist[4, kk, i] = g[10]
            if delta > ZERO:
                bmin = spd[s, E_BMIN] if UNIFORM else min(min(ba, ca), min(bb, cb))
                ov = delta / bmin
                if ov > worst:
                    worst = ov
        force[0, i] = fx
        force[1, i] = fy
        force[2, i] = fz
        torque[0, i] = tx
        torque[1, i] = ty
        torque[2, i] = tz
        w64 = f64(worst)
        if w64 > spf[s, F_OVL]:
            b0 = SS0 + NSS * s
            cuda.atomic.max(status, b0 + SS_OVL, w64)
            fail(status, spi, s, SS_OVL_ID, ids[i], step)

    # ---- one-step kernels (large scenes: launch overhead is negligible) ---------------------------------

    @cuda.jit
    def kick_drift(n, first, pos, vel, angm, quat, force, torque, inv_m, inv_i, x_ref, vel_p, omega_p, pos_prev,
                   quat_prev, ids, sc, spd, spf, spi, status, step):
        sh = cuda.shared.array(SH2, ct.float64)
        md = 0.0
        mv = 0.0
        for i in range(cuda.grid(1), n, cuda.gridsize(1)):
            d2, v2 = kick_drift_one(i, first, pos, vel, angm, quat, force, torque, inv_m, inv_i, x_ref, vel_p,
                                    omega_p, pos_prev, quat_prev, ids, sc, spd, spf, spi, status, step)
            md = max(md, d2)
            mv = max(mv, v2)
        block_max2(sh, md, mv)
        if cuda.threadIdx.x == 0:
            cuda.atomic.max(status, S_D2, sh[0])
            cuda.atomic.max(status, S_V2, sh[TPB])

    @cuda.jit
    def forces(n, pos, vel_p, omega_p, quat, axes, bound, inv_m, force, torque, nbr, nn, hist, pos_prev, quat_prev,
               ids, sc, spd, spf, spi, status, step):
        i0 = cuda.grid(1)
        if i0 == 0:  # reset the per-step maxima for the next kick_drift (stream-ordered after its copy)
            status[S_D2] = 0.0
            status[S_V2] = 0.0
        for i in range(i0, n, cuda.gridsize(1)):
            forces_one(i, pos, vel_p, omega_p, quat, axes, bound, inv_m, force, torque, nbr, nn, hist, pos_prev,
                       quat_prev, ids, sc, spd, spf, spi, status, step)

    @cuda.jit
    def half_kick(n, vel, angm, force, torque, inv_m, sc, spd, spi):
        """Closing half kick (velocities and L synchronous with positions), as cpu.half_kick with unit 1/I."""
        for i in range(cuda.grid(1), n, cuda.gridsize(1)):
            s = sc[i]
            if spi[s, I_ACTIVE] == 0:
                continue
            hk = spd[s, D_HP]
            im = spd[s, D_IM0] if UNIFORM else inv_m[i]
            for k in range(3):
                vel[k, i] = kick(vel[k, i], force[k, i], im, hk)
            for k in range(3):
                angm[k, i] = kick(angm[k, i], torque[k, i], ONE, hk)

    # ---- many steps per launch (small scenes and ensembles: launch overhead paid once per chunk) -------

    @cuda.jit
    def run_steps(n, nmax, first, pos, vel, angm, quat, force, torque, inv_m, inv_i, axes, bound, x_ref, vel_p,
                  omega_p, pos_prev, quat_prev, nbr, nn, hist, ids, sc, spd, spf, spi, status, step0):
        """Up to nmax whole steps in one cooperative launch, the phases separated by grid syncs.

        As the sphere module's run_steps: stops after the drift of a step and before its forces when a
        particle has moved more than L_v/2 since the list build (status[S_RUN_REBUILD] = 1,
        status[S_RUN_DONE] = whole steps completed; the host rebuilds, computes that step's forces and
        relaunches) -- exactly the CPU backend's rebuild rule, step for step.
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
            step = step0 + st
            if i0 == 0:
                status[S_D2B if even else S_D2] = 0.0  # the other parity's slot, free until next step
            md = 0.0
            for i in range(i0, n, stride):
                d2, v2 = kick_drift_one(i, first if st == 0 else 0, pos, vel, angm, quat, force, torque, inv_m,
                                        inv_i, x_ref, vel_p, omega_p, pos_prev, quat_prev, ids, sc, spd, spf, spi,
                                        status, step)
                md = max(md, d2)
            block_max2(sh, md, 0.0)
            if cuda.threadIdx.x == 0:
                cuda.atomic.max(status, slot, sh[0])
            g.sync()
            if status[slot] > 1.0:
                break
            for i in range(i0, n, stride):
                forces_one(i, pos, vel_p, omega_p, quat, axes, bound, inv_m, force, torque, nbr, nn, hist, pos_prev,
                           quat_prev, ids, sc, spd, spf, spi, status, step)
            done += 1
            g.sync()
        if i0 == 0:
            status[S_RUN_DONE] = f64(done)
            status[S_RUN_REBUILD] = 1.0 if done < nmax else 0.0

    # ---- observables ----------------------------------------------------------------------------------

    block_accumulate = SK.observe_reducer(TPB, NACC, A_OVL)
    SH_OBS = NACC * TPB

    @cuda.jit
    def observe(vel, angm, quat, mass, inv_i, nn, hist, spd, spf, spi, acc):
        """acc[s] += the sums of cpu_ellipsoid.observe_ell, in float64 per particle, one block row per scene
        (blockIdx.y = s) reduced per block (cuda_kernels.observe_reducer): E_tr = m v^2/2; E_rot = sum_k
        I_k w_b,k^2/2 with the body-frame w_b = I^-1 R^T L; E_rot,perp the part about the two axes
        perpendicular to body x (the 2 active dof of paper 003 Eq. 25b as corrected in PHYSICS-NOTES §3.3);
        contacts (each pair counted twice, previous overlap > 0); elastic energy k_n delta^2/2 (half per list
        slot); momentum; largest delta; the Sonine moments sum e_tr^2, sum e_perp^2, sum e_tr e_perp."""
        s = cuda.blockIdx.y
        sh = cuda.shared.array(SH_OBS, ct.float64)
        vals = cuda.local.array(NACC, ct.float64)
        for q in range(NACC):
            vals[q] = 0.0
        if spi[s, I_ACTIVE] != 0:
            a0 = spi[s, I_START]
            for li in range(cuda.blockIdx.x * TPB + cuda.threadIdx.x, spi[s, I_N], cuda.gridDim.x * TPB):
                i = a0 + li
                if UNIFORM:
                    m = f64(spd[s, D_M0])
                    ii1 = spd[s, E_II1]
                    ii2 = spd[s, E_II2]
                    ii3 = spd[s, E_II3]
                else:
                    m = f64(mass[0, i])
                    ii1 = inv_i[0, i]
                    ii2 = inv_i[1, i]
                    ii3 = inv_i[2, i]
                vx = f64(vel[0, i])
                vy = f64(vel[1, i])
                vz = f64(vel[2, i])
                wb0, wb1, wb2 = body_omega(quat[0, i], quat[1, i], quat[2, i], quat[3, i], angm[0, i], angm[1, i],
                                           angm[2, i], ii1, ii2, ii3, HALF)
                w0 = f64(wb0)
                w1 = f64(wb1)
                w2 = f64(wb2)
                ep = 0.5 * (w1 * w1 / f64(ii2) + w2 * w2 / f64(ii3))
                vals[A_TR] += 0.5 * m * (vx * vx + vy * vy + vz * vz)
                vals[A_ROT] += 0.5 * w0 * w0 / f64(ii1) + ep
                vals[A_PERP] += ep
                vals[A_PX] += m * vx
                vals[A_PY] += m * vy
                vals[A_PZ] += m * vz
                et_i = 0.5 * m * (vx * vx + vy * vy + vz * vz)
                vals[A_TR2] += et_i * et_i
                vals[A_ROT2] += ep * ep
                vals[A_X] += et_i * ep
                for kk in range(nn[i]):
                    d = f64(hist[3, kk, i])
                    if d > 0.0:
                        vals[A_CON] += 1.0
                        vals[A_EL] += 0.5 * contact_elastic_energy(d, 0.0, 0.0, 0.0, spf[s, F_KN], 0.0, 0.5)
                        vals[A_OVL] = max(vals[A_OVL], d)
        block_accumulate(sh, vals, acc, s)

    @cuda.jit
    def clamp_history(n, nn, hist):
        """A fresh list holds bounding-sphere overlaps in slot 3: no contact history at t = 0 (CPU _prime)."""
        for i in range(cuda.grid(1), n, cuda.gridsize(1)):
            for kk in range(min(nn[i], hist.shape[1])):
                if hist[3, kk, i] > ZERO:
                    hist[3, kk, i] = ZERO

    return dict(kick_drift=kick_drift, forces=forces, half_kick=half_kick, run_steps=run_steps, observe=observe,
                clamp_history=clamp_history)
