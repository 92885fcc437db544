"""Small many-particle scenes driven directly through a backend."""

from __future__ import annotations

import math

import numpy as np

from engine.backends.base import ContactParams, SphereSystem
from engine.setup.params import Q_SPHERE, gamma_n_from_restitution, k_t_paper
from engine.setup.scene import maxwellian, place_spheres

RADIUS, MASS, K_N = 0.01, 1.0e-2, 1.0e5


def gas(n=64, phi=0.2, e_n=0.8, e_t=0.8, v_rms=0.05, seed=1, skin=0.4, friction=None, precision="float64",
        dt_fraction=50, orientation=True):
    """(system, params) of a periodic rough-sphere gas of radius 1 cm."""
    rng = np.random.default_rng(seed)
    box = (n * 4 / 3 * math.pi * RADIUS**3 / phi) ** (1 / 3)
    pos = place_spheres(n, box, RADIUS, rng)
    vel = maxwellian(n, v_rms, rng)
    inertia = Q_SPHERE * MASS * RADIUS**2
    omega = maxwellian(n, v_rms * math.sqrt(MASS / inertia), rng)
    system = SphereSystem(box, pos, vel, omega, np.tile([1.0, 0, 0, 0], (n, 1)), np.full(n, RADIUS),
                          np.full(n, MASS), np.full(n, inertia))
    m12 = MASS / 2
    tc = math.pi * math.sqrt(m12 / K_N)
    params = ContactParams(k_n=K_N, gamma_n_coef=gamma_n_from_restitution(e_n, K_N, m12) / math.sqrt(m12),
                           k_t=None if e_t == -1 else k_t_paper(e_t, K_N), friction=friction,
                           dt=tc / dt_fraction, skin=skin * RADIUS, precision=precision,
                           orientation=orientation, overlap_limit=0.2)
    return system, params


def total_energy(be) -> float:
    o = be.observe()
    return o["kinetic_energy_translational"] + o["kinetic_energy_rotational"] + o["elastic_energy"]
