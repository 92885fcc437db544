"""The tangential contact law for spheroids (engine/physics/rough_spheroid.py): effective tangential
mass, its sphere limit, the spring step's conservation and Coulomb properties, against the sphere law."""

from __future__ import annotations

import math

import numpy as np
import pytest

from engine.physics import rough_spheroid as R
from engine.physics.contact import sphere_contact

H = 0.5


def _quat(rng):
    q = rng.normal(size=4)
    return q / np.linalg.norm(q)


def _body(rng, a, b, c, rho=2000.0):
    """Mass, principal inverse inertias of a solid ellipsoid (a along body x), a random orientation."""
    m = rho * 4.0 / 3.0 * math.pi * a * b * c
    inert = m / 5.0 * np.array([b * b + c * c, a * a + c * c, a * a + b * b])
    q = _quat(rng)
    return m, 1.0 / inert, q, np.array(R.inverse_inertia_space(*q, *(1.0 / inert), H))


def _sym(s):
    return np.array([[s[0], s[1], s[2]], [s[1], s[3], s[4]], [s[2], s[4], s[5]]])


def _cross_matrix(r):
    return np.array([[0, -r[2], r[1]], [r[2], 0, -r[0]], [-r[1], r[0], 0]])


def _geometry(rng, xi=2.0):
    b = 1e-3
    ma, _, qa, sa = _body(rng, xi * b, b, b)
    mb, _, qb, sb = _body(rng, xi * b, b, b)
    n = rng.normal(size=3)
    n /= np.linalg.norm(n)
    ra = rng.normal(size=3) * b
    rb = rng.normal(size=3) * b
    return ma, mb, sa, sb, ra, rb, n


def test_the_impulse_response_matrix_is_k_and_its_means_are_the_masses():
    rng = np.random.default_rng(1)
    for _ in range(20):
        ma, mb, sa, sb, ra, rb, n = _geometry(rng)
        inv_m12 = 1.0 / ma + 1.0 / mb
        K = np.column_stack([R.impulse_response(inv_m12, sa, *ra, sb, *rb, *e) for e in np.eye(3)])
        ref = inv_m12 * np.eye(3) + sum(_cross_matrix(r).T @ _sym(s) @ _cross_matrix(r)
                                        for r, s in ((ra, sa), (rb, sb)))
        assert np.allclose(K, ref, rtol=1e-12, atol=0) and np.allclose(K, K.T, rtol=1e-12)
        assert np.all(np.linalg.eigvalsh(K) > 0)
        # normal: n.K n (the D of docs/physics.md §2.4); tangential: the mean of t.K t over the tangent plane
        assert R.normal_inverse_mass(inv_m12, sa, *ra, sb, *rb, *n) == pytest.approx(n @ K @ n, rel=1e-12)
        t1 = np.cross(n, rng.normal(size=3))
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(n, t1)
        ang = np.linspace(0, 2 * np.pi, 64, endpoint=False)
        mean = np.mean([(np.cos(p) * t1 + np.sin(p) * t2) @ K @ (np.cos(p) * t1 + np.sin(p) * t2) for p in ang])
        inv_mt = R.tangential_inverse_mass(inv_m12, sa, *ra, sb, *rb, *n, H)
        assert inv_mt == pytest.approx(mean, rel=1e-12)
        assert inv_mt == pytest.approx((np.trace(K) - n @ K @ n) / 2, rel=1e-12)
        assert inv_mt > inv_m12


def test_the_sphere_limit_gives_hidalgo_2013_eq_4():
    """Identical spheres (a = b = c), contact point on the line of centres: m_t/m12 = q/(1+q), q = 2/5, so k_t is
    the k_n q/(1+q) (arccos(-e_t)/pi)^2 of Hidalgo et al. (2013)."""
    rng = np.random.default_rng(2)
    a = 1e-3
    ma, _, _, sa = _body(rng, a, a, a)
    mb, _, _, sb = _body(rng, a, a, a)
    n = np.array([0.3, -0.4, math.sqrt(1 - 0.25)])
    d = 2 * a - 1e-6
    inv_m12 = 1.0 / ma + 1.0 / mb
    inv_mt = R.tangential_inverse_mass(inv_m12, sa, *(d / 2 * n), sb, *(-d / 2 * n), *n, H)
    q = 0.4
    # lever d/2 instead of a: (d/2a)^2 = 1 - 1e-3
    assert inv_m12 / inv_mt == pytest.approx(1.0 / (1.0 + (d / (2 * a)) ** 2 / q), rel=1e-12)
    e_t, k_n = 0.8, 1e8
    k_t = R.tangential_stiffness(k_n, 1.0 / inv_m12, inv_mt, R.tangential_factor(e_t))
    assert k_t == pytest.approx(k_n * q / (1 + q) * (math.acos(-e_t) / math.pi) ** 2, rel=2e-3)  # the lever


@pytest.mark.parametrize("mu", [None, 0.3])
def test_the_spring_step_matches_the_sphere_law_for_spheres(mu):
    """Same inputs as engine.physics.contact.sphere_contact (i = B, j = A; lever arms l_i, l_j on the line of
    centres): the same tangential force, torque and spring to rounding."""
    rng = np.random.default_rng(3)
    a, k_n, k_t, dt = 1e-3, 1e8, 2.5e7, 1e-7
    n = rng.normal(size=3)
    n /= np.linalg.norm(n)
    d = 2 * a - 2e-6
    r = d * n  # r_i - r_j = c_B - c_A
    v = rng.normal(size=3) * 0.5
    wa, wb = rng.normal(size=3) * 300, rng.normal(size=3) * 300
    xi = np.cross(n, rng.normal(size=3)) * 1e-7
    m12 = 0.5 * 2000 * 4 / 3 * math.pi * a ** 3
    gamma_n = 0.0
    out = sphere_contact(*r, d, *v, *v, *wb, *wa, a, a, *xi, 1e-6, 0.0, m12, k_n, gamma_n, k_t, mu, dt, H)
    fn = k_n * (2 * a - d)
    li = lj = d / 2
    ra, rb = lj * n, -li * n
    t = R.contact_point_slip(*v, *wa, *wb, *ra, *rb, *n)
    g = R.spheroid_tangential(*n, *ra, *rb, *t, *xi, k_t, fn, mu, dt)
    f_normal = fn * n
    assert np.allclose(np.array(g[:3]) + f_normal, out[:3], rtol=1e-9, atol=1e-12 * fn)
    assert np.allclose(g[6:9], out[3:6], rtol=1e-9, atol=1e-15)  # torque on B = torque on i
    assert np.allclose(g[9:12], out[6:9], rtol=1e-9, atol=1e-20)


def test_the_spring_step_conserves_momentum_and_angular_momentum_and_respects_coulomb():
    rng = np.random.default_rng(4)
    for mu in (None, 0.2):
        for _ in range(50):
            _, _, _, _, ra, rb, n = _geometry(rng, xi=rng.uniform(1.2, 3.0))
            ca = rng.normal(size=3) * 1e-2
            cpoint = ca + ra
            cb = cpoint - rb
            t = np.cross(n, rng.normal(size=3))
            xi = np.cross(n, rng.normal(size=3)) * 1e-6
            fn = abs(rng.normal()) * 10
            g = R.spheroid_tangential(*n, *ra, *rb, *t, *xi, 1e6, fn, mu, 1e-6)
            fb = np.array(g[:3])
            ta, tb = np.array(g[3:6]), np.array(g[6:9])
            # F_A = -F_B; tau_A + tau_B + c_A x F_A + c_B x F_B = 0 (common contact point)
            total = ta + tb + np.cross(ca, -fb) + np.cross(cb, fb)
            scale = np.linalg.norm(fb) * (np.linalg.norm(ca) + np.linalg.norm(cb) + 1e-3)
            assert np.linalg.norm(total) <= 1e-13 * scale
            assert abs(fb @ n) <= 1e-12 * np.linalg.norm(fb)  # tangential
            if mu is not None:
                assert np.linalg.norm(fb) <= mu * fn * (1 + 1e-12)
