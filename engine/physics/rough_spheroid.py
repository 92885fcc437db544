"""The tangential contact law of rough spheres applied to spheroids (issue 17): pure njit functions.

Not yet called by the backends (the rough-ellipsoid time loop comes with issue 19's one loop per device);
these are the single physics source that both backends will call, tested on their own
(tests/engine/test_rough_spheroid_physics.py). Derivation: docs/rough-spheroids.md.

Conventions (those of engine.physics.ellipsoid.ellipsoid_pair_screened): body A at c_A, body B at c_B,
r = c_B - c_A, the contact point C, lever arms r_A = C - c_A and r_B = C - c_B, the unit normal n from A to B.
The spring xi (m) is the tangential displacement of B's material point at C relative to A's, carried in the
tangent plane (rotated with the normal, as the sphere code does: engine.physics.contact.
rotate_spring_into_plane); the tangential force on B is F_t = -k_t xi (gamma_t = 0, paper 001), on A -F_t,
capped at mu |F_n| when mu is given (the cap of the sphere code, on |F_n|: PHYSICS-NOTES §1.2 condition 1).
Torques r_B x F_t on B and r_A x (-F_t) on A: with the common point C, angular momentum about any fixed point
is conserved to rounding.

Stiffness (paper 001 Eq. 4 with the pair's effective tangential mass at C). The impulse response of the
relative velocity g = (u_B + w_B x r_B) - (u_A + w_A x r_A) of the two material points at C to an impulse J on
B (-J on A) is dg = K J with the symmetric positive-definite

    K = (1/m_A + 1/m_B) 1 + [r_A]^T S_A [r_A] + [r_B]^T S_B [r_B],

S = R diag(1/I_1, 1/I_2, 1/I_3) R^T the space-frame inverse inertia, [r] the cross-product matrix
([r] x = r x x). n.K n = (1 + D)/m12 is the normal counterpart (PHYSICS-NOTES §3.2's D-term). The
effective tangential mass is taken as the inverse of K's mean over the tangent plane:

    1/m_t = (tr K - n.K n)/2
          = 1/m12 + sum_{X = A, B} (|r_X|^2 tr S_X - r_X.S_X r_X - (r_X x n).S_X (r_X x n))/2,

and k_t = k_n (m_t/m12) (arccos(-e_t)/pi)^2, paper 001 Eq. 4 (which is this with m_t/m12 = q/(1 + q) for
identical spheres: the same formula in the sphere limit). Exact (the sticking slip is one harmonic
oscillator and e_t is e_t) only when K's tangential block is isotropic and uncoupled from the normal: spheres,
and the ξ -> 1 limit. For a spheroid the tangential block has two eigenvalues (two slip frequencies) and an
off-diagonal n-t part: e_t is then the value of the equivalent isotropic contact, not the exact restitution
of every collision (docs/rough-spheroids.md). k_t is evaluated at the first step of a contact and kept for
the contact's lifetime (a spring whose stiffness changed with the geometry would create energy).

Units: SI (m, kg, s, N). Every function takes ``half`` = 0.5 in the working precision.
"""

import math

import numba

from engine.physics.contact import tangential_spring_step
from engine.physics.ellipsoid import sym_mul_vec, sym_quad, sym_rotated


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
    """n.K n = (1 + D)/m12 (1/kg): PHYSICS-NOTES §3.2's D-term, the normal counterpart of 1/m_t."""
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
    """k_t = k_n (m_t/m12) f (N/m), f = (arccos(-e_t)/pi)^2 (paper 001 Eq. 4; engine.params computes f)."""
    return k_n * tangential_factor / (m12 * inv_mt)


@numba.njit
def tangential_factor(e_t):
    """(arccos(-e_t)/pi)^2 of paper 001 Eq. 4 (-1 <= e_t <= 1)."""
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
