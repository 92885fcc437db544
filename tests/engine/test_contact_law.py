"""Two-sphere collisions against the analytic restitution of the spring-dashpot model (Hidalgo et al. 2013)."""

import math

import numpy as np
import pytest

from engine.setup.params import e_t_effective
from tests.engine.twobody import collide, contact_point_velocity

N_HAT = np.array([-1.0, 0.0, 0.0])   # from sphere 2 (+x) to sphere 1 (-x)
# Impact speeds chosen so the contact starts at different phases of the time step (the event
# correction of engine.physics.contact makes the result independent of that phase).
SPEEDS = (0.05, 0.0713, 0.0931, 0.12)


@pytest.mark.parametrize("e_n", [0.3, 0.6, 0.8, 0.95, 1.0])
def test_head_on_normal_restitution(e_n):
    # Tolerance 1e-3 (docs/physics.md §3.4): the remaining error is O(dt^2) at dt = t_c/50 (5e-5 at t_c/200).
    for v in SPEEDS:
        r = collide([v, 0.0, 0.0], e_n=e_n, dt_fraction=50)
        e = (r["velocity"][1, 0] - r["velocity"][0, 0]) / v
        assert abs(e - e_n) < 1e-3, (v, e)


@pytest.mark.parametrize("e_t", [0.2, 0.6, 0.8])
def test_oblique_sticking_tangential_restitution(e_t):
    """Tangential restitution of the contact point for a sticking contact (no Coulomb limit).

    Analytic value of the spring model with k_t from Hidalgo et al. (2013) Eq. 4: the tangential oscillator
    turns through arccos(-e_t) sqrt(1 + (ln e_n/pi)^2) during the damped contact, so
    e_t,eff = -cos(arccos(-e_t) sqrt(1 + (ln e_n/pi)^2)) (docs/physics.md §1.3). Eq. 4 is exact
    (e_t,eff = e_t) only for e_n = 1, i.e. gamma_n = 0.
    """
    e_n = 0.8
    ang = math.radians(10.0)     # near-normal: the normal barely turns during the contact
    for v in SPEEDS[:2]:
        v_rel = v * np.array([math.cos(ang), math.sin(ang), 0.0])
        g0 = contact_point_velocity(np.array([v_rel / 2, -v_rel / 2]), np.zeros((2, 3)), N_HAT)
        r = collide(v_rel, e_n=e_n, e_t=e_t, dt_fraction=50)
        g1 = contact_point_velocity(r["velocity"], r["omega"], N_HAT)
        gt0 = g0 - g0.dot(N_HAT) * N_HAT
        gt1 = g1 - g1.dot(N_HAT) * N_HAT
        measured = -gt1.dot(gt0) / gt0.dot(gt0)
        # 1e-2: O(dt) phase effects are corrected; what remains is O(dt^2) and the
        # O(delta/a) lever-arm and normal-rotation effects (docs/physics.md §1.7).
        assert abs(measured - e_t_effective(e_n, e_t)) < 1e-2, (v, measured)


def test_eq4_exact_without_damping():
    """With e_n = 1 the published Eq. 4 is exact: e_t,eff = e_t."""
    assert e_t_effective(1.0, 0.6) == pytest.approx(0.6, abs=1e-12)
    ang = math.radians(1.0)
    v_rel = 0.05 * np.array([math.cos(ang), math.sin(ang), 0.0])
    g0 = contact_point_velocity(np.array([v_rel / 2, -v_rel / 2]), np.zeros((2, 3)), N_HAT)
    r = collide(v_rel, e_n=1.0, e_t=0.6, dt_fraction=100)
    g1 = contact_point_velocity(r["velocity"], r["omega"], N_HAT)
    gt0 = g0 - g0.dot(N_HAT) * N_HAT
    gt1 = g1 - g1.dot(N_HAT) * N_HAT
    # 5e-3: overlap is 0.1 % of the radius here; the lever arm a - delta/2 shifts e_t by ~3e-3
    assert -gt1.dot(gt0) / gt0.dot(gt0) == pytest.approx(0.6, abs=5e-3)


def test_coulomb_cap_has_no_attractive_tail_trap():
    """A huge mu must not change e_t: the cap uses |F_n|, not max(F_n, 0) (docs/physics.md §1.4)."""
    ang = math.radians(10.0)
    v_rel = 0.05 * np.array([math.cos(ang), math.sin(ang), 0.0])
    free = collide(v_rel, e_n=0.6, e_t=0.6)
    capped = collide(v_rel, e_n=0.6, e_t=0.6, friction=1e30)
    assert np.allclose(free["velocity"], capped["velocity"], rtol=0, atol=1e-15)
    assert np.allclose(free["omega"], capped["omega"], rtol=0, atol=1e-12)


def test_sliding_contact_obeys_coulomb():
    """A grazing impact with small mu slides throughout: tangential impulse = mu x normal impulse."""
    mu = 0.1
    ang = math.radians(60.0)
    v_rel = 0.05 * np.array([math.cos(ang), math.sin(ang), 0.0])
    # start almost touching: a longer approach would slide the pair sideways and tilt the normal
    # away from the x axis in which the impulse is decomposed here
    r = collide(v_rel, e_n=0.8, e_t=0.8, friction=mu, gap_fraction=1e-5)
    dv = r["velocity"][0] - v_rel / 2        # change of sphere 1's velocity, m/s
    j_n = abs(dv[0])
    j_t = abs(dv[1])
    # ratio exact for a contact that slides all the time along a fixed normal; the normal turns by
    # ~1e-3 rad during the contact here, which is the 2 % allowance
    assert j_t / j_n == pytest.approx(mu, rel=0.02)
    # the spin picks up the torque of the tangential impulse: I dw = a_lever * m dv_t
    assert abs(r["omega"][0, 2]) > 0


def test_precision_float32_restitution():
    r = collide([0.05, 0.0, 0.0], e_n=0.8, precision="float32")
    e = (r["velocity"][1, 0] - r["velocity"][0, 0]) / 0.05
    # float32 positions near 0.5 m are quantised to ~3e-8 m, against a peak overlap of 1.1e-5 m here:
    # ~3e-3 relative per force evaluation, which is the measured float32 cost (not a tolerance of the model)
    assert abs(e - 0.8) < 1e-2


