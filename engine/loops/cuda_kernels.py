"""CUDA layout and neighbour-list kernels of the GPU backend: K independent scenes advanced together (K = 1 for
one run), for every particle shape.

This module owns the device layout (below), the per-scene tables and status words, the block reductions and
the blow-up record shared by every kernel (:func:`device_helpers`, :func:`observe_reducer`), and the
single-grid neighbour-list kernels (:func:`grid_kernels`: cells, scan, scatter, per-cell id sort, permutation,
compact history store, full Verlet list build; the cell arithmetic is engine/neighbours/cells.py's). The time loop is
engine/loops/cuda_loop.py's, specialised by a shape's device functions (engine/shapes/<shape>/device.py);
the multigrid and CPU-built lists are engine/loops/cuda_lists.py's. Kernels are built by factories keyed on
what the scenes need (docs/design.md §1) and call the same ``@numba.njit`` functions as the CPU backend.

Layout (device, structure of arrays, particle index fastest). The scenes lie back to back: scene s owns
the slots [start_s, start_s + n_s) and keeps them (its cells come before the next scene's, so the cell
sort never moves a particle into another scene's range); ``sc[i]`` is the scene of slot i (a lone scene holds one
word, never read: :func:`scene_of`).
    pos, vel, spin (3, N) (spin: the rotational state the torque kicks, the shape's); quat (4, N); f0/f1
    (3, N) (double buffer: the sphere force phase reads the previous step's forces for the predicted
    velocities of *other* particles while writing its own); torque (3, N); x_ref (3, N) (float32 beside float64
    positions where its rounding is small against the skin: cuda_memory.xref_dtype); ids (N) int32 =
    ensemble-wide particle id (start_s + id within the scene); a shape's own arrays (``ext``).
    Neighbour list (of the list radius: a sphere's radius, a spheroid's bounding radius), packed rows (below):
    nn (N + 1) int32 rows, nbr (slots) int32, hist (H, slots) per-slot contact history (H = 5:
    tangential spring x, y, z, previous overlap, previous dashpot force).
    Compact history store (rebuilds only): the slots whose history matters across a rebuild (in contact
    at the previous step or overlapping now) are copied to cj/chist before the list is rebuilt in place;
    every other slot restarts from zero history with the current gap as its previous overlap, which gives
    the same forces bit for bit (a pair apart at the previous step has zero spring, and its previous
    dashpot force is never read). This keeps one list buffer instead of two (a smaller GPU memory footprint per
    particle).
Per-scene constants: spd (K, ND + the shape's columns) in the working precision, spf (K, NF) float64,
spi (K, NI) int32; a scene whose ``spi[s, I_ACTIVE]`` is 0 is skipped by every kernel (finished, cancelled or
failed: a blow-up clears it on the device so a failing scene cannot disturb the others).

Status (float64): global slots S_* (rebuild decision, list slots, compaction count, multi-step exit)
then NSS words per scene at SS0 + NSS s (first bad value, worst overlap beyond the limit).
"""

from __future__ import annotations

import math

import numpy as np
from numba import cuda
from numba.cuda import types as ct

from engine.loops.cuda_cache import SIM, cache_kernels
from engine.neighbours.cells import cell_coords, cell_index_of, distance2, neighbour_row, offset_span, row_runs
from engine.physics.contact import min_image

# per-scene constants: spd (working precision)
D_BOX, D_INVBOX, D_DT, D_HP, D_KN, D_GN, D_KT, D_MU, D_R0, D_M0, D_I0, D_IM0, D_II0, D_SKIN = range(14)
ND = 14
# spf (float64)
F_OVL, F_INVCELL, F_LIM2INV, F_V2F, F_KN, F_KT = range(6)
NF = 6
# spi (int32)
I_NC, I_COFF, I_ACTIVE, I_START, I_N, I_ORIENT = range(6)
NI = 6

# global status slots; S_D2 (+1): max over particles of (displacement since the build / (L_v/2))^2 (two
# slots: the multi-step kernel and the fused force-and-kick-drift kernel alternate them by step parity); S_V2
# (and S_V2B, its other parity): max (2 |v| dt / (L_v/2))^2
# S_CHECK: max (displacement from a list's snapshot / (L_v/2))^2, the a-posteriori check of a CPU-built list
# S_D2C: the third slot of the fused many-steps kernel, which rotates the step maxima through S_D2, S_D2B, S_D2C
# S_SLOTS: the slots of a new list's rows (slot_total; ListBuilds._list_room)
S_D2, S_D2B, S_V2, S_NCOMP, S_RUN_DONE, S_RUN_REBUILD, S_CHECK, S_V2B, S_D2C, S_SLOTS = range(10)
SS0 = 10
# per-scene status words
SS_BAD_ID, SS_BAD_STEP, SS_OVL, SS_OVL_ID, SS_OVL_STEP = range(5)
NSS = 5
HW = 5  # history words per list slot: spring x, y, z, previous overlap, previous dashpot force (a shape's
#        pair law may keep more: the host allocates hist/chist with its own count, the kernels read shape[0])
# The list: nn (N + 1): nn[i] the first slot of particle i's row, nn[N] the slots in all (the rows back to back in
# particle order, only the slots in use: an exclusive scan of a build's per-row counts, which are scratch of the build);
# slot q of the list holds the neighbour nbr[q] (int32, packed) and its contact history hist[:, q] (words x slots), so
# neighbouring threads read neighbouring slots; row i's count is nn[i + 1] - nn[i] (one cache line a warp)

_cache: dict = {}


def status_len(k: int) -> int:
    return SS0 + NSS * k


def grid_kernels(dtype, uniform: bool, tpb: int) -> dict:
    """The neighbour-list kernels (cells, scan, scatter, sort, permute, compact history store, build) for one
    precision, uniformity and block size (cached): every shape's broad phase is this list of its list radius
    (a sphere's radius, a spheroid's bounding radius)."""
    key = (np.dtype(dtype).str, uniform, tpb)
    if key not in _cache:
        _cache[key] = cache_kernels(_make(np.dtype(dtype).type, uniform, tpb), ("grid",) + key)
    return _cache[key]


def device_helpers(tpb: int):
    """(block_max2, fail): the block reduction and the per-scene blow-up record shared by the sphere and
    ellipsoid kernel sets (cached per block size)."""
    key = ("helpers", tpb)
    if key not in _cache:
        _cache[key] = _make_helpers(tpb)
    return _cache[key]


def observe_reducer(tpb: int, nv: int, max_slot: int):
    """Device function ``block_accumulate(sh, vals, acc, s)``: the block-wide reduction of the nv float64
    values ``vals`` of every thread (sums, except slot ``max_slot``: a maximum) into ``acc[s, :]`` with one
    atomic per value per block (cached). ``sh`` is a shared float64 array of nv * tpb; every thread of the
    block must call it, and all of them must add to the same scene s (observe grids are one block row per
    scene)."""
    key = ("reducer", tpb, nv, max_slot)
    if key not in _cache:
        _cache[key] = _make_reducer(tpb, nv, max_slot)
    return _cache[key]


def _make_reducer(TPB, NV, MAXSLOT):
    @cuda.jit(device=True)
    def block_accumulate(sh, vals, acc, s):
        t = cuda.threadIdx.x
        for q in range(NV):
            sh[q * TPB + t] = vals[q]
        cuda.syncthreads()
        st = TPB // 2
        while st > 0:
            if t < st:
                for q in range(NV):
                    a = sh[q * TPB + t]
                    b = sh[q * TPB + t + st]
                    if q == MAXSLOT:
                        if b > a:
                            sh[q * TPB + t] = b
                    else:
                        sh[q * TPB + t] = a + b
            cuda.syncthreads()
            st //= 2
        if t < NV:
            v = sh[t * TPB]
            if t == MAXSLOT:
                cuda.atomic.max(acc, (s, t), v)
            elif v != 0.0:
                cuda.atomic.add(acc, (s, t), v)

    return block_accumulate


def _make_helpers(TPB):
    f64 = np.float64

    WARPS = TPB // 32

    @cuda.jit(device=True)
    def block_max2_shuffle(sh, a, b):
        """Block-wide max of (a, b) into sh[0], sh[TPB], for thread 0 to read (all threads must call; TPB a
        multiple of 32). Each warp reduces by shuffles, then thread 0 over the warps' maxima: one block barrier
        instead of one per halving of a shared-memory tree (the many-steps kernel of a small scene, latency-bound,
        runs this reduction every step)."""
        t = cuda.threadIdx.x
        off = 16
        while off > 0:
            oa = cuda.shfl_down_sync(0xFFFFFFFF, a, off)
            ob = cuda.shfl_down_sync(0xFFFFFFFF, b, off)
            if oa > a:
                a = oa
            if ob > b:
                b = ob
            off //= 2
        if (t & 31) == 0:
            sh[t >> 5] = a
            sh[(t >> 5) + TPB] = b
        cuda.syncthreads()
        if t == 0:
            for w in range(1, WARPS):
                if sh[w] > sh[0]:
                    sh[0] = sh[w]
                if sh[w + TPB] > sh[TPB]:
                    sh[TPB] = sh[w + TPB]

    @cuda.jit(device=True)
    def block_max2_tree(sh, a, b):
        """The same maxima by a shared-memory tree (the CUDA simulator has no warp shuffles)."""
        t = cuda.threadIdx.x
        sh[t] = a
        sh[t + TPB] = b
        cuda.syncthreads()
        s = TPB // 2
        while s > 0:
            if t < s:
                if sh[t + s] > sh[t]:
                    sh[t] = sh[t + s]
                if sh[t + TPB + s] > sh[t + TPB]:
                    sh[t + TPB] = sh[t + TPB + s]
            cuda.syncthreads()
            s //= 2

    block_max2 = block_max2_tree if SIM else block_max2_shuffle

    @cuda.jit(device=True)
    def fail(status, spi, s, word, value, step):
        """Record a blow-up of scene s (first offender, first step) and stop the scene on the device."""
        b = SS0 + NSS * s
        cuda.atomic.min(status, b + word, f64(value))
        cuda.atomic.min(status, b + word + 1, f64(step))
        spi[s, I_ACTIVE] = 0

    return block_max2, fail


def _make(DT, UNIFORM, TPB):  # noqa: C901  (one closure per specialisation)
    ZERO = DT(0)
    HALF = DT(0.5)
    f64 = np.float64

    # ---- neighbour list: cells, sort, permute, compact history, build -----------------------------------

    @cuda.jit(device=True)
    def cell_of(i, pos, sc, spf, spi):
        s = scene_of(i, sc, spi)
        return spi[s, I_COFF] + cell_index_of(pos[0, i], pos[1, i], pos[2, i], spf[s, F_INVCELL], spi[s, I_NC])

    @cuda.jit
    def fill_i32(a, value):
        for i in range(cuda.grid(1), a.shape[0], cuda.gridsize(1)):
            a[i] = value

    @cuda.jit
    def set_word(a, slot, value):
        """a[slot] = value, in stream order (a status word reset before a kernel that accumulates into it)."""
        if cuda.grid(1) == 0:
            a[slot] = value

    @cuda.jit
    def count_cells(n, pos, sc, spf, spi, count):
        for i in range(cuda.grid(1), n, cuda.gridsize(1)):
            cuda.atomic.add(count, cell_of(i, pos, sc, spf, spi), 1)

    @cuda.jit
    def tile_scan(src, dst, n, bsum, items):
        """Exclusive scan of src[0:n] per tile of TPB*items elements; tile totals into bsum."""
        sh = cuda.shared.array(TPB, ct.int64)
        t = cuda.threadIdx.x
        base = cuda.blockIdx.x * TPB * items + t * items
        s = 0
        for k in range(items):
            if base + k < n:
                s += src[base + k]
        sh[t] = s
        cuda.syncthreads()
        off = 1
        while off < TPB:
            v = 0
            if t >= off:
                v = sh[t - off]
            cuda.syncthreads()
            sh[t] += v
            cuda.syncthreads()
            off *= 2
        run = sh[t] - s
        for k in range(items):
            if base + k < n:
                x = src[base + k]
                dst[base + k] = run
                run += x
        if t == TPB - 1:
            bsum[cuda.blockIdx.x] = sh[t]

    @cuda.jit
    def add_offsets(dst, n, offs, tile):
        for i in range(cuda.grid(1), n, cuda.gridsize(1)):
            dst[i] += offs[i // tile]

    @cuda.jit
    def scatter(n, pos, sc, spf, spi, cell_start, cursor, order):
        for i in range(cuda.grid(1), n, cuda.gridsize(1)):
            c = cell_of(i, pos, sc, spf, spi)
            order[cell_start[c] + cuda.atomic.add(cursor, c, 1)] = i

    @cuda.jit
    def sort_cells(ncell, cell_start, order, ids):
        """Insertion sort of each cell's particles by id: a deterministic order (cell, id)."""
        for c in range(cuda.grid(1), ncell, cuda.gridsize(1)):
            a = cell_start[c]
            b = cell_start[c + 1]
            for p in range(a + 1, b):
                v = order[p]
                key = ids[v]
                q = p - 1
                while q >= a and ids[order[q]] > key:
                    order[q + 1] = order[q]
                    q -= 1
                order[q + 1] = v

    @cuda.jit
    def gather_rows(n, src, dst, order):
        """dst[:, k] = src[:, order[k]] (also for 1-row arrays given as (1, N))."""
        for k in range(cuda.grid(1), n, cuda.gridsize(1)):
            o = order[k]
            for r in range(src.shape[0]):
                dst[r, k] = src[r, o]

    @cuda.jit
    def gather_i32(n, src, dst, order):
        for k in range(cuda.grid(1), n, cuda.gridsize(1)):
            dst[k] = src[order[k]]

    @cuda.jit
    def inverse_perm(n, order, inv):
        for k in range(cuda.grid(1), n, cuda.gridsize(1)):
            inv[order[k]] = k

    @cuda.jit(device=True)
    def keeps_history(i, q, j, pos, radius, hist, s, spd):
        """A slot (history slot q of particle i, neighbour j) whose history must survive a rebuild: in contact at the
        previous step or now."""
        if hist[3, q] > ZERO:
            return True
        box = spd[s, D_BOX]
        inv_box = spd[s, D_INVBOX]
        r0 = spd[s, D_R0]
        rx = min_image(pos[0, i] - pos[0, j], box, inv_box, HALF)
        ry = min_image(pos[1, i] - pos[1, j], box, inv_box, HALF)
        rz = min_image(pos[2, i] - pos[2, j], box, inv_box, HALF)
        rs = (r0 + r0) if UNIFORM else (radius[i] + radius[j])
        return rx * rx + ry * ry + rz * rz < rs * rs

    @cuda.jit
    def compact(n, pos, radius, nbr, nn, hist, sc, spd, spi, c_off, c_cnt, cj, chist, status):
        """Copy the slots that keep history into the compact store (old slot order); the total goes to
        status[S_NCOMP]; nothing is written past the store's capacity (the host grows it and reruns)."""
        cap = cj.shape[0]
        for i in range(cuda.grid(1), n, cuda.gridsize(1)):
            s = scene_of(i, sc, spi)
            cnt = 0
            h0 = nn[i]
            h1 = nn[i + 1]
            if spi[s, I_ACTIVE] != 0:
                for q in range(h0, h1):
                    if keeps_history(i, q, nbr[q], pos, radius, hist, s, spd):
                        cnt += 1
            off = 0
            if cnt > 0:
                off = int(cuda.atomic.add(status, S_NCOMP, f64(cnt)))
            c_off[i] = off
            c_cnt[i] = cnt
            if cnt > 0 and off + cnt <= cap:
                c = off
                for q in range(h0, h1):
                    j = nbr[q]
                    if keeps_history(i, q, j, pos, radius, hist, s, spd):
                        cj[c] = j
                        for w in range(chist.shape[0]):
                            chist[w, c] = hist[w, q]
                        c += 1

    @cuda.jit
    def build(n, pos, radius, cell_start, order, permuted, nbr, nn, counts, x_ref, sc, spd, spf, spi, fill, kept,
              keep):
        """Full Verlet list, in two passes: ``fill`` 0 searches the cells, counts each row into counts[i] and keeps
        its first ``keep`` neighbours in kept[k, i] (the host then hands out the rows, an exclusive scan of the
        counts into nn, and makes room for them); ``fill`` 1 writes the neighbours into the rows nbr[nn[i] + k]:
        copied from ``kept`` for a row of at most ``keep`` (most rows of a thin skin: a search costs the same for
        an empty row as for a full one), found by the same search again for a longer one (``keep`` 0: every row).
        A cell's particles are the slots cell_start[c] ... cell_start[c + 1] - 1 of the cell order: the particles
        themselves where they were ``permuted`` into it, else order[slot] (the sort's (cell, id) order, the
        particles left where they are). Either way a row lists the same particles in the same order. The rows'
        history follows (:func:`fill_history`)."""
        for i in range(cuda.grid(1), n, cuda.gridsize(1)):
            if fill != 0 and keep > 0:
                h0 = nn[i]
                m = nn[i + 1] - h0
                if m <= keep:
                    for k in range(m):
                        nbr[h0 + k] = kept[k, i]
                    continue
            xi, yi, zi, s, box, inv_box, skin = list_origin(i, pos, x_ref, sc, spd, spi)
            if s < 0:
                if fill == 0:
                    counts[i] = 0
                continue
            nc = spi[s, I_NC]
            coff = spi[s, I_COFF]
            r0 = spd[s, D_R0]
            cx, cy, cz = cell_coords(xi, yi, zi, spf[s, F_INVCELL], nc)
            ri = r0 if UNIFORM else radius[i]
            base = nn[i] if fill != 0 else -1
            cnt = 0
            # neighbour_cell's cells in its order, a row's z-cells as runs of the cell-sorted particles
            # (cells.row_runs): neighbour_cell's integer divisions per cell took most of the build
            span = offset_span(nc)
            z0, z1, z2, z3 = row_runs(cz, nc)
            for ox in range(span):
                for oy in range(span):
                    row = coff + neighbour_row(cx, cy, ox, oy, nc)
                    for slot in range(cell_start[row + z0], cell_start[row + z1]):
                        j = slot if permuted != 0 else order[slot]
                        rj = r0 if UNIFORM else radius[j]
                        cnt = keep_candidate(i, j, cnt, add_candidate(i, j, cnt, xi, yi, zi, ri, rj, skin, pos,
                                                                      box, inv_box, HALF, nbr, base)[0], kept, keep)
                    for slot in range(cell_start[row + z2], cell_start[row + z3]):
                        j = slot if permuted != 0 else order[slot]
                        rj = r0 if UNIFORM else radius[j]
                        cnt = keep_candidate(i, j, cnt, add_candidate(i, j, cnt, xi, yi, zi, ri, rj, skin, pos,
                                                                      box, inv_box, HALF, nbr, base)[0], kept, keep)
            if fill == 0:
                counts[i] = cnt

    @cuda.jit
    def slot_total(n, nn, counts, status):
        """nn[n] and status[S_SLOTS] = the slots of the list's rows, nn[n-1] + counts[n-1] (after the exclusive scan
        of a build's counts into the rows' first slots nn[:n]; in int64 for the status: the host checks it)."""
        if cuda.grid(1) == 0:
            total = np.int64(0)
            if n > 0:
                total = np.int64(nn[n - 1]) + np.int64(counts[n - 1])
            nn[n] = total
            status[S_SLOTS] = f64(total)

    @cuda.jit
    def fill_history(n, pos, radius, c_off, c_cnt, cj, chist, order, inv_old, permuted, nbr, nn, hist, sc, spd,
                     spi):
        """The history of every slot of a new list (built on the GPU, single grid or multigrid, or on the host), in
        its row's slots hist[:, nn[i] + k]: the kept history from the compact store, indexed by the previous
        order where the particles were ``permuted`` (old slot of new i: order[i]; old neighbour index o: new index
        inv_old[o]), else by the particles' own slots (a host-built list permutes nothing); a slot without kept
        history is fresh, its previous overlap the gap R_i + R_j - |r_ij| from the candidate test's own squared
        distance (cells.distance2)."""
        for i in range(cuda.grid(1), n, cuda.gridsize(1)):
            s = scene_of(i, sc, spi)
            if spi[s, I_ACTIVE] == 0:
                continue
            h0 = nn[i]
            cnt = nn[i + 1] - h0
            if cnt == 0:
                continue
            box = spd[s, D_BOX]
            inv_box = spd[s, D_INVBOX]
            r0 = spd[s, D_R0]
            ri = r0 if UNIFORM else radius[i]
            xi = pos[0, i]
            yi = pos[1, i]
            zi = pos[2, i]
            oi = order[i] if permuted != 0 else i
            k0 = c_off[oi]
            k1 = k0 + c_cnt[oi]
            for q in range(h0, h0 + cnt):
                j = nbr[q]
                rj = r0 if UNIFORM else radius[j]
                d2 = distance2(xi, yi, zi, pos[0, j], pos[1, j], pos[2, j], box, inv_box, HALF)
                init_slot(q, j, ri + rj - math.sqrt(d2), k0, k1, cj, chist, inv_old, permuted, hist)

    return dict(fill_i32=fill_i32, set_word=set_word, slot_total=slot_total, fill_history=fill_history,
                count_cells=count_cells, tile_scan=tile_scan, add_offsets=add_offsets, scatter=scatter,
                sort_cells=sort_cells, gather_rows=gather_rows, gather_i32=gather_i32, inverse_perm=inverse_perm,
                compact=compact, build=build)


@cuda.jit
def gather_scene(src, ids, a0, n_k, lo, hi, dst):
    """dst[o - lo, r] = src[r, a0 + l] for l < n_k where o = ids[a0 + l] - a0 lies in [lo, hi): the particles lo ...
    hi - 1 (in id order within the scene) of one scene's (rows, N) state array, particle-major, for the host copy of
    a snapshot or checkpoint (lo = 0, hi = n_k: the whole scene; a piece of a large one otherwise)."""
    for li in range(cuda.grid(1), n_k, cuda.gridsize(1)):
        i = a0 + li
        o = ids[i] - a0
        if lo <= o < hi:
            for r in range(src.shape[0]):
                dst[o - lo, r] = src[r, i]


@cuda.jit
def scatter_rows(src, a0, dst):
    """dst[r, a0 + i] = src[i, r], cast to dst's type: a host (n, rows) array, uploaded as it is, into the rows
    of a (rows, N) state array from column a0 (the transposition and the precision cast of an upload run on the
    device, which shortens a job's set-up)."""
    for i in range(cuda.grid(1), src.shape[0], cuda.gridsize(1)):
        for r in range(src.shape[1]):
            dst[r, a0 + i] = src[i, r]


@cuda.jit
def slot_ids_and_scenes(ends, ids, sc):
    """ids[i] = i and sc[i] = the scene of slot i, scene k holding slots ends[k - 1] .. ends[k] - 1 (ends: the
    cumulative scene sizes, ends[-1] = N): an ensemble's first identity order and scene index, made on the device
    (uploaded, they were two N-long host arrays and copies of a large job's set-up). A lone scene's sc (one word)
    is left alone (:func:`scene_of`)."""
    nk = ends.shape[0]
    for i in range(cuda.grid(1), ids.shape[0], cuda.gridsize(1)):
        ids[i] = i
        if nk == 1:
            continue
        lo = 0
        hi = nk - 1
        while lo < hi:          # the first scene whose end lies beyond i
            mid = (lo + hi) // 2
            if ends[mid] > i:
                hi = mid
            else:
                lo = mid + 1
        sc[i] = lo


@cuda.jit
def cast_rows(src, dst):
    """dst[r, i] = src[r, i], cast to dst's type: a (rows, N) array copied into one of another precision (the
    positions a host-built list was made from into a float32 x_ref)."""
    for i in range(cuda.grid(1), src.shape[1], cuda.gridsize(1)):
        for r in range(src.shape[0]):
            dst[r, i] = src[r, i]


cache_kernels({"gather_scene": gather_scene, "scatter_rows": scatter_rows,
               "slot_ids_and_scenes": slot_ids_and_scenes, "cast_rows": cast_rows}, ("gather",))


@cuda.jit(device=True)
def scene_of(i, sc, spi):
    """The scene of particle slot i: 0 when there is one (sc is then not read, nor held: one word)."""
    return 0 if spi.shape[0] == 1 else sc[i]


@cuda.jit(device=True)
def list_origin(i, pos, x_ref, sc, spd, spi):
    """Start of particle i's row of a list build: its position, recorded as the list's reference x_ref (in x_ref's
    type: cuda_memory.xref_dtype), its scene s and the scene's box, 1/box and skin; s = -1 when the scene is
    inactive (its row is empty)."""
    xi = pos[0, i]
    yi = pos[1, i]
    zi = pos[2, i]
    x_ref[0, i] = xi
    x_ref[1, i] = yi
    x_ref[2, i] = zi
    s = scene_of(i, sc, spi)
    box = spd[s, D_BOX]
    inv_box = spd[s, D_INVBOX]
    skin = spd[s, D_SKIN]
    if spi[s, I_ACTIVE] == 0:
        return xi, yi, zi, -1, box, inv_box, skin
    return xi, yi, zi, s, box, inv_box, skin


@cuda.jit(device=True)
def add_candidate(i, j, cnt, xi, yi, zi, ri, rj, skin, pos, box, inv_box, half, nbr, base):
    """The candidate test of every CUDA list build (engine/neighbours/cells.distance2): j (!= i) joins i's row
    when |r_ij| < R_i + R_j + L_v, stored at nbr[base + cnt] (a build's counting pass, base < 0, stores nothing).
    Returns (the new count, the squared distance; 0 for j = i)."""
    if j == i:
        return cnt, half - half
    d2 = distance2(xi, yi, zi, pos[0, j], pos[1, j], pos[2, j], box, inv_box, half)
    rc = ri + rj + skin
    if d2 < rc * rc:
        if base >= 0:
            nbr[base + cnt] = j
        return cnt + 1, d2
    return cnt, d2


@cuda.jit(device=True)
def keep_candidate(i, j, cnt, new, kept, keep):
    """A counting pass's row after the candidate test (count ``cnt`` before it, ``new`` after): a neighbour found
    (j) among the row's first ``keep`` is kept at kept[cnt, i] for the filling pass. Returns the new count."""
    if new != cnt and cnt < keep:
        kept[cnt, i] = j
    return new


@cuda.jit(device=True)
def init_slot(q, j, gap, k0, k1, cj, chist, inv_old, permuted, hist):
    """History slot q (neighbour j) after a rebuild: the kept history from the compact store entries k0..k1 of its
    particle (old indices o map to new ones by inv_old[o] where the rebuild ``permuted`` the particles, else they
    are the same), else a fresh slot (zero spring, zero dashpot force, previous overlap = the current gap, m)."""
    for c in range(k0, k1):
        o = cj[c]
        if (inv_old[o] if permuted != 0 else o) == j:
            for w in range(hist.shape[0]):
                hist[w, q] = chist[w, c]
            return
    for w in range(hist.shape[0]):
        hist[w, q] = 0
    hist[3, q] = gap
