"""Ellipsoid contact geometry (docs/physics.md §7.7): engine/physics/ellipsoid.py against an oracle.

The oracle (tests/engine/test_ellipsoid_oracle.py) is a different method in higher precision:
bisection on the primal tangency curve in 80-bit longdouble. The full 10^4-sample error table is
written by the one-off study bench/ellipsoid_geometry_accuracy.py (in the git history before the bench/ pruning); here a
CI-sized sample of 2000 asserts the bounds.
Also: hand-made cases with closed forms (docs/physics.md §2.6), the quadric and quartic of Rubio-Largo et al. (2015),
its tetrahedron construction, and the cases where its Delta/P overlap test fails (docs/physics.md §2.2).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import pytest

from engine.physics.ellipsoid import (
    characteristic_quartic, ellipsoid_contact, ellipsoid_overlap_pw, paper_disjoint, paper_quartic,
    paper_tetrahedron, quadric_matrix, quartic_discriminant, shape_matrix)
from tests.engine.test_ellipsoid_oracle import contact_distance, random_overlapping

H = 0.5
TOL = {np.float64: 1e-15, np.float32: 1e-7}
Q0 = (1.0, 0.0, 0.0, 0.0)
QZ90 = (math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4))   # body x -> space y
QY90 = (math.cos(math.pi / 4), 0.0, math.sin(math.pi / 4), 0.0)   # body x -> space -z


@numba.njit
def contact_batch(r, qa, aa, qb, ab, tol, half, out):
    for k in range(r.shape[0]):
        g = ellipsoid_contact(r[k, 0], r[k, 1], r[k, 2], qa[k, 0], qa[k, 1], qa[k, 2], qa[k, 3],
                              aa[k, 0], aa[k, 1], aa[k, 2], qb[k, 0], qb[k, 1], qb[k, 2], qb[k, 3],
                              ab[k, 0], ab[k, 1], ab[k, 2], tol, half)
        for m in range(9):
            out[k, m] = g[m]


def engine_on(data, dtype):
    """Run the engine on the oracle's sample in the given precision; (K, 9) results in longdouble."""
    def c(x):
        return np.ascontiguousarray(np.asarray(x, dtype=dtype))

    out = np.zeros((len(data["h"]), 9), dtype)
    contact_batch(c(data["r"]), c(data["qa"]), c(data["axes_a"]), c(data["qb"]), c(data["axes_b"]),
                  dtype(TOL[dtype]), dtype(H), out)
    return out


def errors(data, out):
    """|delta error| (units of b = 1), |n error| (rad), |C error| (units of b)."""
    o = out.astype(np.longdouble)
    ed = np.abs(o[:, 2] - data["delta"])
    en = np.linalg.norm(o[:, 3:6] - data["n"], axis=1)
    ec = np.linalg.norm(o[:, 6:9] - data["c"], axis=1)
    return np.asarray(ed, float), np.asarray(en, float), np.asarray(ec, float)


@pytest.fixture(scope="module")
def sample():
    return random_overlapping(2000, seed=11)


@pytest.mark.parametrize("dtype, bounds", [
    (np.float64, (1e-14, 1e-13, 1e-13)),
    (np.float32, (1e-5, 1e-5, 3e-5)),
])
def test_accuracy_against_oracle(sample, dtype, bounds):
    out = engine_on(sample, dtype)
    assert out.dtype == dtype and not np.isnan(out).any()
    ed, en, ec = errors(sample, out)
    assert ed.max() < bounds[0], ed.max()
    assert en.max() < bounds[1], en.max()
    assert ec.max() < bounds[2], ec.max()
    # the robust test never misses an overlap (every sample overlaps by >= ~7e-7 b) ...
    assert np.all(out[:, 0] < 1)
    # ... and delta is an overlap (> 0) for every sample deeper than the precision can resolve
    deep = np.asarray(sample["delta"], float) > (1e-6 if dtype == np.float32 else 0)
    assert np.all(out[deep, 2] > 0)


def test_float32_in_float32_out():
    """No literal promotes float32 to float64 anywhere in the call tree (compiled return types)."""
    from numba import types

    f = np.float32
    ellipsoid_contact(f(2.9), f(0.1), f(0), *map(f, Q0), f(2), f(1), f(1), *map(f, QZ90), f(2), f(1), f(1),
                      f(1e-7), f(H))
    c = characteristic_quartic(*map(f, shape_matrix(*Q0, 2.0, 1.0, 1.0, H)),
                               *map(f, shape_matrix(*QZ90, 2.0, 1.0, 1.0, H)), f(2.9), f(0), f(0), f(1), f(H))
    quartic_discriminant(*map(f, c), f(H))
    paper_disjoint(*map(f, (2.9, 0, 0, *Q0, 2, 1, 1, *QZ90, 2, 1, 1, H)))
    for fn in (ellipsoid_contact, characteristic_quartic, quartic_discriminant):
        sigs = [fn.overloads[s].signature for s in fn.overloads if all(a == types.float32 for a in s)]
        assert sigs, fn
        for sig in sigs:
            assert all(t == types.float32 for t in sig.return_type), (fn, sig)


# ---- hand-made cases (a = 2, b = 1 unless stated) ---------------------------------------------------

def contact(r, qa, axes_a, qb, axes_b):
    return ellipsoid_contact(r[0], r[1], r[2], *qa, *axes_a, *qb, *axes_b, 1e-15, H)


@pytest.mark.parametrize("name, r_hat, qb, sigma, n_exp, c_exp", [
    ("tip-to-tip", (1.0, 0, 0), Q0, 4.0, (1, 0, 0), (2.0, 0, 0)),         # 2a
    ("side-by-side", (0, 1.0, 0), Q0, 2.0, (0, 1, 0), (0, 1.0, 0)),       # 2b
    ("crossed T", (1.0, 0, 0), QZ90, 3.0, (1, 0, 0), (2.0, 0, 0)),        # a + b
    ("crossed X", (0, 0, 1.0), QZ90, 2.0, (0, 0, 1), (0, 0, 1.0)),        # 2b
])
def test_hand_made(name, r_hat, qb, sigma, n_exp, c_exp):
    r_hat = np.array(r_hat)
    for depth in (0.0, 1e-6, 1e-3, 0.05):
        d = sigma - depth
        f, lam, delta, nx, ny, nz, cx, cy, cz = contact(r_hat * d, Q0, (2.0, 1.0, 1.0), qb, (2.0, 1.0, 1.0))
        assert abs(math.sqrt(f) - d / sigma) < 1e-15, name        # W_0 = d / sigma
        assert abs(delta - depth) < 2e-15, (name, delta, depth)   # overlap along the normal = sigma - d
        assert np.allclose((nx, ny, nz), n_exp, atol=1e-15, rtol=0)
        assert np.allclose((cx, cy, cz), np.array(c_exp) * d / sigma, atol=1e-14, rtol=0)
    # touching exactly: W_0 = 1, delta = 0; separated: W_0 > 1, delta < 0 (the gap)
    assert abs(contact(r_hat * sigma, Q0, (2.0, 1, 1), qb, (2.0, 1, 1))[0] - 1.0) < 1e-15
    g = contact(r_hat * (sigma + 0.1), Q0, (2.0, 1, 1), qb, (2.0, 1, 1))
    assert g[0] > 1 and abs(g[2] + 0.1) < 1e-14


def test_t_configuration_quartic_roots():
    """docs/physics.md §2.6: at touch (d = a + b = 3) the roots are -1, -1/4 and the double root 2."""
    c = paper_quartic(3.0, 0, 0, *Q0, 2.0, 1, 1, *QZ90, 2.0, 1, 1, 1.0, H)
    roots = np.sort(np.roots(c).real)
    assert np.allclose(roots, [-1.0, -0.25, 2.0, 2.0], atol=1e-6)
    lam = contact((3.0, 0, 0), Q0, (2.0, 1, 1), QZ90, (2.0, 1, 1))[1]
    assert abs(lam - 2 / 3) < 1e-14 and abs(lam / (1 - lam) - 2.0) < 1e-13


@pytest.mark.parametrize("ra, rb", [(1.0, 1.0), (1.5, 0.5), (0.3, 2.0)])
def test_xi_one_is_the_sphere_formula(ra, rb):
    rng = np.random.default_rng(3)
    for _ in range(20):
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        d = (ra + rb) * rng.uniform(0.9, 1.05)
        qa, qb = rng.normal(size=4), rng.normal(size=4)
        qa /= np.linalg.norm(qa)
        qb /= np.linalg.norm(qb)
        f, lam, delta, nx, ny, nz, cx, cy, cz = contact(u * d, qa, (ra,) * 3, qb, (rb,) * 3)
        assert abs(delta - (ra + rb - d)) < 4e-15
        assert np.allclose((nx, ny, nz), u, atol=2e-15, rtol=0)
        assert abs(lam - ra / (ra + rb)) < 1e-14
        assert abs(f - (d / (ra + rb)) ** 2) < 1e-14
        assert np.allclose((cx, cy, cz), u * d * ra / (ra + rb), atol=1e-14, rtol=0)


def test_parallel_at_angle_closed_form():
    for th in np.radians([0.0, 15, 30, 45, 60, 75, 90]):
        u = np.array([math.cos(th), math.sin(th), 0.0])
        sigma = 2 / math.sqrt(math.cos(th) ** 2 / 4 + math.sin(th) ** 2)
        f = contact(u * sigma, Q0, (2.0, 1, 1), Q0, (2.0, 1, 1))[0]
        assert abs(f - 1.0) < 2e-15


# ---- the algebra of Rubio-Largo et al. (2015) -------------------------------------------------------

def paper_r(q):
    """The rotation matrix of Rubio-Largo et al. (2015) with its typo corrected (R_00 = 1 - 2 q2^2 - 2 q3^2)."""
    q0, q1, q2, q3 = q
    return np.array([[1 - 2 * q2**2 - 2 * q3**2, 2 * q1 * q2 - 2 * q0 * q3, 2 * q1 * q3 + 2 * q0 * q2, 0],
                     [2 * q1 * q2 + 2 * q0 * q3, 1 - 2 * q1**2 - 2 * q3**2, 2 * q2 * q3 - 2 * q0 * q1, 0],
                     [2 * q1 * q3 - 2 * q0 * q2, 2 * q2 * q3 + 2 * q0 * q1, 1 - 2 * q1**2 - 2 * q2**2, 0],
                     [0, 0, 0, 1]])


def full(e):
    m = np.empty((4, 4))
    for v, (i, j) in zip(e, [(0, 0), (0, 1), (0, 2), (0, 3), (1, 1), (1, 2), (1, 3), (2, 2), (2, 3), (3, 3)]):
        m[i, j] = m[j, i] = v
    return m


def test_quadric_is_trsrt_tt_and_quartic_is_det():
    rng = np.random.default_rng(8)
    for _ in range(10):
        c, q = rng.normal(size=3), rng.normal(size=4)
        q /= np.linalg.norm(q)
        axes, w = rng.uniform(0.5, 3, size=3), rng.uniform(0.5, 1.5)
        t = np.eye(4)
        t[3, :3] = -c
        s = np.diag([axes[0] ** -2, axes[1] ** -2, axes[2] ** -2, -w * w])
        r = paper_r(q)
        a_lit = t @ r @ s @ r.T @ t.T                                      # Rubio-Largo et al. (2015) Eq. 7
        a_eng = full(quadric_matrix(*c, *q, *axes, w, H))
        assert np.allclose(a_eng, a_lit, rtol=1e-12, atol=1e-12)
        p = rng.normal(size=3) * 0.5
        x = np.r_[c + p, 1.0]
        assert math.isclose(x @ a_eng @ x, p @ r[:3, :3] @ np.diag(axes ** -2.0) @ r[:3, :3].T @ p - w * w,
                            rel_tol=1e-10, abs_tol=1e-12)
        # quartic coefficients of det(lambda A + B), B of a second ellipsoid
        c2, q2 = c + rng.normal(size=3), rng.normal(size=4)
        q2 /= np.linalg.norm(q2)
        axes2 = rng.uniform(0.5, 3, size=3)
        b_eng = full(quadric_matrix(*c2, *q2, *axes2, w, H))
        coef = characteristic_quartic(*shape_matrix(*q, *axes, H), *shape_matrix(*q2, *axes2, H),
                                      *(c2 - c), w * w, H)
        for lam in (-2.0, -0.5, 0.3, 1.0, 4.0):
            assert math.isclose(np.polyval(coef, lam), np.linalg.det(lam * a_eng + b_eng), rel_tol=1e-9,
                                abs_tol=1e-9 * np.abs(coef).max() * max(1, abs(lam)) ** 4)


def test_scaled_quartic_has_positive_double_root_at_w0(sample):
    """Shrunk by W_0 = sqrt(F), det(lambda A_s + B_s) has the double root lambda* / (1 - lambda*)."""
    out = engine_on({k: v[:50] for k, v in sample.items()}, np.float64)
    for k in range(50):
        f, lam = out[k, 0], out[k, 1]
        coef = paper_quartic(*np.asarray(sample["r"][k], float), *sample["qa"][k], *sample["axes_a"][k],
                             *sample["qb"][k], *sample["axes_b"][k], f, H)   # W is dimensionless
        lam0 = lam / (1 - lam)
        scale = np.abs(coef).max()
        assert abs(np.polyval(coef, lam0)) < 1e-9 * scale
        assert abs(np.polyval(np.polyder(coef), lam0)) < 1e-7 * scale


def test_paper_tetrahedron_converges_to_engine_contact(sample):
    """Eigenvectors of -A_s^-1 B_s: C = (V2 + V3)/2 and n of Eq. 22 tend to the engine's C and n."""
    out = engine_on({k: v[:30] for k, v in sample.items()}, np.float64)
    for k in range(30):
        if sample["axes_a"][k][0] == 1.0 and sample["axes_b"][k][0] == 1.0:
            continue    # spheres: the root -1 is double with a 2-d eigenspace; Eq. 22 needs a choice
        w0 = math.sqrt(out[k, 0])
        r = np.asarray(sample["r"][k], float)
        errs = []
        for eps in (1e-3, 1e-5):
            mu, pts, c, n = paper_tetrahedron(np.zeros(3), sample["qa"][k], sample["axes_a"][k], r,
                                              sample["qb"][k], sample["axes_b"][k], w0 * (1 - eps))
            assert np.sum(mu > 0) == 2                      # disjoint when shrunk below W_0 (P2)
            # n of Eq. 22 at w is the normal at the shrunk touch point; C moves with w linearly
            errs.append((np.linalg.norm(c / (1 - eps) - out[k, 6:9]), np.linalg.norm(n - out[k, 3:6])))
        assert errs[1][0] < 1e-3 and errs[1][1] < 1e-3
        assert errs[1][0] < errs[0][0] and errs[1][1] < errs[0][1]


# ---- where the paper's Delta/P test fails (docs/physics.md §2.2) ------------------------------------

def test_paper_test_degenerate_for_identical_parallel_pairs():
    """Delta == 0 identically (roots -1, -1, lambda+-): its sign, hence the verdict, is rounding noise."""
    a = (2.0, 1.0, 1.0)
    # aligned lattice neighbours, all clearly separated (contact at 2a = 4 along x, 2b = 2 across)
    for r in [(5.0, 0, 0), (0, 3.0, 0), (3.0, 3.0, 0), (4.5, 2.5, 1.0)]:
        delta, p = quartic_discriminant(*paper_quartic(*r, *Q0, *a, *Q0, *a, 1.0, H), H)
        assert abs(delta) < 1e-14
        assert not ellipsoid_overlap_pw(*r, *Q0, *a, *Q0, *a, 1e-15, H)[0]
    # verdict "colliding" for separated pairs: these two come out so on this machine
    assert not paper_disjoint(5.0, 0, 0, *Q0, *a, *Q0, *a, H) or not paper_disjoint(3.0, 3.0, 0, *Q0, *a, *Q0, *a, H)
    rng = np.random.default_rng(0)
    wrong = 0
    for _ in range(200):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        s = float(contact_distance(q[None], [a], q[None], [a], u[None].astype(np.longdouble))[0])
        wrong += not paper_disjoint(*(1.2 * s * u), *q, *a, *q, *a, H)     # 20 % apart
    assert wrong > 40, wrong      # about half of the separated parallel pairs are called "colliding"


def test_paper_test_float32_sign_noise_near_parallel():
    """theta = 1e-4 rad, overlapping by 2 % of the contact distance: float32 says 'disjoint'."""
    f = np.float32
    u = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    for ang in (1e-4, 3e-4):
        qb = (math.cos(ang / 2), 0.0, 0.0, math.sin(ang / 2))
        s = float(contact_distance(np.array([Q0]), [[2.0, 1, 1]], np.array([qb]), [[2.0, 1, 1]],
                                   u[None].astype(np.longdouble))[0])
        r = 0.98 * s * u
        assert not paper_disjoint(*r, *Q0, 2.0, 1.0, 1.0, *qb, 2.0, 1.0, 1.0, H)       # float64: right
        assert paper_disjoint(*map(f, (*r, *Q0, 2.0, 1.0, 1.0, *qb, 2.0, 1.0, 1.0, H)))  # float32: wrong
        ov, w0 = ellipsoid_overlap_pw(*map(f, (*r, *Q0, 2.0, 1.0, 1.0, *qb, 2.0, 1.0, 1.0, 1e-7, H)))
        assert ov and abs(w0 - 0.98) < 1e-5                                              # robust: right


DEEP = [  # xi = 3 pairs at 64 % and 51 % of their contact distance (found by random search, seed 1)
    ([-0.8412784561089692, -0.1647416634910914, -0.40507692594597133, -0.31784182805801203],
     [0.7553940820409111, 0.41099700487357443, -0.061655898465496, -0.5066160212497556],
     [-2.0128699282760025, 0.5600393454799916, 1.6580396412312128]),
    ([0.5928901855589765, 0.30331000584906503, -0.4108464291709638, -0.6226471551827335],
     [-0.2623814136222525, 0.45150071660900226, 0.5220535648612282, 0.6743613067954219],
     [-1.019450280954858, -0.4731044086748315, 1.8178452249403645]),
]


@pytest.mark.parametrize("qa, qb, r", DEEP)
def test_paper_test_calls_deep_overlaps_disjoint(qa, qb, r):
    a = (3.0, 1.0, 1.0)
    coef = paper_quartic(*r, *qa, *a, *qb, *a, 1.0, H)
    roots = np.roots(coef)
    assert np.all(np.abs(roots.imag) < 1e-9) and np.all(roots.real < 0)   # four negative real roots
    assert paper_disjoint(*r, *qa, *a, *qb, *a, H)                          # paper: "disjoint"
    ov, w0 = ellipsoid_overlap_pw(*r, *qa, *a, *qb, *a, 1e-15, H)
    assert ov and w0 < 0.7                                                  # truth: deep overlap
