"""The spheroid's pair evaluator and rotation step: the one place where a list slot's contact law and a particle's
orientation update are written.

:func:`spheroid_pair`, :func:`spheroid_gap` and :func:`spheroid_rotation` are plain ``@numba.njit`` functions of
scalars (tuples of scalars where a call would otherwise take more than 30 arguments: a longer call compiles to
bytecode that numba-cuda does not read on Python 3.12). The CPU time loop (kernels.py ``pair`` and ``rotate``, rows
per particle) and the CUDA time loop (device.py ``pair`` and ``rotate``, particle index fastest) both call them;
each of them only gathers its inputs from its own layout and scatters the results into it. The equations are
engine/physics/ellipsoid.py's (Perram-Wertheim contact, exact screens, normal force with the contact start and end
rules), engine/physics/rough_spheroid.py's (tangential spring at the contact point) and engine/physics/rotation.py's
(Fincham's leap-frog): docs/physics.md §2.2-2.5 and §3.3.

Units: SI (m, kg, s, N); ``half`` = 0.5 in the working precision.
"""

from __future__ import annotations

import math

import numba

from engine.physics.ellipsoid import ellipsoid_contact, ellipsoid_pair_screened
from engine.physics.rotation import fincham_quat_step_body, space_omega
from engine.physics.rough_spheroid import rough_spheroid_pair

#: indices into :func:`spheroid_pair`'s result (after F_A, tau_A, tau_B at 0-8): the overlap (m), the dashpot
#: force (N), the spring xi (m), the contact's k_t (N/m) and the status (engine.physics.ellipsoid.PAIR_DONE,
#: PAIR_SCREENED, PAIR_NEEDS_PREV)
S_DELTA, S_FD, S_XI_X, S_XI_Y, S_XI_Z, S_KT, S_STATUS = range(9, 16)


@numba.njit
def mid_step_omega(q_prev, q, angm, inv_i, half):
    """Space-frame angular velocity (rad/s) at mid-step, for the rough spring (an input of :func:`spheroid_pair`,
    evaluated by the caller once per slot, outside its retry after a screened step): the angular momentum
    L(t + dt/2) = ``angm`` (kg m^2/s, after the kick) with the orientation normalize(q(t) + q(t + dt)) (second
    order in dt; the midpoint rule of the sphere code). q_prev = q(t), q = q(t + dt) (4 each), inv_i the principal
    1/I (1/(kg m^2), 3)."""
    q0 = q_prev[0] + q[0]
    q1 = q_prev[1] + q[1]
    q2 = q_prev[2] + q[2]
    q3 = q_prev[3] + q[3]
    s = (half + half) / math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
    return space_omega(q0 * s, q1 * s, q2 * s, q3 * s, angm[0], angm[1], angm[2], inv_i[0], inv_i[1], inv_i[2],
                       half)


@numba.njit
def spheroid_pair(rx, ry, rz, qa, qb, sa, sb, u, wa, wb, d_prev, fd_prev, m12, law, rough, dt, half):
    """The law of one list slot for the ordered pair (A, B) = (lower id, higher id), evaluated once.

    Inputs: r = c_B - c_A (m, minimum image); qa, qb the orientations (unit quaternions body to space, 4 each);
    sa, sb the semi-axes (a, b, c) (m); u = u_B - u_A the predicted end-of-step relative velocity (m/s) and wa, wb
    the predicted space-frame angular velocities (rad/s), which the normal dashpot reads; d_prev, fd_prev the
    slot's overlap (m; negative: the gap; -inf: screened) and dashpot force (N) at the previous step; m12 the
    reduced mass (kg); law = (k_n (N/m), gn_coef (kg^1/2 / s: gamma_n = gn_coef sqrt(m12)), tol (Perram-Wertheim
    Newton tolerance), margin (relative margin of the exact screens; < 0: no screens), screened_gap (the gap a
    screened pair stores: -inf)); dt (s).
    ``rough``: None for frictionless spheroids (Rubio-Largo et al. 2015; pruned at compile time), else the tangential
    inputs (v, ma, mb, ia, ib, spring, f_t, mu): v = v_B - v_A the mid-step relative velocity (m/s) and ma, mb the
    mid-step space-frame spins of A and B (rad/s; :func:`mid_step_omega`), which load the spring; ia, ib the
    principal 1/I of A and B (1/(kg m^2)); spring = (xi_x, xi_y, xi_z, k_t) the slot's spring (m) and the
    contact's k_t (N/m; 0 before its first step);
    f_t = (arccos(-e_t)/pi)^2 (0: frictionless scene in a rough-compiled GPU ensemble); mu the Coulomb coefficient
    or None (no cap).

    The equations. The contact function of Perram and Wertheim, F(l) = l (1 - l) r^T [(1 - l) M_A^-1 + l M_B^-1]^-1
    r, maximised over l in [0, 1], gives the contact point C, the unit normal n from A to B and the overlap delta
    (the chord through C along n between the two surfaces; negative: the gap) (docs/physics.md §2.2-2.3). A pair
    that was not in contact at the previous step first goes through two exact disjointness screens; one proven
    disjoint returns screened_gap as its delta and nothing else (status PAIR_SCREENED). In contact (delta > 0):
    the normal force on B is F n with F = k_n delta - gamma_n v_n, v_n the normal velocity of B's surface point at C
    relative to A's (from u, wa, wb), with the contact-start weight of the sphere law for the first step; A gets
    -F n; the torques act about the centres through the common point C (docs/physics.md §2.4). A contact that
    ended inside this step (delta <= 0 < d_prev) settles the dashpot impulse it owes. Rough: the spring xi,
    rotated into the new tangent plane and loaded by the slip of the contact point at mid-step, adds
    F_t = -k_t xi on B (capped at mu |F_n|; k_t fixed at the contact's first step from the effective tangential
    mass at C), -F_t on A, torques r_A x (-F_t) and r_B x F_t; a contact that ended inside the step settles the
    cut spring's missing impulse and resets the spring and k_t (docs/physics.md §2.5).
    A contact that starts right after a screened step (delta > 0, d_prev == screened_gap) returns only the status
    PAIR_NEEDS_PREV: the caller evaluates the previous step's gap with :func:`spheroid_gap` from the state before
    the step and calls again with it (the results are then those without screens, bit for bit).

    Returns (F_A (3), tau_A (3), tau_B (3), delta, F_dashpot, xi (3), k_t, status) (N, N m, m, N, m, N/m;
    indices S_*): the force on A (B gets -F_A), the torques on A and B, the slot's new overlap and dashpot
    force, the new spring and k_t (zero when frictionless; the slot keeps its old spring unless status is
    PAIR_DONE).
    """
    k_n, gn_coef, tol, margin, screened_gap = law
    gamma_n = gn_coef * math.sqrt(m12)
    if rough is None:
        zero = half - half
        g = ellipsoid_pair_screened(rx, ry, rz, qa[0], qa[1], qa[2], qa[3], sa[0], sa[1], sa[2],
                                    qb[0], qb[1], qb[2], qb[3], sb[0], sb[1], sb[2], u[0], u[1], u[2],
                                    wa[0], wa[1], wa[2], wb[0], wb[1], wb[2], d_prev, fd_prev, m12, k_n, gamma_n, dt,
                                    tol, margin, screened_gap, half)
        return (g[0], g[1], g[2], g[3], g[4], g[5], g[6], g[7], g[8], g[9], g[10], zero, zero, zero, zero, g[11])
    v, ma, mb, ia, ib, spring, f_t, mu = rough
    return rough_spheroid_pair(rx, ry, rz, qa[0], qa[1], qa[2], qa[3], sa[0], sa[1], sa[2],
                               qb[0], qb[1], qb[2], qb[3], sb[0], sb[1], sb[2], u[0], u[1], u[2],
                               wa[0], wa[1], wa[2], wb[0], wb[1], wb[2], v[0], v[1], v[2],
                               ma[0], ma[1], ma[2], mb[0], mb[1], mb[2], ia[0], ia[1], ia[2], ib[0], ib[1], ib[2],
                               d_prev, fd_prev, spring[0], spring[1], spring[2], spring[3],
                               m12, k_n, gamma_n, f_t, mu, dt, tol, margin, screened_gap, half)


@numba.njit
def spheroid_gap(rx, ry, rz, qa, qb, sa, sb, tol, half):
    """The overlap (m; negative: the gap) of the pair (A, B) at r = c_B - c_A (m, minimum image) with the
    orientations qa, qb and semi-axes sa, sb: what :func:`spheroid_pair` needs as d_prev when it answers
    PAIR_NEEDS_PREV, evaluated from the state before the step (engine.physics.ellipsoid.ellipsoid_contact)."""
    return ellipsoid_contact(rx, ry, rz, qa[0], qa[1], qa[2], qa[3], sa[0], sa[1], sa[2],
                             qb[0], qb[1], qb[2], qb[3], sb[0], sb[1], sb[2], tol, half)[2]


@numba.njit
def spheroid_rotation(q0, q1, q2, q3, lx, ly, lz, tx, ty, tz, ii1, ii2, ii3, hk, hp, dt, half):
    """One rotation step of a spheroid after the shared translation of the kick-drift.

    Inputs: the orientation q (unit quaternion, body to space), the space-frame angular momentum L (kg m^2/s)
    before the kick, the torque tau (N m), the principal 1/I (1/(kg m^2)), the kick hk (s: dt/2 on the first step
    of a call, else dt), hp = dt/2 (s) and dt (s).

    L += tau hk (the torque is dL/dt: no inertia factor), which makes L = L(t + dt/2); q advances by Fincham's
    leap-frog (engine.physics.rotation.fincham_quat_step_body, docs/physics.md §3.3) with L(t) = L - tau dt/2 and
    L(t + dt/2), renormalised; the predicted space-frame angular velocity at t + dt is R I^-1 R^T (L + tau dt/2)
    with the new orientation (the dashpot's).

    Returns (L (3), q (4), w_p (3)): the kicked angular momentum, the new orientation and the predicted angular
    velocity (rad/s).
    """
    lx = lx + tx * hk
    ly = ly + ty * hk
    lz = lz + tz * hk
    n0, n1, n2, n3 = fincham_quat_step_body(q0, q1, q2, q3, lx - tx * hp, ly - ty * hp, lz - tz * hp, lx, ly, lz,
                                            ii1, ii2, ii3, dt, half)
    wx, wy, wz = space_omega(n0, n1, n2, n3, lx + tx * hp, ly + ty * hp, lz + tz * hp, ii1, ii2, ii3, half)
    return lx, ly, lz, n0, n1, n2, n3, wx, wy, wz
