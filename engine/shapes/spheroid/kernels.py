"""The spheroid shape plug-in (prolate ellipsoids, Rubio-Largo et al. 2015; frictionless or rough): what an ellipsoid
adds to the shared CPU time loop (engine/loops/cpu.py ``make_run_steps``, ``make_forces``; the interface is in
engine/shapes/sphere/kernels.py). The contact law and the rotation step are law.py's (``spheroid_pair``,
``spheroid_gap``, ``spheroid_rotation``, the functions the CUDA loop's device.py calls too); this module gathers
their inputs from the CPU backend's rows and scatters their results into them.

- Broad phase: the list radius ``rad`` is the bounding-sphere radius (largest semi-axis); the force loop runs the
  Perram-Wertheim contact (engine/physics/ellipsoid.py) only for pairs whose bounding spheres overlap, behind
  two exact screens for pairs not in contact at the previous step (ellipsoid_pair_screened). A screened pair
  stores -inf as its gap; when a contact starts right after a screened step the gap of that step is evaluated
  from the state before the step (pos_prev, quat_prev), so every result is the one without the screens, bit
  for bit (tests/engine/test_ellipsoid_screen.py).
- Each pair is evaluated with the lower id as "A" in both partners' loops, so F_ji = -F_ij to the last bit
  without atomics.
- Rotation: ``spin`` is the space-frame angular momentum L (kicked by the torque: ``spin_inv`` = 1), the
  quaternions advance by Fincham's leap-frog with the body-frame angular velocity I^-1 R^T L
  (engine/physics/rotation.py: fincham_quat_step_body), renormalised every step; predicted end-of-step
  velocities and angular velocities feed the dashpot.
- ``EXACT_DISPLACEMENT = True``: ``step`` measures every particle's displacement since the last build.
- ``law = (tol, margin, screened_gap, f_t, mu)``: Perram-Wertheim Newton tolerance, screen margin, stored gap of
  a screened pair, the rough law's factor (None: frictionless) and Coulomb coefficient (None: no cap);
  ``ext = (inv_i, axes, omega_p, pos_prev, quat_prev)``: inverse principal moments (N, 3), semi-axes (N, 3),
  predicted space-frame angular velocities, positions and orientations before the step.
- List slots 3 and 4 hold the overlap (-inf: screened) and the dashpot force of the previous step; rough
  contacts (6 words) the spring in 0-2 (m) and the contact's k_t in 5 (N/m); frictionless: 0-2 unused.
"""

from __future__ import annotations

import math

import numba

from engine.numba_support.jitcache import fast_loads  # before any cache=True kernel: keys the disk cache by source

from engine.physics.contact import contact_elastic_energy, min_image
from engine.physics.ellipsoid import PAIR_DONE, PAIR_NEEDS_PREV
from engine.physics.rotation import body_omega
from engine.shapes.spheroid.law import (S_DELTA, S_FD, S_KT, S_STATUS, S_XI_X, S_XI_Y, S_XI_Z, mid_step_omega,
                                        spheroid_gap, spheroid_pair, spheroid_rotation)

NAME = "ellipsoid"
EXACT_DISPLACEMENT = True


@numba.njit(inline="always")
def pre_step(i, pos, quat, ext):
    """Keep position and orientation before the step (ext[3], ext[4]) for a contact that starts after a screened
    step (engine.physics.ellipsoid.ellipsoid_pair_screened)."""
    pos_prev = ext[3]
    quat_prev = ext[4]
    for k in range(4):
        quat_prev[i, k] = quat[i, k]
    for k in range(3):
        pos_prev[i, k] = pos[i, k]


@numba.njit(inline="always")
def rotate(i, v2, pos, vel, spin, quat, torque, tq, spin_inv, x_ref, ext, hk, hp, dt, box, inv_box, half, s):
    """The ellipsoid's half of the kick-drift of particle i after the shared translation: the gather from and
    scatter into this backend's rows of the spheroid's one rotation step (law.spheroid_rotation: L += tau hk, q by
    Fincham's leap-frog, the predicted space-frame angular velocity at t + dt into ext[2]); ``tq`` the torque on i
    (tau_x, tau_y, tau_z) (N m). Returns (squared displacement since the last list build (m^2), finite)."""
    angm = spin
    inv_i = ext[0]
    omega_p = ext[2]
    lx, ly, lz, q0, q1, q2, q3, wx, wy, wz = spheroid_rotation(
        quat[i, 0], quat[i, 1], quat[i, 2], quat[i, 3], angm[i, 0], angm[i, 1], angm[i, 2],
        tq[0], tq[1], tq[2], inv_i[i, 0], inv_i[i, 1], inv_i[i, 2], hk, hp, dt, half)
    angm[i, 0] = lx
    angm[i, 1] = ly
    angm[i, 2] = lz
    quat[i, 0] = q0
    quat[i, 1] = q1
    quat[i, 2] = q2
    quat[i, 3] = q3
    omega_p[i, 0] = wx
    omega_p[i, 1] = wy
    omega_p[i, 2] = wz
    dx = min_image(pos[i, 0] - x_ref[i, 0], box, inv_box, half)
    dy = min_image(pos[i, 1] - x_ref[i, 1], box, inv_box, half)
    dz = min_image(pos[i, 2] - x_ref[i, 2], box, inv_box, half)
    d2 = dx * dx + dy * dy + dz * dz
    ok = (d2 < 1e300) and (abs(vel[i, 0]) + abs(vel[i, 1]) + abs(vel[i, 2]) < 1e300) \
        and (abs(lx) + abs(ly) + abs(lz) < 1e300) and (abs(q0) <= 1.5)
    return d2, ok


@numba.njit
def settle(spin, quat, torque, ext, drifted, dt, half, every):
    """Nothing pending when the loop returns: a spheroid's orientation is advanced at every step (its w changes
    between contacts)."""
    return


@numba.njit  # not inlined: its f_t None branch is pruned by the argument's type
def rough_inputs(f_t, mu, a, b, i, kk, vel, quat, quat_prev, angm, inv_i, hist, half):
    """The tangential inputs of law.spheroid_pair for the ordered pair (a, b) from this backend's rows: None for
    frictionless contacts (f_t None, pruned at compile time), else (v_b - v_a at mid-step, the mid-step spins of a
    and b (law.mid_step_omega), 1/I of a and b, the slot's spring and k_t (history words 0-2 and 5), f_t, mu)."""
    if f_t is None:
        return None
    ia = (inv_i[a, 0], inv_i[a, 1], inv_i[a, 2])
    ib = (inv_i[b, 0], inv_i[b, 1], inv_i[b, 2])
    return ((vel[b, 0] - vel[a, 0], vel[b, 1] - vel[a, 1], vel[b, 2] - vel[a, 2]),
            mid_step_omega((quat_prev[a, 0], quat_prev[a, 1], quat_prev[a, 2], quat_prev[a, 3]),
                           (quat[a, 0], quat[a, 1], quat[a, 2], quat[a, 3]), (angm[a, 0], angm[a, 1], angm[a, 2]),
                           ia, half),
            mid_step_omega((quat_prev[b, 0], quat_prev[b, 1], quat_prev[b, 2], quat_prev[b, 3]),
                           (quat[b, 0], quat[b, 1], quat[b, 2], quat[b, 3]), (angm[b, 0], angm[b, 1], angm[b, 2]),
                           ib, half),
            ia, ib, (hist[i, kk, 0], hist[i, kk, 1], hist[i, kk, 2], hist[i, kk, 5]), f_t, mu)


@numba.njit(inline="always")
def pair(i, kk, j, pos, vel, vel_p, spin, quat, rad, inv_m, hist, box, inv_box, half, k_n, gn_coef, law, dt,
         ext):
    """Force (3, N) and torque (3, N m) on i from list slot kk (neighbour j), overlap/dashpot (and rough: spring)
    history updated, and the overlap (m) relative to the smallest semi-axis of the pair (0 when not in contact),
    for the shared force loop: the gather from and scatter into this backend's rows of the spheroid's one pair
    evaluator (law.spheroid_pair), behind the bounding-sphere test.

    law = (tol, margin, screened_gap, f_t, mu): f_t None for frictionless contacts (Rubio-Largo et al. 2015), else
    (arccos(-e_t)/pi)^2 of the rough law; mu None: no Coulomb cap. ext = (inv_i, axes, omega_p, pos_prev,
    quat_prev). Both partners evaluate the pair as (a, b) = (lower id, higher id): their slots hold the same
    (a, b) spring, bit for bit. A contact that starts right after a screened step gets the previous gap
    evaluated from pos_prev/quat_prev (law.spheroid_gap).
    """
    inv_i = ext[0]
    axes = ext[1]
    omega_p = ext[2]
    pos_prev = ext[3]
    quat_prev = ext[4]
    tol = law[0]
    a = i if i < j else j
    b = j if i < j else i
    rx = min_image(pos[b, 0] - pos[a, 0], box, inv_box, half)
    ry = min_image(pos[b, 1] - pos[a, 1], box, inv_box, half)
    rz = min_image(pos[b, 2] - pos[a, 2], box, inv_box, half)
    rc = rad[a] + rad[b]
    d2 = rx * rx + ry * ry + rz * rz
    if d2 >= rc * rc and hist[i, kk, 3] <= 0:
        hist[i, kk, 3] = rc - math.sqrt(d2)     # negative: no contact possible
        hist[i, kk, 4] = 0
        return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    m12 = 1 / (inv_m[a] + inv_m[b])
    qa = (quat[a, 0], quat[a, 1], quat[a, 2], quat[a, 3])
    qb = (quat[b, 0], quat[b, 1], quat[b, 2], quat[b, 3])
    sa = (axes[a, 0], axes[a, 1], axes[a, 2])
    sb = (axes[b, 0], axes[b, 1], axes[b, 2])
    rough = rough_inputs(law[3], law[4], a, b, i, kk, vel, quat, quat_prev, spin, inv_i, hist, half)
    d_prev = hist[i, kk, 3]
    for _ in range(2):
        g = spheroid_pair(rx, ry, rz, qa, qb, sa, sb,
                          (vel_p[b, 0] - vel_p[a, 0], vel_p[b, 1] - vel_p[a, 1], vel_p[b, 2] - vel_p[a, 2]),
                          (omega_p[a, 0], omega_p[a, 1], omega_p[a, 2]), (omega_p[b, 0], omega_p[b, 1], omega_p[b, 2]),
                          d_prev, hist[i, kk, 4], m12, (k_n, gn_coef, tol, law[1], law[2]), rough, dt, half)
        if g[S_STATUS] != PAIR_NEEDS_PREV:
            break
        # a contact starts after a screened step: the gap of that step, from its state
        d_prev = spheroid_gap(min_image(pos_prev[b, 0] - pos_prev[a, 0], box, inv_box, half),
                              min_image(pos_prev[b, 1] - pos_prev[a, 1], box, inv_box, half),
                              min_image(pos_prev[b, 2] - pos_prev[a, 2], box, inv_box, half),
                              (quat_prev[a, 0], quat_prev[a, 1], quat_prev[a, 2], quat_prev[a, 3]),
                              (quat_prev[b, 0], quat_prev[b, 1], quat_prev[b, 2], quat_prev[b, 3]), sa, sb, tol, half)
    delta = g[S_DELTA]
    hist[i, kk, 3] = delta
    hist[i, kk, 4] = g[S_FD]
    if law[3] is not None and g[S_STATUS] == PAIR_DONE:
        hist[i, kk, 0] = g[S_XI_X]
        hist[i, kk, 1] = g[S_XI_Y]
        hist[i, kk, 2] = g[S_XI_Z]
        hist[i, kk, 5] = g[S_KT]
    ov = 0.0
    if delta > 0:
        ov = delta / min(min(sa[1], sa[2]), min(sb[1], sb[2]))
    if i == a:
        return g[0], g[1], g[2], g[3], g[4], g[5], ov
    return -g[0], -g[1], -g[2], g[6], g[7], g[8], ov


@numba.njit(cache=True)  # a plain loop over particles: the CPU backend calls it once per record
def observe(vel, angm, quat, mass, inv_i, nn, hist, half, k_n_val):
    """(E_tr, E_rot, E_rot of the active dof, contacts, elastic energy, max overlap (m), P_x, P_y, P_z, S_tr2,
    S_rot2, S_x): the last three are the Sonine moments sum e_tr,i^2, sum e_act,i^2 and sum e_tr,i e_act,i (J^2)
    with e_act,i the energy of the active rotational dof (engine/physics/sonine.py): smooth contacts (5 history
    words) the two axes perpendicular to body x (d = 2), rough ones (6 words) all three (d = 3)."""
    n = vel.shape[0]
    rough = hist.shape[2] > 5
    contacts = 0
    e_tr = e_rot = e_perp = e_spring = worst = 0.0       # energies (J), largest overlap (m)
    px = py = pz = 0.0                                    # momentum (kg m/s)
    s_tr2 = s_rot2 = s_x = 0.0                            # energy moments (J^2)
    for i in range(n):
        m = mass[i]
        e_tr += 0.5 * m * (vel[i, 0] ** 2 + vel[i, 1] ** 2 + vel[i, 2] ** 2)
        et_i = 0.5 * m * (vel[i, 0] ** 2 + vel[i, 1] ** 2 + vel[i, 2] ** 2)
        px += m * vel[i, 0]
        py += m * vel[i, 1]
        pz += m * vel[i, 2]
        wb = body_omega(quat[i, 0], quat[i, 1], quat[i, 2], quat[i, 3], angm[i, 0], angm[i, 1], angm[i, 2],
                        inv_i[i, 0], inv_i[i, 1], inv_i[i, 2], half)
        e1 = 0.5 * wb[0] * wb[0] / inv_i[i, 0]
        ep = 0.5 * (wb[1] * wb[1] / inv_i[i, 1] + wb[2] * wb[2] / inv_i[i, 2])
        e_rot += e1 + ep
        if rough:
            ep = e1 + ep          # rough contacts exchange energy with all three rotational dof
        e_perp += ep
        s_tr2 += et_i * et_i
        s_rot2 += ep * ep
        s_x += et_i * ep
        for kk in range(nn[i]):
            d = hist[i, kk, 3]
            if d > 0:
                contacts += 1
                # each pair appears in both partners' lists; rough: the spring with the contact's own k_t
                if rough:
                    e_spring += 0.5 * contact_elastic_energy(d, hist[i, kk, 0], hist[i, kk, 1], hist[i, kk, 2],
                                                             k_n_val, hist[i, kk, 5], 0.5)
                else:
                    e_spring += 0.5 * contact_elastic_energy(d, 0.0, 0.0, 0.0, k_n_val, 0.0, 0.5)
                worst = max(worst, d)
    return e_tr, e_rot, e_perp, contacts // 2, e_spring, worst, px, py, pz, s_tr2, s_rot2, s_x


fast_loads(globals())  # their disk-cache loads skip numba's target refresh (engine/numba_support/jitcache.py)
