"""Hydrodynamic-mode observables (engine/analysis/hydro_modes.py) and the linear shear-stability theory
(engine/analysis/shear_instability.py): exact cases, sampling-error bounds, and the theory's limits."""

import math

import numpy as np
import pytest

from engine.analysis.hydro_modes import SHEAR_MODES, file_mode_series, frame_modes, mode_amplitudes, structure_factor_cs
from engine.analysis.shear_instability import (effective_restitution, eta_star, predicted_mode_energy,
                                               predicted_unstable_excess, shear_stability, zeta_star)

L = 2.0


def _shear_frame(n, amp, sigma, rng):
    """v_x = amp sin(2 pi y / L) + Gaussian noise (sigma per component); y on a shuffled uniform lattice,
    x and z uniform random."""
    y = (np.arange(n) + 0.5) * L / n
    pos = np.column_stack([rng.uniform(0, L, n), rng.permutation(y), rng.uniform(0, L, n)])
    vel = sigma * rng.standard_normal((n, 3))
    vel[:, 0] += amp * np.sin(2 * math.pi * pos[:, 1] / L)
    return pos, vel


def test_uniform_shear_flow_recovers_its_amplitude_exactly_without_noise():
    rng = np.random.default_rng(1)
    pos, vel = _shear_frame(1000, 0.7, 0.0, rng)
    fm = frame_modes(pos, vel, L)
    k = SHEAR_MODES.index((1, 0))                     # wavevector along y, velocity along x
    assert fm["shear_amplitude"][k] == pytest.approx(0.7, rel=1e-12)
    # the flow's kinetic energy M <v_x^2>/2 = M A^2/4 sits in that one mode
    assert fm["E_shear"][k] == pytest.approx(1000 * 0.7**2 / 4, rel=1e-12)
    # modes of v_y, v_z are empty; v_x seen along z (random z) only as sampling noise, <M|U|^2> = A^2/2
    for j, (a, b) in enumerate(SHEAR_MODES):
        if b != 0:
            assert fm["E_shear"][j] < 1e-20
    assert fm["E_shear"][SHEAR_MODES.index((2, 0))] < 10 * 0.7**2 / 2


def test_uniform_shear_flow_on_thermal_noise_recovers_its_amplitude():
    # noise on 2|U|: each of Re, Im of U has SD sigma/sqrt(2N), so 2|U| scatters by sigma sqrt(2/N) = 0.0089
    n, amp, sigma = 50_000, 0.5, 1.0
    rng = np.random.default_rng(2)
    tol = 5 * sigma * math.sqrt(2.0 / n)
    for _ in range(5):
        pos, vel = _shear_frame(n, amp, sigma, rng)
        fm = frame_modes(pos, vel, L)
        k = SHEAR_MODES.index((1, 0))
        assert abs(fm["shear_amplitude"][k] - amp) < tol
        # the five other shear modes stay at the noise level x ~ 1 (exponential; 5-mode mean < 4 at >> 5 sigma)
        temp = fm["temperature"]
        assert np.mean(np.delete(fm["E_shear"], k)) / temp < 4.0
        assert fm["E_shear"][k] / temp > 100.0       # M A^2/4 / T = 3125 here


def test_maxwellian_gives_thermal_noise_level_for_any_masses():
    # <M |U|^2> = sum m_i^2 (T/m_i)/M = T: x = 1; per frame the 6-mode mean scatters by 1/sqrt(6),
    # over 400 frames the SE is 0.020 (longitudinal 3 modes: 0.029).
    rng = np.random.default_rng(3)
    n, frames, temp = 400, 400, 2.5
    xs, xl, fr = [], [], []
    for _ in range(frames):
        m = rng.uniform(1.0, 3.0, n)
        pos = rng.uniform(0, L, (n, 3))
        vel = rng.standard_normal((n, 3)) * np.sqrt(temp / m)[:, None]
        u, _ = mode_amplitudes(pos, vel, L, m)
        xs.append(np.mean([m.sum() * abs(u[a, b]) ** 2 for a, b in SHEAR_MODES]) / temp)
        fm = frame_modes(pos, vel, L, m)
        xl.append(fm["x_long"])
        fr.append(fm["shear_fraction"])
    assert abs(np.mean(xs) - 1.0) < 4 * 1.0 / math.sqrt(6 * frames)
    assert abs(np.mean(xl) - 1.0) < 4 * 1.0 / math.sqrt(3 * frames)
    assert np.mean(fr) == pytest.approx(4.0 / n, rel=0.15)   # six modes of T out of 3NT/2


def test_random_uniform_positions_give_ideal_gas_structure_factor():
    # E|sum exp(i theta_j)|^2 = N exactly for independent uniform phases; per direction ~exponential (SD 1)
    rng = np.random.default_rng(4)
    n, frames = 500, 400
    s = [frame_modes(rng.uniform(0, L, (n, 3)), np.zeros((n, 3)), L)["S"] for _ in range(frames)]
    assert abs(np.mean(s) - 1.0) < 4 / math.sqrt(3 * frames)


def j1(x: float) -> float:
    """Bessel J_1 by its power series sum_m (-1)^m (x/2)^(2m+1) / (m! (m+1)!): 25 terms reach rounding for |x| <= 2."""
    return sum((-1) ** m * (x / 2) ** (2 * m + 1) / (math.factorial(m) * math.factorial(m + 1)) for m in range(25))


def test_density_wave_gives_its_exact_structure_factor():
    assert j1(1.0) == pytest.approx(0.44005058574493352, rel=1e-15)   # Abramowitz & Stegun, table 9.1
    # x_j = u_j + b sin(k u_j), u_j a uniform lattice: sum_j exp(i k x_j) = sum_n J_n(kb) sum_j e^{i(n+1)k u_j}
    # = -N J_1(kb) (all other terms vanish on the lattice up to J_{N-1}), so S_x = N J_1(kb)^2 exactly.
    rng = np.random.default_rng(5)
    n = 2000
    k = 2 * math.pi / L
    for kb in (0.05, 0.3, 1.0):
        u = (np.arange(n) + 0.5) * L / n
        x = u + (kb / k) * np.sin(k * u)
        pos = np.column_stack([x, rng.uniform(0, L, n), rng.uniform(0, L, n)])
        fm = frame_modes(pos, np.zeros((n, 3)), L)
        assert fm["S_dir"][0] == pytest.approx(n * j1(kb) ** 2, rel=1e-9)
        # translating the wave or wrapping positions by L changes nothing
        fm2 = frame_modes(pos + np.array([0.37 * L, 3 * L, -L]), np.zeros((n, 3)), L)
        assert fm2["S_dir"][0] == pytest.approx(fm["S_dir"][0], rel=1e-9)


def test_bad_frames_are_refused_with_the_field_named():
    with pytest.raises(ValueError, match="box_length"):
        frame_modes(np.zeros((3, 3)), np.zeros((3, 3)), 0.0)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        frame_modes(np.zeros((3, 2)), np.zeros((3, 2)), 1.0)
    with pytest.raises(ValueError, match="mass"):
        frame_modes(np.zeros((3, 3)), np.zeros((3, 3)), 1.0, mass=np.array([1.0, 0.0, 1.0]))


def test_file_mode_series_reads_the_snapshot_frames(tmp_path):
    from engine.output.h5md import H5MDWriter

    rng = np.random.default_rng(6)
    n = 50
    frames = [(rng.uniform(0, L, (n, 3)), rng.standard_normal((n, 3))) for _ in range(3)]
    w = H5MDWriter(tmp_path / "r.h5", n=n, box_length=L, spec_json="{}", derived={}, radius=np.full(n, 0.01),
                   mass=np.full(n, 2.0))
    for j, (p, v) in enumerate(frames):
        w.snapshot(10 * j, 0.1 * j, {"position": p, "velocity": v})
    path = w.finish({})
    series = file_mode_series(path)
    assert list(series["step"]) == [0, 10, 20]
    for j, (p, v) in enumerate(frames):
        fm = frame_modes(p, v, L, np.full(n, 2.0))
        assert series["x_shear"][j] == pytest.approx(fm["x_shear"], rel=1e-12)
        assert series["S"][j] == pytest.approx(fm["S"], rel=1e-12)
    w2 = H5MDWriter(tmp_path / "none.h5", n=n, box_length=L, spec_json="{}", derived={})
    with pytest.raises(ValueError, match="no snapshot frames"):
        file_mode_series(w2.finish({}))


# ---- linear theory --------------------------------------------------------------------------------------

def test_transport_coefficients_have_their_limits():
    assert eta_star(1.0, 1e-12) == pytest.approx(1.0, abs=1e-9)          # elastic dilute: eta = eta_0
    assert zeta_star(1.0, 0.1) == 0.0
    # dilute smooth spheres: eta* = 1/(nu_eta* - zeta*/2), nu_eta* = (3 - e)(1 + e)/4 (Brey et al. 1998)
    e = 0.8
    assert eta_star(e, 1e-12) == pytest.approx(1.0 / ((3 - e) * (1 + e) / 4 - 5 / 24 * (1 - e * e)), rel=1e-9)
    assert effective_restitution(0.7, -1.0) == 0.7                         # smooth: e_eff = e_n
    # elastic limit = Enskog's dense hard-sphere viscosity, eta/eta_0 = 1/chi + 0.8 b n + 0.7614 (b n)^2 chi,
    # b n = 4 phi (Chapman & Cowling); the first-Sonine form differs in the last coefficient (0.771)
    for phi in (0.01, 0.1, 0.2):
        chi = (1 - phi / 2) / (1 - phi) ** 3
        enskog = 1 / chi + 0.8 * 4 * phi + 0.7614 * (4 * phi) ** 2 * chi
        assert eta_star(1.0, phi) == pytest.approx(enskog, rel=0.01)
    assert structure_factor_cs(1e-9) == pytest.approx(1.0)


def test_critical_wavenumber_matches_the_dimensional_balance():
    # k_c^2 = zeta n m / (2 eta) with zeta = (1 - e^2) omega_E / 3 and eta = eta_0 eta*, written out in SI
    e, phi, n_part, box = 0.7, 0.02, 5000, 3.0
    st = shear_stability(e, -1.0, phi, n_part, box)
    n = n_part / box**3
    sigma = 2 * (3 * phi / (4 * math.pi * n)) ** (1 / 3)
    m, temp = 1.3, 0.7                                                      # cancel out
    chi = (1 - phi / 2) / (1 - phi) ** 3
    omega = 4 * sigma**2 * n * chi * math.sqrt(math.pi * temp / m)
    eta = 5 / (16 * sigma**2) * math.sqrt(m * temp / math.pi) * eta_star(e, phi)
    assert st.k_c == pytest.approx(math.sqrt((1 - e * e) * omega / 3 * n * m / (2 * eta)), rel=1e-12)
    assert st.L_c == pytest.approx(2 * math.pi / st.k_c)
    assert st.box_over_Lc == pytest.approx(box / st.L_c)


def test_hidalgo_2013_box_is_stable_and_a_dense_large_box_is_not():
    for e in (0.8, 0.6):
        st = shear_stability(e, e, 0.008, 4096, 2.0)
        assert st.box_over_Lc < 0.35 and st.lambda_kmin < 0 and st.unstable_pairs == 0
        assert 1.0 < st.x_stationary < 1.2
        big = shear_stability(e, e, 0.1, 32768, 4.0)
        assert big.box_over_Lc > 2.5 and big.lambda_kmin > 0 and big.unstable_pairs >= 3


def test_mode_energy_prediction_limits():
    tau = np.linspace(0, 60, 61)
    # elastic gas: no cooling, the mode stays at the noise level
    st = shear_stability(1.0, -1.0, 0.05, 4096, 2.0)
    x, s = predicted_mode_energy(1.0, -1.0, st, tau)
    assert np.allclose(x, 1.0, atol=1e-6) and s[-1] == pytest.approx(0.75 * 60)
    # stable inelastic box: relaxes to x* = 1/(1 - k_c^2/k^2)
    st = shear_stability(0.8, -1.0, 0.05, 1000, 2.0)
    x, _ = predicted_mode_energy(0.8, -1.0, st, tau)
    assert x[-1] == pytest.approx(st.x_stationary, rel=1e-3)
    assert np.all(predicted_unstable_excess(0.8, -1.0, st, 1000, tau) == 0)
    # unstable box: grows as exp(2 lambda s) at late times (smooth: no rotational transient)
    st = shear_stability(0.6, -1.0, 0.1, 32768, 4.0)
    x, s = predicted_mode_energy(0.6, -1.0, st, tau)
    x_star = st.mu_kmin / (-st.lambda_kmin)                # x(s) = x* + (1 - x*) exp(2 lambda s)
    rate = np.log((x[-1] - x_star) / (x[-11] - x_star)) / (s[-1] - s[-11])
    assert rate == pytest.approx(2 * st.lambda_kmin, rel=1e-4)
    assert np.all(np.diff(predicted_unstable_excess(0.6, -1.0, st, 32768, tau)) > 0)
