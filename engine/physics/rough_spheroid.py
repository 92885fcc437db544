"""The tangential contact law of rough spheres applied to spheroids: pure njit functions.

:func:`rough_spheroid_pair` is the whole pair law that both backends call, through the spheroid's pair evaluator
(engine/shapes/spheroid/law.py); the functions above it are its parts, tested on their own
(tests/engine/test_rough_spheroid_physics.py). Derivation: docs/physics.md §2.5.

Conventions (those of engine.physics.ellipsoid.ellipsoid_pair_screened): body A at c_A, body B at c_B,
r = c_B - c_A, the contact point C, lever arms r_A = C - c_A and r_B = C - c_B, the unit normal n from A to B.
The spring xi (m) is the tangential displacement of B's material point at C relative to A's, carried in the
tangent plane (rotated with the normal, as the sphere code does: engine.physics.contact.
rotate_spring_into_plane); the tangential force on B is F_t = -k_t xi (gamma_t = 0, Hidalgo et al. 2013), on A -F_t,
capped at mu |F_n| when mu is given (the cap of the sphere code, on |F_n|: docs/physics.md §1.4).
Torques r_B x F_t on B and r_A x (-F_t) on A: with the common point C, angular momentum about any fixed point
is conserved to rounding.

Stiffness (Hidalgo et al. 2013, Eq. 4 with the pair's effective tangential mass at C). The impulse response of the
relative velocity g = (u_B + w_B x r_B) - (u_A + w_A x r_A) of the two material points at C to an impulse J on
B (-J on A) is dg = K J with the symmetric positive-definite

    K = (1/m_A + 1/m_B) 1 + [r_A]^T S_A [r_A] + [r_B]^T S_B [r_B],

S = R diag(1/I_1, 1/I_2, 1/I_3) R^T the space-frame inverse inertia, [r] the cross-product matrix
([r] x = r x x). n.K n = (1 + D)/m12 is the normal counterpart (the D of docs/physics.md §2.4). The
effective tangential mass is taken as the inverse of K's mean over the tangent plane:

    1/m_t = (tr K - n.K n)/2
          = 1/m12 + sum_{X = A, B} (|r_X|^2 tr S_X - r_X.S_X r_X - (r_X x n).S_X (r_X x n))/2,

and k_t = k_n (m_t/m12) (arccos(-e_t)/pi)^2, Hidalgo et al. (2013) Eq. 4 (which is this with m_t/m12 = q/(1 + q) for
identical spheres: the same formula in the sphere limit). Exact (the sticking slip is one harmonic
oscillator and e_t is e_t) only when K's tangential block is isotropic and uncoupled from the normal: spheres,
and the ξ -> 1 limit. For a spheroid the tangential block has two eigenvalues (two slip frequencies) and an
off-diagonal n-t part: e_t is then the value of the equivalent isotropic contact, not the exact restitution
of every collision (docs/physics.md §2.5). k_t is evaluated at the first step of a contact and kept for
the contact's lifetime (a spring whose stiffness changed with the geometry would create energy).

Units: SI (m, kg, s, N). Every function takes ``half`` = 0.5 in the working precision.
"""

import math

import numba

from engine.physics.contact import rotate_spring_into_plane, tangential_spring_step
from engine.physics.ellipsoid import (PAIR_DONE, ellipsoid_pair_geometry_screened, sym_mul_vec, sym_quad,
                                      sym_rotated)


@numba.njit
def inverse_inertia_space(q0, q1, q2, q3, inv_i1, inv_i2, inv_i3, half):
    """S = R diag(1/I_1, 1/I_2, 1/I_3) R^T (1/(kg m^2)) of a body with orientation q, symmetric 6-tuple."""
    return sym_rotated(q0, q1, q2, q3, inv_i1, inv_i2, inv_i3, half)


@numba.njit
def lever_tangent_mean(s00, s01, s02, s11, s12, s22, rx, ry, rz, nx, ny, nz, half):
    """Mean over unit tangents t (t.n = 0) of (r x t).S (r x t) (1/kg): (|r|^2 tr S - r.S r - (r x n).S (r x n))/2."""
    r2 = rx * rx + ry * ry + rz * rz
    tr = s00 + s11 + s22
    cx = ry * nz - rz * ny
    cy = rz * nx - rx * nz
    cz = rx * ny - ry * nx
    return (r2 * tr - sym_quad(s00, s01, s02, s11, s12, s22, rx, ry, rz)
            - sym_quad(s00, s01, s02, s11, s12, s22, cx, cy, cz)) * half


@numba.njit
def tangential_inverse_mass(inv_m12, sa, ra_x, ra_y, ra_z, sb, rb_x, rb_y, rb_z, nx, ny, nz, half):
    """1/m_t (1/kg) of the pair at its contact point (module docstring); sa, sb space-frame inverse inertias."""
    return (inv_m12 + lever_tangent_mean(sa[0], sa[1], sa[2], sa[3], sa[4], sa[5], ra_x, ra_y, ra_z, nx, ny, nz, half)
            + lever_tangent_mean(sb[0], sb[1], sb[2], sb[3], sb[4], sb[5], rb_x, rb_y, rb_z, nx, ny, nz, half))


@numba.njit
def normal_inverse_mass(inv_m12, sa, ra_x, ra_y, ra_z, sb, rb_x, rb_y, rb_z, nx, ny, nz):
    """n.K n = (1 + D)/m12 (1/kg): the D of docs/physics.md §2.4, the normal counterpart of 1/m_t."""
    ax = ra_y * nz - ra_z * ny
    ay = ra_z * nx - ra_x * nz
    az = ra_x * ny - ra_y * nx
    bx = rb_y * nz - rb_z * ny
    by = rb_z * nx - rb_x * nz
    bz = rb_x * ny - rb_y * nx
    return (inv_m12 + sym_quad(sa[0], sa[1], sa[2], sa[3], sa[4], sa[5], ax, ay, az)
            + sym_quad(sb[0], sb[1], sb[2], sb[3], sb[4], sb[5], bx, by, bz))


@numba.njit
def tangential_stiffness(k_n, m12, inv_mt, tangential_factor):
    """k_t = k_n (m_t/m12) f (N/m), f = (arccos(-e_t)/pi)^2 (Hidalgo et al. 2013, Eq. 4; engine.setup.params
    computes f)."""
    return k_n * tangential_factor / (m12 * inv_mt)


@numba.njit
def tangential_factor(e_t):
    """(arccos(-e_t)/pi)^2 of Hidalgo et al. (2013) Eq. 4 (-1 <= e_t <= 1)."""
    return (math.acos(-e_t) / math.pi) ** 2


@numba.njit
def contact_point_slip(ux, uy, uz, wax, way, waz, wbx, wby, wbz, ra_x, ra_y, ra_z, rb_x, rb_y, rb_z,
                       nx, ny, nz):
    """Tangential part (m/s) of g = (u_B + w_B x r_B) - (u_A + w_A x r_A), u = u_B - u_A."""
    gx = ux + (wby * rb_z - wbz * rb_y) - (way * ra_z - waz * ra_y)
    gy = uy + (wbz * rb_x - wbx * rb_z) - (waz * ra_x - wax * ra_z)
    gz = uz + (wbx * rb_y - wby * rb_x) - (wax * ra_y - way * ra_x)
    gn = gx * nx + gy * ny + gz * nz
    return gx - gn * nx, gy - gn * ny, gz - gn * nz


@numba.njit
def spheroid_tangential(nx, ny, nz, ra_x, ra_y, ra_z, rb_x, rb_y, rb_z, tx, ty, tz, xix, xiy, xiz, k_t, fn, mu,
                        h):
    """One step of the tangential spring at a spheroid contact.

    n the unit normal (A to B); r_A, r_B the lever arms to the contact point (m); t the tangential slip of B
    relative to A (m/s, :func:`contact_point_slip`); xi the spring of the previous step (m); k_t (N/m); fn the
    normal force magnitude this step (N, for the cap); mu (-) or None; h the time the spring loads in this
    step (s: dt, or the part of the step since the contact began, as the sphere code).

    Returns (F_B (3), tau_A (3), tau_B (3), xi (3)): the tangential force on B (A gets -F_B), the torques (N m)
    and the new spring (m).
    """
    gx, gy, gz, px, py, pz = tangential_spring_step(xix, xiy, xiz, nx, ny, nz, tx, ty, tz, h, k_t, fn, mu)
    # tau_A = r_A x (-F), tau_B = r_B x F
    return (gx, gy, gz,
            -(ra_y * gz - ra_z * gy), -(ra_z * gx - ra_x * gz), -(ra_x * gy - ra_y * gx),
            rb_y * gz - rb_z * gy, rb_z * gx - rb_x * gz, rb_x * gy - rb_y * gx,
            px, py, pz)


@numba.njit
def impulse_response(inv_m12, sa, ra_x, ra_y, ra_z, sb, rb_x, rb_y, rb_z, jx, jy, jz):
    """K J (m/s per N s): the change of the contact-point relative velocity g for an impulse J on B (-J on A)."""
    # J / m12 + (S_A (r_A x J)) x r_A ... written as -r_A x (S_A (r_A x J)) + same for B
    ax = ra_y * jz - ra_z * jy
    ay = ra_z * jx - ra_x * jz
    az = ra_x * jy - ra_y * jx
    sax, say, saz = sym_mul_vec(sa[0], sa[1], sa[2], sa[3], sa[4], sa[5], ax, ay, az)
    bx = rb_y * jz - rb_z * jy
    by = rb_z * jx - rb_x * jz
    bz = rb_x * jy - rb_y * jx
    sbx, sby, sbz = sym_mul_vec(sb[0], sb[1], sb[2], sb[3], sb[4], sb[5], bx, by, bz)
    return (inv_m12 * jx + (say * ra_z - saz * ra_y) + (sby * rb_z - sbz * rb_y),
            inv_m12 * jy + (saz * ra_x - sax * ra_z) + (sbz * rb_x - sbx * rb_z),
            inv_m12 * jz + (sax * ra_y - say * ra_x) + (sbx * rb_y - sby * rb_x))


@numba.njit
def rough_spheroid_pair(rx, ry, rz, qa0, qa1, qa2, qa3, aa, ba, ca, qb0, qb1, qb2, qb3, ab, bb, cb,
                        ux, uy, uz, wax, way, waz, wbx, wby, wbz,
                        vx, vy, vz, mwax, mway, mwaz, mwbx, mwby, mwbz,
                        ia1, ia2, ia3, ib1, ib2, ib3,
                        delta_prev, fd_prev, xix, xiy, xiz, kt_prev,
                        m12, k_n, gamma_n, f_t, mu, dt, tol, margin, screened_gap, half):
    """The rough spheroid pair law: the normal contact of Rubio-Largo et al. (2015) plus the tangential spring of
    Hidalgo et al. (2013) at the contact point C. The one source both backends call (through
    engine/shapes/spheroid/law.py).

    Geometry and normal force are :func:`engine.physics.ellipsoid.ellipsoid_pair_geometry_screened` (same
    arguments, same screens and contact start/end rules), so the normal part is bit for bit the smooth law's.
    u, w_A, w_B: predicted end-of-step relative velocity u_B - u_A and spins (the normal dashpot, as smooth);
    v, mw_A, mw_B: mid-step relative velocity and spins, which load the spring (the midpoint rule of the
    sphere code, engine.physics.contact.sphere_contact). ia, ib: principal 1/I of A and B (1/(kg m^2)).
    History: delta_prev, fd_prev (overlap m, dashpot force N), the spring xi (m) and the contact's k_t (N/m; 0
    before its first step: then k_t = k_n f_t m_t/m12, :func:`tangential_stiffness`, with the tangential mass of
    the undeformed contact, lever arms to the surface points C -+ (delta/2) n, which makes k_t the value of
    Hidalgo et al. (2013) for spheres; kept for the contact's lifetime). f_t = (arccos(-e_t)/pi)^2; mu the Coulomb
    coefficient or None (no cap).

    In contact: the spring is rotated into the new tangent plane, loaded by the contact-point slip for the step
    (for the part of the step since the contact began at its first step), F_t = -k_t xi on B (capped at
    mu |F_n| with F_n = k_n delta + F_dashpot, the spring shortened on sliding), -F_t on A, torques
    r_A x (-F_t), r_B x F_t about the centres with the common point C (angular momentum conserved to rounding).
    Ended inside the step (delta <= 0 < delta_prev): the cut spring's missing impulse is settled as in
    engine.physics.contact.sphere_contact_end, -k_t [xi (p - 1/2) + v_t dt (p^2 - 1/4)/2] with p the part of the
    step the contact lasted; the spring and k_t are reset. Otherwise nothing tangential.

    Returns (F_A (3), tau_A (3), tau_B (3), delta, F_dashpot, xi (3), k_t, status): status as the smooth law's
    (PAIR_NEEDS_PREV: call again with the previous step's gap).
    """
    g = ellipsoid_pair_geometry_screened(rx, ry, rz, qa0, qa1, qa2, qa3, aa, ba, ca, qb0, qb1, qb2, qb3, ab, bb, cb,
                                         ux, uy, uz, wax, way, waz, wbx, wby, wbz, delta_prev, fd_prev, m12, k_n,
                                         gamma_n, dt, tol, margin, screened_gap, half)
    zero = half - half
    delta = g[9]
    fd = g[10]
    status = g[11]
    in_contact = delta > zero
    ended = (not in_contact) and delta_prev > zero
    # f_t = 0: a frictionless scene in a rough-compiled GPU ensemble; it keeps an empty spring, as it would alone
    if status != PAIR_DONE or not (in_contact or ended) or not (f_t > zero):
        return (g[0], g[1], g[2], g[3], g[4], g[5], g[6], g[7], g[8], delta, fd, zero, zero, zero, zero, status)
    nx, ny, nz, cx, cy, cz = g[12], g[13], g[14], g[15], g[16], g[17]
    rbx = cx - rx
    rby = cy - ry
    rbz = cz - rz
    k_t = kt_prev
    if not (k_t > zero):
        # the tangential mass of the undeformed contact: lever arms to the two surface points C -+ (delta/2) n
        # (for spheres |r| = a, so k_t is the k_n f q/(1 + q) of Hidalgo et al. (2013) to rounding); the forces act at C
        hd = half * delta
        sa = inverse_inertia_space(qa0, qa1, qa2, qa3, ia1, ia2, ia3, half)
        sb = inverse_inertia_space(qb0, qb1, qb2, qb3, ib1, ib2, ib3, half)
        inv_mt = tangential_inverse_mass((half + half) / m12, sa, cx + hd * nx, cy + hd * ny, cz + hd * nz,
                                         sb, rbx - hd * nx, rby - hd * ny, rbz - hd * nz, nx, ny, nz, half)
        k_t = tangential_stiffness(k_n, m12, inv_mt, f_t)
    tx, ty, tz = contact_point_slip(vx, vy, vz, mwax, mway, mwaz, mwbx, mwby, mwbz, cx, cy, cz, rbx, rby, rbz,
                                    nx, ny, nz)
    if in_contact:
        h = dt if delta_prev > zero else dt * (delta / (delta - delta_prev))
        fn = k_n * delta + fd
        gx, gy, gz, ta_x, ta_y, ta_z, tb_x, tb_y, tb_z, px, py, pz = spheroid_tangential(
            nx, ny, nz, cx, cy, cz, rbx, rby, rbz, tx, ty, tz, xix, xiy, xiz, k_t, fn, mu, h)
    else:
        p = delta_prev / (delta_prev - delta)
        weight = p - half
        s = dt * (p * p - half * half) * half
        px, py, pz = rotate_spring_into_plane(xix, xiy, xiz, nx, ny, nz)
        gx = -k_t * (px * weight + tx * s)
        gy = -k_t * (py * weight + ty * s)
        gz = -k_t * (pz * weight + tz * s)
        ta_x = -(cy * gz - cz * gy)
        ta_y = -(cz * gx - cx * gz)
        ta_z = -(cx * gy - cy * gx)
        tb_x = rby * gz - rbz * gy
        tb_y = rbz * gx - rbx * gz
        tb_z = rbx * gy - rby * gx
        px = zero
        py = zero
        pz = zero
        k_t = zero
    return (g[0] - gx, g[1] - gy, g[2] - gz, g[3] + ta_x, g[4] + ta_y, g[5] + ta_z, g[6] + tb_x, g[7] + tb_y,
            g[8] + tb_z, delta, fd, px, py, pz, k_t, status)
