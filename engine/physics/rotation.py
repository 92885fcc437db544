"""Quaternion algebra and the rotational integrators (Fincham 1992 leap-frog; paper 001, paper 003).

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
def quat_normalize(q0, q1, q2, q3):
    s = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
    inv = (s / s) / s  # = 1/s exactly, in the working precision (a literal 1 would promote float32)
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
    """Advance the orientation by dt given the mid-step space-frame angular velocity w(t + dt/2).

    Fincham's leap-frog (Mol. Sim. 8, 165 (1992)): estimate q(t + dt/2) = q(t) + dt/2 q'(t), then
    q(t + dt) = q(t) + dt q'(t + dt/2) with q'(t + dt/2) from w(t + dt/2) and q(t + dt/2);
    renormalised every step. For spheres w in the space frame is all the dynamics needs.
    """
    h = dt * half
    d0, d1, d2, d3 = quat_rate_space(q0, q1, q2, q3, wx, wy, wz, half)
    m0, m1, m2, m3 = q0 + h * d0, q1 + h * d1, q2 + h * d2, q3 + h * d3
    e0, e1, e2, e3 = quat_rate_space(m0, m1, m2, m3, wx, wy, wz, half)
    return quat_normalize(q0 + dt * e0, q1 + dt * e1, q2 + dt * e2, q3 + dt * e3)
