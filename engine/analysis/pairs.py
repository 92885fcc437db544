"""All pairs of points closer than a cut-off in a cubic periodic box (minimum image), in NumPy.

A cell list: the box is cut into n^3 cells of edge box/n >= r_cut, so the partner of a point within r_cut lies
in its own cell or one of the 26 around it; each pair of neighbouring cells is visited once (the cell itself
and 13 of its 26 neighbours). With fewer than 3 cells per edge the neighbours would repeat, and every pair is
tested instead (in blocks). The result is the exact set of pairs with minimum-image distance <= r_cut, the
same set as ``scipy.spatial.cKDTree(x, boxsize=box).query_pairs(r_cut)`` (tests/engine/test_pairs.py).
Units: any length unit, the same for positions, box and r_cut.
"""

from __future__ import annotations

import numpy as np

# the cell itself and 13 of its 26 neighbours: one of each pair of opposite offsets
_HALF = [(0, 0, 0)] + [(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)
                       if (i, j, k) > (0, 0, 0)]


def _minimum_image_d2(x, i, j, box: float):
    r = x[j] - x[i]
    r -= box * np.round(r / box)
    return np.einsum("ij,ij->i", r, r)


def periodic_pairs(position, box: float, r_cut: float) -> np.ndarray:
    """(P, 2) int64 array of the pairs (i, j), i < j, whose minimum-image distance is <= r_cut, sorted by i
    then j. position: (N, 3), wrapped into [0, box) here; r_cut must be below box/2 (one image per pair)."""
    x = np.mod(np.asarray(position, dtype=float), box)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"positions must have shape (N, 3), got {x.shape}")
    if not 0.0 <= r_cut < 0.5 * box:
        raise ValueError(f"r_cut = {r_cut} must be in [0, box/2) with box = {box}")
    n_pts = len(x)
    r2 = float(r_cut) ** 2
    # cells a little wider than r_cut, so that rounding in x n/box cannot put a pair two cells apart
    n = int(box // (r_cut * (1.0 + 1e-9))) if r_cut > 0 else 3
    n = min(n, max(3, int(round(n_pts ** (1.0 / 3.0)))))   # not (much) more cells than points
    found = []
    if n < 3:
        block = max(1, 2_000_000 // max(n_pts, 1))
        for a in range(0, n_pts, block):
            i = np.repeat(np.arange(a, min(a + block, n_pts)), n_pts)
            j = np.tile(np.arange(n_pts), min(a + block, n_pts) - a)
            keep = j > i
            i, j = i[keep], j[keep]
            d2 = _minimum_image_d2(x, i, j, box)
            found.append(np.stack([i[d2 <= r2], j[d2 <= r2]], axis=1))
    else:
        cell3 = np.minimum((x * (n / box)).astype(np.int64), n - 1)   # x/box rounding up to n at the top edge
        cell = (cell3[:, 0] * n + cell3[:, 1]) * n + cell3[:, 2]
        order = np.argsort(cell, kind="stable")
        counts = np.bincount(cell, minlength=n**3)
        start = np.cumsum(counts) - counts
        sorted_cell3, xs = cell3[order], x[order]        # points of a cell next to each other in memory
        for off in _HALF:
            nb = (sorted_cell3 + np.asarray(off)) % n
            nb = (nb[:, 0] * n + nb[:, 1]) * n + nb[:, 2]
            m = counts[nb]                           # candidates of each point (in sorted order) in that cell
            s = np.repeat(np.arange(n_pts), m)
            first = np.repeat(np.cumsum(m) - m, m)
            t = start[nb][s] + (np.arange(len(s)) - first)
            if off == (0, 0, 0):
                keep = t > s                         # each pair of the same cell once
                s, t = s[keep], t[keep]
            d2 = _minimum_image_d2(xs, s, t, box)
            near = d2 <= r2
            found.append(np.stack([order[s[near]], order[t[near]]], axis=1))
    pairs = np.concatenate(found) if found else np.empty((0, 2), dtype=np.int64)
    pairs = np.sort(pairs, axis=1).astype(np.int64)
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]
