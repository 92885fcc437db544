"""Linear stability of the homogeneous cooling state (HCS) against the transverse (shear) mode.

Navier–Stokes hydrodynamics of a freely cooling granular gas, linearised about the HCS (Goldhirsch &
Zanetti, PRL 70, 1619 (1993); Brey, Ruiz-Montero & Cubero, PRE 60, 3150 (1999); Garzó, PRE 72, 021106
(2005); for rough spheres Garzó, Santos & Kremer, PRE 97, 052901 (2018)). The transverse momentum of
a Fourier mode k obeys rho d u_perp/dt = -eta k^2 u_perp and is not coupled to density or temperature.
Measured against the thermal speed sqrt(T/m), which decays at rate zeta/2 (dT/dt = -zeta T), the scaled
amplitude u* = u_perp / sqrt(T/m) obeys

    d u*/dt = (zeta/2 - nu k^2) u*,      nu = eta / (n m)  (kinematic viscosity, m^2/s)        (1)

so the mode grows when k < k_c with

    k_c^2 = zeta n m / (2 eta) = (zeta* / (2 eta*)) (256 pi / 25) n^2 sigma^4                  (2)

(sigma = 2a the diameter; eta = eta_0 eta*, eta_0 = (5/(16 sigma^2)) sqrt(m T/pi) the elastic dilute
viscosity; zeta = zeta* nu_0, nu_0 = n T/eta_0). zeta and eta both scale with sqrt(T), so k_c does not
change as the gas cools; a periodic box of edge L is linearly unstable when L > L_c = 2 pi/k_c.
Per collision (ds = omega_E dt, omega_E = 4 sigma^2 n chi sqrt(pi T/m) the Enskog collision frequency
per particle) the growth rate of u* is lambda(k) = zeta/(2 omega_E) - mu(k), mu = nu k^2/omega_E.

What is used here (the derivation of (1)-(2) is standard and was redone; the coefficients below are
quoted from the papers named, from memory checked against an independent implementation — the
denominator nu_eta* - zeta*/2 of the Garzó–Dufty viscosity in SedFoam's GarzoDuftyModViscosity.C):

- cooling rate of the rough gas from Luding's mean-field ODE (Hidalgo et al. 2013; engine/analysis/theory.py) in its
  asymptotic state R/T = r_inf: zeta = (4/3) omega_E (A - B r_inf). For smooth spheres this is
  (1 - e^2) omega_E/3, i.e. zeta* = (5/12) chi (1 - e^2) (Maxwellian; Sonine corrections neglected);
- shear viscosity of inelastic hard spheres, Garzó & Dufty, PRE 59, 5895 (1999), Enskog, first Sonine,
  a2 neglected:  eta* = eta_k* (1 + (4/5) phi chi (1+e)) + (3/5) gamma*,
  eta_k* = (1 - (2/5)(1+e)(1-3e) phi chi) / (nu_eta* - zeta*/2),  nu_eta* = chi (1 - (1-e)^2/4),
  gamma* = (128/(5 pi)) phi^2 chi (1+e).  Dilute elastic limit eta* = 1;
- rough spheres: the smooth-sphere formulas at the effective normal restitution e_eff that gives the
  same HCS cooling rate, (1 - e_eff^2)/4 = A - B r_inf (A, B from e_n and the contact model's e_t,eff).
  This is the "elastic-viscosity / effective-restitution" approximation: the viscosity of elastic
  perfectly rough spheres (Pidduck; Chapman & Cowling's factor 6(1+K)^2/(6+13K), K = q = 2/5, quoted from
  memory) differs from the smooth one by ~5 %, and Garzó, Santos & Kremer (2018; abstract read) find
  that roughness shifts the threshold either way depending on e_t; treat L_c as +-20 %.

Fluctuating hydrodynamics (van Noije, Ernst, Brito & Orza, PRL 79, 411 (1997); Brey, Ruiz-Montero &
Cubero 1999): with the elastic fluctuation–dissipation noise, the mean energy of one transverse mode
pair in units of the temperature, x = <M |u_perp(k)|^2>/T (x = 1 for an uncorrelated Maxwellian gas,
engine/analysis/hydro_modes.py), obeys

    dx/ds = 2 lambda(s) x + 2 mu,        x(0) = 1,                                            (3)

with the stationary value x* = 1/(1 - k_c^2/k^2) for a stable mode (k > k_c) and exponential growth
~ exp(2 lambda s) for an unstable one. While (T, R) follow the ODE, s(tau) = (3/4) int sqrt(T/T0) dtau.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from engine.analysis.theory import collisions_per_particle, luding_coefficients, luding_ode, r_infinity
from engine.setup.params import carnahan_starling_g, e_t_effective


def effective_restitution(e_n: float, e_t: float) -> float:
    """e_eff with (1 - e_eff^2)/4 = A - B r_inf: the smooth-sphere restitution with the same HCS cooling
    rate as rough spheres of (e_n, e_t) (e_t as the contact produces it, e.g. e_t,eff); e_t = -1: e_n."""
    if e_t <= -1.0:
        return e_n
    a, b, _ = luding_coefficients(e_n, e_t)
    loss = a - b * r_infinity(e_n, e_t)
    if not 0.0 <= loss < 0.25:
        raise ValueError(f"A - B r_inf = {loss} outside [0, 1/4): no effective restitution for e_n={e_n}, e_t={e_t}")
    return math.sqrt(1.0 - 4.0 * loss)


def zeta_star(e: float, phi: float) -> float:
    """Reduced cooling rate zeta/nu_0 = (5/12) chi (1 - e^2) (Enskog, Maxwellian; Garzó & Dufty 1999)."""
    return 5.0 / 12.0 * carnahan_starling_g(phi) * (1.0 - e * e)


def eta_star(e: float, phi: float) -> float:
    """Reduced shear viscosity eta/eta_0 of inelastic hard spheres (Garzó & Dufty 1999, first Sonine,
    a2 neglected; see the module docstring). Dilute elastic limit 1."""
    chi = carnahan_starling_g(phi)
    nu_eta = chi * (1.0 - 0.25 * (1.0 - e) ** 2)
    eta_k = (1.0 - 0.4 * (1.0 + e) * (1.0 - 3.0 * e) * phi * chi) / (nu_eta - 0.5 * zeta_star(e, phi))
    gamma = 128.0 / (5.0 * math.pi) * phi * phi * chi * (1.0 + e)
    return eta_k * (1.0 + 0.8 * phi * chi * (1.0 + e)) + 0.6 * gamma


@dataclass(frozen=True)
class ShearStability:
    """Linear shear-mode stability of one scene (SI units; rates per collision are dimensionless)."""

    e_eff: float          # effective normal restitution used in zeta*, eta*
    zeta_star: float      # zeta / nu_0
    eta_star: float       # eta / eta_0
    k_c: float            # critical wavenumber, 1/m (Eq. 2)
    L_c: float            # critical box edge 2 pi/k_c, m
    k_min: float          # smallest wavenumber of the box, 2 pi/L, 1/m
    box_over_Lc: float    # L / L_c (> 1: the k_min shear mode is unstable)
    mean_free_path: float  # 1/(sqrt 2 pi sigma^2 n chi), m
    lambda_kmin: float    # growth rate of u* per collision at k_min (HCS, r = r_inf)
    mu_kmin: float        # viscous rate nu k_min^2 / omega_E
    x_stationary: float   # 1/(1 - k_c^2/k_min^2) for a stable box, nan for an unstable one
    unstable_pairs: int   # number of wavevector pairs (k, -k) of the box with |k| < k_c


def shear_stability(e_n: float, e_t: float, volume_fraction: float, n_particles: int, box_length: float,
                    effective_tangential: bool = True) -> ShearStability:
    """Shear-mode stability of a monodisperse sphere scene (module docstring, Eqs. 1-2).

    e_t: the nominal tangential restitution of the spec (-1 = smooth); with ``effective_tangential`` the
    contact model's e_t,eff (engine.setup.params.e_t_effective) is used, as in the ODE comparison.
    """
    if not 0.0 < volume_fraction < 0.5:
        raise ValueError(f"volume_fraction = {volume_fraction} outside (0, 0.5): Enskog estimate not meaningful")
    if n_particles < 2 or box_length <= 0.0:
        raise ValueError(f"n_particles = {n_particles}, box_length = {box_length}: need N >= 2 and L > 0")
    et = e_t_effective(e_n, e_t) if (effective_tangential and e_t > -1.0) else e_t
    e = effective_restitution(e_n, et)
    n = n_particles / box_length**3
    sigma = 2.0 * (3.0 * volume_fraction / (4.0 * math.pi * n)) ** (1.0 / 3.0)
    chi = carnahan_starling_g(volume_fraction)
    zs, es = zeta_star(e, volume_fraction), eta_star(e, volume_fraction)
    k_c = math.sqrt(zs / (2.0 * es) * 256.0 * math.pi / 25.0) * n * sigma**2
    k_min = 2.0 * math.pi / box_length
    # per collision: zeta/omega_E = (4/3)(A - B r_inf) = (1 - e^2)/3;
    # nu k^2/omega_E = eta* k^2 eta_0/(n m omega_E) = 5 eta* k^2 / (64 pi chi n^2 sigma^4)
    half_zeta = (1.0 - e * e) / 6.0
    mu = 5.0 * es * k_min**2 / (64.0 * math.pi * chi * n**2 * sigma**4)
    lam = half_zeta - mu
    x_st = 1.0 / (1.0 - (k_c / k_min) ** 2) if k_min > k_c else float("nan")
    m_max = int(k_c / k_min) + 1
    grid = np.arange(-m_max, m_max + 1)
    m2 = grid[:, None, None] ** 2 + grid[None, :, None] ** 2 + grid[None, None, :] ** 2
    pairs = int(np.count_nonzero((m2 > 0) & (m2 * k_min**2 < k_c**2))) // 2
    return ShearStability(e_eff=e, zeta_star=zs, eta_star=es, k_c=k_c,
                          L_c=2.0 * math.pi / k_c if k_c > 0 else math.inf, k_min=k_min,
                          box_over_Lc=box_length * k_c / (2.0 * math.pi),
                          mean_free_path=1.0 / (math.sqrt(2.0) * math.pi * sigma**2 * n * chi),
                          lambda_kmin=lam, mu_kmin=mu, x_stationary=x_st, unstable_pairs=pairs)


def predicted_mode_energy(e_n: float, e_t: float, stab: ShearStability, tau, r0: float = 1.0,
                          k_over_kmin: float = 1.0, x0: float = 1.0):
    """x(tau) = <M |u_perp(k)|^2>/T of one transverse mode pair by Eq. 3, with the rough gas's transient:
    zeta(s)/omega_E = (4/3)(A - B r(s)) and s(tau) = (3/4) int sqrt(T/T0) dtau from Luding's ODE (e_t as
    given, normally e_t,eff; r0 = R(0)/T(0)); k = k_over_kmin * k_min. Returns (x, s) arrays like tau."""
    from engine.analysis.ode import solve

    tau = np.asarray(tau, dtype=float)
    a, b, _ = luding_coefficients(e_n, e_t)
    # viscous rate per collision: nu k^2 / omega_E is T-independent; nu/omega_E fixed by the HCS value
    mu = stab.mu_kmin * k_over_kmin**2
    grid = np.unique(np.concatenate([[0.0], np.linspace(0.0, max(float(tau.max()), 1e-9), 2001)]))
    T, R = luding_ode(e_n, e_t, grid, 1.0, r0)
    s_grid = collisions_per_particle(T, grid)
    ratio = R / np.maximum(T, 1e-300)

    def rhs(s, y):
        r = float(np.interp(s, s_grid, ratio))
        lam = 2.0 / 3.0 * (a - b * r) - mu
        return [2.0 * lam * y[0] + 2.0 * mu]

    s_eval = np.interp(tau, grid, s_grid)
    # rtol 1e-10: the rate is piecewise linear in s (kinks at the grid's nodes), which loosens the step
    # control's error estimate; at 1e-10 x(tau) is within ~2e-7 of a 1e-13 integration
    x = solve(rhs, (0.0, float(s_grid[-1])), [x0], np.clip(s_eval, 0.0, s_grid[-1]), rtol=1e-10, atol=1e-12)
    return x[0], s_eval


def onset_tau(tau, x, level: float) -> float:
    """First tau at which x(tau) reaches ``level`` (linear interpolation); inf if it never does."""
    tau, x = np.asarray(tau, float), np.asarray(x, float)
    above = np.nonzero(x >= level)[0]
    if above.size == 0:
        return math.inf
    i = int(above[0])
    if i == 0:
        return float(tau[0])
    return float(tau[i - 1] + (level - x[i - 1]) * (tau[i] - tau[i - 1]) / (x[i] - x[i - 1]))


def box_wavenumbers(stab: ShearStability, k_max: float) -> tuple[np.ndarray, np.ndarray]:
    """Distinct |k|/k_min of the box's wavevector pairs (k, -k) with 0 < |k| < k_max, and how many pairs
    share each."""
    m_max = int(k_max / stab.k_min) + 1
    g = np.arange(-m_max, m_max + 1)
    m2 = (g[:, None, None] ** 2 + g[None, :, None] ** 2 + g[None, None, :] ** 2).ravel()
    m2 = m2[(m2 > 0) & (m2 * stab.k_min**2 < k_max**2)]
    vals, counts = np.unique(m2, return_counts=True)
    return np.sqrt(vals.astype(float)), counts // 2


def predicted_unstable_excess(e_n: float, e_t: float, stab: ShearStability, n_particles: int, tau,
                              r0: float = 1.0):
    """Predicted excess translational energy in the box's unstable shear modes, as a fraction of the
    translational kinetic energy: (2/(3N)) sum over pairs with |k| < k_c and both polarisations of
    (x_k(tau) - 1) (Eq. 3). The ODE describes the thermal part, while the recorded temperature contains
    this flow energy, so it estimates T_measured/T_ODE - 1 once the modes have grown. Zeros for a
    stable box."""
    tau = np.asarray(tau, dtype=float)
    out = np.zeros_like(tau)
    ks, pairs = box_wavenumbers(stab, stab.k_c)
    for kk, cnt in zip(ks, pairs):
        x, _ = predicted_mode_energy(e_n, e_t, stab, tau, r0=r0, k_over_kmin=float(kk))
        out += cnt * 2 * (x - 1.0) * 2.0 / (3.0 * n_particles)
    return out
