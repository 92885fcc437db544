"""Hydrodynamic-mode observables of one frame: shear (transverse) velocity modes and S(k_min).

For the three smallest wavevectors of a periodic cubic box of edge L, k_a = (2 pi/L) e_a (a = x, y, z):

    U[a, b] = sum_i m_i v_ib exp(i k_a r_ia) / M,        M = sum_i m_i              (m/s)     (1)
    rho[a]  = sum_i exp(i k_a r_ia)                                                            (2)

U[a, b] with b != a is a transverse (shear) mode — two polarisations per direction, six in all — and
U[a, a] the longitudinal (sound) mode. The velocity field v_b(r) = A sin(k r_a + phase) gives
|U[a, b]| = A/2 (exactly when the particles sample the phase uniformly), so ``2 |U|`` is the shear
amplitude, and

    E[a, b] = M |U[a, b]|^2                                                            (J)       (3)

is the kinetic energy of that flow (the +-k pair: M A^2/4 = (1/2) M <v_b^2>).

Normalisation (derived here): for velocities independent of positions with zero mean and
<v_ib^2> = T/m_i (a Maxwellian at temperature T per degree of freedom, any masses),
<M |U[a, b]|^2> = sum_i m_i^2 (T/m_i) / M = T. So x = E/T = 1 is the thermal-noise level of every mode
(equipartition: the cos and sin parts of the +-k pair are two degrees of freedom of T/2 each), and
E/E_tr = 2/(3N) per mode. |U|^2 M/T of one mode is exponentially distributed (|complex Gaussian|^2),
so the mean x over the six shear modes of one frame scatters by 1/sqrt(6) ~ 41 %.

Structure factor S(k_a) = |rho[a]|^2 / N: 1 for uncorrelated positions (ideal gas), each direction
exponentially distributed about its mean, so the mean over the three directions scatters by
1/sqrt(3) ~ 58 % per frame; for hard spheres at small k it tends to the compressibility value
S(0) = (1 - phi)^4 / (1 + 4 phi + 4 phi^2 - 4 phi^3 + phi^4) (Carnahan–Starling), 0.94 at phi = 0.008.
A density wave, clusters and bands raise it far above 1.

Units SI; positions may be wrapped or unwrapped (exp(i k_a r_a) is L-periodic).
"""

from __future__ import annotations

import math

import numpy as np

#: (direction a, polarisation b) of the six transverse modes
SHEAR_MODES = tuple((a, b) for a in range(3) for b in range(3) if a != b)


def structure_factor_cs(phi: float) -> float:
    """S(k -> 0) of equilibrium hard spheres from the Carnahan–Starling equation of state."""
    return (1.0 - phi) ** 4 / (1.0 + 4.0 * phi + 4.0 * phi**2 - 4.0 * phi**3 + phi**4)


def _check(pos, vel, box_length, mass):
    pos = np.asarray(pos, dtype=np.float64)
    vel = np.asarray(vel, dtype=np.float64)
    if pos.ndim != 2 or pos.shape[1] != 3 or vel.shape != pos.shape:
        raise ValueError(f"positions {pos.shape} and velocities {vel.shape} must both be (N, 3)")
    if pos.shape[0] < 1:
        raise ValueError("a frame needs at least one particle")
    if not (box_length > 0.0 and math.isfinite(box_length)):
        raise ValueError(f"box_length = {box_length} must be a finite number > 0 (m)")
    n = pos.shape[0]
    if mass is None:
        m = np.ones(n)
    else:
        m = np.broadcast_to(np.asarray(mass, dtype=np.float64), (n,))
        if np.any(m <= 0.0):
            raise ValueError("mass: every particle mass must be > 0 (kg)")
    return pos, vel, m


def mode_amplitudes(pos, vel, box_length: float, mass=None):
    """(U, rho) of Eqs. 1-2: U complex (3, 3) in m/s (row = wavevector direction, column = velocity
    component), rho complex (3,). mass: (N,) or scalar in kg (None = equal masses)."""
    pos, vel, m = _check(pos, vel, box_length, mass)
    phase = np.exp(1j * (2.0 * math.pi / box_length) * pos)      # (N, 3): exp(i k_a r_ia)
    u = (phase * m[:, None]).T @ vel / m.sum()                    # U[a, b]
    return u, phase.sum(axis=0)


def frame_modes(pos, vel, box_length: float, mass=None) -> dict:
    """Hydrodynamic-mode observables of one frame (module docstring).

    Returns: ``temperature`` (J, sum m |v - V|^2 / (3N), V the centre-of-mass velocity),
    ``E_shear`` (6,) and ``E_long`` (3,) mode energies in J (Eq. 3, order of SHEAR_MODES / x, y, z),
    ``x_shear``, ``x_long`` (mean mode energy / temperature; 1 = thermal noise), ``shear_fraction``
    (sum of the six shear-mode energies / translational kinetic energy; 4/N for noise),
    ``shear_amplitude`` (6,) = 2 |U[a, b]| in m/s, ``S_dir`` (3,) and ``S`` (their mean).
    """
    pos, vel, m = _check(pos, vel, box_length, mass)
    n = pos.shape[0]
    u, rho = mode_amplitudes(pos, vel, box_length, m)
    big_m = m.sum()
    v_cm = (m[:, None] * vel).sum(axis=0) / big_m
    e_kin = 0.5 * float(np.sum(m[:, None] * (vel - v_cm) ** 2))
    temp = 2.0 * e_kin / (3.0 * n)
    e_shear = np.array([big_m * abs(u[a, b]) ** 2 for a, b in SHEAR_MODES])
    e_long = np.array([big_m * abs(u[a, a]) ** 2 for a in range(3)])
    s_dir = np.abs(rho) ** 2 / n
    with np.errstate(divide="ignore", invalid="ignore"):
        return {
            "temperature": temp,
            "E_shear": e_shear,
            "E_long": e_long,
            "x_shear": float(e_shear.mean() / temp) if temp > 0 else math.nan,
            "x_long": float(e_long.mean() / temp) if temp > 0 else math.nan,
            "shear_fraction": float(e_shear.sum() / e_kin) if e_kin > 0 else math.nan,
            "shear_amplitude": np.array([2.0 * abs(u[a, b]) for a, b in SHEAR_MODES]),
            "S_dir": s_dir,
            "S": float(s_dir.mean()),
        }


def file_mode_series(path) -> dict:
    """Frame-by-frame :func:`frame_modes` of a result file's snapshots (engine/output/h5md.py layout).

    Returns arrays over the K frames: ``step``, ``time`` (s), ``temperature``, ``x_shear``, ``x_long``,
    ``shear_fraction``, ``S``, ``S_dir`` (K, 3), and ``n_particles``, ``box_length``. A file without
    snapshot frames raises ValueError naming it.
    """
    from engine.output.h5md import read_frames

    keys = ("temperature", "x_shear", "x_long", "shear_fraction", "S")
    rows, steps, times, n, box = [], [], [], 0, 0.0
    for fr in read_frames(path):
        rows.append(frame_modes(fr["position"], fr["velocity"], fr["box"], fr["mass"]))
        steps.append(fr["step"])
        times.append(fr["time"])
        n, box = fr["position"].shape[0], fr["box"]
    out = {key: np.array([r[key] for r in rows], dtype=float) for key in keys}
    out["S_dir"] = np.array([r["S_dir"] for r in rows], dtype=float).reshape(len(rows), 3)
    out["step"] = np.array(steps, dtype=np.int64)
    out["time"] = np.array(times, dtype=float)
    out["n_particles"] = int(n)
    out["box_length"] = float(box)
    return out
