"""Mean-field references for homogeneous cooling (Hidalgo et al. 2013, Eqs. 1-2; Rubio-Largo et al. 2015, Eqs. 27-29).

Temperatures are per degree of freedom in J (k_B = 1): T = 2 E_tr/(3N), R = 2 E_rot/(3N) for spheres.
Luding, Huthmann, McNamara & Zippelius, PRE 58, 3416 (1998), as quoted by Hidalgo et al. (2013):

    dT/dtau = -A T^(3/2) + B T^(1/2) R,      dR/dtau = B T^(3/2) - C T^(1/2) R,
    A = (1 - e_n^2)/4 + eta (1 - eta),  B = eta^2/q,  C = (eta/q)(1 - eta/q),  eta = q (1 + e_t)/(2q + 2),
    tau = (2/3) G T(0)^(1/2) t,  G = 8 (2a)^2 (N/V) sqrt(pi/m) g(2a)  (Carnahan-Starling g).

with T and R normalised by T(0). The equations were checked against an independent derivation and
the LSODA values of docs/physics.md §6.3 (tests/engine/test_theory.py); they are integrated with engine/analysis/ode.py.
"""

from __future__ import annotations

import math

import numpy as np

from engine.setup.params import Q_SPHERE, carnahan_starling_g


def luding_coefficients(e_n: float, e_t: float, q: float = Q_SPHERE) -> tuple[float, float, float]:
    """(A, B, C) of Hidalgo et al. (2013) Eqs. 1-2."""
    eta = q * (1.0 + e_t) / (2.0 * q + 2.0)
    a = (1.0 - e_n**2) / 4.0 + eta * (1.0 - eta)
    b = eta**2 / q
    c = (eta / q) * (1.0 - eta / q)
    return a, b, c


def luding_per_collision(t, r, coeffs):
    """Changes of T/T0 and R/T0 per collision and particle in Luding's Maxwellian closure, at the state (t, r)
    = (T/T0, R/T0): Hidalgo et al. (2013) Eqs. 1-2 divided by the Enskog collision frequency (3/4) (T/T0)^(1/2) per unit
    tau, i.e. (4/3) (-A t + B r) and (4/3) (B t - C r). coeffs = (A, B, C) of :func:`luding_coefficients`; t, r scalars
    or arrays. :func:`luding_ode` integrates these times the Enskog frequency."""
    a, b, c = coeffs
    return 4.0 / 3.0 * (-a * t + b * r), 4.0 / 3.0 * (b * t - c * r)


def r_infinity(e_n: float, e_t: float, q: float = Q_SPHERE) -> float:
    """Asymptotic R/T of the homogeneous cooling state, h + sqrt(1 + h^2), h = (A - C)/(2B)."""
    a, b, c = luding_coefficients(e_n, e_t, q)
    if b == 0.0:
        return math.inf
    h = (a - c) / (2.0 * b)
    return h + math.sqrt(1.0 + h * h)


def luding_ode(e_n: float, e_t: float, tau, t0: float = 1.0, r0: float = 1.0, q: float = Q_SPHERE,
               rates=None):
    """T(tau)/T(0) and R(tau)/T(0) solving Hidalgo et al. (2013) Eqs. 1-2
    (Dormand-Prince 5(4) of engine/analysis/ode.py, rtol 1e-10).

    tau: increasing array of scaled times starting anywhere >= 0; returns two arrays like tau.
    rates: optional callable T -> (f_tr, f_rot) that scales the right-hand sides of dT/dtau and dR/dtau (a
    correction to the collision operator measured elsewhere, e.g. engine.validation.hcs_dsmc's soft contact).
    """
    from engine.analysis.ode import solve

    tau = np.asarray(tau, dtype=float)
    coeffs = luding_coefficients(e_n, e_t, q)

    def rhs(_, y):
        t, r = max(y[0], 0.0), y[1]
        freq = 0.75 * math.sqrt(t)          # Enskog's collisions per particle per unit tau
        d_t, d_r = luding_per_collision(t, r, coeffs)
        if rates is None:
            return [freq * d_t, freq * d_r]
        f_tr, f_rot = rates(t)
        return [f_tr * freq * d_t, f_rot * freq * d_r]

    if tau.size == 0:
        return tau.copy(), tau.copy()
    span = (0.0, float(max(tau.max(), 0.0)))
    if span[1] == 0.0:
        return np.full_like(tau, t0), np.full_like(tau, r0)
    y = solve(rhs, span, [t0, r0], np.clip(tau, 0.0, None), rtol=1e-10, atol=1e-13)
    return y[0], y[1]


def collisions_per_particle(t_over_t0, tau) -> np.ndarray:
    """s(tau) = (3/4) int_0^tau (T/T0)^(1/2) dtau': collisions per particle by tau for a Maxwellian gas (the
    tau of Hidalgo et al. 2013, in which the Enskog collision frequency is (3/4) (T/T0)^(1/2)); cumulative trapezoid on
    the grid."""
    root = np.sqrt(np.maximum(np.asarray(t_over_t0, dtype=float), 0.0))
    return 0.75 * np.concatenate([[0.0], np.cumsum(0.5 * (root[1:] + root[:-1]) * np.diff(tau))])


def collision_g(radius: float, number_density: float, mass: float, volume_fraction: float) -> float:
    """G = 8 (2a)^2 n sqrt(pi/m) g(2a) in s^-1 J^-1/2 (Hidalgo et al. 2013)."""
    return 8.0 * (2.0 * radius) ** 2 * number_density * math.sqrt(math.pi / mass) * \
        carnahan_starling_g(volume_fraction)


def tau_factor(radius: float, number_density: float, mass: float, volume_fraction: float,
               temperature0: float) -> float:
    """d tau / d t = (2/3) G T(0)^(1/2) in 1/s (Hidalgo et al. 2013)."""
    return 2.0 / 3.0 * collision_g(radius, number_density, mass, volume_fraction) * math.sqrt(temperature0)


def tau_factor_for(spec) -> float:
    """tau = tau_factor_for(spec) * t for a sphere spec at its starting temperature."""
    from engine.setup.params import derive

    p = derive(spec)
    return tau_factor(p.radius, p.number_density, p.mass, spec.volume_fraction, p.temperature0)


def haff(t, t0_inverse: float):
    """Haff's law T(t)/T(0) = (1 + t/t0)^-2 (Rubio-Largo et al. 2015, Eq. 27 with 1/t0 = t0_inverse)."""
    return (1.0 + np.asarray(t, dtype=float) * t0_inverse) ** -2


#: Degrees of freedom that share the energy in Haff's law: smooth spheres (translation only) and smooth
#: prolate spheroids (translation + the two rotations perpendicular to the axis; Rubio-Largo et al. 2015).
DOF_SMOOTH_SPHERE, DOF_SMOOTH_SPHEROID = 3, 5


def haff_rate(e_n: float, collision_rate0: float, dof: int) -> float:
    """Haff's 1/t0 = (1 - e_n^2) Gamma_0 / (2 D_f) for smooth particles whose D_f degrees of freedom
    share the energy equally (each collision loses (1 - e^2) T; docs/physics.md §6.2): D_f = 3 for smooth
    spheres, 5 for prolate spheroids (Rubio-Largo et al. 2015); Gamma_0 the collision frequency per particle at T(0)."""
    return (1.0 - e_n**2) * collision_rate0 / (2.0 * dof)


def haff_rate_smooth_spheres(e_n: float, radius: float, number_density: float, mass: float,
                             volume_fraction: float, temperature0: float) -> float:
    """1/t0 = (2/3)(1 - e^2)(2a)^2 n g sqrt(pi T0/m) for smooth spheres (docs/physics.md §6.2)."""
    return 2.0 / 3.0 * (1.0 - e_n**2) * (2.0 * radius) ** 2 * number_density * \
        carnahan_starling_g(volume_fraction) * math.sqrt(math.pi * temperature0 / mass)
