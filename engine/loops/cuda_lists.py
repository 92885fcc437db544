"""CUDA kernels for neighbour lists beyond the single-grid build of :mod:`engine.loops.cuda_kernels`.

- Multigrid linked cells (Skorych & Dosta 2022, §2.2, Algorithm 1) for wide size distributions. Each scene has grid
  levels l = 0 (coarsest, cell >= 2 R_max + L_v) ... (see :mod:`engine.neighbours.multigrid`); ``lvl[i]`` is the level
  where particle i is *main*; it is *secondary* at every coarser level. Bins: for scene s and level l,
  ``mgi[s, l] = (nc, first main bin, first secondary bin)``; the bin of a particle is that offset plus
  its cell in the level's grid. A particle i finds its neighbours j among the main particles of every
  level l < lvl[i] and among the main and secondary particles of l = lvl[i] (the 27 cells around it in
  each grid): every pair once from each side, large-large at their level, large-small at the larger
  one's, each level's cell covering R_i + R_j + L_v (Eqs. 1, 3, 4). Rows are sorted by neighbour index,
  which makes the list independent of the atomic order of the binning.
- ``check_snapshot``: the a-posteriori test of a list built from earlier positions (Skorych & Dosta 2022, §3, B10):
  max over particles of (|x - x_snapshot| / (L_v/2))^2 into status[S_CHECK].

The row start and the candidate test are the single-grid build's (:func:`cuda_kernels.list_origin`,
:func:`cuda_kernels.add_candidate`), and so is the history of every list, built here, there or on the host
(:func:`cuda_kernels.fill_history`); the cell arithmetic is engine/neighbours/cells.py's.

Layout and per-scene tables as in :mod:`engine.loops.cuda_kernels`.
"""

from __future__ import annotations

import numpy as np
from numba import cuda
from numba.cuda import types as ct

from engine.loops import cuda_kernels as K
from engine.loops.cuda_cache import cache_kernels
from engine.loops.cuda_kernels import add_candidate, list_origin, scene_of
from engine.neighbours.cells import cell_coords, cell_index_of, neighbour_row, neighbour_z, offset_span
from engine.physics.contact import min_image

_cache: dict = {}


def list_kernels(dtype, tpb: int) -> dict:
    """The list kernels for one precision (cached)."""
    key = (np.dtype(dtype).str, tpb)
    if key not in _cache:
        _cache[key] = cache_kernels(_make(np.dtype(dtype).type, tpb), ("lists",) + key)
    return _cache[key]


def _make(DT, TPB):  # noqa: C901  (one closure per precision)
    HALF = DT(0.5)
    SH2 = 2 * TPB
    block_max2, _fail = K.device_helpers(TPB)
    D_BOX, D_INVBOX = K.D_BOX, K.D_INVBOX
    I_ACTIVE, F_LIM2INV = K.I_ACTIVE, K.F_LIM2INV
    S_CHECK = K.S_CHECK

    @cuda.jit(device=True)
    def level_bin(i, l, li, pos, s, mgi, mgf):
        """Bin of particle i at level l: main bin when l is its own level, secondary bin when coarser."""
        c = cell_index_of(pos[0, i], pos[1, i], pos[2, i], mgf[s, l], mgi[s, l, 0])
        return (mgi[s, l, 1] if l == li else mgi[s, l, 2]) + c

    @cuda.jit
    def mg_count(n, pos, sc, spi, lvl, mgi, mgf, count):
        for i in range(cuda.grid(1), n, cuda.gridsize(1)):
            s = scene_of(i, sc, spi)
            li = lvl[i]
            for l in range(li + 1):
                cuda.atomic.add(count, level_bin(i, l, li, pos, s, mgi, mgf), 1)

    @cuda.jit
    def mg_scatter(n, pos, sc, spi, lvl, mgi, mgf, start, cursor, items):
        for i in range(cuda.grid(1), n, cuda.gridsize(1)):
            s = scene_of(i, sc, spi)
            li = lvl[i]
            for l in range(li + 1):
                b = level_bin(i, l, li, pos, s, mgi, mgf)
                items[start[b] + cuda.atomic.add(cursor, b, 1)] = i

    @cuda.jit
    def mg_build(n, pos, radius, lvl, mgi, mgf, start, items, nbr, nn, counts, x_ref, sc, spd, spi, fill):
        """Full Verlet list over the grid levels (module docstring), in the single-grid build's two passes
        (cuda_kernels.build): ``fill`` 0 counts each row into counts[i], ``fill`` 1 writes it at nbr[nn[i]:] and sorts
        it by neighbour index (the binning order is atomic); the history follows (cuda_kernels.fill_history)."""
        for i in range(cuda.grid(1), n, cuda.gridsize(1)):
            xi, yi, zi, s, box, inv_box, skin = list_origin(i, pos, x_ref, sc, spd, spi)
            if s < 0:
                if fill == 0:
                    counts[i] = 0
                continue
            ri = radius[i]
            li = lvl[i]
            base = nn[i] if fill != 0 else -1
            cnt = 0
            for l in range(li + 1):
                nc = mgi[s, l, 0]
                cx, cy, cz = cell_coords(xi, yi, zi, mgf[s, l], nc)
                kinds = 2 if l == li else 1
                span = offset_span(nc)
                # neighbour_cell's cells in its order, wrapped by comparisons (its divisions per cell cost most)
                for ox in range(span):
                    for oy in range(span):
                        row = neighbour_row(cx, cy, ox, oy, nc)
                        for oz in range(span):
                            cc = row + neighbour_z(cz, oz, nc)
                            for kind in range(kinds):
                                b = mgi[s, l, 1 + kind] + cc
                                for p in range(start[b], start[b + 1]):
                                    j = items[p]
                                    cnt, _ = add_candidate(i, j, cnt, xi, yi, zi, ri, radius[j], skin, pos, box,
                                                           inv_box, HALF, nbr, base)
            if fill == 0:
                counts[i] = cnt
            else:
                for p in range(base + 1, base + cnt):
                    v = nbr[p]
                    q = p - 1
                    while q >= base and nbr[q] > v:
                        nbr[q + 1] = nbr[q]
                        q -= 1
                    nbr[q + 1] = v

    @cuda.jit
    def check_snapshot(n, pos, snap, sc, spd, spf, spi, status):
        """status[S_CHECK] = max (|x - x_snap| / (L_v/2))^2 over the active particles (Skorych & Dosta 2022, Eq. 2)."""
        sh = cuda.shared.array(SH2, ct.float64)
        md = 0.0
        for i in range(cuda.grid(1), n, cuda.gridsize(1)):
            s = scene_of(i, sc, spi)
            if spi[s, I_ACTIVE] == 0:
                continue
            box = spd[s, D_BOX]
            inv_box = spd[s, D_INVBOX]
            d2 = 0.0
            for k in range(3):
                d = min_image(pos[k, i] - snap[k, i], box, inv_box, HALF)
                d2 += np.float64(d * d)
            md = max(md, d2 * spf[s, F_LIM2INV])
        block_max2(sh, md, 0.0)
        if cuda.threadIdx.x == 0:
            cuda.atomic.max(status, S_CHECK, sh[0])

    return dict(mg_count=mg_count, mg_scatter=mg_scatter, mg_build=mg_build, check_snapshot=check_snapshot)
