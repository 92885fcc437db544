"""Velocity correlations of near neighbours in a snapshot frame (docs/physics.md §6.6: what molecular chaos leaves out).

The Boltzmann equation, the DSMC and the collision rules they use (one impulse or a whole two-body encounter)
all assume molecular chaos: two particles about to collide have independent velocities. In a cooling granular
gas that assumption fails: each collision leaves the two partners moving more alike, and at finite density
the correlation is carried to the next collisions (van Noije, Ernst, Brito & Orza, PRL 79, 411 (1997); the
sphere HCS of `demq validate hcs-long` measures its effect per collision). This module measures
it directly in a frame, for the pairs whose centres are closer than ``r_cut``:

- ``c_v = <v_i . v_j> / <|v|^2>`` over those pairs (velocities relative to the frame's mean velocity): 0 for
  independent velocities, 1 for equal ones;
- ``g_n_ratio = <(g . r_hat)^2>_approaching / (2 <|v|^2> / 3) - 1`` over the pairs that approach each other
  (g = v_j - v_i, r_hat from i to j, g . r_hat < 0). With independent, isotropic velocities both partners'
  components along r_hat have variance <|v|^2>/3, so 0; correlated partners approach more slowly, below 0
  (-1 for equal velocities). The energy a collision dissipates scales with this normal relative speed squared.

Units: any consistent velocity unit (ratios are dimensionless); positions and ``r_cut`` in the box's length unit.
Pairs in a periodic box (minimum image), found with the cell list of engine/analysis/pairs.py.
"""

from __future__ import annotations

import math

import numpy as np


def neighbour_velocity_correlation(position, velocity, box: float, r_cut: float) -> dict:
    """c_v, g_n_ratio and the pair counts of one frame (module docstring). position, velocity: (N, 3)."""
    from engine.analysis.pairs import periodic_pairs

    x = np.mod(np.asarray(position, dtype=float), box)
    v = np.asarray(velocity, dtype=float)
    v = v - v.mean(axis=0)
    v2 = float(np.mean(np.sum(v * v, axis=1)))
    if not r_cut < 0.5 * box:
        raise ValueError(f"r_cut = {r_cut} must be below half the box edge {box} (minimum image)")
    pairs = periodic_pairs(x, box, r_cut)
    if len(pairs) == 0 or v2 == 0.0:
        return {"c_v": math.nan, "g_n_ratio": math.nan, "pairs": int(len(pairs)), "approaching": 0}
    i, j = pairs[:, 0], pairs[:, 1]
    r = x[j] - x[i]
    r -= box * np.round(r / box)
    r_hat = r / np.linalg.norm(r, axis=1)[:, None]
    g_n = np.sum((v[j] - v[i]) * r_hat, axis=1)
    app = g_n < 0.0
    return {"c_v": float(np.mean(np.sum(v[i] * v[j], axis=1)) / v2),
            "g_n_ratio": float(np.mean(g_n[app] ** 2) / (2.0 * v2 / 3.0) - 1.0) if app.any() else math.nan,
            "pairs": int(len(pairs)), "approaching": int(app.sum())}


def file_correlations(path, r_cut: float) -> dict:
    """:func:`neighbour_velocity_correlation` of every snapshot frame of a result file (engine/output/h5md.py layout):
    arrays ``time`` (s), ``c_v``, ``g_n_ratio``, ``pairs``."""
    from engine.output.h5md import read_frames

    rows, times = [], []
    for fr in read_frames(path):
        rows.append(neighbour_velocity_correlation(fr["position"], fr["velocity"], fr["box"], r_cut))
        times.append(fr["time"])
    return {"time": np.array(times, dtype=float),
            **{key: np.array([r[key] for r in rows], dtype=float) for key in ("c_v", "g_n_ratio", "pairs")}}
