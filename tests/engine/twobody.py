"""Two-sphere collisions with the real CPU backend, for the contact-law tests."""

from __future__ import annotations

import math

import numpy as np

from engine.backends.base import ContactParams, SphereSystem
from engine.shapes.sphere.cpu_backend import CpuBackend
from engine.setup.params import Q_SPHERE, gamma_n_from_restitution, k_t_paper

RADIUS = 0.01     # m
MASS = 1.0e-2     # kg
K_N = 1.0e5       # N/m


def contact_time(k_n: float = K_N, mass: float = MASS) -> float:
    return math.pi * math.sqrt(0.5 * mass / k_n)


def collide(v_rel, *, e_n=0.8, e_t=None, friction=None, omega1=(0.0, 0.0, 0.0), omega2=(0.0, 0.0, 0.0),
            dt_fraction=50, k_t=None, precision="float64", gap_fraction=0.01):
    """Shoot sphere 1 (at -x) at sphere 2 (at +x) with relative velocity v_rel; return both after.

    The pair starts gap_fraction of a radius apart (1 % by default), so the contact begins inside the first step or two
    and ends long before the returned state (3 contact times later).
    Returns a dict with velocities, angular velocities, positions and the backend.
    """
    m12 = 0.5 * MASS
    gamma = gamma_n_from_restitution(e_n, K_N, m12)
    if k_t is None and e_t is not None:
        k_t = k_t_paper(e_t, K_N)
    tc = contact_time()
    dt = tc / dt_fraction
    box = 1.0
    gap = gap_fraction * RADIUS
    pos = np.array([[0.5 - RADIUS - gap / 2, 0.5, 0.5], [0.5 + RADIUS + gap / 2, 0.5, 0.5]])
    v_rel = np.asarray(v_rel, float)
    vel = np.array([0.5 * v_rel, -0.5 * v_rel])
    inertia = Q_SPHERE * MASS * RADIUS**2
    system = SphereSystem(box, pos, vel, np.array([omega1, omega2], float), np.tile([1.0, 0, 0, 0], (2, 1)),
                          np.full(2, RADIUS), np.full(2, MASS), np.full(2, inertia))
    params = ContactParams(k_n=K_N, gamma_n_coef=gamma / math.sqrt(m12), k_t=k_t, friction=friction, dt=dt,
                           skin=0.4 * RADIUS, precision=precision, overlap_limit=0.5)
    be = CpuBackend(system, params)
    speed = max(np.linalg.norm(v_rel), 1e-12)
    approach = gap / max(abs(v_rel[0]), 1e-12)
    be.advance(int((approach + 3 * tc) / dt) + 1)
    return {"velocity": be.vel.copy(), "omega": be.omega.copy(), "position": be.pos.copy(), "backend": be,
            "speed": speed}


def contact_point_velocity(vel, omega, n):
    """g = v1 - v2 - a (w1 + w2) x n with n from 2 to 1 (docs/physics.md §1.7)."""
    return vel[0] - vel[1] - RADIUS * np.cross(omega[0] + omega[1], n)
