"""The counter-based generator of the parallel starts (engine/setup/scene.py, engine/setup/cell_rsa.py, and on the
GPU engine/loops/cuda_start.py): SplitMix64 of (stream key, particle or cell, draw index), uniforms and normals from
it; the same values on the host and the device, whatever the thread count."""

from __future__ import annotations

import math

from engine.numba_support.numba_import import coverage_hidden

with coverage_hidden():
    import numba
import numpy as np

from engine.numba_support.jitcache import fast_loads  # before any cache=True kernel: keys the disk cache by source
from engine.physics.rotation import quat_unit

_DRAWS = 8           # counter values reserved per particle and stream
_U = np.uint64
_GOLDEN = _U(0x9E3779B97F4A7C15)
_M1 = _U(0xBF58476D1CE4E5B9)
_M2 = _U(0x94D049BB133111EB)


@numba.njit(cache=True, inline="always")
def _mix64(x):
    """SplitMix64's finaliser (a bijection of uint64 with full avalanche)."""
    x = (x ^ (x >> _U(30))) * _M1
    x = (x ^ (x >> _U(27))) * _M2
    return x ^ (x >> _U(31))


@numba.njit(cache=True, inline="always")
def _bits(key, i, k):
    return _mix64(key + (_U(i) * _U(_DRAWS) + _U(k)) * _GOLDEN)


@numba.njit(cache=True, inline="always")
def _uniform(key, i, k):
    """A uniform double in (0, 1), draw k of particle i in the stream of ``key``."""
    return ((_bits(key, i, k) >> _U(11)) + 0.5) * (1.0 / 9007199254740992.0)


@numba.njit(cache=True, inline="always")
def _normal_pair(key, i, k):
    """Two independent standard normals (Box-Muller) from draws k, k + 1 of particle i."""
    r = math.sqrt(-2.0 * math.log(_uniform(key, i, k)))
    t = 2.0 * math.pi * _uniform(key, i, k + 1)
    return r * math.cos(t), r * math.sin(t)


@numba.njit(cache=True, inline="always")
def uniform_quaternion(key, i):
    """A uniformly distributed orientation (unit quaternion w, x, y, z): four standard normals, draws 0-3 of i in the
    stream of ``key``, over their norm."""
    g0, g1 = _normal_pair(key, i, 0)
    g2, g3 = _normal_pair(key, i, 2)
    return quat_unit(g0, g1, g2, g3)


fast_loads(globals())  # their disk-cache loads skip numba's target refresh (engine/numba_support/jitcache.py)
