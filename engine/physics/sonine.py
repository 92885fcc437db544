"""Velocity-distribution shape: Sonine coefficients from per-scene energy moments (docs/physics.md §6.5).

The observe kernels of every backend add, next to E = sum_i e_i, the second moments

    S2 = sum_i e_i^2                 (J^2)    for e_i = m_i |v_i|^2 / 2 (translation) and the rotational
    X  = sum_i e_tr,i e_rot,i        (J^2)    energy e_rot,i of the dof that exchange energy

in float64, one term per particle, so a record stays O(1) host work (docs/design.md §2). This module turns them into
the dimensionless cumulants; it is the only place that formula lives.

**Energy form.** For d quadratic degrees of freedom of temperature T, the Maxwellian energy of one particle
is Gamma(d/2)-distributed, <e> = d T / 2 and <e^2> = (d/2)(d/2 + 1) T^2, *whatever its mass*. The fourth
cumulant is therefore defined as

    a2 = d/(d+2) <e^2>/<e>^2 - 1,          <.> = (1/N) sum_i                                   (1)

which is 0 for a Maxwellian of any mass (or inertia) distribution at a common temperature, so it is the
correct measure for species and polydisperse scenes. With equal masses, e = m v^2/2 gives
<e^2>/<e>^2 = <v^4>/<v^2>^2 = <c^4>/<c^2>^2 (c = v / sqrt(2T/m)), and (1) is the classic

    a2 = d/(d+2) <c^4>/<c^2>^2 - 1,  i.e. <c^4> = d(d+2)/4 (1 + a2)   (van Noije & Ernst 1998, Eq. 3.4;
                                                                      Brilliantov & Pöschel 2004, §4)

(d = 3 translation: a2 = (3/5) <v^4>/<v^2>^2 - 1; tests/engine/test_sonine.py checks the identity). With
unequal masses the two forms differ already for an equilibrium mixture (the velocity kurtosis of a mass
mixture is not 3), which is why the energy form is used everywhere here.

Translation uses d = 3; rotation of spheres d = 3 (e_rot = I |omega|^2 / 2); spheroids use the two active
rotational dof about the axes perpendicular to the symmetry axis, d = 2 (docs/physics.md §2.4, §2.7; the spin about
the symmetry axis of a frictionless spheroid never changes). The cross cumulant of rough particles,

    a11 = <e_tr e_rot> / (<e_tr> <e_rot>) - 1                                                  (2)

equals the a11 of Santos, Kremer & dos Santos (Phys. Fluids 23, 030604 (2011), arXiv 1009.6180), defined by
<c^2 w^2> = (d_t d_r / 4)(1 + a11) with c^2 = m v^2 / 2T_tr and w^2 = I omega^2 / 2T_rot.

**Frame.** Velocities are taken in the lab frame, not about the centre-of-mass velocity: the engine's scenes
start with zero total momentum (engine/setup/scene.py removes the mean) and pair forces conserve it, so the lab
frame is the centre-of-mass frame to round-off (the result file carries ``momentum`` to check it). A drift u
would add O(m u^2 / T) to (1).

**Sampling error.** For N independent particles drawn from the Maxwellian, the delta method on (1) with the
Gamma(k = d/2) moments <e^n> = k (k+1) ... (k+n-1) T^n gives

    var(a2_hat) = 2 / (k (k+1) N) = 8 / (d (d+2) N)       (= 8/(15 N) for d = 3, 1/N for d = 2)   (3)

and for independent translational and rotational Maxwellians

    var(a11_hat) = 1 / (k_t k_r N) = 4 / (d_t d_r N)      (= 4/(9 N) for spheres)                (4)

The estimator (1) also has a bias: for a Maxwellian the e_i / sum e are Dirichlet-distributed independently of
the sum, which gives exactly E[a2_hat] = -1/(N d/2 + 1) = -2/(N d + 2), far below (3) for N >= 100.
"""

from __future__ import annotations

import math

#: quadratic dof per particle of each family of energies
DOF_TRANSLATION = 3
DOF_ROTATION_SPHERE = 3
DOF_ROTATION_SPHEROID = 2


def sonine_a2(sum_e: float, sum_e2: float, n: int, dof: int) -> float:
    """a2 of Eq. (1) from sum_i e_i (J), sum_i e_i^2 (J^2), the particle count n and the dof d per particle.

    Returns 0.0 where sum_e <= 0 (no energy in these dof: nothing to measure; e.g. spheres started without
    spin), so that result files never hold a non-finite value."""
    if n <= 0 or dof <= 0:
        raise ValueError(f"sonine_a2: n ({n}) and dof ({dof}) must be positive")
    if not sum_e > 0.0:
        return 0.0
    return dof / (dof + 2.0) * n * sum_e2 / (sum_e * sum_e) - 1.0


def cross_cumulant(sum_et: float, sum_er: float, sum_etr: float, n: int) -> float:
    """a11 of Eq. (2) from sum e_tr, sum e_rot (J) and sum e_tr e_rot (J^2); 0.0 where either sum is <= 0."""
    if n <= 0:
        raise ValueError(f"cross_cumulant: n ({n}) must be positive")
    if not (sum_et > 0.0 and sum_er > 0.0):
        return 0.0
    return n * sum_etr / (sum_et * sum_er) - 1.0


def a2_sampling_sigma(n: int, dof: int) -> float:
    """Standard deviation of a2_hat for n Maxwellian particles, Eq. (3)."""
    return math.sqrt(8.0 / (dof * (dof + 2.0) * n))


def a11_sampling_sigma(n: int, dof_t: int = 3, dof_r: int = 3) -> float:
    """Standard deviation of a11_hat for independent Maxwellians, Eq. (4)."""
    return math.sqrt(4.0 / (dof_t * dof_r * n))


def a2_van_noije_ernst(e: float) -> float:
    """First Sonine approximation of a2 in the HCS of smooth inelastic hard spheres, d = 3 (van Noije & Ernst,
    Granular Matter 1, 57 (1998)): a2 = 16 (1-e)(1-2e^2) / (81 - 17e + 30 e^2 (1-e))."""
    return 16.0 * (1.0 - e) * (1.0 - 2.0 * e * e) / (81.0 - 17.0 * e + 30.0 * e * e * (1.0 - e))


def two_temperature_a2(t1: float, t2: float) -> float:
    """Exact a2 of Eq. (1) for an equal-number mixture of two Maxwellians at temperatures t1, t2 (any d, any
    masses): <e^2>/<e>^2 = (d+2)/d (t1^2 + t2^2) / 2 / ((t1 + t2)/2)^2, so a2 = ((t1 - t2)/(t1 + t2))^2."""
    return ((t1 - t2) / (t1 + t2)) ** 2


def shell_a2(dof: int) -> float:
    """Exact a2 of Eq. (1) when every particle carries the same energy (e.g. all |v| equal, equal masses):
    <e^2> = <e>^2, so a2 = d/(d+2) - 1 = -2/(d+2)."""
    return dof / (dof + 2.0) - 1.0


#: the observe dict's key of the raw moments (S_tr2, S_rot2, X) in J^2, and of the rotational dof they count
MOMENTS_KEY = "energy_moments"
ROT_DOF_KEY = "sonine_rotational_dof"
#: result-file observables (dimensionless) written by engine/driver/simulate.record()
OBSERVABLES = ("sonine_a2_translational", "sonine_a2_rotational", "sonine_a11")


def sonine_sums(s_tr2: float, s_rot2: float, s_x: float, rot_dof: int) -> dict:
    """The entries a backend's observe() adds for this module: the raw moments and the rotational dof."""
    return {MOMENTS_KEY: (float(s_tr2), float(s_rot2), float(s_x)), ROT_DOF_KEY: int(rot_dof)}


def sonine_observables(obs: dict, n: int) -> dict:
    """{sonine_a2_translational, sonine_a2_rotational, sonine_a11} of one observe() dict of n particles
    (Eqs. 1-2), or {} where the backend gives no moments. The rotational energy is the active one where the
    backend reports it (spheroids: ``kinetic_energy_rotational_active``, d = 2), else the total (d = 3)."""
    mom = obs.get(MOMENTS_KEY)
    if mom is None:
        return {}
    s_tr2, s_rot2, s_x = mom
    e_tr = obs["kinetic_energy_translational"]
    e_rot = obs.get("kinetic_energy_rotational_active", obs["kinetic_energy_rotational"])
    return {"sonine_a2_translational": sonine_a2(e_tr, s_tr2, n, DOF_TRANSLATION),
            "sonine_a2_rotational": sonine_a2(e_rot, s_rot2, n, int(obs[ROT_DOF_KEY])),
            "sonine_a11": cross_cumulant(e_tr, e_rot, s_x, n)}
