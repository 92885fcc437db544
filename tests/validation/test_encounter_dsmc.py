"""Encounter DSMC of smooth spheroids (docs/physics.md §6.4): the two-body DEM integrator used as a collision rule
(engine/validation/encounter_dsmc.py) against conservation laws, the sphere restitution, the hard-impulse rule
in the stiff limit, and the energy of the elastic gas. The DEM constants are those of the scene of
Rubio-Largo et al. (2015)."""

import math

import numpy as np
import pytest

from engine.validation import encounter_dsmc as E


def _contact_states(xi, e_n, kn_factor=1.0, seed=4, nper=3000):
    """Contact states drawn by the DSMC sampler from a Maxwellian gas at the scene's T0 (A at the origin)."""
    c = E.dem_constants(xi, e_n, kn_factor)
    a, b, m = c["a"], c["b"], c["m"]
    inertia = np.array(c["inertia"])
    rng = np.random.default_rng(seed)
    E._seed(seed)
    v = rng.normal(size=(nper, 3)) * math.sqrt(c["T0"] / m)
    w2 = rng.normal(size=(nper, 2)) * math.sqrt(c["T0"] / inertia[1])
    I, J, Q, NV, XA, XB, U = E.sample_sweep(v, w2, a, b, E.weight_bound(a, b))
    states = [E._body_state(v[I[k]], v[J[k]], w2[I[k]], w2[J[k]], Q[k], XA[k], XB[k], inertia[1])
              for k in range(len(I))]
    return c, states


def _back_off(x, v, q, L, c):
    """The DEM contact starts inside a step: move the touching pair half a step back in free flight."""
    inv_i = 1.0 / np.array(c["inertia"])
    for k in range(2):
        E.free_flight(x[k], v[k], q[k], L[k], inv_i, -0.5 * c["dt"])


def _momenta(x, v, L, m):
    p = m * v.sum(0)
    ang = sum(np.cross(x[k], m * v[k]) + L[k] for k in range(2))       # about the fixed origin
    scale = sum(np.linalg.norm(np.cross(x[k], m * v[k])) + np.linalg.norm(L[k]) for k in range(2))
    return p, ang, m * np.abs(v).sum(), scale


def test_encounter_conserves_linear_and_angular_momentum_elastic():
    c, states = _contact_states(2.5, 1.0)
    a, b, m = c["a"], c["b"], c["m"]
    inv_i = 1.0 / np.array(c["inertia"])
    assert len(states) >= 10
    multi = 0
    for x, v, q, L in states:
        _back_off(x, v, q, L, c)
        p0, l0, ps, ls = _momenta(x, v, L, m)
        st, contacts, steps, _ = E.soft_encounter(x, v, q, L, m, inv_i, a, b, c["k_n"], c["gamma_n"], c["dt"],
                                                  10**6, True)
        assert st == E.ENC_OK and contacts >= 1
        multi += contacts > 1
        p1, l1, _, _ = _momenta(x, v, L, m)
        # forces are equal and opposite to the bit and torques balance about the common contact point
        # (engine.physics.ellipsoid.ellipsoid_pair); free flight is exact: rounding only (~50-500 steps)
        assert np.abs(p1 - p0).max() < 1e-13 * ps
        assert np.abs(l1 - l0).max() < 1e-12 * ls
    assert multi >= 1          # repeat contacts are part of what was integrated


@pytest.mark.parametrize("e_n", [0.9, 0.6, 1.0])
def test_sphere_limit_head_on_restitution(e_n):
    c = E.dem_constants(1.0001, e_n)
    a, b, m = c["a"], c["b"], c["m"]
    inv_i = 1.0 / np.array(c["inertia"])
    x = np.zeros((2, 3))
    x[1, 0] = 2 * a + 1e-9
    v = np.zeros((2, 3))
    v[0, 0], v[1, 0] = 1.0, -1.0
    q = np.zeros((2, 4))
    q[:, 0] = 1.0
    L = np.zeros((2, 3))
    st, contacts, _, _ = E.soft_encounter(x, v, q, L, m, inv_i, a, b, c["k_n"], c["gamma_n"], c["dt"], 10**6, False)
    assert st == E.ENC_OK and contacts == 1
    e = (v[1, 0] - v[0, 0]) / 2.0
    # the spring-dashpot at dt = t_c/50 with the engine's start/end rules: measured |e - e_n| <= 5e-4 (e_n = 0.6)
    assert abs(e - e_n) < 1e-3, e
    assert np.abs(L).max() == 0.0 and abs(v[0, 1]) + abs(v[0, 2]) == 0.0


def test_stiff_limit_approaches_the_hard_impulse_with_e_eff():
    """Single-contact encounters: soft (DEM) outcome -> hard impulse with e_eff(D) as k_n -> infinity.

    At the scene's k_n they differ by up to ~2 % of |g| (the geometry turns during the contact, overlap ~1 % of
    b); at 1e4 k_n (overlap /100) by ~2e-4, the dashpot's own discretisation at dt = t_c/50."""
    errs = {}
    for kn in (1.0, 1e4):
        c, states = _contact_states(2.5, 0.9, kn)
        a, b, m = c["a"], c["b"], c["m"]
        inv_i = 1.0 / np.array(c["inertia"])
        zeta = E.zeta_of(0.9)
        e = []
        for x, v, q, L in states:
            g0 = np.linalg.norm(v[1] - v[0])
            xs, vs, qs, ls = x.copy(), v.copy(), q.copy(), L.copy()
            _back_off(xs, vs, qs, ls, c)
            ss = E.soft_encounter(xs, vs, qs, ls, m, inv_i, a, b, c["k_n"], c["gamma_n"], c["dt"], 10**6, True)
            xh, vh, qh, lh = x.copy(), v.copy(), q.copy(), L.copy()
            sh = E.hard_encounter(xh, vh, qh, lh, m, inv_i, a, b, zeta, 1e-3 * c["dt"], 10**6)
            if ss[1] == 1 and sh[1] == 1:
                e.append(np.abs((vs[1] - vs[0]) - (vh[1] - vh[0])).max() / g0)
        assert len(e) >= 8
        errs[kn] = max(e)
    assert errs[1e4] < 1e-3, errs
    assert errs[1.0] > 5 * errs[1e4], errs       # the soft contact is not the hard rule at the scene's k_n


def test_dsmc_elastic_keeps_total_energy():
    r = E.run_dsmc(2.0, 1.0, "soft", n=400, coll_per_particle=2, seed=3, rescale=False)
    assert r["encounters"] >= 400 and r["capped"] == 0
    # e_n = 1: only the leap-frog's contact energy error, measured <= 4e-4 of the pair's energy per encounter
    # and of either sign; 400 encounters in a gas of 400 particles: expected |dE/E| ~ 1e-4
    assert abs(r["energy_change_relative"]) < 1e-3, r["energy_change_relative"]
    ri = E.run_dsmc(2.0, 1.0, "impulse", n=400, coll_per_particle=2, seed=3, rescale=False)
    assert abs(ri["energy_change_relative"]) < 1e-12       # an elastic impulse is exact


def test_near_sphere_dsmc_gives_the_sphere_loss_for_both_rules():
    """xi = 1.0001, e = 0.9: every smooth sphere collision loses (1 - e^2) T_tr on average (docs/physics.md §6.2,
    Maxwellian), no contact repeats, the rotation is untouched (D ~ 1e-8)."""
    for rule in ("impulse", "soft"):
        r = E.run_dsmc(1.0001, 0.9, rule, n=2000, coll_per_particle=2, seed=2)
        # 2000 collisions, per-collision loss of relative spread ~1: SE ~2.5 %; 8 % = 3 SE
        assert abs(r["loss_per_collision_over_T"] / (1 - 0.9**2) - 1) < 0.08, r["loss_per_collision_over_T"]
        assert r["rejected_share"] == 0.0 and r["later_contact_share"] == 0.0
        # spheres: T_rot never changes, and the Haff loss in collision units is d ln T_tr / dc = -(1 - e^2)/3
        # (c collisions per particle); the rescaling multiplies both temperatures, so T_tr/T_rot =
        # exp(-(1 - e^2) c/3); 4 % ~ 2 sigma of T_tr at N = 2000 (sqrt(2/(3N)) = 1.8 %)
        c, ratio = np.array(r["profile"])[-1]
        assert abs(ratio / math.exp(-(1 - 0.9**2) * c / 3) - 1) < 0.04, (c, ratio)


@pytest.mark.parametrize("kn_factor", [1.0, 1e4])
def test_near_sphere_same_collisions_same_outcome(kn_factor):
    """The same sampled collisions resolved by both rules: the DEM sphere contact -> the impulse with e_n.

    Not exactly at the scene's k_n: the centre line turns during the contact by ~ v_t t_c / (2a) ~ 1 %
    (tangential speed ~5 m/s, t_c ~ 1e-4 s, a = 0.03 m), which a hard impulse cannot do; with k_n x 1e4 the
    contact is 100 x shorter."""
    c = E.dem_constants(1.0001, 0.9, kn_factor)
    a, b, m = c["a"], c["b"], c["m"]
    inertia = np.array(c["inertia"])
    rng = np.random.default_rng(8)
    E._seed(8)
    n = 4000
    v = rng.normal(size=(n, 3)) * math.sqrt(c["T0"] / m)
    w2 = rng.normal(size=(n, 2)) * math.sqrt(c["T0"] / inertia[1])
    I, J, Q, NV, XA, XB, U = E.sample_sweep(v, w2, a, b, E.weight_bound(a, b))
    assert len(I) > 100
    vi, wi = v.copy(), w2.copy()
    E.impulse_batch(vi, wi, I, J, Q, NV, XA, XB, m, inertia[1], E.zeta_of(0.9))
    k = len(I)
    out_v, out_w2, stat = np.zeros((k, 2, 3)), np.zeros((k, 2, 2)), np.zeros((k, 5))
    E.resolve_batch(E.RULE_SOFT, v, w2, I, J, Q, XA, XB, U, m, 1 / inertia, a, b, c["k_n"], c["gamma_n"], c["dt"],
                    E.zeta_of(0.9), 10**6, True, out_v, out_w2, stat)
    assert np.all(stat[:, 0] == E.ENC_OK) and np.all(stat[:, 1] == 1)
    g = np.linalg.norm(v[J] - v[I], axis=1)
    err = np.max(np.abs((out_v[:, 1] - out_v[:, 0]) - (vi[J] - vi[I])).max(axis=1) / g)
    e0 = np.sum(v[I] ** 2 + v[J] ** 2)
    loss_imp = e0 - np.sum(vi[I] ** 2 + vi[J] ** 2)
    loss_soft = e0 - np.sum(out_v ** 2)
    if kn_factor == 1.0:
        assert 1e-3 < err < 0.05, err
        assert abs(loss_soft / loss_imp - 1) < 0.01       # the loss depends on the normal speed only: ~1e-3
    else:
        # what remains is the dashpot's discretisation at dt = t_c/50 (|e - e_n| ~ 1e-4)
        assert err < 1e-3, err
        assert abs(loss_soft / loss_imp - 1) < 2e-3


def test_elastic_gas_stays_at_equipartition_only_with_whole_encounters():
    """e_n = 1, xi = 2.5: a Maxwellian with T_tr = T_rot is stationary (detailed balance) for a correct collision
    rule. The encounter rule keeps it (first-contact sampling + all repeat contacts); dropping the non-first
    contacts without resolving the repeats ('first') does not: it drifts to T_tr/T_rot ~ 0.82, which shows what
    the backward check removes and that the forward encounter puts it back."""
    def late(rule):
        r = E.run_dsmc(2.5, 1.0, rule, n=2000, coll_per_particle=10, seed=5)
        p = np.array(r["profile"])
        return p[p[:, 0] > 4, 1].mean(), r

    soft, r = late("soft")
    assert r["rejected_share"] > 0.08 and r["capped"] == 0
    # late mean over 6 collisions per particle at N = 2000: scatter ~1.5 % (measured 1.2 % at N = 4000)
    assert abs(soft - 1) < 0.05, soft
    first, _ = late("first")
    assert first < 0.9, first
