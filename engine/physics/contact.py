"""Sphere contact law of Hidalgo et al. (2013): linear spring-dashpot normal force, tangential spring with history.

Conventions (forces on particle i from its partner j):
- r = r_i - r_j (minimum image), d = |r|, n = r/d points from j to i, overlap delta = a_i + a_j - d.
- Normal force F_n = k_n delta - gamma_n v_n along n (Hidalgo et al. 2013, "F^N = -k^N delta - gamma^N v^N_rel"
  with the sign chosen so that positive is repulsive); v_n = (v_i - v_j).n < 0 while approaching.
  The contact ends when delta returns to 0 (docs/physics.md §1.2), so the late dashpot force can
  be attractive; gamma_n from e_n by Hidalgo et al. (2013) is then exact.
- Contact point at the middle of the overlap: lever arms l_i = (d + a_i - a_j)/2 and l_j = (d + a_j - a_i)/2
  (l_i + l_j = d), so the torques balance the orbital term and angular momentum is conserved (to rounding).
- Tangential spring xi (m), d xi/dt = v_t (relative tangential velocity of the contact point, rotation
  included); each step the old spring is rotated into the current tangent plane keeping its length
  (docs/physics.md §1.3), then integrated. F_t = -k_t xi (gamma_t = 0, Hidalgo et al. 2013).
- Coulomb limit |F_t| <= mu |F_n| with the spring shortened to the cap on sliding. The cap uses |F_n|,
  not max(F_n, 0): the latter zeroes the spring in the attractive tail of the dashpot and silently
  lowers e_t (docs/physics.md §1.4). mu = None means no sliding limit (Luding's model).

Every expression is written so that swapping i and j negates the inputs exactly, which negates the
outputs exactly in IEEE arithmetic: F_ji = -F_ij and xi_ji = -xi_ij to the last bit.
"""

import math

import numba


@numba.njit
def min_image(d, box, inv_box, half):
    """Minimum-image component of a separation d (m) in a periodic box of edge `box` (half = 0.5)."""
    # = d - box * floor(d / box + 1/2) for |d| < 3/2 box (always so for two positions in [0, box));
    # written with comparisons because math.floor returns an int64 that would promote float32 to
    # float64, and numba-cuda has no np.floor; the results are bit-identical to the floor form.
    t = d * inv_box + half
    if t >= half + half:
        return d - box
    if t < half - half:
        return d + box
    return d


@numba.njit
def sphere_separation(rx, ry, rz, rs, half):
    """(r_x, r_y, r_z, d, delta) of a sphere pair in the state precision, the precision of ``half``: the
    minimum-image separation r (m) in the position precision, its length d = |r| and the overlap
    delta = a_i + a_j - d (rs = a_i + a_j, m) formed in the position precision, then rounded once.

    With one precision for both (float64, float32) the rounding is no operation. In 'mixed' (float64 positions,
    engine/setup/precision.py) d and delta are taken in float64 before they are rounded to float32, so delta keeps
    float32's relative precision of delta itself (not of the box edge) and the force law that follows runs in
    float32."""
    c = type(half)
    d = math.sqrt(rx * rx + ry * ry + rz * rz)
    return c(rx), c(ry), c(rz), c(d), c(rs - d)


@numba.njit
def contact_begins(delta, delta_prev):
    """Whether a contact begins in this step: overlap delta > 0 now, none (delta_prev <= 0, m) the step before
    (one collision; the ``collisions`` observable counts these)."""
    return delta > 0 and not delta_prev > 0


@numba.njit
def normal_force(delta, vn, k_n, gamma_n):
    """Normal force magnitude in N along n: k_n delta - gamma_n v_n (repulsive > 0; Hidalgo et al. 2013)."""
    return k_n * delta - gamma_n * vn


@numba.njit
def contact_elastic_energy(delta, xix, xiy, xiz, k_n, k_t, half):
    """Energy (J) stored in a contact: k_n delta^2/2 in the normal spring, k_t |xi|^2/2 in the tangential one."""
    return half * (k_n * delta * delta + k_t * (xix * xix + xiy * xiy + xiz * xiz))


@numba.njit
def rotate_spring_into_plane(xx, xy, xz, nx, ny, nz):
    """Project the spring onto the plane normal to n and restore its length (rigid rotation). A spring along n
    to rounding (old2 / new2 beyond the precision's range) has no direction in the plane to be restored along: its
    projection is returned as it is, not scaled by an infinite factor (which gave NaN)."""
    dot = xx * nx + xy * ny + xz * nz
    px = xx - dot * nx
    py = xy - dot * ny
    pz = xz - dot * nz
    old2 = xx * xx + xy * xy + xz * xz
    new2 = px * px + py * py + pz * pz
    if new2 > 0:
        ratio = old2 / new2
        if ratio < math.inf:
            s = math.sqrt(ratio)
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
def tangential_spring_step(xix, xiy, xiz, nx, ny, nz, tx, ty, tz, h, k_t, fn, mu):
    """One step of the tangential spring (Hidalgo et al. 2013; spheres and rough spheroids): the old spring xi (m)
    rotated into the plane normal to n, loaded by the slip t (m/s) for h seconds, the force -k_t xi (N) capped at
    mu |F_n| (fn, N; mu None: no cap) with the spring shortened on sliding. Returns (F (3), xi (3))."""
    px, py, pz = rotate_spring_into_plane(xix, xiy, xiz, nx, ny, nz)
    px += tx * h
    py += ty * h
    pz += tz * h
    gx = -k_t * px
    gy = -k_t * py
    gz = -k_t * pz
    if mu is not None:
        gx, gy, gz, sliding, qx, qy, qz = coulomb_cap(gx, gy, gz, fn, mu, k_t)
        if sliding:
            px = qx
            py = qy
            pz = qz
    return gx, gy, gz, px, py, pz


@numba.njit
def tangential_slip(nx, ny, nz, vx, vy, vz, wix, wiy, wiz, wjx, wjy, wjz, li, lj):
    """Tangential part of the contact-point velocity v_i - v_j - (l_i w_i + l_j w_j) x n (m/s)."""
    sx = li * wix + lj * wjx
    sy = li * wiy + lj * wjy
    sz = li * wiz + lj * wjz
    cx = vx - (sy * nz - sz * ny)
    cy = vy - (sz * nx - sx * nz)
    cz = vz - (sx * ny - sy * nx)
    cn = cx * nx + cy * ny + cz * nz
    return cx - cn * nx, cy - cn * ny, cz - cn * nz


@numba.njit
def sphere_contact(rx, ry, rz, d, vx, vy, vz, ux, uy, uz, wix, wiy, wiz, wjx, wjy, wjz, ai, aj,
                   xix, xiy, xiz, delta_prev, fd_prev, m12, k_n, gamma_n, k_t, mu, dt, half):
    """Force and torque on sphere i from an overlapping sphere j, and the updated tangential spring.

    r = r_i - r_j (m, minimum image) with d = |r| < a_i + a_j; v = v_i - v_j at mid-step (m/s), which
    integrates the spring (midpoint rule); u = v_i - v_j predicted at the end of the step, which the
    normal dashpot uses (velocity Verlet evaluates forces at t + dt); w_i, w_j mid-step angular
    velocities (rad/s, space frame); a_i, a_j radii (m); xi the spring from the previous step (m);
    delta_prev, fd_prev the overlap (m) and dashpot force (N) of this pair one step earlier
    (delta_prev <= 0 when the contact starts in this step, which weights the dashpot impulse by
    :func:`contact_start_weight`); m12 the pair's reduced mass (kg);
    k_n, k_t (N/m), gamma_n (kg/s), mu (-) or None, dt (s), half = 0.5 in the working precision.

    The dashpot velocity is solved implicitly for this pair: the predicted u contains the pair's own
    force of the last step, F_old dt/(2 m12); replacing it by the new force gives
    u_n (1 + w gamma_n dt/(2 m12)) = u_pred,n + dt/(2 m12) (k_n delta - F_old), exact (trapezoidal) for an
    isolated pair and O(dt^2) better than the plain predictor in strongly damped contacts.
    k_t = None marks smooth spheres: no tangential force, no torque, the spring stays zero.

    Returns (F_x, F_y, F_z, tau_x, tau_y, tau_z, xi_x, xi_y, xi_z, delta, F_d): force (N) and torque
    (N m) on i, the new spring (m), the overlap (m) and the dashpot force -gamma_n u_n (N) of this step.

    Coincident centres (d = 0, also when |r|^2 underflows) leave the normal undefined: the pair then
    exerts no force and no torque, keeps its spring and reports the overlap a_i + a_j (dashpot force 0),
    so the overlap guard of the caller stops the run (2 radii > any allowed overlap_limit) instead of
    a division by zero or a NaN.
    """
    if not d > 0:
        zero = d - d
        return zero, zero, zero, zero, zero, zero, xix, xiy, xiz, ai + aj - d, zero
    inv_d = (half + half) / d  # not 1 / d: an int literal promotes float32 to float64
    nx = rx * inv_d
    ny = ry * inv_d
    nz = rz * inv_d
    delta = ai + aj - d
    # the spring part k_n delta is continuous at the contact start; only the dashpot jumps
    w = half + half
    f_old = k_n * delta_prev + fd_prev
    if delta_prev <= 0:
        w = contact_start_weight(delta, delta_prev, half)
        f_old = delta - delta
    c = dt * half / m12
    un = (ux * nx + uy * ny + uz * nz + c * (k_n * delta - f_old)) / (half + half + w * gamma_n * c)
    fd = -gamma_n * un
    fn = normal_force(delta, un, k_n, gamma_n)
    fa = k_n * delta + w * fd
    fx = fa * nx
    fy = fa * ny
    fz = fa * nz
    zero = delta - delta
    if k_t is None:
        return fx, fy, fz, zero, zero, zero, zero, zero, zero, delta, fd
    li = (d + ai - aj) * half
    lj = (d + aj - ai) * half  # not d - li: swapping i and j must swap l_i and l_j bit for bit
    tx, ty, tz = tangential_slip(nx, ny, nz, vx, vy, vz, wix, wiy, wiz, wjx, wjy, wjz, li, lj)
    # a contact that began inside this step has loaded its spring only since then
    h = dt if delta_prev > 0 else dt * (delta / (delta - delta_prev))
    gx, gy, gz, px, py, pz = tangential_spring_step(xix, xiy, xiz, nx, ny, nz, tx, ty, tz, h, k_t, fn, mu)
    # torque on i: (-l_i n) x F_t
    taux = -li * (ny * gz - nz * gy)
    tauy = -li * (nz * gx - nx * gz)
    tauz = -li * (nx * gy - ny * gx)
    return fx + gx, fy + gy, fz + gz, taux, tauy, tauz, px, py, pz, delta, fd


# ---- contact events inside a time step ------------------------------------------------------------
#
# Velocity Verlet applies the force F_k of step k as an impulse F_k dt centred on t_k. A contact that
# starts at t* inside (t_k, t_k+1) or ends at t_e inside (t_k, t_k+1) makes the force jump there (the
# dashpot force -gamma v_n is not zero at delta = 0), and the centred impulse is then wrong at first
# order in dt by an amount that depends on where in the step the jump fell: single head-on collisions
# scatter by ~2 |ln e_n| dt/t_c around e_n (4 % at e_n = 0.3, dt = t_c/50). Locating the event by
# linear interpolation of the overlap and correcting the impulse of the step next to it makes the
# error second order (docs/physics.md §1.5: e_n is then e_n to ~1e-4 at dt = t_c/50).


@numba.njit
def contact_start_weight(delta, delta_prev, half):
    """Weight of the first in-contact dashpot force so that its impulse covers only the contact time.

    The contact began a fraction f = delta/(delta - delta_prev) of the step before t_k+1; the centred
    impulse F dt stands for [t_k+1 - dt/2, t_k+1 + dt/2], so the right weight is 1/2 + f.
    """
    return half + delta / (delta - delta_prev)


@numba.njit
def contact_end_fraction(delta_prev, delta):
    """Fraction p of the step after the last in-contact step during which the contact still lasted.

    The last in-contact force F_k stood for [t_k - dt/2, t_k + dt/2] but the contact lasted until
    t_k + p dt with p = delta_prev/(delta_prev - delta): a jumping force owes F_k (p - 1/2) dt.
    """
    return delta_prev / (delta_prev - delta)


@numba.njit
def sphere_contact_end(rx, ry, rz, d, vx, vy, vz, wix, wiy, wiz, wjx, wjy, wjz, ai, aj, fd_prev, xix, xiy, xiz,
                       k_t, p, dt, half):
    """Force and torque on i that settle the impulse of a contact that ended inside this step.

    Only the parts of the force that jump at the end are settled: the dashpot (fd_prev, N, of the last
    in-contact step) and the tangential spring that is cut. p is the fraction of the step the contact
    still lasted (:func:`contact_end_weight` + 1/2). The spring kept loading at the mid-step slip v_t
    after the last in-contact step, so its missing impulse over [t_k + dt/2, t_k + p dt] is
    -k_t [xi (p - 1/2) + v_t dt (p^2 - 1/4)/2] dt; k_n delta goes to zero continuously.
    v, w: mid-step relative and angular velocities as in :func:`sphere_contact`.
    Returns (F_x, F_y, F_z, tau_x, tau_y, tau_z).
    """
    inv_d = (half + half) / d  # not 1 / d: an int literal promotes float32 to float64
    nx = rx * inv_d
    ny = ry * inv_d
    nz = rz * inv_d
    weight = p - half
    fn = fd_prev * weight
    fx = fn * nx
    fy = fn * ny
    fz = fn * nz
    zero = d - d
    if k_t is None:
        return fx, fy, fz, zero, zero, zero
    li = (d + ai - aj) * half
    lj = (d + aj - ai) * half  # not d - li: swapping i and j must swap l_i and l_j bit for bit
    tx, ty, tz = tangential_slip(nx, ny, nz, vx, vy, vz, wix, wiy, wiz, wjx, wjy, wjz, li, lj)
    px, py, pz = rotate_spring_into_plane(xix, xiy, xiz, nx, ny, nz)
    s = dt * (p * p - half * half) * half
    gx = -k_t * (px * weight + tx * s)
    gy = -k_t * (py * weight + ty * s)
    gz = -k_t * (pz * weight + tz * s)
    return (fx + gx, fy + gy, fz + gz, -li * (ny * gz - nz * gy), -li * (nz * gx - nx * gz),
            -li * (nx * gy - ny * gx))
