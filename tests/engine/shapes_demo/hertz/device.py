"""The ``hertz`` shape's CUDA parts: the sphere's device functions (engine/shapes/sphere/device.py) with this
package's pair evaluator and elastic energy (interface: that module's docstring).

The flags are the sphere's (rough, coulomb, orient); the spec refuses rough and Coulomb contacts for this shape
(hertz/__init__.py ``spec_error``), so only orient varies. The observe sums are the sphere's.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
from numba import cuda

from engine.physics.contact import contact_begins, min_image
from engine.shapes.sphere import device as sphere
from tests.engine.shapes_demo.hertz.law import hertz_energy, hertz_force

FLAGS = sphere.FLAGS
NOBS = sphere.NOBS


def make_cuda(L, DT, UNIFORM, TPB, ROUGH, COULOMB, ORIENT):
    """The sphere's device functions for this specialisation with the Hertz ``pair`` and ``observe_one``."""
    parts = sphere.make_cuda(L, DT, UNIFORM, TPB, ROUGH, COULOMB, ORIENT)
    ZERO = DT(0)
    HALF = DT(0.5)
    f64 = np.float64
    D_BOX, D_INVBOX, D_R0, D_KN = L.D_BOX, L.D_INVBOX, L.D_R0, L.D_KN
    F_KN = L.F_KN
    observe_sphere = parts.observe_one

    @cuda.jit(device=True)
    def pair(i, q, j, s, p, acc, pos, vel, spin, quat, rad, inv_m, f_old, hist, ids, ext, spd):
        """Hertz force on i from a list slot (neighbour j, history hist[:, q]), no torque; the slot keeps the
        overlap."""
        xi, yi, zi, ri, box, inv_box = p       # the sphere's ``particle``: position, radius, box
        fx, fy, fz, tx, ty, tz, wsi = acc
        rj = ri if UNIFORM else rad[j]
        rx = min_image(xi - pos[0, j], box, inv_box, HALF)
        ry = min_image(yi - pos[1, j], box, inv_box, HALF)
        rz = min_image(zi - pos[2, j], box, inv_box, HALF)
        d = math.sqrt(rx * rx + ry * ry + rz * rz)
        delta = ri + rj - d
        if delta > ZERO:
            if contact_begins(delta, hist[3, q]):
                ext[1][i] += 1      # one collision (counted in both partners' lists)
            f_over_d = hertz_force(delta, ri * rj / (ri + rj), spd[s, D_KN]) / d
            fx += f_over_d * rx
            fy += f_over_d * ry
            fz += f_over_d * rz
            ov = delta / min(ri, rj)
            if ov > wsi:
                wsi = ov
        hist[3, q] = delta
        return fx, fy, fz, tx, ty, tz, wsi

    @cuda.jit(device=True)
    def observe_one(i, s, vals, v0, v1, v2, pos, spin, quat, rad, mass, inertia, nbr, nn, hist, spd, spf, ext):
        """The sphere's sums of particle i with the Hertz elastic energy in slot 3 instead of the spring's."""
        e_sphere = vals[3]
        observe_sphere(i, s, vals, v0, v1, v2, pos, spin, quat, rad, mass, inertia, nbr, nn, hist, spd, spf, ext)
        vals[3] = e_sphere
        box = spd[s, D_BOX]
        inv_box = spd[s, D_INVBOX]
        r0 = spd[s, D_R0]
        ri = r0 if UNIFORM else rad[i]
        for q in range(nn[i], nn[i + 1]):         # the row's slots (engine/loops/cuda_kernels.py)
            j = nbr[q]
            rx = min_image(pos[0, i] - pos[0, j], box, inv_box, HALF)
            ry = min_image(pos[1, i] - pos[1, j], box, inv_box, HALF)
            rz = min_image(pos[2, i] - pos[2, j], box, inv_box, HALF)
            rj = r0 if UNIFORM else rad[j]
            delta = f64(ri + rj - math.sqrt(rx * rx + ry * ry + rz * rz))
            if delta > 0:
                vals[3] += 0.5 * hertz_energy(delta, f64(ri) * f64(rj) / (f64(ri) + f64(rj)), spf[s, F_KN])

    # after a force pass too its sums come from the positions (the sphere's reads the spring's overlaps)
    return SimpleNamespace(**{**vars(parts), "pair": pair, "observe_one": observe_one,
                              "observe_after_forces": observe_one})
