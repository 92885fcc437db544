"""The linked-cell arithmetic: the one source of "which cell is a position in" and "which cells are its
neighbours", shared by every neighbour search (CPU list build, CUDA list build, multigrid levels,
random sequential placement, bench/multigrid_cost.py).

A grid of ``nc``^3 cubic cells of edge ``box / nc`` covers the periodic box; cell (cx, cy, cz) has the flat
index ``(cx nc + cy) nc + cz``. A particle's cell is found from the float64 product of its coordinate and
``inv_cell = nc / box`` (1/m), truncated and clamped to [0, nc - 1] (a coordinate wrapped into [0, box)
can round to exactly ``box``). The neighbour cells of a cell are the 3 x 3 x 3 block around it, wrapped
periodically; on a grid of fewer than 3 cells per side the block shrinks so that no cell is visited
twice (nc = 2: offsets 0, 1; nc = 1: offset 0). They are numbered k = 0 ... neighbour_cell_count(nc) - 1
in the order ox (outermost), oy, oz (innermost), each from -1 to +1: every search visits the cells, and so
the candidates, in this one order, which makes the lists of the backends equal entry for entry.

How a layout then stores the particles of a cell (a CSR cell list, a cell-sorted particle order, the
main/secondary bins of a multigrid level, linked lists per species) is the caller's; the functions here
are plain ``@numba.njit`` functions, callable from CPU njit code and from Numba CUDA kernels alike.
"""

from __future__ import annotations

import numba
import numpy as np

from engine.physics.contact import min_image


@numba.njit
def cell_coords(x, y, z, inv_cell, nc):
    """(cx, cy, cz) of the position (x, y, z) (m) on an nc^3 grid with inv_cell = nc / box (1/m); the
    products are taken in float64 whatever the precision of the position, and clamped into the grid."""
    cx = min(max(int(np.float64(x) * inv_cell), 0), nc - 1)
    cy = min(max(int(np.float64(y) * inv_cell), 0), nc - 1)
    cz = min(max(int(np.float64(z) * inv_cell), 0), nc - 1)
    return cx, cy, cz


@numba.njit
def cell_index(cx, cy, cz, nc):
    """Flat index (cx nc + cy) nc + cz of cell (cx, cy, cz)."""
    return (cx * nc + cy) * nc + cz


@numba.njit
def cell_index_of(x, y, z, inv_cell, nc):
    """Flat index of the cell of position (x, y, z): cell_index(cell_coords(...))."""
    cx, cy, cz = cell_coords(x, y, z, inv_cell, nc)
    return (cx * nc + cy) * nc + cz


@numba.njit
def cell_coords_of(c, nc):
    """(cx, cy, cz) of flat cell index c (the inverse of cell_index)."""
    return c // (nc * nc), (c // nc) % nc, c % nc


@numba.njit
def offset_low(nc):
    """The first offset per axis: -1, or 0 when the grid has fewer than 3 cells per side."""
    return -1 if nc >= 3 else 0


@numba.njit
def offset_span(nc):
    """Offsets per axis: 3 (nc >= 3), 2 (nc = 2) or 1 (nc = 1), so that no cell is visited twice."""
    return 3 if nc >= 3 else nc


@numba.njit(inline="always")
def wrap_cell(c, nc):
    """Cell coordinate c (-1 <= c <= nc, a coordinate plus an offset) wrapped into [0, nc): (c + nc) % nc by a
    comparison instead of an integer division (a list build wraps 81 of them per particle)."""
    if c < 0:
        return c + nc
    if c >= nc:
        return c - nc
    return c


@numba.njit(inline="always")
def neighbour_row(cx, cy, ox, oy, nc):
    """Flat index of the first cell (z = 0) of row (ox, oy) of cell (cx, cy, .)'s neighbour block: the cells of
    neighbour_cell's k with k // m = ox m + oy (m = offset_span(nc)), wrapped by comparisons (:func:`wrap_cell`)."""
    low = offset_low(nc)
    return (wrap_cell(cx + low + ox, nc) * nc + wrap_cell(cy + low + oy, nc)) * nc


@numba.njit(inline="always")
def neighbour_z(cz, oz, nc):
    """The z-coordinate of offset oz (0 <= oz < offset_span(nc)) of cell (., ., cz)'s neighbour block, wrapped:
    neighbour_row(...) + neighbour_z(...) is neighbour_cell's cell, without its divisions."""
    return wrap_cell(cz + offset_low(nc) + oz, nc)


@numba.njit(inline="always")
def row_runs(cz, nc):
    """The z-cells of one row (fixed ox, oy) of cell (., ., cz)'s neighbour block, in neighbour_cell's order (oz
    ascending, wrapped), as two runs of consecutive z-indices [z0, z1) then [z2, z3), the second empty (0, 0) unless
    the block wraps in z. In a cell-sorted particle order each run's particles lie in one range, so a build reads
    a row as one range (two ranges where it wraps) instead of three cells, and wraps nothing per cell."""
    lo = cz + offset_low(nc)
    hi = lo + offset_span(nc)
    if lo < 0:
        return lo + nc, nc, 0, hi
    if hi > nc:
        return lo, nc, 0, hi - nc
    return lo, hi, 0, 0


@numba.njit
def neighbour_cell_count(nc):
    """How many distinct neighbour cells (the cell itself included) a cell has: 27, 8 or 1."""
    m = offset_span(nc)
    return m * m * m


@numba.njit
def neighbour_cell(cx, cy, cz, k, nc):
    """Flat index of the k-th neighbour cell (0 <= k < neighbour_cell_count(nc)) of cell (cx, cy, cz),
    wrapped periodically; k runs over the offsets ox (outermost), oy, oz (innermost), each ascending."""
    m = offset_span(nc)
    lo = offset_low(nc)
    ax = (cx + lo + k // (m * m) + nc) % nc
    ay = (cy + lo + (k // m) % m + nc) % nc
    az = (cz + lo + k % m + nc) % nc
    return (ax * nc + ay) * nc + az


@numba.njit
def distance2(xi, yi, zi, xj, yj, zj, box, inv_box, half):
    """Squared minimum-image distance (m^2) between (xi, yi, zi) and (xj, yj, zj) in the periodic box of
    edge ``box``: the candidate test of every list build (|r_ij|^2 < (R_i + R_j + L_v)^2)."""
    dx = min_image(xi - xj, box, inv_box, half)
    dy = min_image(yi - yj, box, inv_box, half)
    dz = min_image(zi - zj, box, inv_box, half)
    return dx * dx + dy * dy + dz * dz
