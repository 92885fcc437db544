"""Property-based tests (hypothesis) of the sphere contact law, called directly with scalar floats.

- swapping i and j negates force and spring exactly (IEEE), overlap and dashpot force unchanged;
- positions enter only through the minimum-image separation: a common translation, with the pair
  across the periodic boundary or not, leaves the force unchanged up to position rounding;
- a common rotation of every vector input rotates force, torque and spring (covariance);
- the torques balance the orbital term (angular momentum of the pair);
- no NaN/inf on degenerate inputs: touching exactly (1 ulp overlap), tiny overlaps, zero relative
  velocity, zero spring, grazing contacts, spring parallel to the normal, coincident centres (d = 0:
  no force, no torque, spring kept, overlap a_i + a_j reported, so the backend's overlap guard stops).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from engine.physics.contact import min_image, sphere_contact, sphere_contact_end

K_N = 1.0e5
M12 = 5.0e-3
DT = math.pi * math.sqrt(M12 / K_N) / 50
HALF = 0.5

SETTINGS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])

fin = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)
vec = st.tuples(fin, fin, fin).map(np.array)
unit = vec.filter(lambda x: np.linalg.norm(x) > 1e-3).map(lambda x: x / np.linalg.norm(x))
radius = st.floats(0.002, 0.02)
overlap_frac = st.floats(1e-6, 0.3)          # overlap / (a_i + a_j)
k_t_s = st.one_of(st.none(), st.floats(1e3, 1e5))
mu_s = st.one_of(st.none(), st.floats(0.0, 1.0))
gamma_s = st.floats(0.0, 50.0)


@st.composite
def contacts(draw):
    """A physically sensible overlapping pair: r, d, velocities, spins, radii, spring, history."""
    ai, aj = draw(radius), draw(radius)
    n = draw(unit)
    d = (ai + aj) * (1.0 - draw(overlap_frac))
    r = n * d
    d = math.sqrt(r @ r)
    v = draw(vec) * 2.0
    u = v + draw(vec) * 0.01
    wi, wj = draw(vec) * 100.0, draw(vec) * 100.0
    # spring near the tangent plane, as the time loop keeps it: up to 1 mm long, with a normal part of at
    # most 1 % of the tangential one (n turning by 0.6 degrees in a step). A spring along n has no
    # tangent-plane direction to rotate into (rotate_spring_into_plane then rescales rounding noise to
    # the full length): that case is only checked for finiteness (test_no_nan_on_degenerate_inputs).
    t = draw(vec)
    t = t - (t @ n) * n
    assume(np.linalg.norm(t) > 1e-3)
    xi = (t + n * np.linalg.norm(t) * draw(st.floats(-0.01, 0.01))) * draw(st.sampled_from([0.0, 1e-6, 1e-3]))
    delta_prev = draw(st.one_of(st.just(-0.0), st.floats(-1e-4, 0.0), st.floats(1e-9, 1e-3)))
    fd_prev = draw(st.floats(-10.0, 10.0))
    return dict(r=r, d=d, v=v, u=u, wi=wi, wj=wj, ai=ai, aj=aj, xi=xi, delta_prev=delta_prev, fd_prev=fd_prev,
                k_t=draw(k_t_s), mu=draw(mu_s), gamma=draw(gamma_s))


def call(c, r=None, d=None, v=None, u=None, wi=None, wj=None, ai=None, aj=None, xi=None):
    r = c["r"] if r is None else r
    d = c["d"] if d is None else d
    v = c["v"] if v is None else v
    u = c["u"] if u is None else u
    wi = c["wi"] if wi is None else wi
    wj = c["wj"] if wj is None else wj
    ai = c["ai"] if ai is None else ai
    aj = c["aj"] if aj is None else aj
    xi = c["xi"] if xi is None else xi
    g = sphere_contact(float(r[0]), float(r[1]), float(r[2]), float(d), float(v[0]), float(v[1]), float(v[2]),
                       float(u[0]), float(u[1]), float(u[2]), float(wi[0]), float(wi[1]), float(wi[2]),
                       float(wj[0]), float(wj[1]), float(wj[2]), float(ai), float(aj),
                       float(xi[0]), float(xi[1]), float(xi[2]), float(c["delta_prev"]), float(c["fd_prev"]),
                       M12, K_N, float(c["gamma"]), c["k_t"], c["mu"], DT, HALF)
    return np.array(g[0:3]), np.array(g[3:6]), np.array(g[6:9]), g[9], g[10]


def swapped(c):
    return call(c, r=-c["r"], v=-c["v"], u=-c["u"], wi=c["wj"], wj=c["wi"], ai=c["aj"], aj=c["ai"], xi=-c["xi"])


def scale(c, f):
    """Force scale of a contact: spring, dashpot and tangential parts (N)."""
    kt = c["k_t"] or 0.0
    return (K_N * (c["ai"] + c["aj"]) + c["gamma"] * np.linalg.norm(c["u"]) + abs(c["fd_prev"])
            + kt * (np.linalg.norm(c["xi"]) + DT * (np.linalg.norm(c["v"]) + 0.04 * np.linalg.norm(c["wi"] + c["wj"])))
            + np.linalg.norm(f))


@SETTINGS
@given(contacts())
def test_swap_negates_force_and_spring_exactly(c):
    f, tau, xi, delta, fd = call(c)
    f2, tau2, xi2, delta2, fd2 = swapped(c)
    assert np.all(np.isfinite(f)) and np.all(np.isfinite(tau)) and np.all(np.isfinite(xi))
    # exact (==): the full neighbour list computes both orderings, so momentum conservation rests on it
    assert np.array_equal(f2, -f), (f, f2)
    assert np.array_equal(xi2, -xi), (xi, xi2)
    assert delta2 == delta and fd2 == fd


@SETTINGS
@given(contacts())
def test_torques_balance_orbital_term(c):
    """tau_i + tau_j + r x F_i = 0: the pair conserves angular momentum (rounding of l_i + l_j = d)."""
    f, tau, _, _, _ = call(c)
    _, tau_j, _, _, _ = swapped(c)
    total = tau + tau_j + np.cross(c["r"], f)
    # each term is |r||F| ~ d |F| with relative rounding ~1e-16 per operation
    assert np.linalg.norm(total) <= 1e-13 * c["d"] * scale(c, f)


@SETTINGS
@given(contacts(), st.floats(0.05, 1.0), st.tuples(fin, fin, fin), vec, st.booleans())
def test_translation_and_periodic_images(c, box_scale, xi_frac, shift, across):
    """Same force from positions shifted by a common vector, wrapped into a periodic box."""
    box = max(10.0 * (c["ai"] + c["aj"]), box_scale)
    inv_box = 1.0 / box
    # x_i anywhere; with `across` it sits just inside a face so that x_j lies across the boundary
    x_i = (np.array(xi_frac) * 0.5 + 0.5) * box
    if across:
        x_i = np.where(c["r"] < 0, 1e-4 * box, box * (1 - 1e-4))
    x_j = np.mod(x_i - c["r"], box)

    def r_of(a, b):
        return np.array([min_image(float(a[k] - b[k]), box, inv_box, HALF) for k in range(3)])

    s = shift * box * 3.0
    r0 = r_of(x_i, x_j)
    r1 = r_of(np.mod(x_i + s, box), np.mod(x_j + s, box))
    assert np.allclose(r0, c["r"], rtol=0, atol=1e-12 * box)
    f0, t0, _, _, _ = call(c, r=r0, d=math.sqrt(r0 @ r0))
    f1, t1, _, _, _ = call(c, r=r1, d=math.sqrt(r1 @ r1))
    # positions round to ~ulp(box); forces are Lipschitz in r with constant ~ scale/d
    tol = 1e-12 * box / c["d"] * scale(c, f0) * 100
    assert np.linalg.norm(f1 - f0) <= tol
    assert abs(np.linalg.norm(f1) - np.linalg.norm(f0)) <= tol
    assert abs(np.linalg.norm(t1) - np.linalg.norm(t0)) <= tol * max(c["ai"], c["aj"])


def rotation(q):
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


@SETTINGS
@given(contacts(), st.tuples(fin, fin, fin, fin).map(np.array).filter(lambda q: np.linalg.norm(q) > 0.1))
def test_rotation_covariance(c, q):
    R = rotation(q)
    f, tau, xi, delta, fd = call(c)
    r = R @ c["r"]
    f2, tau2, xi2, delta2, fd2 = call(c, r=r, d=math.sqrt(r @ r), v=R @ c["v"], u=R @ c["u"], wi=R @ c["wi"],
                                      wj=R @ c["wj"], xi=R @ c["xi"])
    sc = scale(c, f)
    # rotated inputs carry ~1e-16 relative rounding; 1e-12 leaves room for the few dozen operations
    assert np.linalg.norm(f2 - R @ f) <= 1e-12 * sc
    assert np.linalg.norm(tau2 - R @ tau) <= 1e-12 * sc * max(c["ai"], c["aj"])
    assert np.linalg.norm(xi2 - R @ xi) <= 1e-12 * (np.linalg.norm(xi) + 1e-3 + DT * 10)
    assert abs(delta2 - delta) <= 1e-14 * (c["ai"] + c["aj"])


# ---- degenerate inputs -----------------------------------------------------------------------------

def finite(*arrays):
    return all(np.all(np.isfinite(np.asarray(a, float))) for a in arrays)


@SETTINGS
@given(contacts(), st.sampled_from(["touch", "tiny", "still", "nospring", "grazing", "parallel"]))
def test_no_nan_on_degenerate_inputs(c, case):
    n = c["r"] / c["d"]
    s = c["ai"] + c["aj"]
    kw = {}
    if case == "touch":      # d = a_i + a_j minus 1 ulp, contact starting
        d = np.nextafter(s, 0.0)
        kw = dict(r=n * d, d=d)
        c = dict(c, delta_prev=draw_prev(c))
    elif case == "tiny":
        d = s * (1 - 1e-14)
        kw = dict(r=n * d, d=d)
    elif case == "still":
        z = np.zeros(3)
        kw = dict(v=z, u=z, wi=z, wj=z)
    elif case == "nospring":
        kw = dict(xi=np.zeros(3))
    elif case == "grazing":  # relative velocity in the tangent plane
        kw = dict(v=c["v"] - (c["v"] @ n) * n, u=c["u"] - (c["u"] @ n) * n)
    elif case == "parallel":  # spring along the normal: no tangent-plane component to rotate into
        kw = dict(xi=n * 1e-4)
    f, tau, xi, delta, fd = call(c, **kw)
    assert finite(f, tau, xi, delta, fd), (case, f, tau, xi)
    cs = {**c, **kw}
    f2, _, xi2, _, _ = swapped(cs)
    assert np.array_equal(f2, -f) and np.array_equal(xi2, -xi)


def draw_prev(c):
    return c["delta_prev"] if c["delta_prev"] <= 0 else -0.0


@SETTINGS
@given(contacts())
def test_coincident_centres_give_no_force_and_no_nan(c):
    """d = 0 (or |r|^2 underflowing to 0): no normal exists; no force, no torque, spring kept, full overlap."""
    for r in (np.zeros(3), np.array([1e-170, 0.0, -1e-170])):
        f, tau, xi, delta, fd = call(c, r=r, d=math.sqrt(r @ r))
        assert finite(f, tau, xi, delta, fd)
        assert np.all(f == 0) and np.all(tau == 0) and fd == 0
        assert np.array_equal(xi, c["xi"])
        assert delta == c["ai"] + c["aj"]
        f2, _, xi2, _, _ = call(c, r=-r, d=math.sqrt(r @ r), v=-c["v"], u=-c["u"], wi=c["wj"], wj=c["wi"],
                                ai=c["aj"], aj=c["ai"], xi=-c["xi"])
        assert np.all(f2 == 0) and np.array_equal(xi2, -c["xi"])


def test_coincident_centres_float32():
    z = np.float32(0.0)
    a = np.float32(0.01)
    g = sphere_contact(z, z, z, z, z, z, z, z, z, z, z, z, z, z, z, z, a, a, np.float32(1e-4), z, z, z, z,
                       np.float32(M12), np.float32(K_N), np.float32(1.0), np.float32(1e4), None,
                       np.float32(DT), np.float32(0.5))
    assert all(np.isfinite(x) for x in g)
    assert g[:6] == (0.0,) * 6 and g[9] == np.float32(0.02)
    assert all(isinstance(x, (float, np.floating)) for x in g)


# ---- the end-of-contact settlement ---------------------------------------------------------------

@SETTINGS
@given(contacts(), st.floats(0.5, 1.5), st.floats(0.0, 0.1))
def test_contact_end_antisymmetric_and_finite(c, p, gap_frac):
    n = c["r"] / c["d"]
    d = (c["ai"] + c["aj"]) * (1.0 + gap_frac)   # the contact has ended: d >= a_i + a_j
    r = n * d
    d = math.sqrt(r @ r)

    def end(r, v, wi, wj, ai, aj, xi):
        return np.array(sphere_contact_end(r[0], r[1], r[2], d, v[0], v[1], v[2], wi[0], wi[1], wi[2],
                                           wj[0], wj[1], wj[2], ai, aj, float(c["fd_prev"]),
                                           xi[0], xi[1], xi[2], c["k_t"], p, DT, HALF))

    e = end(r, c["v"], c["wi"], c["wj"], c["ai"], c["aj"], c["xi"])
    e2 = end(-r, -c["v"], c["wj"], c["wi"], c["aj"], c["ai"], -c["xi"])
    assert finite(e)
    assert np.array_equal(e2[:3], -e[:3])
    # grazing end with a spring parallel to n and zero velocities: still finite
    z = np.zeros(3)
    assert finite(end(r, z, z, z, c["ai"], c["aj"], n * 1e-4))


@pytest.mark.parametrize("dtype, spring, off_axis", [(np.float64, 1e-4, 1e-160), (np.float32, 1e-2, 5e-22)])
def test_a_spring_along_n_to_rounding_stays_finite(dtype, spring, off_axis):
    """The kind of case the property test above found: a spring along n but for a component so small that its
    projection onto the contact plane, squared, is a subnormal number, so that scaling it back to the spring's
    length overflowed to inf (and 0 x inf gave NaN). Projected and rotated, and settled at a contact's end, it
    must stay finite, in both precisions."""
    from engine.physics.contact import rotate_spring_into_plane

    c = dtype
    z = c(0.0)
    d = c(0.019)
    xi = (z, c(spring), c(off_axis))
    out = rotate_spring_into_plane(*xi, z, c(1.0), z)
    assert all(np.isfinite(out)) and out[2] == c(off_axis)    # the projection, not scaled
    e = sphere_contact_end(z, d, z, d, z, z, z, z, z, z, z, z, z, c(0.0146), c(0.0038), z, *xi, c(1e4), c(0.7),
                           c(DT), c(HALF))
    assert all(np.isfinite(e))


if __name__ == "__main__":  # pragma: no cover
    pytest.main([__file__, "-q"])
