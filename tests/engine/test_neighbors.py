"""Verlet lists (Skorych & Dosta 2022): complete, rebuilt on the L_v/2 rule, tangential springs carried over."""

import numpy as np

from engine.shapes.sphere.cpu_backend import CpuBackend
from tests.engine.scenes import gas


def _brute_contacts(pos, radius, box):
    d = pos[:, None, :] - pos[None, :, :]
    d -= box * np.round(d / box)
    r = np.sqrt((d**2).sum(-1))
    s = radius[:, None] + radius[None, :]
    np.fill_diagonal(r, np.inf)
    return {(i, j) for i, j in zip(*np.nonzero(r < s))}


def test_list_holds_every_contact_between_rebuilds():
    system, params = gas(n=128, phi=0.3, v_rms=0.2, skin=0.1)
    be = CpuBackend(system, params)
    for _ in range(20):
        be.advance(37)
        listed = {(i, int(be.nbr[i, k])) for i in range(be.n) for k in range(be.nn[i])}
        assert _brute_contacts(be.pos, be.radius, be.box) <= listed
    assert be.builds > 3


def test_springs_survive_rebuilds():
    """The same scene with a thin skin (many rebuilds) and a thick one (few) gives the same trajectory."""
    runs = []
    for skin in (0.05, 1.0):
        system, params = gas(n=64, phi=0.3, v_rms=0.05, skin=skin, e_n=0.7, e_t=0.5)
        be = CpuBackend(system, params)
        be.advance(1500)
        runs.append((be.pos.copy(), be.omega.copy(), be.builds))
    (p1, w1, b1), (p2, w2, b2) = runs
    assert b1 > 3 * b2
    # only the summation order differs (rounding); a lost spring would change spins at O(1)
    assert np.abs(w1 - w2).max() < 1e-8 * np.abs(w1).max()
    assert np.abs(p1 - p2).max() < 1e-10


def test_row_runs_hold_a_rows_cells_in_neighbour_cell_order():
    """engine.neighbours.cells.row_runs (the CUDA list build's walk of a neighbour block row): its two runs of
    z-cells, read in turn, are the row's cells of neighbour_cell in its order, on grids of 1, 2, 3 and more cells per
    side and at every cz (the block wrapping below 0 and above nc - 1)."""
    from engine.neighbours.cells import neighbour_cell, offset_span, row_runs

    for nc in range(1, 7):
        span = offset_span(nc)
        for cz in range(nc):
            want = [neighbour_cell(0, 0, cz, k, nc) % nc for k in range(span)]   # oz only: ox, oy fixed
            z0, z1, z2, z3 = row_runs(cz, nc)
            assert 0 <= z0 <= z1 <= nc and 0 <= z2 <= z3 <= nc
            assert list(range(z0, z1)) + list(range(z2, z3)) == want, (nc, cz)


def test_neighbour_row_and_z_are_neighbour_cell_without_its_divisions():
    """neighbour_row(cx, cy, ox, oy, nc) + neighbour_z(cz, oz, nc), walked ox, oy, oz ascending (every list build's
    nested loops), is neighbour_cell's k-th cell for k = (ox m + oy) m + oz, at every cell of grids of 1-6 cells."""
    from engine.neighbours.cells import neighbour_cell, neighbour_row, neighbour_z, offset_span

    for nc in range(1, 7):
        m = offset_span(nc)
        for cx, cy, cz in np.ndindex(nc, nc, nc):
            walked = [neighbour_row(cx, cy, ox, oy, nc) + neighbour_z(cz, oz, nc)
                      for ox in range(m) for oy in range(m) for oz in range(m)]
            assert walked == [neighbour_cell(cx, cy, cz, k, nc) for k in range(m ** 3)], (nc, cx, cy, cz)
