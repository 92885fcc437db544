"""Sonine coefficients (docs/physics.md §6.5): the formula of engine/physics/sonine.py on known distributions, the
backends' energy moments against numpy, and the observables in the result and batch files.

Tolerances: sampled distributions are checked within 4 standard deviations of the estimator (Eq. 3/4 of
engine/physics/sonine.py for Maxwellians, the scatter of 20 sub-samples otherwise): a false failure has a
probability below 1e-4 and the seeds are fixed; exact constructions are checked to round-off (1e-12).
"""

import math

import numpy as np
import pytest

from engine.physics.sonine import (a2_sampling_sigma, a2_van_noije_ernst, a11_sampling_sigma, cross_cumulant,
                                   shell_a2, sonine_a2, sonine_observables, two_temperature_a2)


def energies(m, v):
    return 0.5 * m * np.sum(v * v, axis=1)


def a2_of(e, dof):
    return sonine_a2(float(e.sum()), float((e * e).sum()), len(e), dof)


def test_maxwellian_gives_zero_within_its_sampling_error():
    rng = np.random.default_rng(11)
    n = 200_000
    for dof in (3, 2):
        v = rng.normal(size=(n, dof)) * 1.7
        a2 = a2_of(energies(2.0, v), dof)
        assert abs(a2) < 4 * a2_sampling_sigma(n, dof), (dof, a2, a2_sampling_sigma(n, dof))


def test_sampling_error_formula_matches_the_scatter_of_repeated_draws():
    """std of a2_hat over 1000 draws of N = 400 against sqrt(8/(d(d+2)N)); the std of a std estimated from
    1000 draws is 2.2 %, the O(1/N) corrections a few %: 12 % tolerance."""
    rng = np.random.default_rng(5)
    n, draws = 400, 1000
    for dof in (3, 2):
        v = rng.normal(size=(draws, n, dof))
        e = 0.5 * np.sum(v * v, axis=2)
        a2 = dof / (dof + 2) * n * (e * e).sum(1) / e.sum(1) ** 2 - 1
        assert abs(a2.std(ddof=1) / a2_sampling_sigma(n, dof) - 1) < 0.12, (dof, a2.std(ddof=1))
    # the exact bias of the ratio estimator, E[a2_hat] = -2/(N d + 2): N = 50, 20000 draws resolve it at 13 s.e.
    e = 0.5 * np.sum(rng.normal(size=(20000, 50, 3)) ** 2, axis=2)
    a2 = 0.6 * 50 * (e * e).sum(1) / e.sum(1) ** 2 - 1
    assert abs(a2.mean() - (-2 / 152)) < 4 * a2.std() / math.sqrt(len(a2)), a2.mean()
    vt = rng.normal(size=(draws, n, 3))
    vr = rng.normal(size=(draws, n, 3))
    et, er = 0.5 * (vt * vt).sum(2), 0.5 * (vr * vr).sum(2)
    a11 = n * (et * er).sum(1) / (et.sum(1) * er.sum(1)) - 1
    assert abs(a11.std(ddof=1) / a11_sampling_sigma(n) - 1) < 0.12, a11.std(ddof=1)
    assert abs(a11.mean()) < 4 * a11_sampling_sigma(n) / math.sqrt(draws)


def test_polydisperse_maxwellian_is_zero_in_the_energy_form_not_in_the_velocity_form():
    """Masses 1 and 1/8 at one temperature: the energy form gives 0; the velocity form of the mass mixture gives
    (3/5)<v^4>/<v^2>^2 - 1 = (3/5)(15/9)((1 + 64)/2)/((1 + 8)/2)^2 - 1 = 0.605 (<v^2> = 3T/m, <v^4> = 15T^2/m^2)."""
    rng = np.random.default_rng(3)
    n = 200_000
    m = np.where(np.arange(n) % 2 == 0, 1.0, 1.0 / 8.0)
    v = rng.normal(size=(n, 3)) / np.sqrt(m)[:, None]
    assert abs(a2_of(energies(m, v), 3)) < 4 * a2_sampling_sigma(n, 3)
    v2 = np.sum(v * v, axis=1)
    velocity_form = 0.6 * np.mean(v2 * v2) / np.mean(v2) ** 2 - 1
    exact = 0.6 * (15 / 9) * (1 + 64) / 2 / ((1 + 8) / 2) ** 2 - 1
    assert abs(velocity_form - exact) < 0.05 and exact > 0.5


def test_equal_masses_energy_form_is_the_classic_kurtosis_form():
    rng = np.random.default_rng(7)
    v = rng.standard_t(5, size=(5000, 3))
    v2 = np.sum(v * v, axis=1)
    classic = 0.6 * np.mean(v2 * v2) / np.mean(v2) ** 2 - 1  # a2 = (d/(d+2)) <c^4>/<c^2>^2 - 1
    assert abs(a2_of(energies(3.3, v), 3) - classic) < 1e-12
    assert classic > 0.3  # a heavy-tailed distribution: far from 0


def test_all_speeds_equal_gives_minus_two_over_d_plus_two_exactly():
    rng = np.random.default_rng(1)
    u = rng.normal(size=(1000, 3))
    v = 2.5 * u / np.linalg.norm(u, axis=1, keepdims=True)
    assert abs(a2_of(energies(1.0, v), 3) - shell_a2(3)) < 1e-12
    assert shell_a2(3) == pytest.approx(-0.4)


def test_two_temperature_mixture_gives_its_exact_value():
    """Half the particles at T1, half at T2 (Maxwellians, masses 1 and 3): a2 = ((T1 - T2)/(T1 + T2))^2 = 0.25
    for T2 = 3 T1, within 4 sigma of 20 sub-samples."""
    rng = np.random.default_rng(2)
    n = 400_000
    t = np.where(np.arange(n) % 2 == 0, 1.0, 3.0)
    m = np.where(np.arange(n) % 4 < 2, 1.0, 3.0)
    v = rng.normal(size=(n, 3)) * np.sqrt(t / m)[:, None]
    e = energies(m, v)
    exact = two_temperature_a2(1.0, 3.0)
    assert exact == pytest.approx(0.25)
    parts = [a2_of(p, 3) for p in np.split(rng.permutation(e), 20)]
    sigma = np.std(parts, ddof=1) / math.sqrt(20)
    assert abs(a2_of(e, 3) - exact) < 4 * sigma + 1e-3, (a2_of(e, 3), sigma)


def test_cross_cumulant_independent_and_proportional():
    rng = np.random.default_rng(4)
    n = 200_000
    et = energies(1.0, rng.normal(size=(n, 3)))
    er = energies(1.0, rng.normal(size=(n, 3)))
    a11 = cross_cumulant(et.sum(), er.sum(), (et * er).sum(), n)
    assert abs(a11) < 4 * a11_sampling_sigma(n)
    # e_rot = c e_tr: a11 = <e^2>/<e>^2 - 1 = (5/3)(1 + a2) - 1 exactly, for the same sample
    a11p = cross_cumulant(et.sum(), 0.3 * et.sum(), 0.3 * (et * et).sum(), n)
    assert abs(a11p - (5 / 3 * (1 + a2_of(et, 3)) - 1)) < 1e-12


def test_degenerate_and_bad_input():
    assert sonine_a2(0.0, 0.0, 10, 3) == 0.0
    assert cross_cumulant(1.0, 0.0, 0.0, 10) == 0.0
    with pytest.raises(ValueError, match="n"):
        sonine_a2(1.0, 1.0, 0, 3)


def test_van_noije_ernst_values():
    """16(1-e)(1-2e^2)/(81 - 17e + 30e^2(1-e)) at e = 0.9, 0.8, 0.6, 0.4 (docs/physics.md §7.4, rounded)."""
    assert a2_van_noije_ernst(1.0) == 0.0
    for e, ref in ((0.9, -0.01456), (0.8, -0.01258), (0.6, 0.02386), (0.4, 0.08470)):
        assert a2_van_noije_ernst(e) == pytest.approx(ref, abs=1e-5)


def _sphere_backend(seed=3, n_side=5):
    from engine.backends.base import ContactParams, SphereSystem
    from engine.shapes.sphere.cpu_backend import CpuBackend

    rng = np.random.default_rng(seed)
    a, spacing = 0.1, 0.25
    g = (np.arange(n_side) + 0.5) * spacing
    pos = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    n = len(pos)
    m = rng.uniform(0.5, 2.0, n)
    vel = rng.normal(size=(n, 3)) / np.sqrt(m)[:, None]
    omega = rng.normal(size=(n, 3)) * 10
    system = SphereSystem(box_length=n_side * spacing, position=pos, velocity=vel, angular_velocity=omega,
                          orientation=np.tile([1.0, 0, 0, 0], (n, 1)), radius=np.full(n, a), mass=m,
                          inertia=0.4 * m * a * a)
    c = ContactParams(k_n=1e5, gamma_n_coef=100.0, k_t=1e4, friction=0.3, dt=1e-4, skin=0.02,
                      precision="float64", orientation=True, overlap_limit=0.2)
    return CpuBackend(system, c), system


def test_cpu_observe_moments_equal_numpy():
    be, sy = _sphere_backend()
    obs = be.observe()
    et = energies(sy.mass, sy.velocity)
    er = 0.5 * sy.inertia * np.sum(sy.angular_velocity ** 2, axis=1)
    s_tr2, s_rot2, s_x = obs["energy_moments"]
    for got, want in ((s_tr2, (et * et).sum()), (s_rot2, (er * er).sum()), (s_x, (et * er).sum())):
        assert got == pytest.approx(want, rel=1e-12)
    from engine.driver.simulate import record

    rec = record(obs, len(et))
    assert rec["sonine_a2_translational"] == pytest.approx(a2_of(et, 3), rel=1e-10)
    assert rec["sonine_a2_rotational"] == pytest.approx(a2_of(er, 3), rel=1e-10)
    assert rec["sonine_a11"] == pytest.approx(cross_cumulant(et.sum(), er.sum(), (et * er).sum(), len(et)),
                                              rel=1e-10)


def test_cpu_ellipsoid_observe_moments_use_the_active_rotational_energy():
    from engine.shapes.spheroid.cpu_backend import CpuEllipsoidBackend
    from engine.physics.rotation import body_omega
    from tests.engine.test_cuda_ellipsoid_simulator import contact, tiny_ellipsoids

    sy = tiny_ellipsoids(mixed=True)
    be = CpuEllipsoidBackend(sy, contact())
    obs = be.observe()
    et = energies(sy.mass, be.vel)
    ep = np.empty(len(et))
    for i in range(len(et)):
        w = body_omega(*be.quat[i], *be.angm[i], *be.inv_i[i], 0.5)
        ep[i] = 0.5 * (w[1] ** 2 / be.inv_i[i, 1] + w[2] ** 2 / be.inv_i[i, 2])
    s_tr2, s_rot2, s_x = obs["energy_moments"]
    assert obs["sonine_rotational_dof"] == 2
    assert s_tr2 == pytest.approx((et * et).sum(), rel=1e-12)
    assert s_rot2 == pytest.approx((ep * ep).sum(), rel=1e-12)
    assert s_x == pytest.approx((et * ep).sum(), rel=1e-12)
    rec = sonine_observables(obs, len(et))
    assert rec["sonine_a2_rotational"] == pytest.approx(a2_of(ep, 2), rel=1e-10)


def test_result_and_batch_files_carry_the_cumulants(tmp_path):
    from engine.analysis.ensemble_stats import Run, aggregate, read_batch_result, write_batch_result
    from engine.output.h5md import read_series
    from engine.driver.simulate import run
    from engine.setup.spec import SimulationSpec

    paths = []
    for seed in (1, 2):
        spec = SimulationSpec(n_particles=64, volume_fraction=0.05, box_length=1.0, e_n=0.8, e_t=-1,
                              velocity_rms=1.0, seed=seed, backend="cpu", snapshots=0, thermalization=0.0,
                              t_end=2e-3, output_interval=5e-4)
        run(spec, tmp_path / f"s{seed}.h5")
        paths.append(tmp_path / f"s{seed}.h5")
    for name in ("sonine_a2_translational", "sonine_a2_rotational", "sonine_a11"):
        s = read_series(paths[0], name)
        assert len(s["value"]) == len(read_series(paths[0], "contacts")["value"]) > 1
        assert np.all(np.isfinite(s["value"])) and np.all(np.abs(s["value"]) < 2)
    groups = aggregate([Run(f"r{i}", p) for i, p in enumerate(paths)])
    out = write_batch_result(tmp_path / "batch.h5", groups)
    g = read_batch_result(out)["groups"][0]
    vals = g["sonine_a2_translational"]["values"]
    assert vals.shape[0] == 2
    assert np.allclose(g["sonine_a2_translational"]["mean"], vals.mean(0))
    assert np.allclose(g["sonine_a2_translational"]["standard_error"], vals.std(0, ddof=1) / math.sqrt(2))
