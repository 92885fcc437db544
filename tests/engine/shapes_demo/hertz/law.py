"""The Hertz pair law of the ``hertz`` shape, plain ``@numba.njit`` functions of scalars (no allocation, no
exceptions: the CPU kernels and the CUDA device functions both call them)."""

from __future__ import annotations

import math

import numba


@numba.njit(inline="always")
def hertz_force(delta, r_eff, k_n):
    """Normal force magnitude (N) at overlap delta > 0 (m): F = k_n delta sqrt(delta / R_eff), k_n in N/m, the
    linear spring's stiffness at delta = R_eff."""
    return k_n * delta * math.sqrt(delta / r_eff)


@numba.njit(inline="always")
def hertz_energy(delta, r_eff, k_n):
    """Elastic energy (J) of a contact at overlap delta (m): U = (2/5) k_n delta^(5/2) / sqrt(R_eff), the
    integral of :func:`hertz_force` over the overlap (dU/d delta = F)."""
    return 0.4 * k_n * delta * delta * math.sqrt(delta / r_eff)
