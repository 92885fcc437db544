"""Multigrid linked cells for wide size distributions (Skorych & Dosta 2022, §2.2, Eqs. 1-4, Algorithm 1).

One linked-cell grid of edge >= 2 R_max + L_v makes every small particle search cells sized for the
largest one: at a size ratio of 10 a small sphere scans ~1000 times the volume it needs. Skorych & Dosta (2022)
keeps a hierarchy of grids j = 0 (coarsest) .. n_levels-1 with nominal cell sizes

    L_c^j = L_c^0 / 2^j,  L_c^0 = 2 R_max + L_v,
    U_max^j = (L_c^j - L_v)/2       (Eq. 3),     U_min^j = (L_c^j/2 - L_v)/2 = L_c^j/4 - L_v/2   (Eq. 4),

so that U_max^j = U_min^(j-1) and U_max^0 = R_max. A cell of level j keeps a main list
(U_min^j < R <= U_max^j) and a secondary list (R <= U_min^j); only main-main and main-secondary pairs
are tested at level j, so the small-small pairs go to the finer levels whose cells suit them.

**Defect of Skorych & Dosta (2022) and what we do instead.** Algorithm 1 tests ``U_min^j < R_i < U_max^j``
(strict on both sides), while the text (below Eq. 4) has ``U_min^j < R_i <= U_max^j``. With the strict
test no particle with R = R_max (U_max^0 = R_max exactly) enters any main list, and a particle whose
radius equals a band edge U_max^j = U_min^(j-1) would be lost too: those pairs are never found. We use
the text's form and define the *main level* of a particle as the first j with R > U_min^j (the last
level when there is none); because U_max^j is stored as the very same float as U_min^(j-1), R <= U_max^j
holds by construction, without relying on rounding.

**Search rule** (the GPU kernels use the same, so the two contact sets agree). A particle i with main
level li finds its neighbours j

- at every level l < li: among the MAIN particles of level l in the 27 cells (fewer when nc_l < 3)
  around i's cell of grid l (the larger partners);
- at l = li: among the main AND the secondary particles of level li (secondary at l: main level > l)
  in the 27 cells around i's cell of grid li (equal-band and smaller partners).

Every pair is then found exactly once from each side (large-large at their common level, large-small at
the larger one's level), which gives a full, symmetric list, and the cell width of the level where a pair
is tested is >= L_c^l >= R_i + R_j + L_v. Pair test as Skorych & Dosta (2022) Eq. 1 and engine/loops/cpu.py:
|r_ij| < R_i + R_j + L_v with the minimum image.

Layout of the binned particles (:class:`MultigridBuilder`): per level a counting sort over the keys
2 cell + (0 main | 1 secondary), so the main particles of cell c of level l are
``cell_list[list_off[l] + cell_start[start_off[l] + 2c] : ... + cell_start[start_off[l] + 2c + 1]]`` and
main+secondary run on to ``cell_start[start_off[l] + 2c + 2]``. Level l holds the particles with main
level >= l; within a cell they are in ascending id order.

All kernels are ``nogil=True``: a Python thread that runs :meth:`MultigridBuilder.build` releases the
GIL (Skorych & Dosta 2022, §3, the pipelined CPU-GPU mode). They use Numba's parallel layer: do not run two of them
at the same time from two Python threads under the default workqueue layer (it is not thread-safe);
one builder thread while the main thread drives CUDA is fine.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
from numba import prange

from engine.numba_support.jitcache import fast_loads  # before any cache=True kernel: keys the disk cache by source

from engine.neighbours.cells import (cell_coords, cell_index_of, distance2, neighbour_cell, neighbour_cell_count,
                                    neighbour_row, neighbour_z, offset_span)
from engine.physics.contact import min_image

#: Relative margin between the cell width box/nc and the nominal cell size L_c: rounding of the pair
#: test (float32 runs: ~1e-7 relative) or of the binning can never move a listed pair two cells apart.
CELL_MARGIN = 1.0e-6


@dataclass(frozen=True, eq=False)
class Levels:
    """Grid levels j = 0 (coarsest) .. n_levels-1 of the multigrid linked cells (Skorych & Dosta 2022, Eqs. 3-4).

    cell:  float64 (n_levels,) nominal cell size L_c^j = L_c^0 / 2^j in m, L_c^0 = 2 R_max + L_v.
    nc:    int64 (n_levels,) cells per box edge, nc_j = max(1, floor(box / (L_c^j (1 + CELL_MARGIN)))),
           so the cell width box/nc_j >= L_c^j; capped so that nc_j^3 <= max(8, 8 N) (a coarser grid is
           always still correct, only slower).
    u_min: float64 (n_levels,) U_min^j = L_c^j/4 - L_v/2 in m (Eq. 4).
    u_max: float64 (n_levels,) U_max^0 = R_max, U_max^j = U_min^(j-1) for j >= 1 (Eq. 3), in m.
    box:   edge of the periodic cube in m;  skin: the Verlet skin L_v in m.
    """

    cell: np.ndarray
    nc: np.ndarray
    u_min: np.ndarray
    u_max: np.ndarray
    box: float = 0.0
    skin: float = 0.0

    @property
    def n_levels(self) -> int:
        return int(self.cell.shape[0])


def _cells_per_edge(box: float, cell: float, cap: int) -> int:
    nc = max(1, int(math.floor(box / (cell * (1.0 + CELL_MARGIN)))))
    while nc > 1 and box / nc < cell * (1.0 + CELL_MARGIN):
        nc -= 1
    top = max(1, int(round(cap ** (1.0 / 3.0))))
    while top**3 > cap:
        top -= 1
    while (top + 1) ** 3 <= cap:
        top += 1
    return min(nc, top)


def grid_levels(box: float, n: int, r_min: float, r_max: float, skin: float, max_levels: int = 8) -> Levels:
    """The grid levels for N spheres with radii in [r_min, r_max] (m) and Verlet skin L_v = skin (m).

    Levels are added while U_min^j >= r_min (then particles can be secondary at level j and need a finer
    level), up to ``max_levels``; particles smaller than the last level's band are main there (still
    correct: the last level's cells are >= 2 U_max + L_v wide). A monodisperse scene has one level,
    which is the single grid of edge >= 2 R + L_v (Skorych & Dosta 2022, §2.2).
    """
    if not (box > 0 and math.isfinite(box)):
        raise ValueError(f"box = {box} must be a finite length > 0 m")
    if n < 1:
        raise ValueError(f"n = {n} particles: need at least 1")
    if not (0.0 < r_min <= r_max < math.inf):
        raise ValueError(f"radii r_min = {r_min}, r_max = {r_max} must satisfy 0 < r_min <= r_max < inf")
    if not (0.0 <= skin < math.inf):
        raise ValueError(f"skin = {skin} must be a finite length >= 0 m")
    if max_levels < 1:
        raise ValueError(f"max_levels = {max_levels} must be >= 1")
    cap = max(8, 8 * int(n))
    lc0 = 2.0 * r_max + skin
    cells, ncs, umins, umaxs = [], [], [], []
    j = 0
    while True:
        lc = lc0 / 2.0**j                 # exact: a power-of-two scaling
        u_min = lc / 4.0 - skin / 2.0
        u_max = r_max if j == 0 else umins[-1]
        cells.append(lc)
        ncs.append(_cells_per_edge(box, lc, cap))
        umins.append(u_min)
        umaxs.append(u_max)
        if u_min < r_min or j + 1 >= max_levels:
            break
        j += 1
    return Levels(cell=np.array(cells, np.float64), nc=np.array(ncs, np.int64),
                  u_min=np.array(umins, np.float64), u_max=np.array(umaxs, np.float64),
                  box=float(box), skin=float(skin))


def main_level(radius: np.ndarray, levels: Levels) -> np.ndarray:
    """int32 main level of every particle: the FIRST j with R > U_min^j, or n_levels-1 (see module doc)."""
    r = np.asarray(radius, np.float64).reshape(-1)
    # U_min^j decreases with j, so the first j with R > U_min^j is the number of levels with R <= U_min^j
    below = (r[:, None] <= levels.u_min[None, :]).sum(axis=1)
    return np.minimum(below, levels.n_levels - 1).astype(np.int32)


# ---- kernels ---------------------------------------------------------------------------------------


@numba.njit(parallel=True, cache=True, nogil=True)
def bin_levels(pos, level, nc, inv_cell, start_off, list_off, cell_start, cell_list):
    """Counting sort of the particles into the main/secondary cells of every level (see module doc).

    Level l holds particle i when level[i] >= l, with key 2 cell + (level[i] > l). After the call
    cell_start[start_off[l] + k] is the first entry of key k of level l (relative to list_off[l]) and
    cell_start[start_off[l] + 2 nc_l^3] the number of particles of level l. The levels run in parallel.
    """
    n = pos.shape[0]
    for l in prange(nc.shape[0]):
        s0 = start_off[l]
        l0 = list_off[l]
        ncl = nc[l]
        ic = inv_cell[l]
        nkeys = 2 * ncl * ncl * ncl
        for k in range(nkeys + 1):
            cell_start[s0 + k] = 0
        for i in range(n):
            if level[i] >= l:
                key = 2 * cell_index_of(pos[i, 0], pos[i, 1], pos[i, 2], ic, ncl) + (1 if level[i] > l else 0)
                cell_start[s0 + key] += 1
        for k in range(1, nkeys):
            cell_start[s0 + k] += cell_start[s0 + k - 1]
        cell_start[s0 + nkeys] = cell_start[s0 + nkeys - 1]
        # reverse fill: each key's counter ends at its first entry, ids ascending within a key
        for i in range(n - 1, -1, -1):
            if level[i] >= l:
                key = 2 * cell_index_of(pos[i, 0], pos[i, 1], pos[i, 2], ic, ncl) + (1 if level[i] > l else 0)
                cell_start[s0 + key] -= 1
                cell_list[l0 + cell_start[s0 + key]] = i


@numba.njit(cache=True, nogil=True)
def _search(i, pos, radius, level, skin, box, inv_box, half, nc, inv_cell, start_off, list_off,
            cell_start, cell_list, nbr, max_nb):
    """Neighbours of particle i by the multigrid search rule into nbr[i, :max_nb]; returns the true count."""
    xi = pos[i, 0]
    yi = pos[i, 1]
    zi = pos[i, 2]
    ri = radius[i]
    li = level[i]
    cnt = 0
    for l in range(li + 1):
        s0 = start_off[l]
        l0 = list_off[l]
        ncl = nc[l]
        span = 1 if l < li else 2        # keys scanned per cell: main only, or main + secondary
        cx, cy, cz = cell_coords(xi, yi, zi, inv_cell[l], ncl)
        m = offset_span(ncl)
        for ox in range(m):          # neighbour_cell's cells in its order, without its divisions
            for oy in range(m):
                row = neighbour_row(cx, cy, ox, oy, ncl)
                for oz in range(m):
                    key = 2 * (row + neighbour_z(cz, oz, ncl))
                    for s in range(cell_start[s0 + key], cell_start[s0 + key + span]):
                        j = cell_list[l0 + s]
                        if j == i:
                            continue
                        rc = ri + radius[j] + skin
                        if distance2(xi, yi, zi, pos[j, 0], pos[j, 1], pos[j, 2], box, inv_box, half) < rc * rc:
                            if cnt < max_nb:
                                nbr[i, cnt] = j
                            cnt += 1
    return cnt


@numba.njit(parallel=True, cache=True, nogil=True)
def build_levels(pos, radius, level, skin, box, inv_box, half, nc, inv_cell, start_off, list_off,
                 cell_start, cell_list, nbr, nn, x_ref):
    """Full Verlet list by the multigrid search rule: nbr[i, k] (k < stride) and the true count nn[i].

    nbr may be any 2-D view (e.g. the transpose of a GPU-layout [max_nb, n] host array); slots beyond
    its stride are not written, nn[i] still gets the true count (the caller grows and builds again).
    x_ref (or None) receives the positions of the build. Returns the largest count.
    """
    n = pos.shape[0]
    max_nb = nbr.shape[1]
    for i in prange(n):
        nn[i] = _search(i, pos, radius, level, skin, box, inv_box, half, nc, inv_cell, start_off, list_off,
                        cell_start, cell_list, nbr, max_nb)
        if x_ref is not None:
            x_ref[i, 0] = pos[i, 0]
            x_ref[i, 1] = pos[i, 1]
            x_ref[i, 2] = pos[i, 2]
    need = 0
    for i in range(n):
        if nn[i] > need:
            need = nn[i]
    return need


@numba.njit(cache=True, nogil=True, inline="always")
def carry_slot(i, k, j, nbr_old, nn_old, hist_old, hist):
    """History of slot k of particle i (neighbour j) in a rebuilt CPU list ([i, slot, word] layout): the
    old slot's words when j was in i's old row (returns True), else zeros (returns False: the caller
    sets word 3, the previous overlap, to the current gap R_i + R_j - |r_ij|)."""
    for ko in range(nn_old[i]):
        if nbr_old[i, ko] == j:
            for q in range(hist.shape[2]):
                hist[i, k, q] = hist_old[i, ko, q]
            return True
    for q in range(hist.shape[2]):
        hist[i, k, q] = 0
    return False


@numba.njit(parallel=True, cache=True, nogil=True)
def build_levels_carry(pos, radius, level, skin, box, inv_box, half, nc, inv_cell, start_off, list_off,
                       cell_start, cell_list, nbr_old, nn_old, hist_old, nbr, nn, hist, x_ref):
    """As :func:`build_levels`, with the contact history of the CPU backend carried over.

    Same contract as engine/loops/cpu.py ``build_list``: a pair found in the old list keeps its slot
    data (tangential spring, previous overlap, dashpot force); a new pair starts with a zero spring and
    its current overlap R_i + R_j - |r_ij| as the previous one.
    """
    n = pos.shape[0]
    max_nb = nbr.shape[1]
    for i in prange(n):
        cnt = _search(i, pos, radius, level, skin, box, inv_box, half, nc, inv_cell, start_off, list_off,
                      cell_start, cell_list, nbr, max_nb)
        nn[i] = cnt
        xi = pos[i, 0]
        yi = pos[i, 1]
        zi = pos[i, 2]
        for kk in range(min(cnt, max_nb)):
            j = nbr[i, kk]
            if not carry_slot(i, kk, j, nbr_old, nn_old, hist_old, hist):
                dx = min_image(xi - pos[j, 0], box, inv_box, half)
                dy = min_image(yi - pos[j, 1], box, inv_box, half)
                dz = min_image(zi - pos[j, 2], box, inv_box, half)
                hist[i, kk, 3] = radius[i] + radius[j] - math.sqrt(dx * dx + dy * dy + dz * dz)
        x_ref[i, 0] = xi
        x_ref[i, 1] = yi
        x_ref[i, 2] = zi


@numba.njit(parallel=True, cache=True, nogil=True)
def count_candidates(pos, level, nc, inv_cell, start_off, list_off, cell_start, cell_list, out):
    """Candidate pairs (distance tests) each particle makes under the multigrid search rule, into out."""
    n = pos.shape[0]
    for i in prange(n):
        li = level[i]
        cnt = 0
        for l in range(li + 1):
            s0 = start_off[l]
            ncl = nc[l]
            span = 1 if l < li else 2
            cx, cy, cz = cell_coords(pos[i, 0], pos[i, 1], pos[i, 2], inv_cell[l], ncl)
            for k in range(neighbour_cell_count(ncl)):
                key = 2 * neighbour_cell(cx, cy, cz, k, ncl)
                cnt += cell_start[s0 + key + span] - cell_start[s0 + key]
        out[i] = cnt - 1          # i itself is in its own cell and is skipped


# ---- host object ----------------------------------------------------------------------------------


class MultigridBuilder:
    """Owns the binning scratch of one scene and builds its full Verlet list by the multigrid rule.

    ``MultigridBuilder(box, radius, levels)``: box in m, radius (N,) in m (its dtype is the working
    precision of the pair test: pass float32 radii for a float32 scene), levels from :func:`grid_levels`
    (its skin is the Verlet skin L_v). Radii are fixed for the life of the builder (main levels are
    computed once). :meth:`build` allocates nothing and releases the GIL.
    """

    def __init__(self, box: float, radius: np.ndarray, levels: Levels, skin: float | None = None):
        self.radius = np.ascontiguousarray(radius)
        if self.radius.dtype not in (np.float32, np.float64):
            self.radius = self.radius.astype(np.float64)
        ft = self.radius.dtype.type
        self.n = self.radius.shape[0]
        self.levels = levels
        self.box = ft(box)
        self.inv_box = ft(1.0 / box)
        self.half = ft(0.5)
        self.skin = ft(levels.skin if skin is None else skin)
        self.level = main_level(self.radius, levels)
        self.arrays = level_arrays(box, self.level, levels)
        (self.nc, self.inv_cell, self.start_off, self.list_off, self.cell_start, self.cell_list) = self.arrays

    def set_radius(self, radius: np.ndarray) -> None:
        """The same radii in another order (a permutation of the particles): main levels recomputed,
        the per-level counts and so the scratch arrays stay valid."""
        self.radius[:] = radius
        self.level[:] = main_level(self.radius, self.levels)

    def bin(self, pos: np.ndarray) -> None:
        """Sort the particles (positions (N,3) in [0, box), m) into the cells of every level."""
        bin_levels(pos, self.level, self.nc, self.inv_cell, self.start_off, self.list_off, self.cell_start,
                   self.cell_list)

    def build(self, pos: np.ndarray, nbr: np.ndarray, nn: np.ndarray, x_ref: np.ndarray | None = None) -> int:
        """Bin and fill nbr[i, k] (k < nbr.shape[1]) and nn[i] (the true count); return max nn.

        nbr: int32 (N, stride), any strides (the lead passes ``host_array.T`` of a [max_nb, N] array);
        nn: int32 (N,); x_ref: (N, 3) or None, set to pos. A return value above the stride means the
        list overflowed: grow it and build again.
        """
        self.bin(pos)
        return int(build_levels(pos, self.radius, self.level, self.skin, self.box, self.inv_box, self.half,
                                self.nc, self.inv_cell, self.start_off, self.list_off, self.cell_start,
                                self.cell_list, nbr, nn, x_ref))

    def candidates(self, pos: np.ndarray) -> np.ndarray:
        """Distance tests per particle (int64 (N,)) of a build at these positions (bins first)."""
        self.bin(pos)
        out = np.zeros(self.n, np.int64)
        count_candidates(pos, self.level, self.nc, self.inv_cell, self.start_off, self.list_off,
                         self.cell_start, self.cell_list, out)
        return out


def level_arrays(box: float, level: np.ndarray, levels: Levels) -> tuple:
    """(nc, inv_cell, start_off, list_off, cell_start, cell_list) for :func:`bin_levels` and the builders.

    Memory: sum_l (2 nc_l^3 + 1) int64 cell starts and sum_i (level_i + 1) int32 entries.
    """
    nl = levels.n_levels
    nc = np.asarray(levels.nc, np.int64).copy()
    inv_cell = (nc / float(box)).astype(np.float64)
    start_off = np.zeros(nl + 1, np.int64)
    start_off[1:] = np.cumsum(2 * nc**3 + 1)
    counts = np.array([(level >= l).sum() for l in range(nl)], np.int64)
    list_off = np.zeros(nl + 1, np.int64)
    list_off[1:] = np.cumsum(counts)
    cell_start = np.zeros(int(start_off[-1]), np.int64)
    cell_list = np.zeros(max(1, int(list_off[-1])), np.int32)
    return nc, inv_cell, start_off, list_off, cell_start, cell_list


fast_loads(globals())  # their disk-cache loads skip numba's target refresh (engine/numba_support/jitcache.py)
