"""The decomposition of the long-time HCS deviation (engine/validation/hcs_dsmc.py): the DSMC's tau axis, the
constant-restitution rule it shares with Luding's ODE, and the soft-contact loss of the DEM contact."""

import math

import numpy as np
import pytest

from engine.analysis.theory import luding_ode
from engine.setup.params import Q_SPHERE
from engine.validation.hcs_dsmc import _hard_rule, cooling, soft_contact_loss
from engine.validation.hcs_long import scene_spec
from engine.validation.sonine import _dsmc
from tests.extras import figure_or_missing_extra


def test_elastic_gas_keeps_t_and_collides_at_three_quarters_per_tau():
    # elastic smooth spheres: T is conserved by every collision, so the rescaled unit times the measured T
    # stays 1 to rounding; and a Maxwellian gas collides (3/4) (T/T0)^(1/2) times per particle per unit tau.
    n = 20_000
    out = _dsmc(n, 1.0, -1.0, Q_SPHERE, 4.0, 2.0, 3, 1.0)
    t = out[:, 7] * 2.0 * out[:, 1] / (3.0 * n)
    assert np.allclose(t, 1.0, rtol=1e-9)
    s, tau = out[-1, 0], out[-1, 6]
    # s counts 4 n / 2 = 40 000 collisions; the time of each is exponential-like: relative error ~ 1/sqrt(4e4)
    assert s / tau == pytest.approx(0.75, rel=0.02)


def test_dsmc_follows_the_ode_while_the_distribution_is_maxwellian():
    # from the Maxwellian start the cooling rates are the ODE's; by tau = 1 (one collision per particle) the
    # cumulants have grown to |a2| ~ 0.01, which moves T by far less than 1 %. A wrong time unit (a factor
    # in tau) would show as a T error of the order of the cooling itself (10-20 %).
    tau = np.array([0.25, 0.5, 1.0])
    for e_n, beta in ((0.8, -1.0), (0.6, 0.6)):
        d = cooling(e_n, beta, 1.0, tau, n=20_000, repeats=2, seed=11)
        t_ode, r_ode = luding_ode(e_n, beta, tau, 1.0, 1.0)
        # 1 %: the sampling error of T for 2 x 2e4 particles (0.4 %) plus the Sonine shift (< 0.3 %)
        assert np.all(np.abs(d["T"] / t_ode - 1.0) < 0.01), (e_n, beta, d["T"] / t_ode)
        if beta > -1:
            assert np.all(np.abs(d["R"] / r_ode - 1.0) < 0.015), (e_n, beta, d["R"] / r_ode)


def test_hard_rule_conserves_momenta_and_energy_when_elastic_and_rough():
    rng = np.random.default_rng(5)
    a, m, q = 0.01, 2.0, Q_SPHERE
    inertia = q * m * a * a
    for _ in range(20):
        v1, v2 = rng.normal(size=3), rng.normal(size=3)
        w1, w2 = rng.normal(size=3) / a, rng.normal(size=3) / a
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        x1, x2 = -a * n, a * n  # centres (n from 1 to 2); the contact point is the origin
        for e_n, beta in ((0.7, 0.4), (1.0, 1.0)):
            u1, u2, o1, o2 = _hard_rule(v1, v2, w1, w2, n, a, q, e_n, beta)
            assert np.allclose(m * (u1 + u2), m * (v1 + v2), atol=1e-12)
            l0 = m * (np.cross(x1, v1) + np.cross(x2, v2)) + inertia * (w1 + w2)
            l1 = m * (np.cross(x1, u1) + np.cross(x2, u2)) + inertia * (o1 + o2)
            assert np.allclose(l1, l0, atol=1e-12)
            if e_n == 1.0:
                e0 = 0.5 * m * (v1 @ v1 + v2 @ v2) + 0.5 * inertia * (w1 @ w1 + w2 @ w2)
                e1 = 0.5 * m * (u1 @ u1 + u2 @ u2) + 0.5 * inertia * (o1 @ o1 + o2 @ o2)
                assert e1 == pytest.approx(e0, rel=1e-12)


def test_soft_contact_loss_vanishes_at_low_speed_and_grows_with_it():
    # the DEM contact equals the constant-restitution rule in the limit of small speeds (the normal does not
    # turn during the contact; e_t,eff is the spring's exact sticking restitution): at v = 0.1 m/s the excess
    # is below 0.3 % (e_t,eff itself matches a binary collision to 2e-4, docs/physics.md §1.3; 300 paired
    # samples), and at v_rms = 10 m/s it is positive by many standard errors (measured +2 %).
    spec = scene_spec("hidalgo2013", 0.8, 0, "cpu")
    slow = soft_contact_loss(spec, 1e-4, 1.0, 300, seed=2)
    fast = soft_contact_loss(spec, 1.0, 1.0, 300, seed=2)
    assert abs(slow["eps_tr"]) < 0.003 and abs(slow["eps_rot"]) < 0.003, slow
    assert fast["eps_tr"] > 5 * fast["eps_tr_err"] and fast["eps_tr"] > 5 * abs(slow["eps_tr"]), (slow, fast)
    assert math.isfinite(fast["eps_rot"])


def test_decomposition_takes_the_collision_rate_only_where_it_is_precise(tmp_path):
    """hcs_dsmc.write: the measured-rate columns (rate, rest - rate) appear for a case whose rate SE passes the
    cut, and a case above it says why they are left out."""
    import numpy as np

    from engine.validation import hcs_dsmc

    tau = np.linspace(0.0, 100.0, 401)
    coll_err = {"precise": np.full_like(tau, 0.05), "noisy": np.full_like(tau, 0.5)}
    res = {}
    for key, err in coll_err.items():
        se = hcs_dsmc.rate_window_se(tau, err)
        z = np.zeros_like(tau)
        res[key] = dict(e_n=0.8, beta=0.5, R0=1.0, seeds=8, tau=tau, n=1000, repeats=2, samples=10,
                        velocity_rms=5.0, dem_T=z + 0.02, dem_T_err=z + 0.001, dem_R=z, dem_R_err=z + 0.001,
                        dsmc_T=z, dsmc_T_err=z, dsmc_R=z, dsmc_R_err=z, soft_T=z - 0.01, soft_R=z,
                        soft_points=[], soft_fit={"tr": dict(c=0, c_err=0, chi2=0, dof=1),
                                                  "rot": dict(c=0, c_err=0, chi2=0, dof=1)},
                        rate_T=z + 0.02, rate_R=z + 0.005, rate_se=se, rate_used=bool(se <= hcs_dsmc.RATE_SE_MAX))
    # ~10 records per tau window at tau >= 5: the window SE is err / sqrt(records)
    assert res["precise"]["rate_used"] and not res["noisy"]["rate_used"]
    with figure_or_missing_extra():              # dsmc.png last, after the tables
        hcs_dsmc.write(tmp_path, res, "test")
    md = (tmp_path / "dsmc.md").read_text()
    precise, noisy = md.split("## noisy")
    assert "rest - rate T %" in precise and "| +3.00 ± 0.10 | +2.00 | +1.00 ± 0.10 |" in precise
    assert "rest - rate T %" not in noisy and "Collision rate not used here" in noisy


def test_collision_change_windows_recover_the_energy_change_per_collision():
    # Luding's ODE with its two right-hand sides scaled by (f_tr, f_rot) and collisions at Enskog's rate
    # (3/4) T^(1/2): per collision, T and R change f_tr and f_rot times what the Maxwellian closure says, so
    # the windows must return exactly those factors (to the midpoint rule's O(h^2) on this grid: < 1e-5).
    from engine.analysis.theory import collisions_per_particle, luding_coefficients
    from engine.validation.hcs_dsmc import collision_change_windows, ratio_of_sums

    e_n, beta = 0.7, 0.5
    tau = np.linspace(0.0, 30.0, 6001)
    grid = np.array([1.0, 5.0, 20.0])
    for f_tr, f_rot in ((1.0, 1.0), (1.3, 0.8)):
        t, r = luding_ode(e_n, beta, tau, 1.0, 0.9, rates=lambda _t: (f_tr, f_rot))
        s = collisions_per_particle(t, tau)
        dt, dt0, dr, dr0 = collision_change_windows(tau, t, r, s, luding_coefficients(e_n, beta), grid)
        assert np.allclose(dt / dt0, f_tr, rtol=1e-5) and np.allclose(dr / dr0, f_rot, rtol=1e-5), (dt / dt0, dr / dr0)
        # twice the collisions for the same change (a rate/count slip of 2) halves the ratio
        dt2, dt20, _, _ = collision_change_windows(tau, t, r, 2.0 * s, luding_coefficients(e_n, beta), grid)
        assert np.allclose(dt2 / dt20, f_tr / 2.0, rtol=1e-5)
    # windows with fewer than two records give NaN, not a ratio of one point
    out = collision_change_windows(tau[:3], t[:3], r[:3], s[:3], luding_coefficients(e_n, beta), [100.0])
    assert all(np.isnan(x[0]) for x in out)
    # ratio of sums and its jackknife SE, against the definition
    num = np.array([[2.0, 1.0], [4.0, 3.0], [3.0, 2.5]])
    den = np.array([[1.0, 1.0], [2.0, 1.0], [1.5, 1.0]])
    ratio, se = ratio_of_sums(num, den)
    assert np.allclose(ratio, num.sum(0) / den.sum(0))
    loo = np.array([(num.sum(0) - num[i]) / (den.sum(0) - den[i]) for i in range(3)])
    assert np.allclose(se, np.sqrt(2 / 3 * ((loo - loo.mean(0)) ** 2).sum(0)))
    assert se[0] == 0.0                          # every run has num = 2 den: no scatter
    assert np.isnan(ratio_of_sums(np.ones((2, 1)), np.zeros((2, 1)))[0][0])


def test_dsmc_energy_change_per_collision_is_the_maxwellian_closure_near_the_start():
    # the DSMC counts its collisions per particle s = 2 C / N like the DEM's counter; from a Maxwellian start its
    # energy change per collision is the closure's up to the Sonine cumulants (|lambda - 1| ~ a2/4 < 0.5 % for
    # e = 0.8 smooth) and sampling: ~1e4 collisions per window and run, per-collision losses spread by ~100 %
    # (relative SE ~1 % per run, 0.5 % over 4). A factor 2 in s would give 0.5.
    tau = np.array([2.0, 4.0])
    d = cooling(0.8, -1.0, 1.0, tau, n=20_000, repeats=4, seed=5, samples_per_collision=20.0)
    assert np.all(np.abs(d["loss_T"] - 1.0) < 0.03), (d["loss_T"], d["loss_T_err"])
    assert np.all(np.isnan(d["loss_R"]))         # smooth spheres: no rotational change to compare
