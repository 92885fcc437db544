"""The sphere shape plug-in (Hidalgo et al. 2013; Skorych & Dosta 2022): what a sphere adds to the shared CPU time loop.

A shape package's ``kernels.py`` (engine/shapes/README.md) provides, for engine/loops/cpu.py's one time loop
(``make_run_steps``, built from the shared kick-drift ``make_step`` and force loop ``make_forces``), plain
``@numba.njit`` functions of one particle or one list slot:

- ``NAME``: the shape's name in the spec (``SimulationSpec.shape``);
- ``EXACT_DISPLACEMENT``: False = ``rotate`` returns |v|^2 (m^2/s^2) and the loop bounds the displacement since
  the last list build by sum max|v| dt (the exact displacement is read only when the bound passes L_v/2);
  True = ``rotate`` returns the exact squared displacement since the last build (m^2);
- ``FREE_DRIFT``: True = a particle under no force and no torque only drifts (its velocity, spin and orientation
  turns stay as they are: spheres); the loop then moves a particle whose list is empty by x += v dt alone
  (engine/loops/cpu.py ``make_step``); False (or absent) = such a particle takes the full kick-drift with zeros;
- ``pre_step(i, pos, quat, ext)``: anything to keep from before particle i's step;
- ``rotate(i, v2, pos, vel, spin, quat, torque, tq, spin_inv, x_ref, ext, hk, hp, dt, box, inv_box, half, s)``:
  the shape's rotation step of particle i after the shared translation (kick hk, predicted velocity at hp = dt/2,
  drift dt) in step s of the loop's call (0, 1, ...), with the torque on i ``tq`` = (tau_x, tau_y, tau_z) (the
  loop's own zeros for a particle whose list is empty; ``torque`` is the torque array, or None when torques are
  off, read only as that switch); returns (displacement measure, state finite);
- ``settle(spin, quat, torque, ext, drifted, dt, half, every)``: called by the loop before it returns, ``drifted``
  kick-drifts after the last full settle: with ``every`` True whatever the shape's ``rotate`` left pending is
  brought up to date and nothing stays pending (the step count restarts from 0); with ``every`` False only what the
  loop's closing half kick (torque x hk) is about to make wrong (spheres: lazy orientations; a shape that advances
  every step: nothing);
- ``pair(i, kk, j, pos, vel, vel_p, spin, quat, rad, inv_m, hist, box, inv_box, half, k_n, gn_coef, law, dt,
  ext)``: the pair evaluator (contact geometry and force law) of list slot kk of particle i (neighbour j):
  returns (F_x, F_y, F_z, T_x, T_y, T_z, overlap relative to the pair's size or 0) on i and advances the slot's
  history ``hist[i, kk, :]`` (cpu_shared.SLOT) in place. engine/loops/cpu.py ``make_forces`` sums it over the
  full Verlet list.

``spin`` is what the closing half kick advances with ``torque * spin_inv`` (spheres: the angular velocity and
1/I), ``rad`` the list radius, ``law`` the shape's contact constants beyond k_n and gamma_n, ``ext`` its own
extra arrays. For spheres: ``law = (k_t, mu)`` (None = smooth / no Coulomb limit: pruned at compile time,
as are ``torque = None`` and ``quat = None``), ``ext = (marks, begun)``: ``marks`` the step of the loop's call from
which each sphere's orientation turns are pending (int64, N; zero whenever the loop has returned), ``begun`` the
contacts each sphere has begun (int64, N, cumulative; each pair counts once in each partner's list: the pair
collisions are sum(begun) / 2, the ``collisions`` observable). The physics is in
engine/physics/contact.py (sphere_contact, sphere_contact_end), engine/physics/integrate.py and
engine/physics/rotation.py.
Array layout: (N, 3) / (N, 4) rows per particle, the CPU backend's.
"""

from __future__ import annotations

import math

import numba
from numba import prange

from engine.numba_support.jitcache import fast_loads  # before any cache=True kernel: keys the disk cache by source

from engine.physics.contact import contact_elastic_energy, min_image, sphere_separation
from engine.physics.integrate import kick
from engine.physics.rotation import sphere_quat_turn
from engine.shapes.sphere.law import sphere_pair

NAME = "sphere"
EXACT_DISPLACEMENT = False
FREE_DRIFT = True


@numba.njit(inline="always")
def pre_step(i, pos, quat, ext):
    """Nothing to keep from before the step (spheres)."""
    return


@numba.njit(inline="always")
def rotate(i, v2, pos, vel, spin, quat, torque, tq, spin_inv, x_ref, ext, hk, hp, dt, box, inv_box, half, s):
    """The sphere's half of the kick-drift of particle i in step s of the call, after the shared translation (v +=
    F/m hk, predicted v + F/m dt/2 for the dashpot, x += v dt wrapped; v2 = |v|^2): w += tau/I hk (rough), and the
    orientation (when tracked) lazily, as the GPU does (engine/shapes/sphere/device.py): ``ext[0][i]`` is the step
    of the call from which sphere i's turns are pending, all with the spin it has now. Only a torque about to
    change that spin brings q up to date, here before the kick (the exact rotation over those steps,
    engine.physics.rotation.sphere_quat_turn); :func:`settle` does it when the loop returns (for the spheres
    under a torque, or for every sphere before the host reads them). A
    free sphere does no orientation work at all. ``tq``: the torque on i, (tau_x, tau_y, tau_z) (N m); ``torque``
    None (smooth spheres): no torques, no spin update (pruned at compile time). Returns (|v|^2, finite).

    The predicted end-of-step velocity: with the mid-step velocity instead, the damping force lags by dt/2,
    which acts like a stiffness change of gamma dt/(2 m12) and shifts e_n at first order in dt (by 4.5e-3 at
    e_n = 0.3, dt = t_c/50); the predictor makes that error second order. The tangential spring integrates
    the mid-step velocity (midpoint rule, like the positions).
    """
    omega = spin
    w2 = 0.0
    if torque is not None:
        tx = tq[0]
        ty = tq[1]
        tz = tq[2]
        if quat is not None:
            if tx != 0 or ty != 0 or tz != 0:    # the kick will change w: turn q with the w it had first
                _catch_up(i, omega, quat, ext, s, dt, half)
        ii = spin_inv[i]
        wx = kick(omega[i, 0], tx, ii, hk)
        wy = kick(omega[i, 1], ty, ii, hk)
        wz = kick(omega[i, 2], tz, ii, hk)
        omega[i, 0] = wx
        omega[i, 1] = wy
        omega[i, 2] = wz
        w2 = wx * wx + wy * wy + wz * wz
    return v2, (v2 < 1e300) and (w2 < 1e300)


@numba.njit
def _catch_up(i, omega, quat, ext, s, dt, half):
    """Bring sphere i's orientation up to step s (counted from the last full settle): the s - ext[0][i] steps
    pending, turned with its present spin; then none pending."""
    k = s - ext[0][i]
    if k > 0:
        q0, q1, q2, q3 = sphere_quat_turn(quat[i, 0], quat[i, 1], quat[i, 2], quat[i, 3],
                                          omega[i, 0], omega[i, 1], omega[i, 2], dt, k, half)
        quat[i, 0] = q0
        quat[i, 1] = q1
        quat[i, 2] = q2
        quat[i, 3] = q3
        ext[0][i] = s


@numba.njit(parallel=True)
def settle(spin, quat, torque, ext, drifted, dt, half, every):
    """Sphere orientations brought up to date after ``drifted`` kick-drifts since the last full settle (the loop
    calls it before it returns). ``every``: every sphere, and the marks start again from 0; otherwise only the
    spheres under a torque, whose spin the closing half kick is about to change (the turns pending are those of
    the spin they have now); a free sphere's turns then stay pending, to be done in one piece later
    (engine/loops/cpu.py make_run_steps)."""
    if quat is not None:
        if every:
            for i in prange(quat.shape[0]):
                _catch_up(i, spin, quat, ext, drifted, dt, half)
                ext[0][i] = 0
        elif torque is not None:   # without torques (smooth spheres) no spin ever changes
            for i in prange(quat.shape[0]):
                if torque[i, 0] != 0 or torque[i, 1] != 0 or torque[i, 2] != 0:
                    _catch_up(i, spin, quat, ext, drifted, dt, half)


@numba.njit(inline="always")  # inlined into the force loop: a call would pass and refcount ~12 arrays
def pair(i, kk, j, pos, vel, vel_p, spin, quat, rad, inv_m, hist, box, inv_box, half, k_n, gn_coef, law, dt,
         ext):
    """Force (3, N) and torque (3, N m) on i from list slot kk (neighbour j), slot history advanced in place,
    and the overlap relative to the smaller radius (0 when not in contact), for the shared force loop: the
    gather from and scatter into this backend's rows of the sphere's one pair evaluator (law.sphere_pair).

    vel, spin: mid-step velocities and angular velocities (spring increment); vel_p: predicted end-of-step
    velocities (normal dashpot). law = (k_t, mu): None = smooth / no Coulomb limit.
    """
    k_t = law[0]
    omega = spin
    ri = rad[i]
    rj = rad[j]
    rx, ry, rz, d, delta = sphere_separation(min_image(pos[i, 0] - pos[j, 0], box, inv_box, half),
                                             min_image(pos[i, 1] - pos[j, 1], box, inv_box, half),
                                             min_image(pos[i, 2] - pos[j, 2], box, inv_box, half), ri + rj, half)
    delta_prev = hist[i, kk, 3]
    hist[i, kk, 3] = delta
    if not (delta > 0 or delta_prev > 0):
        return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    m12 = 1 / (inv_m[i] + inv_m[j])
    fx, fy, fz, tx, ty, tz, xix, xiy, xiz, fd, began = sphere_pair(
        rx, ry, rz, d, delta, delta_prev, vel[i, 0] - vel[j, 0], vel[i, 1] - vel[j, 1], vel[i, 2] - vel[j, 2],
        vel_p[i, 0] - vel_p[j, 0], vel_p[i, 1] - vel_p[j, 1], vel_p[i, 2] - vel_p[j, 2],
        omega[i, 0], omega[i, 1], omega[i, 2], omega[j, 0], omega[j, 1], omega[j, 2], ri, rj,
        hist[i, kk, 0], hist[i, kk, 1], hist[i, kk, 2], hist[i, kk, 4], m12, (k_n, gn_coef, k_t, law[1]), dt, half)
    if began:
        ext[1][i] += 1      # one collision (counted in both partners' lists)
    if k_t is not None:     # smooth spheres: the evaluator's torque is zero and the spring stays untouched
        hist[i, kk, 0] = xix
        hist[i, kk, 1] = xiy
        hist[i, kk, 2] = xiz
    hist[i, kk, 4] = fd
    return fx, fy, fz, tx, ty, tz, (delta / min(ri, rj)) if delta > 0 else 0.0


@numba.njit(cache=True)  # a plain loop over particles: the CPU backend calls it once per record
def observe(pos, vel, omega, radius, mass, inertia, nbr, nn, hist, box, inv_box, half, k_n_val, k_t_val):
    """(E_tr, E_rot, contacts, elastic energy, max overlap/radius, P_x, P_y, P_z, S_tr2, S_rot2, S_x) in SI units.

    The elastic energy is that of the normal springs (k_n delta^2 / 2) and of the tangential springs
    (k_t |xi|^2 / 2) of the contacts; each pair appears twice in the full list, hence the factors 1/4.
    S_tr2 = sum_i e_tr,i^2, S_rot2 = sum_i e_rot,i^2, S_x = sum_i e_tr,i e_rot,i (J^2) with the particle
    energies e_tr,i = m_i |v_i|^2 / 2 and e_rot,i = I_i |omega_i|^2 / 2: the moments of the Sonine
    coefficients (engine/physics/sonine.py), in sums of their own (the existing sums are unchanged).
    """
    n = pos.shape[0]
    e_tr = 0.0
    e_rot = 0.0
    contacts = 0
    e_spring = 0.0
    px = 0.0
    py = 0.0
    pz = 0.0
    worst = 0.0
    s_tr2 = 0.0
    s_rot2 = 0.0
    s_x = 0.0
    for i in range(n):
        m = mass[i]
        e_tr += 0.5 * m * (vel[i, 0] ** 2 + vel[i, 1] ** 2 + vel[i, 2] ** 2)
        e_rot += 0.5 * inertia[i] * (omega[i, 0] ** 2 + omega[i, 1] ** 2 + omega[i, 2] ** 2)
        et_i = 0.5 * m * (vel[i, 0] ** 2 + vel[i, 1] ** 2 + vel[i, 2] ** 2)
        er_i = 0.5 * inertia[i] * (omega[i, 0] ** 2 + omega[i, 1] ** 2 + omega[i, 2] ** 2)
        s_tr2 += et_i * et_i
        s_rot2 += er_i * er_i
        s_x += et_i * er_i
        px += m * vel[i, 0]
        py += m * vel[i, 1]
        pz += m * vel[i, 2]
        ci = 0
        es = 0.0
        wi = 0.0
        for kk in range(nn[i]):
            j = nbr[i, kk]
            rx = min_image(pos[i, 0] - pos[j, 0], box, inv_box, half)
            ry = min_image(pos[i, 1] - pos[j, 1], box, inv_box, half)
            rz = min_image(pos[i, 2] - pos[j, 2], box, inv_box, half)
            s = radius[i] + radius[j]
            d2 = rx * rx + ry * ry + rz * rz
            if d2 < s * s:
                ci += 1
                delta = s - math.sqrt(d2)
                # each pair appears in both partners' lists
                es += 0.5 * contact_elastic_energy(delta, hist[i, kk, 0], hist[i, kk, 1], hist[i, kk, 2],
                                                   k_n_val, k_t_val, 0.5)
                ov = delta / min(radius[i], radius[j])
                wi = max(wi, ov)
        contacts += ci
        e_spring += es
        worst = max(worst, wi)
    return e_tr, e_rot, contacts // 2, e_spring, worst, px, py, pz, s_tr2, s_rot2, s_x


fast_loads(globals())  # their disk-cache loads skip numba's target refresh (engine/numba_support/jitcache.py)
