"""Sphere contact law of paper 001: linear spring-dashpot normal force, tangential spring with history.

Conventions (forces on particle i from its partner j):
- r = r_i - r_j (minimum image), d = |r|, n = r/d points from j to i, overlap delta = a_i + a_j - d.
- Normal force F_n = k_n delta - gamma_n v_n along n (paper 001, "F^N = -k^N delta - gamma^N v^N_rel"
  with the sign chosen so that positive is repulsive); v_n = (v_i - v_j).n < 0 while approaching.
  The contact ends when delta returns to 0 (PHYSICS-NOTES §1.1 rule (a)), so the late dashpot force can
  be attractive; gamma_n from e_n by paper 001 is then exact.
- Contact point at the middle of the overlap: lever arms l_i = (d + a_i - a_j)/2 and l_j = d - l_i, so
  the torques balance the orbital term and angular momentum is conserved exactly.
- Tangential spring xi (m), d xi/dt = v_t (relative tangential velocity of the contact point, rotation
  included); each step the old spring is rotated into the current tangent plane keeping its length
  (PHYSICS-NOTES §1.2 condition 4), then integrated. F_t = -k_t xi (gamma_t = 0, paper 001).
- Coulomb limit |F_t| <= mu |F_n| with the spring shortened to the cap on sliding. The cap uses |F_n|,
  not max(F_n, 0): the latter zeroes the spring in the attractive tail of the dashpot and silently
  lowers e_t (PHYSICS-NOTES §1.2 condition 1). mu = None means no sliding limit (Luding's model).

Every expression is written so that swapping i and j negates the inputs exactly, which negates the
outputs exactly in IEEE arithmetic: F_ji = -F_ij and xi_ji = -xi_ij to the last bit.
"""

import math

import numba


@numba.njit
def min_image(d, box, inv_box, half):
    """Minimum-image component of a separation d (m) in a periodic box of edge `box` (half = 0.5)."""
    return d - box * math.floor(d * inv_box + half)


@numba.njit
def normal_force(delta, vn, k_n, gamma_n):
    """Normal force magnitude in N along n: k_n delta - gamma_n v_n (repulsive > 0; paper 001)."""
    return k_n * delta - gamma_n * vn


@numba.njit
def rotate_spring_into_plane(xx, xy, xz, nx, ny, nz):
    """Project the spring onto the plane normal to n and restore its length (rigid rotation)."""
    dot = xx * nx + xy * ny + xz * nz
    px = xx - dot * nx
    py = xy - dot * ny
    pz = xz - dot * nz
    old2 = xx * xx + xy * xy + xz * xz
    new2 = px * px + py * py + pz * pz
    if new2 > 0:
        s = math.sqrt(old2 / new2)
        return px * s, py * s, pz * s
    return px, py, pz


@numba.njit
def coulomb_cap(fx, fy, fz, fn, mu, k_t):
    """Cap the tangential force at mu|F_n|; on sliding return the shortened spring -F_t/k_t.

    Returns (fx, fy, fz, sliding, xx, xy, xz); the spring is only meaningful when sliding is True.
    """
    fmax = mu * abs(fn)
    f2 = fx * fx + fy * fy + fz * fz
    if f2 > fmax * fmax:
        s = fmax / math.sqrt(f2)
        gx = fx * s
        gy = fy * s
        gz = fz * s
        return gx, gy, gz, True, -gx / k_t, -gy / k_t, -gz / k_t
    return fx, fy, fz, False, fx, fy, fz


@numba.njit
def sphere_contact(rx, ry, rz, d, vx, vy, vz, wix, wiy, wiz, wjx, wjy, wjz, ai, aj,
                   xix, xiy, xiz, k_n, gamma_n, k_t, mu, dt, half):
    """Force and torque on sphere i from an overlapping sphere j, and the updated tangential spring.

    r = r_i - r_j (m, minimum image) with d = |r| < a_i + a_j; v = v_i - v_j (m/s); w_i, w_j angular
    velocities (rad/s, space frame); a_i, a_j radii (m); xi the spring from the previous step (m);
    k_n, k_t (N/m), gamma_n (kg/s), mu (-) or None, dt (s), half = 0.5 in the working precision.
    k_t = None marks smooth spheres: no tangential force, no torque, the spring stays zero.

    Returns (F_x, F_y, F_z, tau_x, tau_y, tau_z, xi_x, xi_y, xi_z, delta): force (N) and torque (N m) on i,
    the new spring (m) and the overlap (m).
    """
    inv_d = 1 / d
    nx = rx * inv_d
    ny = ry * inv_d
    nz = rz * inv_d
    delta = ai + aj - d
    vn = vx * nx + vy * ny + vz * nz
    fn = normal_force(delta, vn, k_n, gamma_n)
    fx = fn * nx
    fy = fn * ny
    fz = fn * nz
    zero = delta - delta
    if k_t is None:
        return fx, fy, fz, zero, zero, zero, zero, zero, zero, delta
    li = (d + ai - aj) * half
    lj = d - li
    # contact-point velocity: v_c = v_i - v_j - (l_i w_i + l_j w_j) x n
    sx = li * wix + lj * wjx
    sy = li * wiy + lj * wjy
    sz = li * wiz + lj * wjz
    cx = vx - (sy * nz - sz * ny)
    cy = vy - (sz * nx - sx * nz)
    cz = vz - (sx * ny - sy * nx)
    cn = cx * nx + cy * ny + cz * nz
    tx = cx - cn * nx
    ty = cy - cn * ny
    tz = cz - cn * nz
    px, py, pz = rotate_spring_into_plane(xix, xiy, xiz, nx, ny, nz)
    px += tx * dt
    py += ty * dt
    pz += tz * dt
    gx = -k_t * px
    gy = -k_t * py
    gz = -k_t * pz
    if mu is not None:
        gx, gy, gz, sliding, qx, qy, qz = coulomb_cap(gx, gy, gz, fn, mu, k_t)
        if sliding:
            px = qx
            py = qy
            pz = qz
    # torque on i: (-l_i n) x F_t
    taux = -li * (ny * gz - nz * gy)
    tauy = -li * (nz * gx - nx * gz)
    tauz = -li * (nx * gy - ny * gx)
    return fx + gx, fy + gy, fz + gz, taux, tauy, tauz, px, py, pz, delta
