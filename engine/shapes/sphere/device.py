"""The sphere shape's CUDA parts (Hidalgo et al. 2013; Skorych & Dosta 2022): what a sphere adds to the one CUDA
time loop.

engine/loops/cuda_loop.py builds the GPU time loop (kick-drift, forces, closing half kick, the many-steps
cooperative kernel, observe) once for every shape; a shape package's ``device.py`` (this file for the sphere,
found by engine.shapes.device(name)) provides :func:`make_cuda`, which returns the device functions that specialise it
at compile time (closures over the precision, uniform particles and the shape's own flags, as
engine/shapes/sphere/kernels.py's njit functions specialise the CPU loop). The interface, for any shape:

- ``make_cuda(L, DT, UNIFORM, TPB, *flags)``: ``L`` is the layout module (engine/loops/cuda_kernels.py: the
  per-scene table columns D_*, F_*; passed in so that a shape module never imports a backend), ``DT`` the
  working precision, ``flags`` the shape's compile-time switches (``FLAGS`` names them; the host passes them
  in that order). Returns a SimpleNamespace with:
  - ``PREDICTS``: the translation hook ``translated`` needs the predicted-velocity half step hp = dt/2;
  - ``TORQUE``: the force phase writes the torque (False: no torque array is ever written);
  - ``FUSABLE``: the pair evaluator reads no state of another particle that the kick-drift rewrites but its
    position and velocity: the per-phase loop then runs a step's forces and the next kick-drift in one pass
    (cuda_loop ``forces_kick_drift``, positions and velocities double-buffered);
  - ``MULTISTEP_FUSABLE``: the same with the spin too (the pair evaluator reads no other particle's state
    the kick-drift rewrites but its position, velocity and ``spin``): the many-steps kernel then runs a step's
    forces and the next kick-drift in one pass, one grid sync a step (cuda_loop ``run_steps_fused``; positions,
    velocities and spins double-buffered);
  - ``OBSERVES_AFTER_FORCES`` (absent: ``FUSABLE``): the force pass leaves the rotational state alone and the
    shape has ``observe_after_forces``: a lone scene's records are summed in the force passes (cuda_loop
    ``forces_observe``);
  - ``NOBS``, ``OBS_MAX``: the observe sums per scene and the slot that is a maximum;
  - ``translated(k, i, x_old, v, f, im, hp, ext)``: after the shared kick of component k of particle i
    (v = the new velocity, f = the force, x_old = the position before the drift);
  - ``rotate(i, s, spin, quat, torque, torqued, spin_inv, ext, spd, spi, hk, hp, dt, step)``: the shape's rotation
    step after the shared translation (``step``: the index of the step; ``torqued`` False: the torque is zero and
    is not to be read); returns True when the rotational state is finite;
  - ``settle_one(i, s, spin, quat, ext, spd, spi, step)`` or None: what the loop does to particle i when an
    advance call ends at ``step``, before the closing half kick (spheres: the lazy orientations brought up to
    date); None: nothing, no kernel launched;
  - ``spin_kick(i, s, spin, torque, spin_inv, spd, hk)``: the closing half kick of the rotational state;
  - ``particle(i, s, pos, rad, inv_m, ids, spd)``: what the force loop of particle i reads once (a tuple);
  - ``pair(i, q, j, s, p, acc, pos, vel, spin, quat, rad, inv_m, f_old, hist, ids, ext, spd)``: the pair
    evaluator of a list slot (neighbour j, history ``hist[:, q]``: engine/loops/cuda_kernels.py, the list's
    layout): adds the force and torque on i to ``acc`` = (F_x, F_y, F_z, T_x, T_y, T_z, worst overlap relative to
    the pair's size) and returns it; advances the slot's history in place;
  - ``observe_one(i, s, vals, v0, v1, v2, pos, spin, quat, rad, mass, inertia, nbr, nn, hist, spd, spf, ext)``:
    particle i's share of the observe sums ``vals`` (float64), its velocity (v0, v1, v2) given (synchronous with
    the positions: the observe kernel reads it, the fused force pass of a record computes it);
  - ``observe_after_forces`` (``observe_one``'s arguments, then ``torque, spin_inv``; a shape with
    ``OBSERVES_AFTER_FORCES``, whose force pass leaves the spins alone): ``observe_one`` called by the force pass of
    a record right after particle i's forces at the same positions, its velocity half a step behind brought level
    (v0, v1, v2 given; the shape brings its spin level with the torque the pass just stored), so it may read what
    that pass stored (the sphere: each slot's overlap, instead of the neighbours' positions);
  - ``kernels``: the shape's own kernels (a dict, may be empty).

Spheres: ``spin`` = angular velocity (3, N), ``spin_inv`` = 1/I (N), ``rad`` = radius (N), ``ext`` = (last,
begun): int64 (N), the step from which each sphere's orientation turns are pending (lazy
orientations), and the contacts each sphere has begun (cumulative; each pair counts in both partners' lists, so
the collisions are sum / 2; the ``collisions`` observable, as on the CPU); the
force phase reads the previous step's forces ``f_old`` of both partners for the predicted end-of-step velocities
(the double buffer of engine/backends/cuda.py). Flags: rough (tangential spring and torque), Coulomb limit,
orientation tracked. The physics is engine/physics/contact.py (sphere_contact,
sphere_contact_end), engine/physics/integrate.py and engine/physics/rotation.py, as on the CPU.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
from numba import cuda

from engine.physics.contact import contact_elastic_energy, min_image, sphere_separation
from engine.physics.integrate import kick
from engine.physics.rotation import sphere_quat_turn
from engine.shapes.sphere.law import sphere_pair

#: the compile-time flags of make_cuda, in order
FLAGS = ("rough", "coulomb", "orient")
#: observe sums per scene: E_tr, E_rot, contacts x 2, elastic energy, P_x, P_y, P_z, max overlap (slot 7, a max),
#: then the Sonine moments sum e_tr^2, sum e_rot^2, sum e_tr e_rot (J^2; engine/physics/sonine.py), then the
#: contact starts (2 x the pair collisions so far)
NOBS = 12
O_MAX = 7
O_TR2, O_ROT2, O_X = 8, 9, 10
O_COLL = 11


def make_cuda(L, DT, UNIFORM, TPB, ROUGH, COULOMB, ORIENT):  # noqa: C901  (one closure per specialisation)
    """The sphere's device functions for one specialisation (module docstring)."""
    ZERO = DT(0)
    HALF = DT(0.5)
    BIG = DT(np.finfo(DT).max)
    f64 = np.float64
    D_BOX, D_INVBOX, D_DT, D_HP, D_KN, D_GN, D_KT, D_MU = L.D_BOX, L.D_INVBOX, L.D_DT, L.D_HP, L.D_KN, L.D_GN, \
        L.D_KT, L.D_MU
    D_R0, D_M0, D_I0, D_IM0, D_II0 = L.D_R0, L.D_M0, L.D_I0, L.D_IM0, L.D_II0
    I_ORIENT, I_ACTIVE, F_KN, F_KT = L.I_ORIENT, L.I_ACTIVE, L.F_KN, L.F_KT

    @cuda.jit(device=True)
    def translated(k, i, x_old, v, f, im, hp, ext):
        """Nothing beyond the shared translation (the force phase predicts from the previous forces)."""
        return

    @cuda.jit(device=True)
    def turn(i, omega, quat, last, step, dt):
        """Bring sphere i's orientation up to date at step ``step``: the steps since last[i] all turned with the
        spin it has now (sphere_quat_turn, exact), then none pending."""
        k = step - last[i]
        if k > 0:
            q0, q1, q2, q3 = sphere_quat_turn(quat[0, i], quat[1, i], quat[2, i], quat[3, i],
                                              omega[0, i], omega[1, i], omega[2, i], dt, k, HALF)
            quat[0, i] = q0
            quat[1, i] = q1
            quat[2, i] = q2
            quat[3, i] = q3
            last[i] = step

    @cuda.jit(device=True)
    def rotate(i, s, spin, quat, torque, torqued, spin_inv, ext, spd, spi, hk, hp, dt, step):
        """w += tau/I hk (rough); the orientation (when tracked) lazily, as on the CPU
        (engine/shapes/sphere/kernels.py ``rotate``): ext[0][i] is the step from which sphere i's turns are
        pending, all with the spin it has; only a torque about to change that spin brings q up to date (before
        the kick), and :func:`settle_one` when the loop returns. A free sphere reads and writes no quaternion, and
        no spin: a kick by a zero torque leaves w as it is (w + 0 is w, a -0.0 kept), finite since its last kick,
        so a sphere out of contact (most of a dilute gas) costs nothing, or the torque's read where the loop does not
        know it zero (``torqued``). The spin array is the one the kick acts on in place (the fused many-steps kernel
        copies it into its output half first)."""
        omega = spin
        w2 = ZERO
        if ROUGH:
            if not torqued:
                return True
            tx = torque[0, i]
            ty = torque[1, i]
            tz = torque[2, i]
            if tx == ZERO and ty == ZERO and tz == ZERO:
                return True
            ii = spd[s, D_II0] if UNIFORM else spin_inv[i]
            if ORIENT:
                if spi[s, I_ORIENT] != 0:
                    turn(i, omega, quat, ext[0], step, dt)
            wx = kick(omega[0, i], tx, ii, hk)
            wy = kick(omega[1, i], ty, ii, hk)
            wz = kick(omega[2, i], tz, ii, hk)
            omega[0, i] = wx
            omega[1, i] = wy
            omega[2, i] = wz
            w2 = wx * wx + wy * wy + wz * wz
        return w2 < BIG

    @cuda.jit(device=True)
    def settle_one(i, s, spin, quat, ext, spd, spi, step):
        """Sphere i's orientation brought up to date when the loop returns at ``step`` (before the closing half
        kick: the pending turns had the mid-step spin); a scene that does not track orientations, or no longer
        runs, only moves its mark."""
        if ORIENT:
            if spi[s, I_ACTIVE] != 0 and spi[s, I_ORIENT] != 0:
                turn(i, spin, quat, ext[0], step, spd[s, D_DT])
            ext[0][i] = step

    @cuda.jit(device=True)
    def spin_kick(i, s, spin, torque, spin_inv, spd, hk):
        if ROUGH:
            ii = spd[s, D_II0] if UNIFORM else spin_inv[i]
            for k in range(3):
                spin[k, i] = kick(spin[k, i], torque[k, i], ii, hk)

    @cuda.jit(device=True)
    def particle(i, s, pos, rad, inv_m, ids, spd):
        """What every list slot of sphere i needs, read once: its position and radius, the box. The contact
        constants and 1/m are read in :func:`pair` only for a slot in contact: few slots are, and values held
        across the whole list loop would cost registers, hence occupancy, in every slot."""
        return (pos[0, i], pos[1, i], pos[2, i], spd[s, D_R0] if UNIFORM else rad[i], spd[s, D_BOX],
                spd[s, D_INVBOX])

    # the contact constants of the compiled law: None prunes the tangential spring / the Coulomb cap
    if ROUGH and COULOMB:
        @cuda.jit(device=True)
        def law_constants(k_n, gn_coef, k_t, mu):
            return k_n, gn_coef, k_t, mu
    elif ROUGH:
        @cuda.jit(device=True)
        def law_constants(k_n, gn_coef, k_t, mu):
            return k_n, gn_coef, k_t, None
    else:
        @cuda.jit(device=True)
        def law_constants(k_n, gn_coef, k_t, mu):
            return k_n, gn_coef, None, None

    @cuda.jit(device=True)
    def pair(i, q, j, s, p, acc, pos, vel, spin, quat, rad, inv_m, f_old, hist, ids, ext, spd):
        """A list slot of sphere i (neighbour j, its history hist[:, q]): the gather from and scatter into this
        backend's layout of the sphere's one pair evaluator (law.sphere_pair), history advanced in place. The
        predicted end-of-step velocities u = v + F_old/m dt/2 of both partners (the CPU's vel_p) are read only
        while in contact."""
        xi, yi, zi, ri, box, inv_box = p
        fx, fy, fz, tx, ty, tz, wsi = acc
        omega = spin
        one = HALF + HALF
        rj = ri if UNIFORM else rad[j]
        rx, ry, rz, d, delta = sphere_separation(min_image(xi - pos[0, j], box, inv_box, HALF),
                                                 min_image(yi - pos[1, j], box, inv_box, HALF),
                                                 min_image(zi - pos[2, j], box, inv_box, HALF), ri + rj, HALF)
        delta_prev = hist[3, q]
        # the new overlap is stored once the slot's other reads are issued (here, and at the end for a contact):
        # stored straight after reading delta_prev, before this branch, it stalled every slot on the load (the
        # force kernel took 2.3 times as long on an H100: long-scoreboard stalls, same instructions and bytes)
        if not (delta > ZERO or delta_prev > ZERO):
            hist[3, q] = delta
            return fx, fy, fz, tx, ty, tz, wsi
        hp = spd[s, D_HP]
        dt = spd[s, D_DT]
        imi = spd[s, D_IM0] if UNIFORM else inv_m[i]
        imj = spd[s, D_IM0] if UNIFORM else inv_m[j]
        vix = vel[0, i]
        viy = vel[1, i]
        viz = vel[2, i]
        vjx = vel[0, j]
        vjy = vel[1, j]
        vjz = vel[2, j]
        ux = vix - vjx
        uy = viy - vjy
        uz = viz - vjz
        if delta > ZERO:
            ux = kick(vix, f_old[0, i], imi, hp) - kick(vjx, f_old[0, j], imj, hp)
            uy = kick(viy, f_old[1, i], imi, hp) - kick(vjy, f_old[1, j], imj, hp)
            uz = kick(viz, f_old[2, i], imi, hp) - kick(vjz, f_old[2, j], imj, hp)
        gx, gy, gz, gtx, gty, gtz, xix, xiy, xiz, fd, began = sphere_pair(
            rx, ry, rz, d, delta, delta_prev, vix - vjx, viy - vjy, viz - vjz, ux, uy, uz,
            omega[0, i] if ROUGH else ZERO, omega[1, i] if ROUGH else ZERO, omega[2, i] if ROUGH else ZERO,
            omega[0, j] if ROUGH else ZERO, omega[1, j] if ROUGH else ZERO, omega[2, j] if ROUGH else ZERO, ri, rj,
            hist[0, q], hist[1, q], hist[2, q], hist[4, q], one / (imi + imj),
            law_constants(spd[s, D_KN], spd[s, D_GN], spd[s, D_KT], spd[s, D_MU]), dt, HALF)
        if began:
            ext[1][i] += 1      # one collision (counted in both partners' lists)
        fx += gx
        fy += gy
        fz += gz
        if ROUGH:
            tx += gtx
            ty += gty
            tz += gtz
            hist[0, q] = xix
            hist[1, q] = xiy
            hist[2, q] = xiz
        if delta > ZERO:
            hist[4, q] = fd
            ov = delta / min(ri, rj)
            if ov > wsi:
                wsi = ov
        hist[3, q] = delta
        return fx, fy, fz, tx, ty, tz, wsi

    @cuda.jit(device=True)
    def observe_own(i, s, vals, v0, v1, v2, w0, w1, w2, mass, inertia, spd, ext):
        """Sphere i's own share of the observe sums: contacts begun, E_tr, E_rot, momentum and the Sonine moments
        (engine.shapes.sphere.kernels.observe), from its velocity (v0, v1, v2) and angular velocity (w0, w1, w2)."""
        vals[O_COLL] += f64(ext[1][i])
        m = f64(spd[s, D_M0]) if UNIFORM else f64(mass[i])
        ii = f64(spd[s, D_I0]) if UNIFORM else f64(inertia[i])
        vx = f64(v0)
        vy = f64(v1)
        vz = f64(v2)
        wx = f64(w0)
        wy = f64(w1)
        wz = f64(w2)
        et_i = 0.5 * m * (vx * vx + vy * vy + vz * vz)
        er_i = 0.5 * ii * (wx * wx + wy * wy + wz * wz)
        vals[0] += et_i
        vals[1] += er_i
        vals[4] += m * vx
        vals[5] += m * vy
        vals[6] += m * vz
        vals[O_TR2] += et_i * et_i
        vals[O_ROT2] += er_i * er_i
        vals[O_X] += et_i * er_i

    @cuda.jit(device=True)
    def observe_contact(vals, delta, q, s, ri, rj, hist, spf):
        """A list slot (history hist[:, q]) in contact with overlap ``delta`` (m, float64): the contacts, the elastic
        energy (half of the pair's: each pair appears in both partners' lists) and the largest overlap relative
        to the smaller radius."""
        vals[2] += 1.0
        vals[3] += 0.5 * contact_elastic_energy(delta, f64(hist[0, q]), f64(hist[1, q]), f64(hist[2, q]),
                                                spf[s, F_KN], spf[s, F_KT], 0.5)
        vals[O_MAX] = max(vals[O_MAX], delta / f64(min(ri, rj)))

    @cuda.jit(device=True)
    def observe_one(i, s, vals, v0, v1, v2, pos, spin, quat, rad, mass, inertia, nbr, nn, hist, spd, spf, ext):
        """E_tr, E_rot, contacts (x2), elastic energy, P, max overlap, Sonine moments, contact starts of
        particle i (engine.shapes.sphere.kernels.observe); the overlaps from the positions."""
        observe_own(i, s, vals, v0, v1, v2, spin[0, i], spin[1, i], spin[2, i], mass, inertia, spd, ext)
        box = spd[s, D_BOX]
        inv_box = spd[s, D_INVBOX]
        r0 = spd[s, D_R0]
        ri = r0 if UNIFORM else rad[i]
        for q in range(nn[i], nn[i + 1]):
            j = nbr[q]
            rx = min_image(pos[0, i] - pos[0, j], box, inv_box, HALF)
            ry = min_image(pos[1, i] - pos[1, j], box, inv_box, HALF)
            rz = min_image(pos[2, i] - pos[2, j], box, inv_box, HALF)
            rj = r0 if UNIFORM else rad[j]
            rs = ri + rj
            d2 = rx * rx + ry * ry + rz * rz
            if d2 < rs * rs:
                observe_contact(vals, f64(rs - math.sqrt(d2)), q, s, ri, rj, hist, spf)

    @cuda.jit(device=True)
    def observe_after_forces(i, s, vals, v0, v1, v2, pos, spin, quat, rad, mass, inertia, nbr, nn, hist, spd, spf,
                             ext, torque, spin_inv):
        """:func:`observe_one` right after the force pass of the same positions has run for sphere i: the
        overlaps are the ones its pair evaluators just stored (hist[3], the overlap each slot's force used), so no
        neighbour position is read again; a rough sphere's spin, half a step behind, brought level in registers,
        w + tau/I dt/2 (the closing half kick's expression, :func:`spin_kick`), from the torque the pass stored."""
        w0 = spin[0, i]
        w1 = spin[1, i]
        w2 = spin[2, i]
        if ROUGH:
            ii = spd[s, D_II0] if UNIFORM else spin_inv[i]
            hk = spd[s, D_HP]
            w0 = kick(w0, torque[0, i], ii, hk)
            w1 = kick(w1, torque[1, i], ii, hk)
            w2 = kick(w2, torque[2, i], ii, hk)
        observe_own(i, s, vals, v0, v1, v2, w0, w1, w2, mass, inertia, spd, ext)
        r0 = spd[s, D_R0]
        ri = r0 if UNIFORM else rad[i]
        for q in range(nn[i], nn[i + 1]):
            delta = hist[3, q]
            if delta > ZERO:
                observe_contact(vals, f64(delta), q, s, ri, r0 if UNIFORM else rad[nbr[q]], hist, spf)

    # FUSABLE for smooth spheres: a rough pair reads the neighbours' spins, which the kick-drift rewrites (with
    # the spins double-buffered too, the fused rough kernel was no faster than the two on an H100: it needs more
    # registers than one block of 256 threads per SM leaves)
    # MULTISTEP_FUSABLE for every sphere: the pair reads the neighbours' positions, velocities and spins only, all
    # three double-buffered by the fused many-steps kernel (small scenes: there a step is bound by its grid syncs)
    # OBSERVES_AFTER_FORCES for every sphere: the force pass (fused or not) leaves the spins alone
    return SimpleNamespace(PREDICTS=False, TORQUE=ROUGH, FUSABLE=not ROUGH, MULTISTEP_FUSABLE=True,
                           OBSERVES_AFTER_FORCES=True, NOBS=NOBS,
                           OBS_MAX=O_MAX, translated=translated, rotate=rotate,
                           settle_one=settle_one if ORIENT else None, spin_kick=spin_kick, particle=particle,
                           pair=pair, observe_one=observe_one, observe_after_forces=observe_after_forces, kernels={})
