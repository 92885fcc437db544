"""The ``hertz`` shape's CPU plug-in: the sphere's translation, rotation and lazy orientations (a smooth contact
exerts no torque, so a Hertz sphere's spin never changes), its own pair evaluator and elastic energy.

Interface: engine/shapes/sphere/kernels.py's docstring. ``law`` is unused (no tangential constants), ``ext`` the
sphere's (marks, begun): the collision counter counts here too.
"""

from __future__ import annotations

import math

import numba

from engine.physics.contact import contact_begins, min_image
from engine.shapes.sphere.kernels import observe as sphere_observe
from engine.shapes.sphere.kernels import pre_step, rotate, settle  # noqa: F401  (the sphere's, unchanged)
from tests.engine.shapes_demo.hertz.law import hertz_energy, hertz_force

NAME = "hertz"
EXACT_DISPLACEMENT = False


@numba.njit(inline="always")
def pair(i, kk, j, pos, vel, vel_p, spin, quat, rad, inv_m, hist, box, inv_box, half, k_n, gn_coef, law, dt,
         ext):
    """Hertz force on i from list slot kk (neighbour j), no torque; the slot keeps the overlap (hist[i, kk, 3])
    for the collision counter; returns (F, T, overlap relative to the smaller radius or 0)."""
    ri = rad[i]
    rj = rad[j]
    rx = min_image(pos[i, 0] - pos[j, 0], box, inv_box, half)
    ry = min_image(pos[i, 1] - pos[j, 1], box, inv_box, half)
    rz = min_image(pos[i, 2] - pos[j, 2], box, inv_box, half)
    d = math.sqrt(rx * rx + ry * ry + rz * rz)
    delta = ri + rj - d
    fx = 0.0
    fy = 0.0
    fz = 0.0
    ov = 0.0
    if delta > 0:
        if contact_begins(delta, hist[i, kk, 3]):
            ext[1][i] += 1      # one collision (counted in both partners' lists)
        f_over_d = hertz_force(delta, ri * rj / (ri + rj), k_n) / d
        fx = f_over_d * rx
        fy = f_over_d * ry
        fz = f_over_d * rz
        ov = delta / min(ri, rj)
    hist[i, kk, 3] = delta
    return fx, fy, fz, 0.0, 0.0, 0.0, ov


@numba.njit
def elastic_energy(pos, radius, nbr, nn, box, inv_box, half, k_n):
    """Sum of the Hertz energies of the contacts (J); each pair appears in both partners' lists, hence 1/2."""
    e = 0.0
    for i in range(pos.shape[0]):
        for kk in range(nn[i]):
            j = nbr[i, kk]
            rx = min_image(pos[i, 0] - pos[j, 0], box, inv_box, half)
            ry = min_image(pos[i, 1] - pos[j, 1], box, inv_box, half)
            rz = min_image(pos[i, 2] - pos[j, 2], box, inv_box, half)
            delta = radius[i] + radius[j] - math.sqrt(rx * rx + ry * ry + rz * rz)
            if delta > 0:
                e += 0.5 * hertz_energy(delta, radius[i] * radius[j] / (radius[i] + radius[j]), k_n)
    return e


@numba.njit
def observe(pos, vel, omega, radius, mass, inertia, nbr, nn, hist, box, inv_box, half, k_n_val, k_t_val):
    """The sphere's observables (engine/shapes/sphere/kernels.py ``observe``) with the Hertz elastic energy."""
    r = sphere_observe(pos, vel, omega, radius, mass, inertia, nbr, nn, hist, box, inv_box, half, 0.0, 0.0)
    e = elastic_energy(pos, radius, nbr, nn, box, inv_box, half, k_n_val)
    return r[0], r[1], r[2], e, r[4], r[5], r[6], r[7], r[8], r[9], r[10]
