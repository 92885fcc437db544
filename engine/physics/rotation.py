"""Quaternion algebra and the rotational integrators (Fincham 1992 leap-frog; Hidalgo et al. 2013,
Rubio-Largo et al. 2015).

Quaternions are scalar-first (w, x, y, z) and map body to space: v_space = q v_body q*.
"""

import math

import numba


@numba.njit
def quat_mul(a0, a1, a2, a3, b0, b1, b2, b3):
    """Hamilton product a b."""
    return (a0 * b0 - a1 * b1 - a2 * b2 - a3 * b3,
            a0 * b1 + a1 * b0 + a2 * b3 - a3 * b2,
            a0 * b2 - a1 * b3 + a2 * b0 + a3 * b1,
            a0 * b3 + a1 * b2 - a2 * b1 + a3 * b0)


@numba.njit
def quat_unit(q0, q1, q2, q3):
    """q / |q| by division, |q|^2 summed in component order: NumPy's ``q / np.linalg.norm(q)`` bit for bit (the
    normalisation of a start's quaternions, engine/setup/scene.py and both ellipsoid backends; quat_normalize's product
    with 1/|q| can differ in the last bit)."""
    n = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
    return q0 / n, q1 / n, q2 / n, q3 / n


@numba.njit
def quat_normalize(q0, q1, q2, q3):
    n2 = q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3
    inv = (n2 / n2) / math.sqrt(n2)  # 1/|q| in the working precision (a literal 1 would promote float32)
    return q0 * inv, q1 * inv, q2 * inv, q3 * inv


@numba.njit
def quat_rotate(q0, q1, q2, q3, vx, vy, vz):
    """Body -> space: q v q* for a unit quaternion q."""
    # t = 2 q_vec x v ; v' = v + q0 t + q_vec x t
    tx = 2 * (q2 * vz - q3 * vy)
    ty = 2 * (q3 * vx - q1 * vz)
    tz = 2 * (q1 * vy - q2 * vx)
    return (vx + q0 * tx + (q2 * tz - q3 * ty),
            vy + q0 * ty + (q3 * tx - q1 * tz),
            vz + q0 * tz + (q1 * ty - q2 * tx))


@numba.njit
def quat_rotate_inverse(q0, q1, q2, q3, vx, vy, vz):
    """Space -> body: q* v q."""
    return quat_rotate(q0, -q1, -q2, -q3, vx, vy, vz)


@numba.njit
def quat_rate_space(q0, q1, q2, q3, wx, wy, wz, half):
    """dq/dt = 1/2 (0, w) q for an angular velocity w given in the space frame (rad/s)."""
    d0, d1, d2, d3 = quat_mul((half - half) * wx, wx, wy, wz, q0, q1, q2, q3)
    return d0 * half, d1 * half, d2 * half, d3 * half


@numba.njit
def fincham_quat_step_space(q0, q1, q2, q3, wx, wy, wz, dt, half):
    """Advance the orientation by dt given the mid-step space-frame angular velocity w(t + dt/2): the
    per-step scheme of Hidalgo et al. (2013) for spheres, kept as the reference the tests measure
    :func:`sphere_quat_turn` against.

    Fincham's leap-frog (Mol. Sim. 8, 165 (1992)): estimate q(t + dt/2) = q(t) + dt/2 q'(t), then
    q(t + dt) = q(t) + dt q'(t + dt/2) with q'(t + dt/2) from w(t + dt/2) and q(t + dt/2);
    renormalised every step. With one w for both stages (spheres: w in the space frame is all the
    dynamics needs) and (0,w)(0,w) = -|w|^2, the two stages collapse exactly into
    q(t + dt) = (1 - dt^2 |w|^2 / 8) q + dt/2 (0, w) q, one quaternion product instead of two.
    """
    h = dt * half
    c = half + half - h * h * (wx * wx + wy * wy + wz * wz) * half
    d0, d1, d2, d3 = quat_mul(h - h, wx, wy, wz, q0, q1, q2, q3)
    return quat_normalize(c * q0 + h * d0, c * q1 + h * d1, c * q2 + h * d2, c * q3 + h * d3)


@numba.njit
def sphere_quat_turn(q0, q1, q2, q3, wx, wy, wz, dt, k, half):
    """The orientation of a sphere after k steps of dt at one space-frame angular velocity w (rad/s), exactly.

    Between two changes of its spin a sphere turns about a fixed axis at a fixed rate, so
    q(t0 + k dt) = exp(k dt/2 (0, w)) q(t0) = cos(a) q + sin(a) (0, w/|w|) q with a = k dt |w| / 2
    (dq/dt = 1/2 (0, w) q), renormalised against rounding. This is the sphere's orientation step:
    the time loops call it with the spin each step had (the mid-step w of the leap-frog, as the Fincham
    update of Hidalgo et al. (2013) uses), for all the steps since the orientation was last brought up to date, when
    a torque is about to change the spin and when the loop returns. A free sphere is thus exact to rounding over any
    number of steps (Fincham's per-step scheme, :func:`fincham_quat_step_space`, turns by
    atan2(h |w|, 1 - h^2 |w|^2 / 2) with h = dt/2, a phase error of (h |w|)^3 / 6 per step); in contact both are
    second order in dt.
    k = 0 returns q unchanged.
    """
    if k == 0:
        return q0, q1, q2, q3
    w2 = wx * wx + wy * wy + wz * wz
    if w2 == 0:
        return quat_normalize(q0, q1, q2, q3)
    wn = math.sqrt(w2)
    a = (k * (dt * half)) * wn
    ca = math.cos(a)
    sa = math.sin(a) / wn
    d0, d1, d2, d3 = quat_mul(wx - wx, wx, wy, wz, q0, q1, q2, q3)
    return quat_normalize(ca * q0 + sa * d0, ca * q1 + sa * d1, ca * q2 + sa * d2, ca * q3 + sa * d3)


# ---- rigid bodies with principal moments (ellipsoids; Rubio-Largo et al. 2015, Eqs. 13-21) -------
#
# Float32-safe (constants from `half`). The state is the space-frame angular momentum L and the
# quaternion q. Euler's equations I w_b' = M_b - w_b x (I w_b) in the body frame are the body-frame form
# of dL/dt = tau (space frame); Fincham's leap-frog (Mol. Sim. 8, 165 (1992)) kicks L with the torque
# (exact for the gyroscopic terms, which never have to be written out) and turns L into the body-frame
# angular velocity w_b = I^-1 R^T L whenever q' = Q(q) w_b / 2 (Rubio-Largo et al. 2015, Eq. 16) is needed.


@numba.njit
def quat_matrix(q0, q1, q2, q3, half):
    """Rotation matrix (body -> space) of a unit quaternion, row-major 9-tuple."""
    one = half + half
    two = one + one
    return (one - two * (q2 * q2 + q3 * q3), two * (q1 * q2 - q0 * q3), two * (q1 * q3 + q0 * q2),
            two * (q1 * q2 + q0 * q3), one - two * (q1 * q1 + q3 * q3), two * (q2 * q3 - q0 * q1),
            two * (q1 * q3 - q0 * q2), two * (q2 * q3 + q0 * q1), one - two * (q1 * q1 + q2 * q2))


@numba.njit
def quat_rate_body(q0, q1, q2, q3, wx, wy, wz, half):
    """dq/dt = 1/2 q (0, w_b) = Q(q) w_b / 2 for the body-frame angular velocity w_b (Rubio-Largo et al. 2015,
    Eq. 16)."""
    d0, d1, d2, d3 = quat_mul(q0, q1, q2, q3, half - half, wx, wy, wz)
    return d0 * half, d1 * half, d2 * half, d3 * half


@numba.njit
def body_omega(q0, q1, q2, q3, lx, ly, lz, inv_i1, inv_i2, inv_i3, half):
    """Body-frame angular velocity w_b = I^-1 R^T L from the space-frame angular momentum (rad/s)."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = quat_matrix(q0, q1, q2, q3, half)
    return ((r00 * lx + r10 * ly + r20 * lz) * inv_i1,
            (r01 * lx + r11 * ly + r21 * lz) * inv_i2,
            (r02 * lx + r12 * ly + r22 * lz) * inv_i3)


@numba.njit
def space_omega(q0, q1, q2, q3, lx, ly, lz, inv_i1, inv_i2, inv_i3, half):
    """Space-frame angular velocity R I^-1 R^T L (rad/s)."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = quat_matrix(q0, q1, q2, q3, half)
    bx = (r00 * lx + r10 * ly + r20 * lz) * inv_i1
    by = (r01 * lx + r11 * ly + r21 * lz) * inv_i2
    bz = (r02 * lx + r12 * ly + r22 * lz) * inv_i3
    return (r00 * bx + r01 * by + r02 * bz, r10 * bx + r11 * by + r12 * bz, r20 * bx + r21 * by + r22 * bz)


@numba.njit
def angular_momentum(q0, q1, q2, q3, wx, wy, wz, i1, i2, i3, half):
    """Space-frame angular momentum R I R^T w of a space-frame angular velocity w (kg m^2/s)."""
    return space_omega(q0, q1, q2, q3, wx, wy, wz, i1, i2, i3, half)


@numba.njit
def fincham_quat_step_body(q0, q1, q2, q3, ltx, lty, ltz, lhx, lhy, lhz, inv_i1, inv_i2, inv_i3, dt, half):
    """Advance q by dt (Fincham's leap-frog, Rubio-Largo et al. 2015, Eqs. 17-21) for a body with principal moments.

    L_t = L(t), L_h = L(t + dt/2) (space frame). q(t + dt/2) = q + dt/2 Q(q) w_b(t)/2 with
    w_b(t) = I^-1 R(q)^T L_t; q(t + dt) = q + dt Q(q_h) w_b(t + dt/2)/2 with w_b(t + dt/2) from
    R(q(t + dt/2)) and L_h; renormalised every step.
    """
    h = dt * half
    wx, wy, wz = body_omega(q0, q1, q2, q3, ltx, lty, ltz, inv_i1, inv_i2, inv_i3, half)
    d0, d1, d2, d3 = quat_rate_body(q0, q1, q2, q3, wx, wy, wz, half)
    m0, m1, m2, m3 = quat_normalize(q0 + h * d0, q1 + h * d1, q2 + h * d2, q3 + h * d3)
    wx, wy, wz = body_omega(m0, m1, m2, m3, lhx, lhy, lhz, inv_i1, inv_i2, inv_i3, half)
    e0, e1, e2, e3 = quat_rate_body(m0, m1, m2, m3, wx, wy, wz, half)
    return quat_normalize(q0 + dt * e0, q1 + dt * e1, q2 + dt * e2, q3 + dt * e3)
