"""Random sequential addition in cell rounds: a large random (equilibrium-like) start placed in parallel, on the
host (Numba prange) or on the GPU that runs the job (engine/loops/cuda_start.py), the same spheres on both; and the
random start of prolate spheroids at any N (their orientations drawn with their centres).

Random sequential addition (RSA) tries uniform random centres one after another and keeps each that overlaps no
sphere kept before. Done in parallel: the box is cut into nc^3 cells (nc even, cell edge h >= the exclusion
distance d = 2 R (1 + RSA_GAP), about RSA_CELL_MEAN spheres a cell), and the cells are coloured by the parities of
their three indices. A pass takes one colour: each of its cells, one thread each, makes a Poisson(RSA_MEAN_ATTEMPTS)
number of attempts, each a uniform centre in the cell kept when it overlaps no sphere in the 27 cells around (its
own included). Two cells of one colour are at least one cell apart, so the attempts of a pass cannot overlap each
other and the pass is RSA with its attempts in some order; the eight colours make a round, rounds go on until N
spheres are kept, and the last round's surplus is removed, latest pass first, at random within a pass (the largest
keys). Attempts arrive as a Poisson process in space and time, as in sequential RSA; what differs is only the order
of the attempts within a pass of one colour and between colours (the result at phi <= 0.3 is checked against the
sequential start in tests/engine/test_cell_rsa.py: the pair correlation at contact and the neighbour counts).

Exactly the same spheres on the host and the device: every draw is a counter-based SplitMix64 value of (pass, cell,
attempt) (engine/setup/counter_rng.py ``_bits``), the attempt counts come from integer thresholds, and a centre is an
integer position on a grid of RSA_Q points a cell edge (box / (nc RSA_Q) apart), tested against the others in exact
int64 arithmetic: (dx^2 + dy^2 + dz^2) >= ceil((d / unit)^2). Particles are numbered in cell order, then in the order a
cell kept them. Units: positions in the box's unit (m).

Spheroids (semi-axes a >= b = c): the cells and the integer test are those of their bounding spheres (radius a), and
each attempt draws a uniform orientation too (a unit quaternion from four normals, :func:`candidate_orientation`). A
candidate whose bounding sphere meets a kept one's is kept only when the two bodies, both scaled by 1 + RSA_GAP about
their centres, are disjoint: the plane normal to the centre line separates them, or the Perram-Wertheim function has
F_max >= (1 + RSA_GAP)^2 (engine/physics/ellipsoid.py; W_0 = sqrt(F_max) is the factor by which both can grow before
they touch). These tests are floating-point: the host's and the device's placements agree unless a candidate lies
within rounding of touching a kept body (never seen; the sphere test stays exact). A spheroid start below the
parallel start's size runs the same rounds on one thread (:func:`_round_serial`), so that the scenes of an ensemble can
be set up on several threads at once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from engine.numba_support.numba_import import coverage_hidden

with coverage_hidden():
    import numba
import numpy as np

from engine.numba_support.jitcache import fast_loads  # before any cache=True kernel: keys the disk cache by source
from engine.errors import SpecError
from engine.physics.ellipsoid import plane_separated, pw_contact, shape_matrix_inverse
from engine.setup.counter_rng import _DRAWS, _GOLDEN, _M1, _U, _bits, _mix64, uniform_quaternion

#: Relative gap RSA keeps between accepted spheres: rounding can never make a start overlap (every random start:
#: the sequential one of engine/setup/scene.py and this one)
RSA_GAP = 1.0e-9
#: mean spheres per cell the cells are sized for (cells are never smaller than the exclusion distance)
RSA_CELL_MEAN = 2.0
#: grid points per cell edge of the centres (15 bits a coordinate: one 64-bit draw places a candidate)
RSA_Q = 1 << 15
#: mean attempts per cell and pass (Poisson)
RSA_MEAN_ATTEMPTS = 1.0
#: rounds after which a start that has not placed its spheres gives up (RSA jams near phi = 0.38)
RSA_MAX_ROUNDS = 20000
_COLOURS = 8
#: Newton tolerance in lambda of the spheroids' Perram-Wertheim test (float64; F is flat at its maximum)
RSA_PW_TOL = 1.0e-13


@dataclass(frozen=True)
class CellRsa:
    """The cells and integer grid of a random start of ``n`` spheres of ``radius`` in a box of edge ``box``: nc cells
    an edge, slots per cell, the grid unit (box / (nc RSA_Q)), the squared exclusion distance in grid units (int)
    and the attempt counts' cumulative thresholds (53-bit integers). ``axes``: () for spheres, (a, b) (m) for prolate
    spheroids, whose bounding spheres (``radius`` = a) size the cells."""

    n: int
    box: float
    nc: int
    slots: int
    unit: float
    thr: int
    cdf: tuple
    axes: tuple = ()

    @property
    def spheroid(self) -> bool:
        return len(self.axes) == 2

    @classmethod
    def of(cls, n: int, box: float, radius: float, axes: tuple = ()) -> "CellRsa":
        d = 2.0 * radius * (1.0 + RSA_GAP)
        fit = int(box / d) // 2 * 2                 # the most cells an edge: even, edge >= d
        if fit < 2:
            raise SpecError(f"a random start needs a box of at least 2 exclusion distances ({2 * d:.4g}); "
                            f"box_length = {box:g}")
        want = 2 * math.ceil(0.5 * (n / RSA_CELL_MEAN) ** (1.0 / 3.0))
        nc = max(2, min(fit, want))
        while nc > 2 and box / nc < d:             # rounding of box / d
            nc -= 2
        unit = box / (nc * RSA_Q)
        thr = math.ceil((d / unit) ** 2)
        mean = n / nc ** 3
        return cls(n=int(n), box=float(box), nc=nc, slots=_slots_for(mean, nc ** 3), unit=unit, thr=thr,
                   cdf=_attempt_thresholds(RSA_MEAN_ATTEMPTS), axes=tuple(float(x) for x in axes))


def _slots_for(mean: float, cells: int) -> int:
    """Slots per cell: the Poisson(mean) count that no cell exceeds but with odds 1e-4 (a full cell is found and the
    start is redone with twice the slots: the spheres do not depend on the slot count)."""
    k, term = 0, math.exp(-mean)
    below = term
    while cells * (1.0 - below) > 1e-4 and k < 4096:
        k += 1
        term *= mean / k
        below += term
    return max(8, k + 1)


def _attempt_thresholds(mean: float) -> tuple:
    """floor(2^53 P(X <= k)), k < _DRAWS, of X ~ Poisson(mean): a 53-bit uniform u gives the attempt count
    min(k : u < thr[k]), or _DRAWS (computed once, in Python, for the host's and the device's counts alike)."""
    out, term, cum = [], math.exp(-mean), 0.0
    for k in range(_DRAWS):
        cum += term
        out.append(min(int(cum * 2.0**53), 2**53))
        term *= mean / (k + 1)
    return tuple(out)


@numba.njit(cache=True, inline="always")
def pass_key(key, p):
    """The key of pass p's draws in the stream of ``key``."""
    return _mix64(key ^ ((_U(p) + _U(1)) * _M1))


@numba.njit(cache=True, inline="always")
def attempts_of(cdf, count_key, cell):
    """The number of attempts a cell makes in a pass (count_key: the pass's): Poisson by integer thresholds."""
    u = _bits(count_key, cell, 0) >> _U(11)
    k = 0
    while k < cdf.shape[0] and u >= cdf[k]:
        k += 1
    return k


@numba.njit(cache=True, inline="always")
def candidate(pos_key, cell, a):
    """Attempt a's centre within its cell: three 15-bit grid offsets of one draw."""
    b = _bits(pos_key, cell, a)
    return (np.int64((b >> _U(49)) & _U(0x7FFF)), np.int64((b >> _U(34)) & _U(0x7FFF)),
            np.int64((b >> _U(19)) & _U(0x7FFF)))


@numba.njit(cache=True, inline="always")
def candidate_orientation(quat_key, cell, a):
    """Attempt a's orientation (a spheroid's): a uniform unit quaternion (w, x, y, z) from four normals, draws of
    (cell, attempt) in the pass's orientation stream."""
    return uniform_quaternion(quat_key, np.int64(cell) * np.int64(_DRAWS) + np.int64(a))


@numba.njit(cache=True, inline="always")
def spheroids_clear(rx, ry, rz, qa0, qa1, qa2, qa3, qb0, qb1, qb2, qb3, a, b):
    """Whether two prolate spheroids (semi-axes a, b, b; m) at centre offset r (m), orientations qa and qb, stay
    disjoint when both are scaled by 1 + RSA_GAP about their centres (module docstring)."""
    half = 0.5
    grow = 1.0 + RSA_GAP
    ia = shape_matrix_inverse(qa0, qa1, qa2, qa3, a, b, b, half)
    ib = shape_matrix_inverse(qb0, qb1, qb2, qb3, a, b, b, half)
    if plane_separated(ia[0], ia[1], ia[2], ia[3], ia[4], ia[5], ib[0], ib[1], ib[2], ib[3], ib[4], ib[5],
                       rx, ry, rz, RSA_GAP, half):
        return True
    f, _, _, _, _, _ = pw_contact(ia[0], ia[1], ia[2], ia[3], ia[4], ia[5], ib[0], ib[1], ib[2], ib[3], ib[4], ib[5],
                                  rx, ry, rz, RSA_PW_TOL, grow * grow, half)
    return f >= grow * grow


@numba.njit(cache=True, inline="always")
def _neighbour(c, offset, nc):
    """The index of the cell ``offset`` (-1, 0 or 1) from cell index c along an axis of nc periodic cells (no
    division: the GPU's int64 division costs tens of instructions)."""
    n = c + offset
    if n < 0:
        return n + nc
    if n >= nc:
        return n - nc
    return n


#: which particles a pass function is compiled for (:func:`pass_functions`): one-size spheres, spheroids, or either
#: as ``axes`` says at run time
SPHERES, SPHEROIDS, EITHER = 0, 1, 2


def pass_functions(kind: int) -> tuple:
    """(is_clear, cell_pass) compiled for ``kind`` (SPHERES, SPHEROIDS or EITHER). The shape is a constant of the
    compiled code for SPHERES and SPHEROIDS: a GPU kernel for spheres then carries no Perram-Wertheim test (with it,
    the sphere pass kernel took 188 registers against 80, and twice the time: H200, 8M spheres); the host's rounds
    take EITHER."""

    @numba.njit(inline="always")
    def spheroid(axes):
        if kind == EITHER:
            return axes.shape[0] != 0
        return kind == SPHEROIDS

    @numba.njit(inline="always")
    def is_clear(gx, gy, gz, cx, cy, cz, nc, thr, counts, slots, cq, quats, axes, unit):
        """Whether a centre at grid point (gx, gy, gz) of cell (cx, cy, cz) overlaps no particle kept in the 27
        cells around: exact int64 squared distances against thr. Spheroids (``axes`` = (a, b)): a kept one within
        the bounding distance is tested with the candidate's orientation ``cq`` and its own (quats[c, k]) by
        :func:`spheroids_clear` (``unit``: the grid's, m)."""
        q = np.int64(RSA_Q)
        # the candidate's offset in its cell; a kept centre in the cell at offset (ox, oy, oz) lies at
        # (ox q + slot - local) from it: that image is the nearest one for nc >= 4, and for nc = 2 (where offsets
        # -1 and +1 name one cell) the other image is at least a cell edge >= the exclusion distance away, so no
        # division or periodic wrap is needed per kept centre
        lx, ly, lz = gx - cx * q, gy - cy * q, gz - cz * q
        for ox in range(-1, 2):
            nx = _neighbour(cx, ox, nc)
            bx = ox * q - lx
            for oy in range(-1, 2):
                ny = _neighbour(cy, oy, nc)
                by = oy * q - ly
                for oz in range(-1, 2):
                    nz = _neighbour(cz, oz, nc)
                    bz = oz * q - lz
                    c = (nx * nc + ny) * nc + nz
                    for k in range(counts[c]):
                        dx = bx + np.int64(slots[c, k, 0])
                        dy = by + np.int64(slots[c, k, 1])
                        dz = bz + np.int64(slots[c, k, 2])
                        if dx * dx + dy * dy + dz * dz < thr:
                            if not spheroid(axes):
                                return False
                            if not spheroids_clear(dx * unit, dy * unit, dz * unit, cq[0], cq[1], cq[2], cq[3],
                                                   quats[c, k, 0], quats[c, k, 1], quats[c, k, 2], quats[c, k, 3],
                                                   axes[0], axes[1]):
                                return False
        return True

    @numba.njit(inline="always")
    def cell_pass(t, colour, p, nc, thr, cdf, pos_key, count_key, quat_key, counts, slots, spass, quats, axes, unit):
        """The attempts of pass p in the t-th cell of colour ``colour``; returns 1 when the cell had no free slot
        for a centre it kept (the start is then redone with more slots), else 0. Spheroids (``axes`` = (a, b)) draw
        an orientation per attempt from ``quat_key`` and keep it in quats[c, slot]."""
        h2 = nc // 2
        cx = 2 * (t // (h2 * h2)) + ((colour >> 2) & 1)
        cy = 2 * ((t // h2) % h2) + ((colour >> 1) & 1)
        cz = 2 * (t % h2) + (colour & 1)
        c = (cx * nc + cy) * nc + cz
        q = np.int64(RSA_Q)
        for a in range(attempts_of(cdf, count_key, c)):
            qx, qy, qz = candidate(pos_key, c, a)
            cq = (1.0, 0.0, 0.0, 0.0)
            if spheroid(axes):
                cq = candidate_orientation(quat_key, c, a)
            if is_clear(cx * q + qx, cy * q + qy, cz * q + qz, cx, cy, cz, nc, thr, counts, slots, cq, quats, axes,
                        unit):
                m = counts[c]
                if m >= slots.shape[1]:
                    return 1
                slots[c, m, 0] = qx
                slots[c, m, 1] = qy
                slots[c, m, 2] = qz
                spass[c, m] = p
                if spheroid(axes):
                    for j in range(4):
                        quats[c, m, j] = cq[j]
                counts[c] = m + 1
        return 0

    return is_clear, cell_pass


is_clear, cell_pass = pass_functions(EITHER)


@numba.njit(cache=True, inline="always")
def final_key(trim_key, cell, k, pass_in_round):
    """The order in which the last round's spheres are removed (largest first): the pass within the round in the top
    three bits, a draw of (cell, slot) below."""
    r = _mix64(_mix64(trim_key + _U(cell) * _GOLDEN) + (_U(k) + _U(1)) * _GOLDEN)
    return (_U(pass_in_round) << _U(61)) | (r >> _U(3))


@numba.njit(cache=True, parallel=True, nogil=True)
def _round(r, nc, thr, cdf, pos_key, count_key, quat_key, counts, slots, spass, quats, axes, unit):
    """Round r's eight passes on the host's threads; returns the number of cells that lacked a slot."""
    h2 = nc // 2
    m = h2 * h2 * h2
    full = 0
    for colour in range(_COLOURS):
        p = _COLOURS * r + colour
        pk, ck, qk = pass_key(pos_key, p), pass_key(count_key, p), pass_key(quat_key, p)
        flags = np.zeros(m, np.int64)
        for t in numba.prange(m):
            flags[t] = cell_pass(t, colour, p, nc, thr, cdf, pk, ck, qk, counts, slots, spass, quats, axes, unit)
        full += flags.sum()
    return full


@numba.njit(cache=True, nogil=True)
def _round_serial(r, nc, thr, cdf, pos_key, count_key, quat_key, counts, slots, spass, quats, axes, unit):
    """:func:`_round` on the calling thread (the same passes in the same order: the same particles)."""
    h2 = nc // 2
    m = h2 * h2 * h2
    full = 0
    for colour in range(_COLOURS):
        p = _COLOURS * r + colour
        pk, ck, qk = pass_key(pos_key, p), pass_key(count_key, p), pass_key(quat_key, p)
        for t in range(m):
            full += cell_pass(t, colour, p, nc, thr, cdf, pk, ck, qk, counts, slots, spass, quats, axes, unit)
    return full


@numba.njit(cache=True, inline="always")
def slot_index(c, k):
    """A slot's number independent of the slots per cell: the tie-break of equal removal keys."""
    return (np.int64(c) << np.int64(20)) | np.int64(k)


@numba.njit(cache=True, inline="always")
def kept(c, k, counts, spass, first_pass, trim_key, cut_key, cut_index):
    """Whether slot k of cell c holds a sphere of the start: kept before the last round, or in it and at or below the
    cut in the order (removal key, slot number)."""
    if k >= counts[c]:
        return False
    if spass[c, k] < first_pass:
        return True
    key = final_key(trim_key, c, k, spass[c, k] - first_pass)
    return key < cut_key or (key == cut_key and slot_index(c, k) <= cut_index)


@numba.njit(cache=True, parallel=True, nogil=True)
def _last_round(first_pass, trim_key, counts, spass, keys, index):
    """The removal keys and slot numbers of the spheres kept in the last round (in cell order)."""
    ncell = counts.shape[0]
    per = np.zeros(ncell + 1, np.int64)
    for c in numba.prange(ncell):
        s = 0
        for k in range(counts[c]):
            if spass[c, k] >= first_pass:
                s += 1
        per[c + 1] = s
    for c in range(ncell):
        per[c + 1] += per[c]
    for c in numba.prange(ncell):
        at = per[c]
        for k in range(counts[c]):
            if spass[c, k] >= first_pass:
                keys[at] = final_key(trim_key, c, k, spass[c, k] - first_pass)
                index[at] = slot_index(c, k)
                at += 1
    return per[ncell]


@numba.njit(cache=True, parallel=True, nogil=True)
def _gather(nc, unit, first_pass, trim_key, cut_key, cut_index, counts, slots, spass, quats, pos, quat):
    """The start's centres, numbered in cell order (then slot order), into pos (n x 3); a spheroid start's orientations
    into quat (n x 4; spheres: quat has no rows)."""
    ncell = counts.shape[0]
    per = np.zeros(ncell + 1, np.int64)
    for c in numba.prange(ncell):
        s = 0
        for k in range(counts[c]):
            if kept(c, k, counts, spass, first_pass, trim_key, cut_key, cut_index):
                s += 1
        per[c + 1] = s
    for c in range(ncell):
        per[c + 1] += per[c]
    q = RSA_Q
    for c in numba.prange(ncell):
        i = per[c]
        cx = c // (nc * nc)
        cy = (c // nc) % nc
        cz = c % nc
        for k in range(counts[c]):
            if kept(c, k, counts, spass, first_pass, trim_key, cut_key, cut_index):
                pos[i, 0] = (cx * q + slots[c, k, 0] + 0.5) * unit
                pos[i, 1] = (cy * q + slots[c, k, 1] + 0.5) * unit
                pos[i, 2] = (cz * q + slots[c, k, 2] + 0.5) * unit
                if quat.shape[0] != 0:
                    for j in range(4):
                        quat[i, j] = quats[c, k, j]
                i += 1
    return per[ncell]


def cut_of(keys: np.ndarray, index: np.ndarray, keep: int) -> tuple:
    """(key, slot number) of the keep-th smallest entry in the order (key, slot number): the last one kept."""
    order = np.lexsort((index, keys))
    j = order[keep - 1]
    return np.uint64(keys[j]), np.int64(index[j])


def run_rounds(g: CellRsa, round_fn, new_arrays) -> tuple:
    """Rounds until n spheres are kept (redone with twice the slots when a cell lacked one): returns (counts, slots,
    spass, rounds run, spheres kept before the last round). ``round_fn(r, arrays)`` runs round r and returns the
    cells that lacked a slot and the spheres kept so far; ``new_arrays(slots_per_cell)`` makes empty arrays."""
    slots_per_cell = g.slots
    while True:
        arrays = new_arrays(slots_per_cell)
        total, prev, r, full = 0, 0, 0, 0
        while total < g.n and not full:
            if r >= RSA_MAX_ROUNDS:
                raise SpecError(f"a random start of {g.n} spheres did not fit after {r} rounds of random sequential "
                                f"addition ({total} placed): the volume fraction is too high for it")
            prev = total
            full, total = round_fn(r, arrays)
            r += 1
        if not full:
            return arrays, r, prev
        slots_per_cell *= 2


def place_random(g: CellRsa, keys: tuple, threads: bool = True):
    """The n centres (n x 3, m) of a random start on the host (see the module docstring), and for spheroids their
    orientations (n x 4): (pos, quat or None). ``keys``: the positions', attempt counts', removal and (spheroids)
    orientations' keys (uint64); ``threads``: run the rounds on the host's threads (else on the calling one)."""
    pos_key, count_key, trim_key = (np.uint64(k) for k in keys[:3])
    quat_key = np.uint64(keys[3]) if g.spheroid else np.uint64(0)
    cdf = np.array(g.cdf, np.uint64)
    axes = np.array(g.axes, np.float64)
    ncell = g.nc ** 3
    rounds_fn = _round if threads else _round_serial

    def new_arrays(per_cell: int) -> tuple:
        return (np.zeros(ncell, np.int32), np.empty((ncell, per_cell, 3), np.int16),
                np.empty((ncell, per_cell), np.int32),
                np.empty((ncell, per_cell, 4) if g.spheroid else (1, 1, 4), np.float64))

    def one_round(r: int, arrays: tuple) -> tuple:
        counts, slots, spass, quats = arrays
        full = rounds_fn(r, g.nc, g.thr, cdf, pos_key, count_key, quat_key, counts, slots, spass, quats, axes, g.unit)
        return full, int(counts.sum())

    (counts, slots, spass, quats), rounds, prev = run_rounds(g, one_round, new_arrays)
    first_pass = _COLOURS * (rounds - 1)
    m = int(counts.sum()) - prev
    keys_last, index_last = np.empty(m, np.uint64), np.empty(m, np.int64)
    _last_round(first_pass, trim_key, counts, spass, keys_last, index_last)
    cut_key, cut_index = cut_of(keys_last, index_last, g.n - prev)
    pos = np.empty((g.n, 3))
    quat = np.empty((g.n if g.spheroid else 0, 4))
    placed = _gather(g.nc, g.unit, first_pass, trim_key, cut_key, cut_index, counts, slots, spass, quats, pos, quat)
    if placed != g.n:
        raise RuntimeError(f"random start: {placed} particles kept for {g.n}")
    return pos, (quat if g.spheroid else None)


fast_loads(globals())  # their disk-cache loads skip numba's target refresh (engine/numba_support/jitcache.py)
