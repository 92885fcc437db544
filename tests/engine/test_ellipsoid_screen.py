"""Exact screens before the Perram-Wertheim solve (docs/physics.md §2.3): they change no result.

engine/physics/ellipsoid.py screens a pair that was not in contact at the previous step with (i) the plane
normal to the centre line (support functions h_A + h_B < |r|) and (ii) an early stop of the PW iteration at the
first iterate with F(lambda_k) > 1 + margin. Claims checked here:

1. A screened pair is never one that the full evaluation (ellipsoid_contact, the engine's classification
   before the screens) calls overlapping, on 2 x 10^4 random near-contact configurations (xi in [1, 4], both
   sides of contact, |gap| from 1e-12 to 1e-1 of the contact distance) in float64 and float32; an unscreened
   pair gets the full evaluation bit for bit.
2. ellipsoid_pair_screened = ellipsoid_pair bit for bit whenever it is not screened, and asks for the
   previous gap when a contact starts after a screened step.
3. The CPU backend's trajectory with the screens equals the one without them bit for bit, in a gas with
   contacts starting right after screened steps (counted) and in a head-on side-by-side collision.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import pytest

from engine.shapes.spheroid import cpu_backend as cpu_ellipsoid
from engine.backends.base import EllipsoidSystem
from engine.shapes.spheroid.cpu_backend import CpuEllipsoidBackend
from engine.physics.ellipsoid import (PAIR_DONE, PAIR_NEEDS_PREV, PAIR_SCREENED, ellipsoid_contact,
                                      ellipsoid_contact_screened, ellipsoid_overlap_pw, ellipsoid_pair,
                                      ellipsoid_pair_screened, plane_separated, shape_matrix_inverse)
from tests.engine.test_ellipsoid_dynamics import spheroid_gas

H = 0.5
TOL = {np.float64: 1e-15, np.float32: 1e-7}
MARGIN = cpu_ellipsoid.PW_SCREEN


def near_contact(k, seed):
    """k random pairs (b = 1, xi_A, xi_B in [1, 4], 20 % identical, random orientations and directions) at
    centre distance sigma (1 + s), sigma the contact distance along the direction; s = +-10^U(-12, -1) (half
    overlapping, half apart), plus 20 % of pairs anywhere inside the bounding spheres."""
    rng = np.random.default_rng(seed)
    xa = rng.uniform(1.0, 4.0, k)
    xb = np.where(rng.random(k) < 0.2, xa, rng.uniform(1.0, 4.0, k))
    axes_a = np.stack([xa, np.ones(k), np.ones(k)], 1)
    axes_b = np.stack([xb, np.ones(k), np.ones(k)], 1)
    qa = rng.normal(size=(k, 4))
    qa /= np.linalg.norm(qa, axis=1, keepdims=True)
    qb = np.where(rng.random((k, 1)) < 0.1, qa, rng.normal(size=(k, 4)))   # some parallel pairs
    qb /= np.linalg.norm(qb, axis=1, keepdims=True)
    u = rng.normal(size=(k, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    w1 = np.array([ellipsoid_overlap_pw(*u[i], *qa[i], *axes_a[i], *qb[i], *axes_b[i], 1e-15, H)[1]
                   for i in range(k)])
    sigma = 1.0 / w1                                   # W_0 is linear in |r| along a fixed direction
    s = 10.0 ** rng.uniform(-12, -1, k) * np.where(rng.random(k) < 0.5, -1.0, 1.0)
    d = sigma * (1.0 + s)
    wide = rng.random(k) < 0.2
    d[wide] = rng.uniform(0.0, 1.0, wide.sum()) * (xa[wide] + xb[wide])
    return dict(r=u * d[:, None], qa=qa, qb=qb, axes_a=axes_a, axes_b=axes_b, s=np.where(wide, np.nan, s))


@numba.njit
def both(r, qa, aa, qb, ab, tol, margin, half, full, scr, plane):
    for k in range(r.shape[0]):
        g = ellipsoid_contact(r[k, 0], r[k, 1], r[k, 2], qa[k, 0], qa[k, 1], qa[k, 2], qa[k, 3],
                              aa[k, 0], aa[k, 1], aa[k, 2], qb[k, 0], qb[k, 1], qb[k, 2], qb[k, 3],
                              ab[k, 0], ab[k, 1], ab[k, 2], tol, half)
        h = ellipsoid_contact_screened(r[k, 0], r[k, 1], r[k, 2], qa[k, 0], qa[k, 1], qa[k, 2], qa[k, 3],
                                       aa[k, 0], aa[k, 1], aa[k, 2], qb[k, 0], qb[k, 1], qb[k, 2], qb[k, 3],
                                       ab[k, 0], ab[k, 1], ab[k, 2], tol, margin, half)
        ia = shape_matrix_inverse(qa[k, 0], qa[k, 1], qa[k, 2], qa[k, 3], aa[k, 0], aa[k, 1], aa[k, 2], half)
        ib = shape_matrix_inverse(qb[k, 0], qb[k, 1], qb[k, 2], qb[k, 3], ab[k, 0], ab[k, 1], ab[k, 2], half)
        plane[k] = plane_separated(ia[0], ia[1], ia[2], ia[3], ia[4], ia[5], ib[0], ib[1], ib[2], ib[3], ib[4],
                                   ib[5], r[k, 0], r[k, 1], r[k, 2], margin, half)
        for m in range(9):
            full[k, m] = g[m]
        scr[k, 0] = 1 if h[0] else 0
        scr[k, 1], scr[k, 2], scr[k, 3], scr[k, 4], scr[k, 5] = h[1], h[2], h[3], h[4], h[5]
        scr[k, 6], scr[k, 7], scr[k, 8], scr[k, 9] = h[6], h[7], h[8], h[9]


@pytest.fixture(scope="module")
def sample():
    return near_contact(20000, seed=5)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_screens_never_reject_an_overlap(sample, dtype):
    c = lambda x: np.ascontiguousarray(np.asarray(x, dtype=dtype))  # noqa: E731
    k = len(sample["s"])
    full = np.zeros((k, 9), dtype)
    scr = np.zeros((k, 10), dtype)
    plane = np.zeros(k, np.bool_)
    margin = dtype(MARGIN[np.dtype(dtype).name])
    both(c(sample["r"]), c(sample["qa"]), c(sample["axes_a"]), c(sample["qb"]), c(sample["axes_b"]),
         dtype(TOL[dtype]), margin, dtype(H), full, scr, plane)
    screened = scr[:, 0] == 1
    overlapping = full[:, 2] > 0          # the engine's classification without the screens
    # exactness: no screened pair overlaps (nor touches) in the full evaluation
    assert not np.any(screened & overlapping)
    assert np.all(full[screened, 0] > 1)
    assert not np.any(plane & overlapping)
    # an unscreened pair gets the full evaluation bit for bit
    assert np.array_equal(scr[~screened, 1:], full[~screened], equal_nan=True)
    # the screens are not vacuous: most separated pairs are screened, the plane test takes a share,
    # and the pairs that are only just apart (relative gap below ~ the margin) are left to the full solve
    apart = ~overlapping
    assert apart.sum() > 0.4 * k and overlapping.sum() > 0.25 * k
    s = sample["s"]
    clear = apart & ~(np.abs(s) < 10 * float(margin))      # apart by more than 10 margins (or anywhere)
    assert screened[clear].mean() > 0.9, screened[clear].mean()
    assert 0.05 < plane[apart].mean() < screened[apart].mean()
    tiny = apart & (np.abs(s) < 0.1 * float(margin))
    assert tiny.sum() > 20 and not screened[tiny].any()
    print(f"{np.dtype(dtype).name}: {k} pairs, {overlapping.sum()} overlapping (0 screened), {apart.sum()} apart: "
          f"{plane[apart].mean():.3f} by the plane, {(screened & ~plane)[apart].mean():.3f} by the PW early stop, "
          f"{(~screened)[apart].mean():.3f} full")


def _pair_args(rng, depth, dprev):
    """A crossed xi = 2 pair at centre distance 3 - depth along x (T contact, touches at a + b = 3)."""
    qa = (1.0, 0.0, 0.0, 0.0)
    qb = (math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4))
    return ((3.0 - depth, 0.0, 0.0) + qa + (2.0, 1.0, 1.0) + qb + (2.0, 1.0, 1.0)
            + tuple(rng.normal(size=9)) + (dprev, 0.0, 0.5, 1e4, 3.0, 1e-4, 1e-15))


def test_pair_screened_matches_pair():
    rng = np.random.default_rng(3)
    inf = -math.inf
    for depth in (0.3, 1e-3, 1e-8, -1e-8, -1e-3, -0.5):
        for dprev in (-1e-3, 0.0, 2e-3):
            args = _pair_args(rng, depth, dprev)
            ref = ellipsoid_pair(*args, H)
            g = ellipsoid_pair_screened(*args, 1e-9, inf, H)
            if g[11] == PAIR_SCREENED:
                assert ref[9] < 0 and dprev <= 0 and g[9] == inf and all(x == 0 for x in g[:9])
            else:
                assert g[11] == PAIR_DONE and g[:11] == ref
    # a contact starting after a screened step asks for the previous gap, then gives the reference result
    args = _pair_args(rng, 1e-3, inf)
    assert ellipsoid_pair_screened(*args, 1e-9, inf, H)[11] == PAIR_NEEDS_PREV
    args = args[:-7] + (-2e-4,) + args[-6:]
    assert ellipsoid_pair_screened(*args, 1e-9, inf, H) == ellipsoid_pair(*args, H) + (PAIR_DONE,)
    # far apart along the centre line: the plane screen; just apart: no screen, the full gap
    assert ellipsoid_pair_screened(*_pair_args(rng, -0.5, -1.0), 1e-9, inf, H)[11] == PAIR_SCREENED
    g = ellipsoid_pair_screened(*_pair_args(rng, -1e-12, -1.0), 1e-9, inf, H)
    assert g[11] == PAIR_DONE and -1e-11 < g[9] < 0


def _run(system, params, steps, screen, monkeypatch, record=None):
    monkeypatch.setitem(cpu_ellipsoid.PW_SCREEN, params.precision, MARGIN[params.precision] if screen else -1.0)
    be = CpuEllipsoidBackend(system, params)
    starts = 0
    for _ in range(steps):
        before, builds = be.hist[:, :, 3].copy(), be.builds
        be.advance(1)
        # contacts that start now after a screened step (same list: no rebuild in between)
        if record is not None and be.builds == builds:
            starts += int(np.sum((before == -np.inf) & (be.hist[:, :, 3] > 0)))
    if record is not None:
        record.append(starts)
    return be


def _same(a, b):
    for name in ("pos", "vel", "angm", "quat", "force", "torque"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert np.array_equal(a.nbr, b.nbr) and np.array_equal(a.nn, b.nn)
    ha, hb = a.hist[:, :, 3], b.hist[:, :, 3]
    scr = ha == -np.inf
    # slots the screened run marks -inf are apart in the other; every other slot holds the same history
    assert np.all(hb[scr] < 0) and np.all(np.isfinite(hb))
    assert np.array_equal(ha[~scr], hb[~scr]) and np.array_equal(a.hist[:, :, 4], b.hist[:, :, 4])


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_backend_trajectory_unchanged_by_screens(precision, monkeypatch):
    system, params = spheroid_gas(n=64, phi=0.07, xi=2.0, e_n=0.8, v_rms=1.0, seed=7, precision=precision)
    starts = []
    on = _run(system, params, 600, True, monkeypatch, starts)
    off = _run(system, params, 600, False, monkeypatch)
    e0 = 0.5 * float(np.sum(system.mass[:, None] * system.velocity ** 2))
    assert on.observe()["kinetic_energy_translational"] < 0.98 * e0    # it collided
    _same(on, off)
    assert np.isinf(on.hist[:, :, 3]).any()          # screens were used ...
    print(f"{precision}: {starts[0]} contacts started right after a screened step")
    if precision == "float64":                         # ... and contacts started right after screened steps
        assert starts[0] >= 3, starts                  # (float32: margin 1e-3, the last step before is rarely)


def test_side_by_side_collision_unchanged(monkeypatch):
    """Two parallel xi = 2 spheroids approach side by side: the plane screen is exact here and holds until the
    step before contact, so the contact-start weight needs the recomputed previous gap."""
    system, params = spheroid_gas(n=2, phi=0.01, xi=2.0, e_n=0.7, seed=1)
    b = system.semi_axes[0, 1]
    box = system.box_length
    pos = np.array([[0.5 * box, 0.5 * box - 1.05 * b, 0.5 * box], [0.5 * box, 0.5 * box + 1.05 * b, 0.5 * box]])
    vel = np.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])
    q = np.tile([1.0, 0.0, 0.0, 0.0], (2, 1))
    sysc = EllipsoidSystem(box, pos, vel, np.zeros((2, 3)), q, system.semi_axes, system.mass, system.inertia)
    starts = []
    on = _run(sysc, params, 200, True, monkeypatch, starts)
    off = _run(sysc, params, 200, False, monkeypatch)
    _same(on, off)
    assert starts == [2]                                   # the pair's slot in both partners' lists
    assert on.vel[0, 1] < 0 < on.vel[1, 1]                 # they bounced
