"""Independent extended-precision oracle for the ellipsoid contact geometry, and its own checks.

The engine (engine/physics/ellipsoid.py) maximises the Perram-Wertheim function over the *inverse*
shape matrices by safeguarded Newton in the working precision. This oracle solves the primal problem
instead, in numpy longdouble (80-bit x87 on x86: 64-bit mantissa, eps = 1.1e-19), vectorised:

- the points where a scaled copy of A and a scaled copy of B are tangent with opposite normals form
  the curve p(t) = argmin (1 - t) rho_A(p)^2 + t rho_B(p)^2, i.e. ((1 - t) M_A + t M_B) p =
  (1 - t) M_A c_A + t M_B c_B, t in (0, 1), with rho_K(p)^2 = (p - c_K)^T M_K (p - c_K);
- along it rho_A^2 rises and rho_B^2 falls monotonically, so the touching point of the equally scaled
  pair is the root of g(t) = rho_A^2 - rho_B^2, found by 90 bisections; W_0 = rho_A(p*);
- normal n = M_A (p* - c_A)/|...|; delta = chord of the line p* + s n between the original surfaces
  (each end by the stable quadratic formula).

The tests below check the oracle itself against closed forms (docs/physics.md §2.6) and against a
direct constrained minimisation of max(rho_A^2, rho_B^2) with scipy (a third method; the reference extra).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

LD = np.longdouble


def quat_to_matrix_ld(q):
    """(K,4) quaternions (normalised here in longdouble) -> (K,3,3) rotation matrices (body -> space)."""
    q = np.asarray(q, dtype=LD)
    q = q / np.sqrt(np.sum(q * q, axis=-1, keepdims=True))
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    one, two = LD(1), LD(2)
    return np.stack([
        np.stack([one - two * (y * y + z * z), two * (x * y - w * z), two * (x * z + w * y)], -1),
        np.stack([two * (x * y + w * z), one - two * (x * x + z * z), two * (y * z - w * x)], -1),
        np.stack([two * (x * z - w * y), two * (y * z + w * x), one - two * (x * x + y * y)], -1)], -2)


def shape_ld(q, axes):
    """(K,3,3) M = R diag(axes^-2) R^T in longdouble."""
    r = quat_to_matrix_ld(q)
    d = LD(1) / np.asarray(axes, dtype=LD) ** 2
    return np.einsum("kij,kj,klj->kil", r, d, r)


def _solve3(m, b):
    """Batched 3x3 solve by the adjugate (numpy.linalg has no longdouble)."""
    a = m
    c00 = a[:, 1, 1] * a[:, 2, 2] - a[:, 1, 2] * a[:, 2, 1]
    c01 = a[:, 0, 2] * a[:, 2, 1] - a[:, 0, 1] * a[:, 2, 2]
    c02 = a[:, 0, 1] * a[:, 1, 2] - a[:, 0, 2] * a[:, 1, 1]
    c10 = a[:, 1, 2] * a[:, 2, 0] - a[:, 1, 0] * a[:, 2, 2]
    c11 = a[:, 0, 0] * a[:, 2, 2] - a[:, 0, 2] * a[:, 2, 0]
    c12 = a[:, 0, 2] * a[:, 1, 0] - a[:, 0, 0] * a[:, 1, 2]
    c20 = a[:, 1, 0] * a[:, 2, 1] - a[:, 1, 1] * a[:, 2, 0]
    c21 = a[:, 0, 1] * a[:, 2, 0] - a[:, 0, 0] * a[:, 2, 1]
    c22 = a[:, 0, 0] * a[:, 1, 1] - a[:, 0, 1] * a[:, 1, 0]
    det = a[:, 0, 0] * c00 + a[:, 0, 1] * c10 + a[:, 0, 2] * c20
    adj = np.stack([np.stack([c00, c01, c02], -1), np.stack([c10, c11, c12], -1),
                    np.stack([c20, c21, c22], -1)], -2)
    return np.einsum("kij,kj->ki", adj, b) / det[:, None]


def _quad(m, x):
    return np.einsum("ki,kij,kj->k", x, m, x)


def oracle_touch(ma, mb, r, iters=90):
    """Touching point p* (relative to c_A = 0), W_0^2 and t of the equally scaled pair."""
    r = np.asarray(r, dtype=LD)
    k = r.shape[0]
    lo = np.zeros(k, dtype=LD)
    hi = np.ones(k, dtype=LD)
    for _ in range(iters):
        t = (lo + hi) / 2
        p = _solve3((1 - t)[:, None, None] * ma + t[:, None, None] * mb,
                    t[:, None] * np.einsum("kij,kj->ki", mb, r))
        g = _quad(ma, p) - _quad(mb, p - r)
        neg = g < 0
        lo = np.where(neg, t, lo)
        hi = np.where(neg, hi, t)
    t = (lo + hi) / 2
    p = _solve3((1 - t)[:, None, None] * ma + t[:, None, None] * mb,
                t[:, None] * np.einsum("kij,kj->ki", mb, r))
    return p, _quad(ma, p), t


def _exit(m, p0, n, cen):
    """Root s >= of (p0 + s n - cen)^T M (...) = 1 nearest to 0 for a start point inside the scaled copy."""
    alpha = _quad(m, n)
    beta = np.einsum("ki,kij,kj->k", n, m, p0 - cen)
    gap = 1 - _quad(m, p0 - cen)
    # alpha s^2 + 2 beta s - gap = 0 ; |beta| > 0 along the normal
    sq = np.sqrt(beta * beta + alpha * gap)
    return np.where(beta >= 0, gap / (beta + sq), -gap / (-beta + sq))


def oracle_contact(qa, axes_a, qb, axes_b, r):
    """Oracle (W0^2, delta, n, C) for K pairs: A at the origin, B at r; all results longdouble."""
    ma = shape_ld(qa, axes_a)
    mb = shape_ld(qb, axes_b)
    r = np.asarray(r, dtype=LD)
    p, w2, _ = oracle_touch(ma, mb, r)
    n = np.einsum("kij,kj->ki", ma, p)
    n = n / np.sqrt(np.sum(n * n, axis=1, keepdims=True))
    s_a = _exit(ma, p, n, np.zeros_like(r))      # along +n to the surface of A
    s_b = _exit(mb, p, -n, r)                      # along -n to the surface of B
    delta = s_a + s_b
    return w2, delta, n, p


def contact_distance(qa, axes_a, qb, axes_b, direction):
    """Centre distance at which the pair touches along the unit direction (W_0 is linear in |r|)."""
    _, w2, _ = oracle_touch(shape_ld(qa, axes_a), shape_ld(qb, axes_b), direction)
    return 1 / np.sqrt(w2)


def random_quaternions(rng, k):
    q = rng.normal(size=(k, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def random_overlapping(k, seed, xi_range=(1.0, 4.0), h_range=(1e-6, 1e-2)):
    """K random overlapping pairs, b = 1: quaternions, semi-axes, r, target depth h and oracle results.

    10 % are spheres, 30 % identical spheroids, the rest independent xi; the centre distance is the
    oracle contact distance along a random direction minus h (log-uniform in h_range, units of b).
    """
    rng = np.random.default_rng(seed)
    xa = rng.uniform(*xi_range, size=k)
    xb = rng.uniform(*xi_range, size=k)
    kind = rng.uniform(size=k)
    xa[kind < 0.1] = 1.0
    xb[kind < 0.4] = xa[kind < 0.4]
    axes_a = np.stack([xa, np.ones(k), np.ones(k)], 1)
    axes_b = np.stack([xb, np.ones(k), np.ones(k)], 1)
    qa = random_quaternions(rng, k)
    qb = random_quaternions(rng, k)
    u = rng.normal(size=(k, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    sigma = contact_distance(qa, axes_a, qb, axes_b, u.astype(LD))
    h = np.exp(rng.uniform(math.log(h_range[0]), math.log(h_range[1]), size=k))
    d = sigma - LD(1) * h.astype(LD)
    r_ld = u.astype(LD) * d[:, None]
    w2, delta, n, c = oracle_contact(qa, axes_a, qb, axes_b, r_ld)
    return dict(qa=qa, qb=qb, axes_a=axes_a, axes_b=axes_b, r=r_ld, h=h, w2=w2, delta=delta, n=n, c=c)


# ---- the oracle's own checks -----------------------------------------------------------------------

EX = np.array([[1.0, 0, 0, 0]])
QZ90 = np.array([[math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)]])


@pytest.mark.parametrize("q_b, r, sigma", [
    (EX, [1.0, 0, 0], 4.0),            # tip to tip: 2a
    (EX, [0, 1.0, 0], 2.0),            # side by side: 2b
    (QZ90, [1.0, 0, 0], 3.0),          # T: a + b
    (QZ90, [0, 0, 1.0], 2.0),          # crossed X: 2b
])
def test_oracle_closed_form_contact_distances(q_b, r, sigma):
    s = contact_distance(EX, [[2.0, 1, 1]], q_b, [[2.0, 1, 1]], np.array([r], dtype=LD))
    assert abs(float(s[0]) - sigma) < 1e-15


def test_oracle_parallel_at_angle_and_sphere():
    for th in np.radians([10.0, 30, 45, 60, 80]):
        s = contact_distance(EX, [[2.0, 1, 1]], EX, [[2.0, 1, 1]],
                             np.array([[math.cos(th), math.sin(th), 0]], dtype=LD))
        exact = 2 / math.sqrt(math.cos(th) ** 2 / 4 + math.sin(th) ** 2)
        assert abs(float(s[0]) - exact) < 1e-15
    w2, delta, n, c = oracle_contact(EX, [[1.5, 1.5, 1.5]], EX, [[0.5, 0.5, 0.5]],
                                     np.array([[1.0, 0.6, 0.0]], dtype=LD))
    d = math.hypot(1.0, 0.6)
    assert abs(float(delta[0]) - (2.0 - d)) < 4e-16   # 2.0 - d itself is rounded in float64
    assert abs(float(w2[0]) - 0.34) < 1e-16             # (d/2)^2 = (1 + 0.36)/4


@pytest.mark.heavy
def test_oracle_agrees_with_direct_minimisation():
    """Third method: W_0^2 = min_p max(rho_A^2(p), rho_B^2(p)) by scipy SLSQP (float64, loose tol; the reference
    extra)."""
    minimize = pytest.importorskip("scipy.optimize", reason="scipy (pip install '.[reference]')").minimize

    data = random_overlapping(12, seed=5, h_range=(1e-2, 1e-1))
    for k in range(12):
        ma = np.asarray(shape_ld(data["qa"][k:k + 1], data["axes_a"][k:k + 1])[0], float)
        mb = np.asarray(shape_ld(data["qb"][k:k + 1], data["axes_b"][k:k + 1])[0], float)
        r = np.asarray(data["r"][k], float)
        cons = [{"type": "ineq", "fun": lambda z: z[3] - z[:3] @ ma @ z[:3]},
                {"type": "ineq", "fun": lambda z: z[3] - (z[:3] - r) @ mb @ (z[:3] - r)}]
        res = minimize(lambda z: z[3], np.r_[0.5 * r, 1.0], constraints=cons, method="SLSQP",
                       options={"ftol": 1e-14, "maxiter": 500})
        # SLSQP stops at its line-search limit ("positive directional derivative") near the optimum
        assert abs(res.x[3] - float(data["w2"][k])) < 1e-7
        assert np.linalg.norm(res.x[:3] - np.asarray(data["c"][k], float)) < 1e-3
