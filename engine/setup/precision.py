"""The precisions a scene can run in (spec field ``precision``) and the array types each one uses.

- ``float64``: every array and every operation in double precision (the reference).
- ``float32``: every array in single precision. Positions are then quantised at L 2^-24 (L: the box edge), so a
  contact overlap delta ~ 1e-3 radius is resolved to only a few digits in a large box: restitution errors of order
  1e-2 (docs/performance.md, accuracy against cost; docs/physics.md §3.6).
- ``mixed``: positions and the list's reference positions x_ref in float64, every other array
  (velocities, spins, orientations, forces, torques, contact histories, constants) in float32. A pair's separation,
  distance and overlap are then formed from float64 positions and rounded once to float32
  (engine.physics.contact.sphere_separation), so the overlap is exact to float32's relative rounding of delta
  itself (not of L); the force law that takes them runs in float32, and what is stored per particle and per
  contact is float32. The box edge is the float32 value, as in
  float32 (the per-scene constant tables are in the state precision; positions wrap at that edge on every
  backend alike). Spheres only (shape trait ``MIXED``): the spheroid's contact solver has no mixed variant.
"""

from __future__ import annotations

import math

import numpy as np

PRECISIONS = ("float64", "float32", "mixed")


def state_dtype(precision: str):
    """NumPy type of the state arrays (velocities, spins, orientations, forces, contact histories, constants)."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    return np.float64 if precision == "float64" else np.float32


def position_dtype(precision: str):
    """NumPy type of the positions and of the list's reference positions."""
    state_dtype(precision)   # validates the name
    return np.float32 if precision == "float32" else np.float64


def output_dtype(precision: str):
    """NumPy type of the snapshot frames in the result file: the state's, except that ``mixed`` writes float64
    (its positions are float64; its float32 arrays are exact in it)."""
    return position_dtype(precision)


def check_shape(precision: str, shape: str) -> None:
    """ValueError naming the field when ``shape`` has no variant in ``precision`` (``mixed``: the shapes whose
    traits say ``MIXED``, engine/shapes/)."""
    from engine.shapes import SHAPES, traits

    if precision == "mixed" and not traits(shape).MIXED:
        which = " or ".join(repr(k) for k in SHAPES if traits(k).MIXED)
        raise ValueError(f"precision = 'mixed' is implemented for shape {which} only, got shape {shape!r}; "
                         f"use 'float64' or 'float32'")


#: the largest part of the Verlet rule's limit L_v / 2 that the rounding of a float32 list reference x_ref of float64
#: positions may take (engine/loops/cuda_memory.py ``xref_dtype``)
XREF_MARGIN_SHARE = 1.0 / 64.0


def float32_copy_error(box: float) -> float:
    """Bound (m) on the distance between a position in [0, box) and its float32 copy: sqrt(3) 2^-24 box (half an ulp
    of a coordinate below box, on each axis)."""
    return math.sqrt(3.0) * 2.0 ** -24 * float(box)


def float32_reference_fits(box: float, skin: float) -> bool:
    """Whether float64 positions in a box of ``box`` m may keep their list reference x_ref in float32 at skin ``skin``
    (m): its rounding takes at most XREF_MARGIN_SHARE of the Verlet rule's limit L_v / 2."""
    return float32_copy_error(box) <= XREF_MARGIN_SHARE * 0.5 * float(skin)


def float32_reference_skin(box: float) -> float:
    """The thinnest skin (m) at which :func:`float32_reference_fits`, with a relative 1e-9 to spare for the rounding
    of that test."""
    return float32_copy_error(box) / (XREF_MARGIN_SHARE * 0.5) * (1.0 + 1e-9)
