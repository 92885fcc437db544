"""The sphere's pair evaluator: the one place where a list slot's contact law is written.

:func:`sphere_pair` is a plain ``@numba.njit`` function of scalars. The CPU time loop (kernels.py ``pair``, rows per
particle) and the CUDA time loop (device.py ``pair``, particle index fastest) both call it; each of them only gathers
its inputs from its own layout and scatters its results into it. The equations are engine/physics/contact.py's
(the linear spring-dashpot of Hidalgo et al. (2013) with the tangential spring and Coulomb cap, and the impulse
corrections of a contact that starts or ends inside a step): docs/physics.md §1.
"""

from __future__ import annotations

import math

import numba

from engine.physics.contact import contact_begins, contact_end_fraction, sphere_contact, sphere_contact_end


@numba.njit
def sphere_pair(rx, ry, rz, d, delta, delta_prev, vx, vy, vz, ux, uy, uz, wix, wiy, wiz, wjx, wjy, wjz, ri, rj,
                xix, xiy, xiz, fd_prev, m12, law, dt, half):
    """The law of one list slot of sphere i (neighbour j) that is in contact now (delta > 0) or was at the
    previous step (delta_prev > 0); a slot in neither state has no force and keeps its history.

    Inputs: r = r_i - r_j (m, minimum image), d = |r|, delta = r_i + r_j - d and delta_prev the overlaps now and
    one step earlier (m); v = v_i - v_j at mid-step and u = v_i - v_j predicted at the end of the step (m/s; u is
    read only while in contact); w_i, w_j the angular velocities (rad/s); the radii r_i, r_j (m); the slot's
    tangential spring xi (m) and previous dashpot force fd_prev (N); the reduced mass m12 (kg); the contact
    constants law = (k_n (N/m), gn_coef (kg^1/2 / s: gamma_n = gn_coef sqrt(m12)), k_t (N/m) or None (smooth
    spheres), mu or None (no Coulomb cap)); dt (s); half = 0.5 in the working precision. (At most 30 arguments:
    a longer call compiles to bytecode that numba-cuda does not read on Python 3.12.)

    Returns (F_x, F_y, F_z, tau_x, tau_y, tau_z, xi_x, xi_y, xi_z, F_d, began): the force (N) and torque (N m) on
    i, the slot's new spring (m) and dashpot force (N), and whether the contact began in this step (one collision).
    In contact: engine.physics.contact.sphere_contact. A contact that ended inside this step: the impulse
    correction of sphere_contact_end, the spring reset to zero, the dashpot force kept.
    """
    k_n, gn_coef, k_t, mu = law
    if delta > half - half:
        g = sphere_contact(rx, ry, rz, d, vx, vy, vz, ux, uy, uz, wix, wiy, wiz, wjx, wjy, wjz, ri, rj, xix, xiy, xiz,
                           delta_prev, fd_prev, m12, k_n, gn_coef * math.sqrt(m12), k_t, mu, dt, half)
        return g[0], g[1], g[2], g[3], g[4], g[5], g[6], g[7], g[8], g[10], contact_begins(delta, delta_prev)
    e = sphere_contact_end(rx, ry, rz, d, vx, vy, vz, wix, wiy, wiz, wjx, wjy, wjz, ri, rj, fd_prev, xix, xiy, xiz,
                           k_t, contact_end_fraction(delta_prev, delta), dt, half)
    zero = half - half
    return e[0], e[1], e[2], e[3], e[4], e[5], zero, zero, zero, fd_prev, False
