"""Ellipsoid contact geometry (Rubio-Largo et al. 2015, §2.1, §3.2; docs/physics.md §2.2-2.3), single source for every
backend.

Plain ``@numba.njit`` functions on scalars and tuples: no allocation, no Python objects, and no numeric
literal in any arithmetic (an int or float literal promotes float32 to float64 in Numba); constants are
built from the argument ``half`` = 0.5 in the working precision. A float32 call returns float32.

Conventions
-----------
- A particle has centre c, unit quaternion q (w, x, y, z; body -> space) and semi-axes (a, b, c_) along
  its body axes x, y, z. Prolate spheroids of the engine have the long axis a along body x, b = c_.
- Shape matrix M = R diag(a^-2, b^-2, c_^-2) R^T (inside: (p - c)^T M (p - c) <= 1) and its inverse
  M^-1 = R diag(a^2, b^2, c_^2) R^T, each as the 6 entries (m00, m01, m02, m11, m12, m22).
- Quadric of Rubio-Largo et al. (2015) Eqs. 3-8 in homogeneous row vectors X = (x, y, z, 1): A = T R S R^T T^T with
  S = diag(a^-2, b^-2, c_^-2, -W^2), i.e. A = [[M, -M c], [-c^T M, c^T M c - W^2]].
  (Rubio-Largo et al. (2015) print R_00 = 1 - q_2^2 - 2 q_3^2; the rotation matrix of a unit quaternion has
  1 - 2 q_2^2 - 2 q_3^2, used here.)
- Pair functions take r = c_B - c_A (minimum image) and return the normal n pointing from A to B and
  points relative to c_A.

What is computed, and how
-------------------------
- :func:`characteristic_quartic`: the coefficients of f(lambda) = det(lambda A + B) (Rubio-Largo et al. 2015,
  Eqs. 9-10), in closed form by a Schur complement (A centred at the origin, which leaves the roots unchanged).
- :func:`paper_disjoint`: the paper's test "Delta > 0 and P = 8ac - 3b^2 < 0 => disjoint" (Eq. 11).
  It is implemented as the paper states it and is NOT used by the engine: docs/physics.md §2.2 and
  tests/engine/test_ellipsoid_geometry.py show where it fails (Delta == 0 exactly for identical
  parallel ellipsoids, sign noise in float32 for near-parallel pairs, deep overlaps called disjoint).
- :func:`pw_contact`: the robust test, Perram & Wertheim (J. Comput. Phys. 58, 409 (1985)):
  F(lambda) = lambda (1 - lambda) r^T C(lambda)^-1 r with C = (1 - lambda) M_A^-1 + lambda M_B^-1, concave
  on [0, 1]; F_max < 1 overlap, = 1 touch, > 1 separated. sqrt(F_max) is the paper's shrink factor W_0
  (both ellipsoids scaled by W_0 about their centres just touch; docs/physics.md §2.2), and the positive
  double root of the scaled quartic is lambda_0 = lambda*/(1 - lambda*). Maximised by safeguarded Newton.
- :func:`ellipsoid_contact`: at W_0 the shrunk ellipsoids A_s, B_s touch at one point. There the two
  positive roots of det(lambda A_s + B_s) merge, so the eigenvectors V_2, V_3 of -A_s^-1 B_s coincide with
  the touching point and the paper's C = (V_2 + V_3)/2 (Eq. 22 context) is that point,
  C - c_A = (1 - lambda*) M_A^-1 x*, x* = C(lambda*)^-1 r. The paper's plane through V_0, V_1 and C is
  the common tangent plane (the tetrahedron is self-polar: the polar plane of C = V_2 = V_3 contains
  V_0, V_1), so its normal (Eq. 22) is n = x*/|x*| = grad of A_s at C. These closed forms are what the
  engine evaluates: they avoid the 4x4 eigen-decomposition, which is degenerate exactly at W_0 and,
  for parallel identical pairs, also in the negative double root -1. :func:`paper_tetrahedron` (numpy,
  float64, for tests and documentation) builds V_0..V_3 and Eq. 22 literally; the tests check that it
  converges to C and n of this module as W -> W_0.
- The overlap delta: the chord of the line through C along n (the limit of the line V_2 V_3) between
  the two original surfaces, x_1 on A and x_2 on B, delta = |x_1 x_2| (Rubio-Largo et al. 2015, §3.2), written without
  cancellation: t_A = (1 - F)/(beta_A + sqrt(beta_A^2 + alpha_A (1 - F))) with alpha_A = n^T M_A n,
  beta_A = (1 - lambda*)|x*| (and the same for B), delta = t_A - t_B. Negative delta is the gap of a
  separated pair along that line.
- Spheres (a = b = c_): lambda* = R_A/(R_A + R_B), C on the centre line, delta = R_A + R_B - d exactly.
- Speed (:func:`ellipsoid_contact_screened`, :func:`ellipsoid_pair_screened`): most pairs whose bounding
  spheres overlap are far from touching. Two exact screens prove such a pair disjoint before the full
  maximisation: the plane normal to the centre line separates the support functions
  (h_A(r_hat) + h_B(r_hat) < |r|), or a Newton iterate has F(lambda_k) > 1 (F at any lambda is a lower bound
  of F_max). Both are asked with a relative margin far above rounding, so a screened pair is one that the
  full evaluation calls separated; the only use of the gap of a separated pair (the contact-start weight
  at the next step) is served by evaluating it when that contact starts.
"""

import math

import numba

from engine.physics.rotation import quat_matrix


# ---- 3x3 symmetric matrices as 6-tuples (m00, m01, m02, m11, m12, m22) ------------------------------


@numba.njit
def sym_rotated(q0, q1, q2, q3, d0, d1, d2, half):
    """R diag(d0, d1, d2) R^T for the rotation R of quaternion q, as a symmetric 6-tuple."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = quat_matrix(q0, q1, q2, q3, half)
    return (r00 * r00 * d0 + r01 * r01 * d1 + r02 * r02 * d2,
            r00 * r10 * d0 + r01 * r11 * d1 + r02 * r12 * d2,
            r00 * r20 * d0 + r01 * r21 * d1 + r02 * r22 * d2,
            r10 * r10 * d0 + r11 * r11 * d1 + r12 * r12 * d2,
            r10 * r20 * d0 + r11 * r21 * d1 + r12 * r22 * d2,
            r20 * r20 * d0 + r21 * r21 * d1 + r22 * r22 * d2)


@numba.njit
def shape_matrix(q0, q1, q2, q3, a, b, c, half):
    """M = R diag(a^-2, b^-2, c^-2) R^T (1/m^2): (p - c)^T M (p - c) <= 1 inside."""
    one = half + half
    return sym_rotated(q0, q1, q2, q3, one / (a * a), one / (b * b), one / (c * c), half)


@numba.njit
def shape_matrix_inverse(q0, q1, q2, q3, a, b, c, half):
    """M^-1 = R diag(a^2, b^2, c^2) R^T (m^2)."""
    return sym_rotated(q0, q1, q2, q3, a * a, b * b, c * c, half)


@numba.njit
def sym_det(s00, s01, s02, s11, s12, s22):
    return (s00 * (s11 * s22 - s12 * s12) - s01 * (s01 * s22 - s12 * s02)
            + s02 * (s01 * s12 - s11 * s02))


@numba.njit
def sym_adj(s00, s01, s02, s11, s12, s22):
    """Adjugate (transposed cofactor matrix) of a symmetric matrix, symmetric 6-tuple."""
    return (s11 * s22 - s12 * s12, s02 * s12 - s01 * s22, s01 * s12 - s02 * s11,
            s00 * s22 - s02 * s02, s01 * s02 - s00 * s12, s00 * s11 - s01 * s01)


@numba.njit
def sym_mul_vec(s00, s01, s02, s11, s12, s22, x, y, z):
    return (s00 * x + s01 * y + s02 * z, s01 * x + s11 * y + s12 * z, s02 * x + s12 * y + s22 * z)


@numba.njit
def sym_quad(s00, s01, s02, s11, s12, s22, x, y, z):
    """x^T S x."""
    return (s00 * x * x + s11 * y * y + s22 * z * z
            + (s01 * x * y + s02 * x * z + s12 * y * z) + (s01 * x * y + s02 * x * z + s12 * y * z))


@numba.njit
def sym_trace_prod(a00, a01, a02, a11, a12, a22, b00, b01, b02, b11, b12, b22):
    """tr(A B) of two symmetric matrices."""
    return (a00 * b00 + a11 * b11 + a22 * b22
            + (a01 * b01 + a02 * b02 + a12 * b12) + (a01 * b01 + a02 * b02 + a12 * b12))


# ---- the quadric and the characteristic quartic (Rubio-Largo et al. 2015, Eqs. 3-11) -----------------


@numba.njit
def quadric_matrix(x, y, z, q0, q1, q2, q3, a, b, c, w, half):
    """A = T R S R^T T^T of Rubio-Largo et al. (2015) Eq. 7 with S = diag(a^-2, b^-2, c^-2, -W^2).

    Returns the 10 entries (A00, A01, A02, A03, A11, A12, A13, A22, A23, A33) of the symmetric 4x4
    matrix (row-vector convention X A X^T = 0, X = (x, y, z, 1)).
    """
    m00, m01, m02, m11, m12, m22 = shape_matrix(q0, q1, q2, q3, a, b, c, half)
    gx, gy, gz = sym_mul_vec(m00, m01, m02, m11, m12, m22, x, y, z)
    return (m00, m01, m02, -gx, m11, m12, -gy, m22, -gz, gx * x + gy * y + gz * z - w * w)


@numba.njit
def characteristic_quartic(ma00, ma01, ma02, ma11, ma12, ma22, mb00, mb01, mb02, mb11, mb12, mb22,
                           rx, ry, rz, w2, half):
    """Coefficients (c4, c3, c2, c1, c0) of f(lambda) = det(lambda A + B), highest power first.

    A: shape matrix M_A centred at the origin, B: M_B centred at r; both scaled by W (w2 = W^2; 1 for
    the particles themselves). With K = lambda M_A + M_B, g = M_B r and s = r^T M_B r the Schur
    complement gives f = (s - W^2 - W^2 lambda) det K - g^T adj(K) g. Then f(0) = -W^2 det M_B < 0 and
    c4 = -W^2 det M_A < 0 (docs/physics.md §2.2). Pass dimensionless lengths for float32 (the roots do
    not depend on the length unit).
    """
    k3 = sym_det(ma00, ma01, ma02, ma11, ma12, ma22)
    k0 = sym_det(mb00, mb01, mb02, mb11, mb12, mb22)
    aa = sym_adj(ma00, ma01, ma02, ma11, ma12, ma22)
    ab = sym_adj(mb00, mb01, mb02, mb11, mb12, mb22)
    k2 = sym_trace_prod(aa[0], aa[1], aa[2], aa[3], aa[4], aa[5], mb00, mb01, mb02, mb11, mb12, mb22)
    k1 = sym_trace_prod(ma00, ma01, ma02, ma11, ma12, ma22, ab[0], ab[1], ab[2], ab[3], ab[4], ab[5])
    ac = sym_adj(ma00 + mb00, ma01 + mb01, ma02 + mb02, ma11 + mb11, ma12 + mb12, ma22 + mb22)
    gx, gy, gz = sym_mul_vec(mb00, mb01, mb02, mb11, mb12, mb22, rx, ry, rz)
    s = gx * rx + gy * ry + gz * rz
    g_a = sym_quad(aa[0], aa[1], aa[2], aa[3], aa[4], aa[5], gx, gy, gz)
    g_b = sym_quad(ab[0], ab[1], ab[2], ab[3], ab[4], ab[5], gx, gy, gz)
    g_c = sym_quad(ac[0], ac[1], ac[2], ac[3], ac[4], ac[5], gx, gy, gz)
    g_mix = g_c - g_a - g_b
    sw = s - w2
    c4 = -w2 * k3
    c3 = sw * k3 - w2 * k2
    c2 = sw * k2 - w2 * k1 - g_a
    c1 = sw * k1 - w2 * k0 - g_mix
    c0 = sw * k0 - g_b
    return c4, c3, c2, c1, c0


@numba.njit
def quartic_discriminant(a, b, c, d, e, half):
    """(Delta, P) of a x^4 + b x^3 + c x^2 + d x + e (Rubio-Largo et al. 2015, Eq. 11 and P = 8ac - 3b^2).

    The coefficients are first divided by the largest |coefficient| (Delta is homogeneous of degree 6,
    P of degree 2, so the signs are unchanged and float32 does not overflow).
    """
    s = max(max(max(abs(a), abs(b)), max(abs(c), abs(d))), abs(e))
    if s > a - a:
        inv = (s / s) / s
        a = a * inv
        b = b * inv
        c = c * inv
        d = d * inv
        e = e * inv
    one = half + half
    two = one + one
    three = two + one
    four = two + two
    six = three + three
    eight = four + four
    n16 = eight + eight
    n18 = n16 + two
    n27 = n18 + eight + one
    n80 = n16 * (four + one)
    n128 = n16 * eight
    n144 = n16 * (eight + one)
    n192 = n16 * (eight + four)
    n256 = n16 * n16
    delta = (n256 * a * a * a * e * e * e - n192 * a * a * b * d * e * e - n128 * a * a * c * c * e * e
             + n144 * a * a * c * d * d * e - n27 * a * a * d * d * d * d + n144 * a * b * b * c * e * e
             - six * a * b * b * d * d * e - n80 * a * b * c * c * d * e + n18 * a * b * c * d * d * d
             + n16 * a * c * c * c * c * e - four * a * c * c * c * d * d - n27 * b * b * b * b * e * e
             + n18 * b * b * b * c * d * e - four * b * b * b * d * d * d - four * b * b * c * c * c * e
             + b * b * c * c * d * d)
    p = eight * a * c - three * b * b
    return delta, p


@numba.njit
def paper_quartic(rx, ry, rz, qa0, qa1, qa2, qa3, aa, ba, ca, qb0, qb1, qb2, qb3, ab, bb, cb, w2, half):
    """Quartic coefficients of a pair in lengths scaled by A's first semi-axis (r = c_B - c_A)."""
    one = half + half
    inv = one / aa
    ma = shape_matrix(qa0, qa1, qa2, qa3, one, ba * inv, ca * inv, half)
    mb = shape_matrix(qb0, qb1, qb2, qb3, ab * inv, bb * inv, cb * inv, half)
    return characteristic_quartic(ma[0], ma[1], ma[2], ma[3], ma[4], ma[5],
                                  mb[0], mb[1], mb[2], mb[3], mb[4], mb[5], rx * inv, ry * inv, rz * inv,
                                  w2, half)


@numba.njit
def paper_disjoint(rx, ry, rz, qa0, qa1, qa2, qa3, aa, ba, ca, qb0, qb1, qb2, qb3, ab, bb, cb, half):
    """The overlap test of Rubio-Largo et al. (2015) as stated: disjoint iff Delta > 0 and P < 0
    (UNSAFE, see module doc)."""
    c4, c3, c2, c1, c0 = paper_quartic(rx, ry, rz, qa0, qa1, qa2, qa3, aa, ba, ca,
                                       qb0, qb1, qb2, qb3, ab, bb, cb, half + half, half)
    delta, p = quartic_discriminant(c4, c3, c2, c1, c0, half)
    return delta > half - half and p < half - half


# ---- Perram-Wertheim contact function: robust overlap test and W_0 ----------------------------------


@numba.njit
def pw_contact(ia00, ia01, ia02, ia11, ia12, ia22, ib00, ib01, ib02, ib11, ib12, ib22, rx, ry, rz, tol, f_stop,
               half):
    """Maximise F(lambda) = lambda (1 - lambda) r^T C(lambda)^-1 r over [0, 1].

    ia, ib: M_A^-1 and M_B^-1 (m^2); r = c_B - c_A (m); tol: stop when the Newton step in lambda is
    below it (1e-13 in float64, 1e-6 in float32 are ample: F is flat at its maximum).
    f_stop > 0: give up as soon as an iterate has F(lambda_k) > f_stop. F at any lambda in (0, 1) is a
    lower bound of F_max, so with f_stop = 1 + margin that proves the pair disjoint (W_0 > 1) without
    the rest of the iteration (the screen of :func:`ellipsoid_contact_screened`); f_stop <= 0: never.
    Returns (F, lambda, x, stopped): (F_max, lambda*, x* = C(lambda*)^-1 r (1/m), False) after the
    full maximisation (F_max = W_0^2), or (F(lambda_k), lambda_k, x_k, True) when stopped early.
    """
    one = half + half
    two = one + one
    zero = half - half
    d00 = ib00 - ia00
    d01 = ib01 - ia01
    d02 = ib02 - ia02
    d11 = ib11 - ia11
    d12 = ib12 - ia12
    d22 = ib22 - ia22
    lo = zero
    hi = one
    lam = half
    xx = zero
    xy = zero
    xz = zero
    for _ in range(60):
        u = one - lam
        c00 = u * ia00 + lam * ib00
        c01 = u * ia01 + lam * ib01
        c02 = u * ia02 + lam * ib02
        c11 = u * ia11 + lam * ib11
        c12 = u * ia12 + lam * ib12
        c22 = u * ia22 + lam * ib22
        j00, j01, j02, j11, j12, j22 = sym_adj(c00, c01, c02, c11, c12, c22)
        det = c00 * j00 + c01 * j01 + c02 * j02
        inv_det = one / det
        xx, xy, xz = sym_mul_vec(j00, j01, j02, j11, j12, j22, rx * inv_det, ry * inv_det, rz * inv_det)
        rtx = rx * xx + ry * xy + rz * xz
        if f_stop > zero:
            fk = lam * u * rtx
            if fk > f_stop:
                return fk, lam, xx, xy, xz, True
        yx, yy, yz = sym_mul_vec(d00, d01, d02, d11, d12, d22, xx, xy, xz)
        xdx = xx * yx + xy * yy + xz * yz
        ycy = sym_quad(j00, j01, j02, j11, j12, j22, yx, yy, yz) * inv_det
        lu = lam * u
        g1 = (u - lam) * rtx - lu * xdx
        g2 = two * (lu * ycy - rtx - (u - lam) * xdx)
        if g1 == zero:
            break
        if g1 > zero:
            lo = lam
        else:
            hi = lam
        if g2 < zero:
            new = lam - g1 / g2
        else:
            new = half * (lo + hi)
        if not (new > lo and new < hi):
            new = half * (lo + hi)
        step = new - lam
        lam = new
        if abs(step) <= tol:
            break
    # x* and F at the final lambda
    u = one - lam
    c00 = u * ia00 + lam * ib00
    c01 = u * ia01 + lam * ib01
    c02 = u * ia02 + lam * ib02
    c11 = u * ia11 + lam * ib11
    c12 = u * ia12 + lam * ib12
    c22 = u * ia22 + lam * ib22
    j00, j01, j02, j11, j12, j22 = sym_adj(c00, c01, c02, c11, c12, c22)
    inv_det = one / (c00 * j00 + c01 * j01 + c02 * j02)
    xx, xy, xz = sym_mul_vec(j00, j01, j02, j11, j12, j22, rx * inv_det, ry * inv_det, rz * inv_det)
    f = lam * u * (rx * xx + ry * xy + rz * xz)
    return f, lam, xx, xy, xz, False


@numba.njit
def ellipsoid_overlap_pw(rx, ry, rz, qa0, qa1, qa2, qa3, aa, ba, ca, qb0, qb1, qb2, qb3, ab, bb, cb, tol, half):
    """Robust overlap test: (overlapping, W_0). Overlapping iff W_0 < 1 (Perram-Wertheim)."""
    ia = shape_matrix_inverse(qa0, qa1, qa2, qa3, aa, ba, ca, half)
    ib = shape_matrix_inverse(qb0, qb1, qb2, qb3, ab, bb, cb, half)
    f, lam, xx, xy, xz, _ = pw_contact(ia[0], ia[1], ia[2], ia[3], ia[4], ia[5],
                                       ib[0], ib[1], ib[2], ib[3], ib[4], ib[5], rx, ry, rz, tol, half - half,
                                       half)
    return f < half + half, math.sqrt(f)


@numba.njit
def _chord_end(alpha, beta, gap):
    """Distance from C along the outward direction to the original surface: gap / (beta + sqrt(...)).

    gap = 1 - F (positive when overlapping); beta > 0 the directional derivative term; the root of
    alpha t^2 + 2 beta t - gap = 0 nearest to 0, written without cancellation.
    """
    disc = beta * beta + alpha * gap
    if disc < gap - gap:
        disc = gap - gap
    return gap / (beta + math.sqrt(disc))


@numba.njit
def _contact_from_pw(f, lam, xx, xy, xz, ia0, ia1, ia2, ia3, ia4, ia5, qa0, qa1, qa2, qa3, aa, ba, ca,
                     qb0, qb1, qb2, qb3, ab, bb, cb, half):
    """n, C and delta from the Perram-Wertheim maximum (F, lambda*, x*) (see :func:`ellipsoid_contact`)."""
    one = half + half
    u = one - lam
    xn = math.sqrt(xx * xx + xy * xy + xz * xz)
    inv = one / xn
    nx = xx * inv
    ny = xy * inv
    nz = xz * inv
    cx, cy, cz = sym_mul_vec(ia0, ia1, ia2, ia3, ia4, ia5, u * xx, u * xy, u * xz)
    ma = shape_matrix(qa0, qa1, qa2, qa3, aa, ba, ca, half)
    mb = shape_matrix(qb0, qb1, qb2, qb3, ab, bb, cb, half)
    alpha_a = sym_quad(ma[0], ma[1], ma[2], ma[3], ma[4], ma[5], nx, ny, nz)
    alpha_b = sym_quad(mb[0], mb[1], mb[2], mb[3], mb[4], mb[5], nx, ny, nz)
    gap = one - f
    delta = _chord_end(alpha_a, u * xn, gap) + _chord_end(alpha_b, lam * xn, gap)
    return f, lam, delta, nx, ny, nz, cx, cy, cz


@numba.njit
def ellipsoid_contact(rx, ry, rz, qa0, qa1, qa2, qa3, aa, ba, ca, qb0, qb1, qb2, qb3, ab, bb, cb, tol, half):
    """Contact geometry of ellipsoids A (at the origin) and B (at r = c_B - c_A, minimum image).

    Returns (F, lambda*, delta, n_x, n_y, n_z, C_x, C_y, C_z):
    F = W_0^2 (< 1 overlapping), lambda* the Perram-Wertheim maximiser, delta the overlap along the
    normal through C (m; negative: gap of a separated pair), n the unit normal from A to B, C the
    touching point of the ellipsoids shrunk by W_0 (the contact point of Rubio-Largo et al. 2015), relative to c_A (m).
    """
    ia = shape_matrix_inverse(qa0, qa1, qa2, qa3, aa, ba, ca, half)
    ib = shape_matrix_inverse(qb0, qb1, qb2, qb3, ab, bb, cb, half)
    f, lam, xx, xy, xz, _ = pw_contact(ia[0], ia[1], ia[2], ia[3], ia[4], ia[5],
                                       ib[0], ib[1], ib[2], ib[3], ib[4], ib[5], rx, ry, rz, tol, half - half,
                                       half)
    return _contact_from_pw(f, lam, xx, xy, xz, ia[0], ia[1], ia[2], ia[3], ia[4], ia[5],
                            qa0, qa1, qa2, qa3, aa, ba, ca, qb0, qb1, qb2, qb3, ab, bb, cb, half)


# ---- exact screens: disjointness proven before (or during) the Perram-Wertheim maximisation ---------


@numba.njit
def plane_separated(ia00, ia01, ia02, ia11, ia12, ia22, ib00, ib01, ib02, ib11, ib12, ib22, rx, ry, rz,
                    margin, half):
    """The plane normal to the centre line separates A and B (exact disjointness, a sufficient test).

    Support function of an ellipsoid with M^-1 = R diag(a^2, b^2, c^2) R^T: h(u) = sqrt(u^T M^-1 u) for a
    unit u, so A lies in r.p <= |r| h_A(r_hat) and B in r.p >= |r|^2 - |r| h_B(r_hat) (p relative to c_A).
    Disjoint when h_A + h_B < |r|; in squared lengths sqrt(r^T M_A^-1 r) + sqrt(r^T M_B^-1 r) < |r|^2,
    asked here with a relative margin, (...)(1 + margin) < |r|^2, so that rounding can never call a pair
    separated that the full Perram-Wertheim evaluation would call overlapping.
    """
    one = half + half
    qa = sym_quad(ia00, ia01, ia02, ia11, ia12, ia22, rx, ry, rz)
    qb = sym_quad(ib00, ib01, ib02, ib11, ib12, ib22, rx, ry, rz)
    d2 = rx * rx + ry * ry + rz * rz
    return (math.sqrt(qa) + math.sqrt(qb)) * (one + margin) < d2


@numba.njit
def ellipsoid_contact_screened(rx, ry, rz, qa0, qa1, qa2, qa3, aa, ba, ca, qb0, qb1, qb2, qb3, ab, bb, cb, tol,
                               margin, half):
    """:func:`ellipsoid_contact` behind two exact screens: (screened, F, lambda*, delta, n, C).

    screened = True: the pair is proven disjoint (by more than ``margin`` in the relative measures below)
    and nothing else is computed (the other entries are zero): (i) :func:`plane_separated`, (ii) the
    Perram-Wertheim iteration stopped at the first iterate with F(lambda_k) > 1 + margin (F(lambda_k) <=
    F_max = W_0^2). Otherwise the entries are those of :func:`ellipsoid_contact`, bit for bit (the same
    arithmetic; the screens only add work). ``margin`` (1e-9 in float64, 1e-3 in float32;
    engine.shapes.spheroid.cpu_backend.PW_SCREEN) is far above the rounding of F, so a screened pair always
    has delta < 0 in ellipsoid_contact (tests/engine/test_ellipsoid_screen.py); margin < 0 disables both.
    """
    one = half + half
    zero = half - half
    ia = shape_matrix_inverse(qa0, qa1, qa2, qa3, aa, ba, ca, half)
    ib = shape_matrix_inverse(qb0, qb1, qb2, qb3, ab, bb, cb, half)
    f_stop = zero
    if margin >= zero:
        if plane_separated(ia[0], ia[1], ia[2], ia[3], ia[4], ia[5], ib[0], ib[1], ib[2], ib[3], ib[4], ib[5],
                           rx, ry, rz, margin, half):
            return True, zero, zero, zero, zero, zero, zero, zero, zero, zero
        f_stop = one + margin
    f, lam, xx, xy, xz, stopped = pw_contact(ia[0], ia[1], ia[2], ia[3], ia[4], ia[5],
                                             ib[0], ib[1], ib[2], ib[3], ib[4], ib[5], rx, ry, rz, tol, f_stop,
                                             half)
    if stopped:
        return True, zero, zero, zero, zero, zero, zero, zero, zero, zero
    g = _contact_from_pw(f, lam, xx, xy, xz, ia[0], ia[1], ia[2], ia[3], ia[4], ia[5],
                         qa0, qa1, qa2, qa3, aa, ba, ca, qb0, qb1, qb2, qb3, ab, bb, cb, half)
    return False, g[0], g[1], g[2], g[3], g[4], g[5], g[6], g[7], g[8]


# ---- contact force (Rubio-Largo et al. 2015, Eqs. 23-24) ---------------------------------------------


@numba.njit
def ellipsoid_normal_force(delta, un, delta_prev, fd_prev, m12, k_n, gamma_n, dt, half):
    """Magnitude (N, repulsive > 0) of F = k_n delta - gamma_n v_n along the contact normal.

    The same law and numerics as engine.physics.contact.sphere_contact with k_t = None (so xi = 1
    reproduces smooth spheres): un the predicted end-of-step normal velocity of the contact point
    (negative approaching), the pair's own last force replaced implicitly, the first in-contact
    dashpot weighted by the fraction of the step the contact lasted (contact_start_weight).
    Returns (F, F_dashpot).
    """
    one = half + half
    w = one
    f_old = k_n * delta_prev + fd_prev
    if delta_prev <= half - half:
        w = half + delta / (delta - delta_prev)
        f_old = delta - delta
    c = dt * half / m12
    u = (un + c * (k_n * delta - f_old)) / (one + w * gamma_n * c)
    fd = -gamma_n * u
    return k_n * delta + w * fd, fd


# ---- the tetrahedron of Rubio-Largo et al. (2015), literally (numpy, float64; reference for tests and
# documentation) ----


def paper_tetrahedron(c_a, q_a, axes_a, c_b, q_b, axes_b, w):
    """V_0..V_3 (eigenvectors of -A_s^-1 B_s, dehomogenised), C = (V_2 + V_3)/2 and n of Eq. 22.

    A_s, B_s are the quadrics scaled by w (Rubio-Largo et al. 2015, Eq. 2; w slightly below W_0 keeps the positive
    roots distinct). V_2, V_3 belong to the two positive roots of det(lambda A_s + B_s), V_0, V_1 to the
    others; n is oriented from A to B. Not used by the engine (see the module docstring).
    """
    import numpy as np

    def quad(c, q, axes):
        h = 0.5
        e = np.array(quadric_matrix(c[0], c[1], c[2], q[0], q[1], q[2], q[3], axes[0], axes[1], axes[2], w, h))
        m = np.empty((4, 4))
        idx = [(0, 0), (0, 1), (0, 2), (0, 3), (1, 1), (1, 2), (1, 3), (2, 2), (2, 3), (3, 3)]
        for v, (i, j) in zip(e, idx):
            m[i, j] = m[j, i] = v
        return m

    a4 = quad(c_a, q_a, axes_a)
    b4 = quad(c_b, q_b, axes_b)
    mu, vec = np.linalg.eig(-np.linalg.solve(a4, b4))
    # eigenvalue mu of -A^-1 B <=> det(mu A + B) = 0 (the paper's lambda)
    order = np.argsort(mu.real)
    mu = mu[order]
    vec = vec[:, order]
    pts = [np.real(vec[:3, k] / vec[3, k]) for k in range(4)]
    v2, v3 = pts[2], pts[3]
    c = 0.5 * (v2 + v3)
    n = np.cross(pts[0] - c, pts[1] - c)
    n /= np.linalg.norm(n)
    if np.dot(n, np.asarray(c_b) - np.asarray(c_a)) < 0:
        n = -n
    return mu.real, pts, c, n


#: status (last entry) of :func:`ellipsoid_pair_screened`
PAIR_DONE, PAIR_SCREENED, PAIR_NEEDS_PREV = 0, 1, 2


@numba.njit
def ellipsoid_pair_geometry_screened(rx, ry, rz, qa0, qa1, qa2, qa3, aa, ba, ca, qb0, qb1, qb2, qb3, ab, bb,
                                     cb, ux, uy, uz, wax, way, waz, wbx, wby, wbz, delta_prev, fd_prev, m12, k_n,
                                     gamma_n, dt, tol, margin, screened_gap, half):
    """:func:`ellipsoid_pair_screened` that also returns the contact geometry: (F_A (3), tau_A (3), tau_B (3),
    delta, F_dashpot, status, n (3), C (3)); n the unit normal from A to B, C the contact point relative to c_A
    (m; B's lever arm is C - r). Zero n and C when the pair was screened or needs the previous gap. The rough
    spheroid law (engine/physics/rough_spheroid.py) adds its tangential force at C."""
    zero = half - half
    one = half + half
    m = margin if not (delta_prev > zero) else -one  # a contact that may end needs its gap: no screen
    screened, f, lam, delta, nx, ny, nz, cx, cy, cz = ellipsoid_contact_screened(
        rx, ry, rz, qa0, qa1, qa2, qa3, aa, ba, ca, qb0, qb1, qb2, qb3, ab, bb, cb, tol, m, half)
    if screened:
        return (zero, zero, zero, zero, zero, zero, zero, zero, zero, screened_gap, zero, PAIR_SCREENED,
                zero, zero, zero, zero, zero, zero)
    if delta > zero:
        if margin >= zero and delta_prev == screened_gap:
            return (zero, zero, zero, zero, zero, zero, zero, zero, zero, delta, zero, PAIR_NEEDS_PREV,
                    zero, zero, zero, zero, zero, zero)
        # velocity of B's surface point at C relative to A's: u + w_B x (C - r) - w_A x C
        bx = cx - rx
        by = cy - ry
        bz = cz - rz
        vx = ux + (wby * bz - wbz * by) - (way * cz - waz * cy)
        vy = uy + (wbz * bx - wbx * bz) - (waz * cx - wax * cz)
        vz = uz + (wbx * by - wby * bx) - (wax * cy - way * cx)
        vn = vx * nx + vy * ny + vz * nz
        fm, fd = ellipsoid_normal_force(delta, vn, delta_prev, fd_prev, m12, k_n, gamma_n, dt, half)
    elif delta_prev > zero:
        p = delta_prev / (delta_prev - delta)
        fm = fd_prev * (p - half)
        fd = zero
    else:
        return zero, zero, zero, zero, zero, zero, zero, zero, zero, delta, zero, PAIR_DONE, nx, ny, nz, cx, cy, cz
    fax = -fm * nx
    fay = -fm * ny
    faz = -fm * nz
    bx = cx - rx
    by = cy - ry
    bz = cz - rz
    return (fax, fay, faz,
            cy * faz - cz * fay, cz * fax - cx * faz, cx * fay - cy * fax,
            -(by * faz - bz * fay), -(bz * fax - bx * faz), -(bx * fay - by * fax),
            delta, fd, PAIR_DONE, nx, ny, nz, cx, cy, cz)


@numba.njit
def ellipsoid_pair_screened(rx, ry, rz, qa0, qa1, qa2, qa3, aa, ba, ca, qb0, qb1, qb2, qb3, ab, bb, cb,
                            ux, uy, uz, wax, way, waz, wbx, wby, wbz, delta_prev, fd_prev, m12, k_n, gamma_n, dt,
                            tol, margin, screened_gap, half):
    """Frictionless contact of ellipsoids A and B (Rubio-Largo et al. 2015, Eqs. 23-24); r = c_B - c_A (minimum image).

    u = u_B - u_A (predicted end-of-step translational velocities, m/s), w_A, w_B predicted space-frame
    angular velocities (rad/s); delta_prev, fd_prev: overlap (m) and dashpot force (N) of the pair at the
    previous step; m12 the reduced mass (kg). The force on B is F n with F = k_n delta - gamma_n v_n
    (:func:`ellipsoid_normal_force`), v_n the normal velocity of B's surface point at the contact point C
    relative to A's; A gets -F n. Both torques act about the centres with the common point C, so
    F_A = -F_B and tau_A + tau_B + c_A x F_A + c_B x F_B = 0 (angular momentum) hold to rounding.
    A contact that ended inside this step (delta <= 0 < delta_prev) settles the dashpot impulse it owes
    (as engine.physics.contact.sphere_contact_end with k_t = None).

    Screening (speed; results unchanged): a pair that was not in contact at the previous step
    (delta_prev <= 0) goes through :func:`ellipsoid_contact_screened` with ``margin``; when it is proven
    disjoint its gap is not computed and ``screened_gap`` (a value no gap can take: -inf) is returned as
    delta, with status PAIR_SCREENED. The gap of a separated pair is read at one place only, the
    contact-start weight of :func:`ellipsoid_normal_force` at the next step; so when a contact starts
    (delta > 0) after a screened step (delta_prev == screened_gap) nothing is returned but status
    PAIR_NEEDS_PREV: the caller evaluates the previous step's gap, ``ellipsoid_contact(previous state)[2]``
    (the value this function returned there before screening existed, bit for bit), and calls again with
    it. margin < 0: no screening and no PAIR_NEEDS_PREV (the reference path).

    Returns (F_A (3), tau_A (3), tau_B (3), delta, F_dashpot, status); delta < 0 is the gap of a
    separated pair.
    """
    g = ellipsoid_pair_geometry_screened(rx, ry, rz, qa0, qa1, qa2, qa3, aa, ba, ca, qb0, qb1, qb2, qb3, ab, bb, cb,
                                         ux, uy, uz, wax, way, waz, wbx, wby, wbz, delta_prev, fd_prev, m12, k_n,
                                         gamma_n, dt, tol, margin, screened_gap, half)
    return g[0], g[1], g[2], g[3], g[4], g[5], g[6], g[7], g[8], g[9], g[10], g[11]


@numba.njit
def ellipsoid_pair(rx, ry, rz, qa0, qa1, qa2, qa3, aa, ba, ca, qb0, qb1, qb2, qb3, ab, bb, cb,
                   ux, uy, uz, wax, way, waz, wbx, wby, wbz, delta_prev, fd_prev, m12, k_n, gamma_n, dt, tol,
                   half):
    """:func:`ellipsoid_pair_screened` without screening (the reference path): (F_A, tau_A, tau_B, delta,
    F_dashpot)."""
    g = ellipsoid_pair_screened(rx, ry, rz, qa0, qa1, qa2, qa3, aa, ba, ca, qb0, qb1, qb2, qb3, ab, bb, cb,
                                ux, uy, uz, wax, way, waz, wbx, wby, wbz, delta_prev, fd_prev, m12, k_n, gamma_n,
                                dt, tol, -(half + half), half - half, half)
    return g[0], g[1], g[2], g[3], g[4], g[5], g[6], g[7], g[8], g[9], g[10]
