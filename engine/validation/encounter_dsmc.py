"""DSMC of smooth prolate spheroids whose collision rule is the whole DEM encounter (docs/physics.md §6.4).

The instantaneous DSMC (engine.validation.hcs_ellipsoids.dsmc_ratio, docs/physics.md §6.4) draws every
contact from uncorrelated pre-collision states (molecular chaos, isotropic orientations) and applies one
impulse. Here the SAME sampling feeds three collision rules, chosen by ``rule``:

- ``RULE_IMPULSE`` (0): one instantaneous impulse at the sampled contact with the restitution the DEM
  dashpot gives at that geometry, e_eff(D) (docs/physics.md §2.4; hcs_ellipsoids.e_effective). This is
  dsmc_ratio(dem=True) in Numba.
- ``RULE_SOFT`` (1): the real DEM pair, integrated through the whole encounter with the engine's own njit
  functions, in the order of engine/shapes/spheroid/cpu_backend.py (kick_drift_ell, compute_forces_ell):
  leap-frog kick/drift of v and of the space-frame angular momentum L, Fincham's body-frame quaternion
  step (engine.physics.rotation.fincham_quat_step_body), predicted end-of-step v and w for the dashpot,
  and engine.physics.ellipsoid.ellipsoid_pair (Perram-Wertheim contact, k_n delta - gamma_n v_n with the
  engine's contact-start weight and contact-end settlement), gamma_n = gamma_n_coef sqrt(m12), dt = t_c/50.
- ``RULE_HARD`` (2): hard bodies, one impulse with e_eff(D) at every contact of the encounter, repeat
  contacts found in exact free flight. The stiff limit of RULE_SOFT (zero contact duration, the same
  repeat contacts).
- ``RULE_FIRST`` (3): a diagnostic between RULE_IMPULSE and RULE_HARD: first contacts only (the backward
  check below), one impulse with e_eff(D), repeat contacts NOT resolved (the pair may be left overlapping or
  approaching). It separates the effect of dropping correlated contacts from that of resolving them.

Encounters (rules 1 and 2). A sampled contact state (touching, approaching) is a state of the Boltzmann
gas only if the pair reached it from free flight: the state is run BACKWARD in exact free flight and is
rejected when the pair overlaps somewhere in its past (it is then a repeat contact of an encounter that
started earlier, whose velocities are correlated, not drawn from f x f; the forward integration of the
first contact produces it). The rate of first contacts is the flux of f x f through the contact surface
restricted to those states (the standard incoming-state form of the collision integral). Then the pair
runs FORWARD until its bounding spheres (radius a) are apart AND the centre distance grows: the centres
then move on straight lines with r.v > 0, so |r| only grows and the pair can never touch again in this
encounter (rigorous end criterion, no time cut-off).

Exact free flight. Frictionless torques have no component along the symmetry axis u (the contact normal of a
surface of revolution meets its axis), and the DSMC spins start with w.u = 0, so L stays perpendicular to u
and a free body turns about a fixed axis at constant rate: q(t) = exp(t (0, w)/2) q(0) exactly. While no
force acts, the pair is advanced in one exact jump by a time that provably ends before any contact: at the
Perram-Wertheim scale factor W0 = sqrt(F_AB) > 1 the scaled bodies W0 E = E + (W0 - 1) E contain
E + ball((W0 - 1) b), so the surfaces are at least 2 (W0 - 1) b apart, and they approach at most at
|v_B - v_A| + (|w_A| + |w_B|) a. The DEM integrates free flight with the same step as contacts (Fincham,
error ~ (w dt)^3 per step, w dt ~ 1e-4 here); everything with a force acting uses the engine step.

Units: SI (m, kg, s) in the encounter functions (the DEM constants of the Rubio-Largo et al. (2015) scene); the DSMC gas
velocities are m/s and spins rad/s. The gas is rescaled after each sweep to a fixed translational
temperature (T_tr = T_ref, J), as in dsmc_ratio; the rescaling keeps T_tr/T_rot and fixes the contact
softness (overlap / b) at that temperature.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import prange

from engine.numba_support.jitcache import fast_loads  # before any cache=True kernel: keys the disk cache by source
from engine.physics.ellipsoid import ellipsoid_contact, ellipsoid_pair
from engine.physics.integrate import kick
from engine.physics.rotation import (body_omega, fincham_quat_step_body, quat_matrix, quat_mul, quat_normalize,
                                     space_omega)

RULE_IMPULSE, RULE_SOFT, RULE_HARD, RULE_FIRST = 0, 1, 2, 3
RULES = {"impulse": RULE_IMPULSE, "soft": RULE_SOFT, "hard": RULE_HARD, "first": RULE_FIRST}
#: encounter status
ENC_OK, ENC_REJECTED, ENC_CAPPED = 0, 1, 2
#: Perram-Wertheim Newton tolerance of the float64 engine (engine.shapes.spheroid.cpu_backend.PW_TOL)
PW_TOL = 1e-15
HALF = 0.5
#: first (and smallest) step of the backward first-contact check, in units of dt: the pair separates
#: locally from its touching point backward in time, so an earlier overlap cannot start within it
BACK_STEP = 0.02
#: iteration cap of a hard encounter: a hard inelastic pair can collapse into an endless chatter of ever
#: weaker contacts (inelastic collapse of two bodies); such encounters are stopped here and counted as capped
HARD_MAX_ITER = 5000


# ---- exact free flight and the pair geometry -----------------------------------------------------------


@numba.njit(cache=True)
def free_flight(x, v, q, L, inv_i, t):
    """Torque-free motion of one body over t seconds (t < 0: backward), in place.

    x += v t; q turned about the constant space-frame w = R I^-1 R^T L by |w| t (exact when L is
    perpendicular to the symmetry axis, see the module docstring)."""
    for k in range(3):
        x[k] += v[k] * t
    wx, wy, wz = space_omega(q[0], q[1], q[2], q[3], L[0], L[1], L[2], inv_i[0], inv_i[1], inv_i[2], HALF)
    w = math.sqrt(wx * wx + wy * wy + wz * wz)
    if w > 0.0:
        s = math.sin(0.5 * w * t) / w
        c = math.cos(0.5 * w * t)
        q0, q1, q2, q3 = quat_mul(c, wx * s, wy * s, wz * s, q[0], q[1], q[2], q[3])
        q[0], q[1], q[2], q[3] = quat_normalize(q0, q1, q2, q3)


@numba.njit(cache=True)
def pair_contact(x, q, a, b):
    """engine.physics.ellipsoid.ellipsoid_contact of body 0 (A) and body 1 (B): (F, lambda, delta, n, C)."""
    return ellipsoid_contact(x[1, 0] - x[0, 0], x[1, 1] - x[0, 1], x[1, 2] - x[0, 2],
                             q[0, 0], q[0, 1], q[0, 2], q[0, 3], a, b, b,
                             q[1, 0], q[1, 1], q[1, 2], q[1, 3], a, b, b, PW_TOL, HALF)


@numba.njit(cache=True)
def _omega_mag(q, L, inv_i, k):
    wx, wy, wz = space_omega(q[k, 0], q[k, 1], q[k, 2], q[k, 3], L[k, 0], L[k, 1], L[k, 2],
                             inv_i[0], inv_i[1], inv_i[2], HALF)
    return math.sqrt(wx * wx + wy * wy + wz * wz)


@numba.njit(cache=True)
def approach_speed_bound(x, v, q, L, inv_i, a):
    """Upper bound (m/s) of the rate at which the surfaces approach: |v_B - v_A| + (|w_A| + |w_B|) a."""
    dv = math.sqrt((v[1, 0] - v[0, 0]) ** 2 + (v[1, 1] - v[0, 1]) ** 2 + (v[1, 2] - v[0, 2]) ** 2)
    return dv + (_omega_mag(q, L, inv_i, 0) + _omega_mag(q, L, inv_i, 1)) * a


@numba.njit(cache=True)
def safe_time(f, x, v, q, L, inv_i, a, b):
    """A time (s) within which free flight cannot bring the pair into contact: 2 (W0 - 1) b / (max approach
    speed), W0 = sqrt(F_AB) (module docstring). 0 when F_AB <= 1."""
    if f <= 1.0:
        return 0.0
    speed = approach_speed_bound(x, v, q, L, inv_i, a)
    if speed <= 0.0:
        return 1e300
    return 2.0 * (math.sqrt(f) - 1.0) * b / speed


@numba.njit(cache=True)
def _apart_for_good(x, v, a):
    """Bounding spheres (radius a) apart and the centre distance growing: no further contact in free flight."""
    rx = x[1, 0] - x[0, 0]
    ry = x[1, 1] - x[0, 1]
    rz = x[1, 2] - x[0, 2]
    rv = rx * (v[1, 0] - v[0, 0]) + ry * (v[1, 1] - v[0, 1]) + rz * (v[1, 2] - v[0, 2])
    return rx * rx + ry * ry + rz * rz > 4.0 * a * a and rv > 0.0


@numba.njit(cache=True)
def zeta_of(e_n):
    le = math.log(e_n)
    return -le / math.sqrt(math.pi ** 2 + le * le)


@numba.njit(cache=True)
def e_eff(zeta, D):
    """Restitution of the linear dashpot (gamma from m12) at coupling D, frozen geometry (docs/physics.md §2.4;
    the same formula as engine.validation.hcs_ellipsoids.e_effective)."""
    if zeta <= 0.0:
        return 1.0
    return math.exp(-math.pi * zeta * math.sqrt(1 + D) / math.sqrt(1 - zeta * zeta * (1 + D)))


# ---- the encounter integrators ---------------------------------------------------------------------------


@numba.njit(cache=True)
def first_contact_clear(x, v, q, L, inv_i, a, b, t_min, max_iter):
    """Run the touching state backward in exact free flight: (True, iterations) when the pair was never
    overlapping before (a first contact), (False, iterations) when it was. Inputs are not modified."""
    xw = x.copy()
    qw = q.copy()
    step = t_min
    for it in range(max_iter):
        free_flight(xw[0], v[0], qw[0], L[0], inv_i, -step)
        free_flight(xw[1], v[1], qw[1], L[1], inv_i, -step)
        f = pair_contact(xw, qw, a, b)[0]
        if f < 1.0 - 1e-12:
            return False, it + 1
        # backward in time the distance grows when r.v < 0: the criterion of _apart_for_good, reversed
        rx = xw[1, 0] - xw[0, 0]
        ry = xw[1, 1] - xw[0, 1]
        rz = xw[1, 2] - xw[0, 2]
        rv = rx * (v[1, 0] - v[0, 0]) + ry * (v[1, 1] - v[0, 1]) + rz * (v[1, 2] - v[0, 2])
        if rx * rx + ry * ry + rz * rz > 4.0 * a * a and rv < 0.0:
            return True, it + 1
        step = max(0.99 * safe_time(f, xw, v, qw, L, inv_i, a, b), t_min)
    return True, max_iter


@numba.njit(cache=True)
def soft_encounter(x, v, q, L, m, inv_i, a, b, k_n, gamma_n, dt, max_steps, skip):
    """Integrate the DEM pair (engine functions, engine step order) from a contact-free start until it is
    apart for good; x, v, q, L (2 x ...) are updated in place (synchronous on entry and exit).

    skip=True jumps over force-free stretches in exact free flight (module docstring); skip=False steps
    every dt like the DEM. Returns (status, contacts, steps, largest overlap / b)."""
    m12 = 0.5 * m
    inv_m = 1.0 / m
    h = HALF * dt
    vp = np.zeros((2, 3))
    wp = np.zeros((2, 3))
    f_a = np.zeros(3)
    tau = np.zeros((2, 3))
    delta_prev = pair_contact(x, q, a, b)[2]
    fd_prev = 0.0
    forced = False
    contacts = 0
    worst = 0.0
    for s in range(max_steps):
        if not forced:
            if _apart_for_good(x, v, a):
                return ENC_OK, contacts, s, worst / b
            # the gap along the normal line (delta_prev < 0) is at least the surface distance, which bounds the
            # safe time from above: skip the Perram-Wertheim call when even that could not give 2 dt
            if skip and -delta_prev > 2.0 * dt * approach_speed_bound(x, v, q, L, inv_i, a):
                c = pair_contact(x, q, a, b)
                ts = safe_time(c[0], x, v, q, L, inv_i, a, b)
                if ts > 2.0 * dt:
                    free_flight(x[0], v[0], q[0], L[0], inv_i, 0.999 * ts)
                    free_flight(x[1], v[1], q[1], L[1], inv_i, 0.999 * ts)
                    delta_prev = pair_contact(x, q, a, b)[2]
                    if _apart_for_good(x, v, a):
                        return ENC_OK, contacts, s, worst / b
        # kick_drift_ell for the two bodies (force on B = -force on A)
        for k in range(2):
            sg = 1.0 if k == 0 else -1.0
            for d in range(3):
                fk = sg * f_a[d]
                vv = kick(v[k, d], fk, inv_m, dt)
                v[k, d] = vv
                vp[k, d] = kick(vv, fk, inv_m, h)
                x[k, d] = x[k, d] + vv * dt
            lx = L[k, 0] + tau[k, 0] * dt
            ly = L[k, 1] + tau[k, 1] * dt
            lz = L[k, 2] + tau[k, 2] * dt
            L[k, 0] = lx
            L[k, 1] = ly
            L[k, 2] = lz
            q0, q1, q2, q3 = fincham_quat_step_body(q[k, 0], q[k, 1], q[k, 2], q[k, 3],
                                                    lx - tau[k, 0] * h, ly - tau[k, 1] * h, lz - tau[k, 2] * h,
                                                    lx, ly, lz, inv_i[0], inv_i[1], inv_i[2], dt, HALF)
            q[k, 0] = q0
            q[k, 1] = q1
            q[k, 2] = q2
            q[k, 3] = q3
            wx, wy, wz = space_omega(q0, q1, q2, q3, lx + tau[k, 0] * h, ly + tau[k, 1] * h, lz + tau[k, 2] * h,
                                     inv_i[0], inv_i[1], inv_i[2], HALF)
            wp[k, 0] = wx
            wp[k, 1] = wy
            wp[k, 2] = wz
        # compute_forces_ell for the pair (A = body 0)
        g = ellipsoid_pair(x[1, 0] - x[0, 0], x[1, 1] - x[0, 1], x[1, 2] - x[0, 2],
                           q[0, 0], q[0, 1], q[0, 2], q[0, 3], a, b, b, q[1, 0], q[1, 1], q[1, 2], q[1, 3], a, b, b,
                           vp[1, 0] - vp[0, 0], vp[1, 1] - vp[0, 1], vp[1, 2] - vp[0, 2],
                           wp[0, 0], wp[0, 1], wp[0, 2], wp[1, 0], wp[1, 1], wp[1, 2],
                           delta_prev, fd_prev, m12, k_n, gamma_n, dt, PW_TOL, HALF)
        f_a[0] = g[0]
        f_a[1] = g[1]
        f_a[2] = g[2]
        tau[0, 0] = g[3]
        tau[0, 1] = g[4]
        tau[0, 2] = g[5]
        tau[1, 0] = g[6]
        tau[1, 1] = g[7]
        tau[1, 2] = g[8]
        delta = g[9]
        if delta > 0.0 and not (delta_prev > 0.0):
            contacts += 1
        if delta > worst:
            worst = delta
        delta_prev = delta
        fd_prev = g[10]
        forced = False
        for d in range(9):
            if g[d] != 0.0:
                forced = True
    # closing half kick (cpu.half_kick): synchronous velocities
    for k in range(2):
        sg = 1.0 if k == 0 else -1.0
        for d in range(3):
            v[k, d] = kick(v[k, d], sg * f_a[d], inv_m, h)
            L[k, d] = L[k, d] + tau[k, d] * h
    return ENC_CAPPED, contacts, max_steps, worst / b


@numba.njit(cache=True)
def hard_impulse(x, v, q, L, m, inv_i, a, b, zeta):
    """Instantaneous frictionless impulse at the touching state (engine contact point C and normal n),
    restitution e_eff(D); returns g_n (m/s, < 0 approaching) before it (no impulse when g_n >= 0)."""
    c = pair_contact(x, q, a, b)
    nx, ny, nz, cx, cy, cz = c[3], c[4], c[5], c[6], c[7], c[8]
    bx = cx - (x[1, 0] - x[0, 0])
    by = cy - (x[1, 1] - x[0, 1])
    bz = cz - (x[1, 2] - x[0, 2])
    wa = space_omega(q[0, 0], q[0, 1], q[0, 2], q[0, 3], L[0, 0], L[0, 1], L[0, 2], inv_i[0], inv_i[1], inv_i[2],
                     HALF)
    wb = space_omega(q[1, 0], q[1, 1], q[1, 2], q[1, 3], L[1, 0], L[1, 1], L[1, 2], inv_i[0], inv_i[1], inv_i[2],
                     HALF)
    gx = v[1, 0] + (wb[1] * bz - wb[2] * by) - v[0, 0] - (wa[1] * cz - wa[2] * cy)
    gy = v[1, 1] + (wb[2] * bx - wb[0] * bz) - v[0, 1] - (wa[2] * cx - wa[0] * cz)
    gz = v[1, 2] + (wb[0] * by - wb[1] * bx) - v[0, 2] - (wa[0] * cy - wa[1] * cx)
    gn = gx * nx + gy * ny + gz * nz
    if gn >= 0.0:
        return gn
    # lever arms r x n (perpendicular to the axis, so I^-1 acts as 1/I_perp)
    lax, lay, laz = cy * nz - cz * ny, cz * nx - cx * nz, cx * ny - cy * nx
    lbx, lby, lbz = by * nz - bz * ny, bz * nx - bx * nz, bx * ny - by * nx
    ip_inv = inv_i[1]
    invmeff = 2.0 / m + (lax * lax + lay * lay + laz * laz + lbx * lbx + lby * lby + lbz * lbz) * ip_inv
    e = e_eff(zeta, invmeff * 0.5 * m - 1.0)
    j = -(1.0 + e) * gn / invmeff
    v[1, 0] += j * nx / m
    v[1, 1] += j * ny / m
    v[1, 2] += j * nz / m
    v[0, 0] -= j * nx / m
    v[0, 1] -= j * ny / m
    v[0, 2] -= j * nz / m
    L[1, 0] += j * lbx
    L[1, 1] += j * lby
    L[1, 2] += j * lbz
    L[0, 0] -= j * lax
    L[0, 1] -= j * lay
    L[0, 2] -= j * laz
    return gn


@numba.njit(cache=True)
def hard_encounter(x, v, q, L, m, inv_i, a, b, zeta, t_min, max_iter):
    """Hard-body encounter from a touching, approaching state: impulses with e_eff(D) at every contact,
    repeat contacts located in exact free flight (bisection of F_AB = 1 to ~1e-13 of t_min). In place;
    returns (status, contacts, iterations)."""
    hard_impulse(x, v, q, L, m, inv_i, a, b, zeta)
    contacts = 1
    x0 = x.copy()
    q0 = q.copy()
    for it in range(max_iter):
        if _apart_for_good(x, v, a):
            return ENC_OK, contacts, it
        f = pair_contact(x, q, a, b)[0]
        ts = safe_time(f, x, v, q, L, inv_i, a, b)
        if ts > t_min:
            free_flight(x[0], v[0], q[0], L[0], inv_i, 0.99 * ts)
            free_flight(x[1], v[1], q[1], L[1], inv_i, 0.99 * ts)
            continue
        x0[:] = x
        q0[:] = q
        free_flight(x[0], v[0], q[0], L[0], inv_i, t_min)
        free_flight(x[1], v[1], q[1], L[1], inv_i, t_min)
        if pair_contact(x, q, a, b)[0] >= 1.0:
            continue
        lo, hi = 0.0, t_min        # F(lo) >= 1 > F(hi)
        for _ in range(45):
            mid = 0.5 * (lo + hi)
            x[:] = x0
            q[:] = q0
            free_flight(x[0], v[0], q[0], L[0], inv_i, mid)
            free_flight(x[1], v[1], q[1], L[1], inv_i, mid)
            if pair_contact(x, q, a, b)[0] >= 1.0:
                lo = mid
            else:
                hi = mid
        x[:] = x0
        q[:] = q0
        free_flight(x[0], v[0], q[0], L[0], inv_i, lo)
        free_flight(x[1], v[1], q[1], L[1], inv_i, lo)
        if hard_impulse(x, v, q, L, m, inv_i, a, b, zeta) < 0.0:
            contacts += 1
    return ENC_CAPPED, contacts, max_iter


# ---- DSMC sampling (the geometry of dsmc_ratio, in Numba) -----------------------------------------------


@numba.njit(cache=True)
def _seed(s):
    np.random.seed(s)


@numba.njit(cache=True)
def random_quat():
    q0, q1, q2, q3 = np.random.normal(), np.random.normal(), np.random.normal(), np.random.normal()
    return quat_normalize(q0, q1, q2, q3)


@numba.njit(cache=True)
def _cross(p, r):
    return np.array([p[1] * r[2] - p[2] * r[1], p[2] * r[0] - p[0] * r[2], p[0] * r[1] - p[1] * r[0]])


@numba.njit(cache=True)
def _dot(p, r):
    # written out: numba's ``p @ r`` calls BLAS through scipy, which the light install leaves out
    return p[0] * r[0] + p[1] * r[1] + p[2] * r[2]


@numba.njit(cache=True)
def _tangent_curvature(u0, u1, u2, n0, n1, n2, t10, t11, t12, t20, t21, t22, a, b):
    """Support point x(n) of a spheroid (axis u, semi-axes a along u, b) at the outward unit normal n and the
    tangential entries (t1 H t1, t2 H t2, t1 H t2) of its curvature-radius tensor
    H = (b^2 1 + c2 u u^T)/h - (M^-1 n)(M^-1 n)^T/h^3, c2 = a^2 - b^2, h = sqrt(n^T M^-1 n)
    (hcs_ellipsoids._support, written on scalars)."""
    c2 = a * a - b * b
    un = u0 * n0 + u1 * n1 + u2 * n2
    hh = math.sqrt(b * b + c2 * un * un)
    x0 = (b * b * n0 + c2 * un * u0) / hh
    x1 = (b * b * n1 + c2 * un * u1) / hh
    x2 = (b * b * n2 + c2 * un * u2) / hh
    ut1 = u0 * t10 + u1 * t11 + u2 * t12
    ut2 = u0 * t20 + u1 * t21 + u2 * t22
    k = c2 / hh - c2 * c2 * un * un / hh ** 3      # (M^-1 n).t = c2 un (u.t) since n.t = 0
    return x0, x1, x2, b * b / hh + k * ut1 * ut1, b * b / hh + k * ut2 * ut2, k * ut1 * ut2


@numba.njit(cache=True)
def sample_sweep(v, w2, a, b, wmax):
    """One DSMC sweep of candidate pairs (a random pairing of all particles) as in dsmc_ratio: isotropic
    orientations (quaternions, long axis = body x), isotropic normal n, excluded-surface weight
    det(t^T (H_A + H_B) t), normal velocity g_n of the contact points; accepted with probability
    w max(0, -g_n) / (wmax max(-g_n)). Returns, for the accepted pairs: I, J, quaternions (k, 2, 4), n,
    support points x_A(n) and x_B(n) of A and of B (B touches with -x_B(n)), and a uniform number."""
    n = v.shape[0]
    k = n // 2
    p = np.random.permutation(n)
    Q = np.empty((k, 2, 4))
    NV = np.empty((k, 3))
    XA = np.empty((k, 3))
    XB = np.empty((k, 3))
    W = np.empty(k)
    G = np.empty(k)
    for c in range(k):
        i, j = p[2 * c], p[2 * c + 1]
        for s in range(2):
            q0, q1, q2, q3 = random_quat()
            Q[c, s, 0] = q0
            Q[c, s, 1] = q1
            Q[c, s, 2] = q2
            Q[c, s, 3] = q3
        n0, n1, n2 = np.random.normal(), np.random.normal(), np.random.normal()
        nn = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
        n0 /= nn
        n1 /= nn
        n2 /= nn
        if abs(n0) < 0.9:        # t = e_x; t1 = n x t
            t10, t11, t12 = 0.0, n2, -n1
        else:                    # t = e_y
            t10, t11, t12 = -n2, 0.0, n0
        tn = math.sqrt(t10 * t10 + t11 * t11 + t12 * t12)
        t10 /= tn
        t11 /= tn
        t12 /= tn
        t20, t21, t22 = n1 * t12 - n2 * t11, n2 * t10 - n0 * t12, n0 * t11 - n1 * t10
        h11 = 0.0
        h22 = 0.0
        h12 = 0.0
        gn = (v[j, 0] - v[i, 0]) * n0 + (v[j, 1] - v[i, 1]) * n1 + (v[j, 2] - v[i, 2]) * n2
        for s in range(2):
            r = quat_matrix(Q[c, s, 0], Q[c, s, 1], Q[c, s, 2], Q[c, s, 3], HALF)
            x0, x1, x2, a11, a22, a12 = _tangent_curvature(r[0], r[3], r[6], n0, n1, n2, t10, t11, t12,
                                                           t20, t21, t22, a, b)
            h11 += a11
            h22 += a22
            h12 += a12
            pi = i if s == 0 else j
            # spin w = w2_0 e_y + w2_1 e_z; its contact-point velocity along n: w.(x x n) for A at +x_A,
            # and -w.(x_B x n) for B at -x_B: g_n = (v_B - v_A).n - w_B.(x_B x n) - w_A.(x_A x n)
            wx = w2[pi, 0] * r[1] + w2[pi, 1] * r[2]
            wy = w2[pi, 0] * r[4] + w2[pi, 1] * r[5]
            wz = w2[pi, 0] * r[7] + w2[pi, 1] * r[8]
            gn -= wx * (x1 * n2 - x2 * n1) + wy * (x2 * n0 - x0 * n2) + wz * (x0 * n1 - x1 * n0)
            if s == 0:
                XA[c, 0], XA[c, 1], XA[c, 2] = x0, x1, x2
            else:
                XB[c, 0], XB[c, 1], XB[c, 2] = x0, x1, x2
        W[c] = h11 * h22 - h12 * h12
        G[c] = gn
        NV[c, 0], NV[c, 1], NV[c, 2] = n0, n1, n2
    gmax = 0.0
    for c in range(k):
        if -G[c] > gmax:
            gmax = -G[c]
    acc = np.zeros(k, np.bool_)
    for c in range(k):
        acc[c] = np.random.random() * wmax * gmax < W[c] * max(0.0, -G[c])
    idx = np.nonzero(acc)[0]
    m = idx.shape[0]
    I = np.empty(m, np.int64)
    J = np.empty(m, np.int64)
    U = np.empty(m)
    for c in range(m):
        I[c] = p[2 * idx[c]]
        J[c] = p[2 * idx[c] + 1]
        U[c] = np.random.random()
    return I, J, Q[idx], NV[idx], XA[idx], XB[idx], U


@numba.njit(cache=True)
def _body_state(vi, vj, w2i, w2j, qp, xa, xb, i_perp):
    """Pair state at the sampled contact: A at the origin, B at x_A(n) + x_B(n); L = I_perp w."""
    x = np.zeros((2, 3))
    v = np.empty((2, 3))
    L = np.empty((2, 3))
    q = qp.copy()
    for d in range(3):
        x[1, d] = xa[d] + xb[d]
        v[0, d] = vi[d]
        v[1, d] = vj[d]
    for k in range(2):
        r = quat_matrix(q[k, 0], q[k, 1], q[k, 2], q[k, 3], HALF)
        w = w2i if k == 0 else w2j
        L[k, 0] = i_perp * (w[0] * r[1] + w[1] * r[2])
        L[k, 1] = i_perp * (w[0] * r[4] + w[1] * r[5])
        L[k, 2] = i_perp * (w[0] * r[7] + w[1] * r[8])
    return x, v, q, L


@numba.njit(parallel=True, cache=True)
def resolve_batch(rule, v, w2, I, J, Q, XA, XB, U, m, inv_i, a, b, k_n, gamma_n, dt, zeta, max_steps, skip,
                  out_v, out_w2, out_stat):
    """Resolve the accepted pairs of a sweep (independent encounters, prange) with RULE_SOFT, RULE_HARD or
    RULE_FIRST.

    out_v (k, 2, 3), out_w2 (k, 2, 2): post-encounter velocities and body-frame spins (w_y, w_z);
    out_stat (k, 5): status, contacts, steps/iterations, backward iterations, |w_x| / |w| after (should be
    ~0: frictionless torques have no axial part) or, for RULE_SOFT, the largest overlap / b."""
    i_perp = 1.0 / inv_i[1]
    for c in prange(I.shape[0]):
        i, j = I[c], J[c]
        x, vv, q, L = _body_state(v[i], v[j], w2[i], w2[j], Q[c], XA[c], XB[c], i_perp)
        clear, nback = first_contact_clear(x, vv, q, L, inv_i, a, b, BACK_STEP * dt, 100000)
        out_stat[c, 3] = nback
        if not clear:
            out_stat[c, 0] = ENC_REJECTED
            continue
        if rule == RULE_SOFT:
            # the DEM contact starts at a uniform phase inside a step: start U dt before the touch
            free_flight(x[0], vv[0], q[0], L[0], inv_i, -U[c] * dt)
            free_flight(x[1], vv[1], q[1], L[1], inv_i, -U[c] * dt)
            st, nc, ns, ov = soft_encounter(x, vv, q, L, m, inv_i, a, b, k_n, gamma_n, dt, max_steps, skip)
            out_stat[c, 4] = ov
        elif rule == RULE_HARD:
            st, nc, ns = hard_encounter(x, vv, q, L, m, inv_i, a, b, zeta, 1e-3 * dt, HARD_MAX_ITER)
            out_stat[c, 4] = 0.0
        else:
            hard_impulse(x, vv, q, L, m, inv_i, a, b, zeta)
            st, nc, ns = ENC_OK, 1, 0
            out_stat[c, 4] = 0.0
        out_stat[c, 0] = st
        out_stat[c, 1] = nc
        out_stat[c, 2] = ns
        for k in range(2):
            wb = body_omega(q[k, 0], q[k, 1], q[k, 2], q[k, 3], L[k, 0], L[k, 1], L[k, 2],
                            inv_i[0], inv_i[1], inv_i[2], HALF)
            out_w2[c, k, 0] = wb[1]
            out_w2[c, k, 1] = wb[2]
            for d in range(3):
                out_v[c, k, d] = vv[k, d]


@numba.njit(cache=True)
def impulse_batch(v, w2, I, J, Q, NV, XA, XB, m, i_perp, zeta):
    """dsmc_ratio's instantaneous rule (e_eff(D)) on the accepted pairs, in place."""
    for c in range(I.shape[0]):
        i, j = I[c], J[c]
        nn = NV[c]
        ra = quat_matrix(Q[c, 0, 0], Q[c, 0, 1], Q[c, 0, 2], Q[c, 0, 3], HALF)
        rb = quat_matrix(Q[c, 1, 0], Q[c, 1, 1], Q[c, 1, 2], Q[c, 1, 3], HALF)
        ya, za = np.array([ra[1], ra[4], ra[7]]), np.array([ra[2], ra[5], ra[8]])
        yb, zb = np.array([rb[1], rb[4], rb[7]]), np.array([rb[2], rb[5], rb[8]])
        oa = w2[i, 0] * ya + w2[i, 1] * za
        ob = w2[j, 0] * yb + w2[j, 1] * zb
        xa, xb = XA[c], XB[c]
        la = _cross(xa, nn)
        lb = _cross(-xb, nn)
        g = (v[j] + _cross(ob, -xb)) - (v[i] + _cross(oa, xa))
        gn = g[0] * nn[0] + g[1] * nn[1] + g[2] * nn[2]
        invmeff = 2.0 / m + (_dot(la, la) + _dot(lb, lb)) / i_perp
        e = e_eff(zeta, invmeff * 0.5 * m - 1.0)
        jimp = -(1.0 + e) * gn / invmeff
        v[j] += jimp * nn / m
        v[i] -= jimp * nn / m
        doa = -jimp * la / i_perp
        dob = jimp * lb / i_perp
        w2[i, 0] += _dot(doa, ya)
        w2[i, 1] += _dot(doa, za)
        w2[j, 0] += _dot(dob, yb)
        w2[j, 1] += _dot(dob, zb)


# ---- the DSMC ----------------------------------------------------------------------------------------------

#: DEM late-window mean T_tr/T_tr(0) of the xi = 2.5, e = 0.9 cooling runs (one-off study
#: bench/ellipsoid_cooling_seeds.py, in git history; its series.json: 0.364 at N = 4096 and 0.367 at N = 16384): the
#: DSMC gas is held at this fraction of the DEM's initial temperature, so the contacts are as soft as in the DEM's late
#: window.
LATE_TEMPERATURE_FRACTION = 0.36


def weight_bound(a: float, b: float) -> float:
    """Upper bound of the pair weight det(t^T (H_A + H_B) t): for 2 x 2 positive matrices det(X) <= (tr X / 2)^2,
    and the tangential trace of H (r_1 + r_2) of a prolate spheroid is largest at its equator, b + a^2/b
    (checked on a grid of (u.n)^2 for xi up to 5), so det <= (b + a^2/b)^2, reached by two equators
    crossed. dsmc_ratio uses max((a^2/b + b)^2, (2 a^2/b)^2), a looser bound: the accepted distribution is
    the same, this one wastes 3x fewer candidates at xi = 2.5 (m^2)."""
    return (b + a * a / b) ** 2


def dem_constants(xi: float, e_n: float, kn_factor: float = 1.0) -> dict:
    """Contact constants of the Rubio-Largo et al. (2015) DEM scene (hcs_ellipsoids.full_spec,
    engine.setup.params.derive), SI: semi-axes a, b (m), mass m (kg), I_perp (kg m^2), k_n (N/m), pair gamma_n (kg/s),
    dt = t_c/50 (s), T0 = m v_rms^2/3 (J). kn_factor scales k_n (and dt with t_c, gamma_n with sqrt(k_n): same e_n)."""
    from engine.setup.params import derive
    from engine.validation.hcs_ellipsoids import full_spec

    spec = full_spec(xi, e_n, 0)
    if kn_factor != 1.0:
        spec = spec.model_copy(update={"stiffness": spec.stiffness * kn_factor})
    p = derive(spec)
    a, b, _ = p.semi_axes
    return {"a": a, "b": b, "m": p.mass, "inertia": tuple(p.inertia), "k_n": p.k_n,
            "gamma_n": p.gamma_n_coef * math.sqrt(p.m12), "dt": p.dt, "t_c": p.contact_time,
            "T0": p.mass * spec.velocity_rms ** 2 / 3.0, "m12": p.m12}


def run_dsmc(xi: float, e_n: float, rule: str = "soft", n: int = 20000, coll_per_particle: float = 60.0,
             seed: int = 1, temp_fraction: float = LATE_TEMPERATURE_FRACTION, kn_factor: float = 1.0,
             skip: bool = True, rescale: bool = True, max_steps: int = 400000) -> dict:
    """T_tr/T_rot of the smooth-spheroid HCS by DSMC with the collision rule ``rule`` (module docstring).

    Starts at T_rot = T_tr = temp_fraction * T0 (the DEM scene's T0) and, with rescale=True, rescales v and w
    after each sweep to that T_tr (as dsmc_ratio). Collisions = accepted encounters (first contacts; for
    'impulse' every accepted contact). Returns the late mean of T_tr/T_rot (collisions per particle >
    coll_per_particle/2), its profile, the share of sampled contacts rejected as not-first, contacts per
    encounter, the energy loss per collision in units of T_tr, and diagnostics. Units: SI.
    """
    import time

    code = RULES[rule]
    c = dem_constants(xi, e_n, kn_factor)
    a, b, m = c["a"], c["b"], c["m"]
    inertia = np.array(c["inertia"], float)
    inv_i = 1.0 / inertia
    ip = inertia[1]
    zeta = zeta_of(e_n) if e_n < 1.0 else 0.0
    t_ref = temp_fraction * c["T0"]
    rng = np.random.default_rng(seed)
    _seed(seed)
    v = rng.normal(size=(n, 3))
    v -= v.mean(0)
    v *= math.sqrt(t_ref / (m * np.mean(np.sum(v * v, 1)) / 3))
    w2 = rng.normal(size=(n, 2)) * math.sqrt(t_ref / ip)
    wmax = weight_bound(a, b)
    ncoll, sampled, rejected, capped = 0, 0, 0, 0
    contacts_hist = {}
    loss_sum, loss_n = 0.0, 0
    worst, steps_sum, back_sum = 0.0, 0.0, 0.0
    hist = []
    t0 = time.time()
    e_start = 0.5 * m * np.sum(v * v) + 0.5 * ip * np.sum(w2 * w2)
    while ncoll < coll_per_particle * n / 2:
        I, J, Q, NV, XA, XB, U = sample_sweep(v, w2, a, b, wmax)
        if len(I) == 0:
            continue
        sampled += len(I)
        ttr_before = m * np.mean(np.sum(v * v, 1)) / 3
        e_before = 0.5 * m * np.sum(v * v) + 0.5 * ip * np.sum(w2 * w2)
        if code == RULE_IMPULSE:
            impulse_batch(v, w2, I, J, Q, NV, XA, XB, m, ip, zeta)
            done = len(I)
            contacts_hist[1] = contacts_hist.get(1, 0) + done
        else:
            k = len(I)
            out_v = np.zeros((k, 2, 3))
            out_w2 = np.zeros((k, 2, 2))
            stat = np.zeros((k, 5))
            resolve_batch(code, v, w2, I, J, Q, XA, XB, U, m, inv_i, a, b, c["k_n"], c["gamma_n"], c["dt"], zeta,
                          max_steps, skip, out_v, out_w2, stat)
            ok = stat[:, 0] != ENC_REJECTED
            rejected += int(np.sum(~ok))
            capped += int(np.sum(stat[:, 0] == ENC_CAPPED))
            v[I[ok]] = out_v[ok, 0]
            v[J[ok]] = out_v[ok, 1]
            w2[I[ok]] = out_w2[ok, 0]
            w2[J[ok]] = out_w2[ok, 1]
            done = int(np.sum(ok))
            for nc, cnt in zip(*np.unique(stat[ok, 1].astype(int), return_counts=True)):
                contacts_hist[int(nc)] = contacts_hist.get(int(nc), 0) + int(cnt)
            if done:
                steps_sum += float(np.sum(stat[ok, 2]))
                if code == RULE_SOFT:
                    worst = max(worst, float(np.max(stat[ok, 4])))
            back_sum += float(np.sum(stat[:, 3]))
        e_after = 0.5 * m * np.sum(v * v) + 0.5 * ip * np.sum(w2 * w2)
        if done:
            loss_sum += (e_before - e_after) / ttr_before
            loss_n += done
        ncoll += done
        ttr = m * np.mean(np.sum(v * v, 1)) / 3
        trot = ip * np.mean(np.sum(w2 * w2, 1)) / 2
        hist.append((ncoll / (n / 2), ttr / trot, ttr, trot))
        if rescale:
            s = math.sqrt(t_ref / ttr)
            v *= s
            w2 *= s
    h = np.array(hist)
    late = h[h[:, 0] > coll_per_particle / 2, 1]
    encounters = sum(contacts_hist.values())
    contacts = sum(k * v_ for k, v_ in contacts_hist.items())
    e_end = 0.5 * m * np.sum(v * v) + 0.5 * ip * np.sum(w2 * w2)
    return {"xi": xi, "e_n": e_n, "rule": rule, "seed": seed, "n": n, "coll_per_particle": coll_per_particle,
            "ratio": float(late.mean()) if len(late) else float("nan"),
            "profile": h[:, :2].tolist(), "sampled": sampled, "rejected_share": rejected / max(sampled, 1),
            "encounters": encounters, "contacts_per_encounter": {str(k): v_ for k, v_ in sorted(contacts_hist.items())},
            "later_contact_share": (contacts - encounters) / max(contacts, 1),
            "multi_contact_share": sum(v_ for k, v_ in contacts_hist.items() if k >= 2) / max(encounters, 1),
            "loss_per_collision_over_T": loss_sum / max(loss_n, 1), "capped": capped,
            "max_overlap_over_b": worst, "mean_steps": steps_sum / max(encounters, 1),
            "mean_backward_iterations": back_sum / max(sampled, 1),
            "energy_change_relative": float(e_end / e_start - 1) if not rescale else None,
            "t_ref": t_ref, "temp_fraction": temp_fraction, "kn_factor": kn_factor,
            "softness_delta_over_b": math.sqrt(2 * t_ref / m) * math.sqrt(c["m12"] / c["k_n"]) / b,
            "constants": c, "wall_s": time.time() - t0}


fast_loads(globals())  # their disk-cache loads skip numba's target refresh (engine/numba_support/jitcache.py)
