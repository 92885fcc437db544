"""Luding's mean-field ODE and the collision frequency against docs/physics.md §6.1, §6.3 (LSODA oracle)."""

import math

import pytest

from engine.analysis.theory import collision_g, luding_coefficients, luding_ode, r_infinity


@pytest.mark.parametrize("e_n,e_t,a,b,c,rinf", [
    (0.8, 0.8, 0.281020, 0.165306, 0.229592, 1.167582),
    (0.6, 0.6, 0.336327, 0.130612, 0.244898, 1.409481),
    (0.9, 1.0, 0.251582, 0.204082, 0.204082, 1.123124),
    (0.9, 0.0, 0.169949, 0.051020, 0.229592, 0.573792),
])
def test_coefficients_table(e_n, e_t, a, b, c, rinf):
    A, B, C = luding_coefficients(e_n, e_t)
    assert (A, B, C) == pytest.approx((a, b, c), abs=1e-6)
    assert r_infinity(e_n, e_t) == pytest.approx(rinf, abs=1e-6)


@pytest.mark.parametrize("e,tvals,rvals", [
    (0.8, (0.896835, 0.452866, 0.0336465), (0.936033, 0.523262, 0.0392850)),
    (0.6, (0.826261, 0.283463, 0.0129979), (0.892488, 0.379965, 0.0183167)),
])
def test_ode_oracle(e, tvals, rvals):
    t, r = luding_ode(e, e, [1.0, 10.0, 100.0])
    assert t == pytest.approx(tvals, rel=2e-6)
    assert r == pytest.approx(rvals, rel=2e-6)


def test_collision_frequency_hidalgo_2013():
    # docs/physics.md §6.3, Hidalgo et al. (2013) scene: G = 40.313 s^-1 J^-1/2 for a = 0.015509 m, n = 512, m = 1/32,
    # phi = 0.008
    from engine.setup.params import derive
    from engine.setup.spec import SimulationSpec

    p = derive(SimulationSpec())
    assert collision_g(p.radius, p.number_density, p.mass, 0.008) == pytest.approx(40.313, rel=1e-4)


def test_per_collision_change_of_smooth_spheres():
    # smooth equal spheres: a collision loses (1 - e^2) m (g.n)^2 / 4, and Maxwellian colliding pairs have
    # <(g.n)^2> = 4 T / m, so each collision takes (1 - e^2) T from E_tr = 3 N T / 2 shared by 2 particles:
    # dT per collision and particle = -(1 - e^2) T / 3, and R is untouched (exact; independent of the A, B, C
    # of Hidalgo et al. (2013))
    from engine.analysis.theory import luding_per_collision

    for e in (0.9, 0.6):
        d_t, d_r = luding_per_collision(0.7, 0.4, luding_coefficients(e, -1.0))
        assert math.isclose(d_t, -(1 - e * e) * 0.7 / 3, rel_tol=1e-12) and d_r == 0.0
