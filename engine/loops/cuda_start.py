"""Large starts drawn on the GPU (a job's time to result).

A GPU job of a large one-size start (engine.setup.scene.device_start) does not draw its start on the host and upload
it: the shape's CUDA ensemble (engine/shapes/sphere/cuda_backend.py; the spheroid's, engine/shapes/spheroid/
cuda_backend.py ``draw_ellipsoid_start``, turns its draws into spins and L after these kernels) draws it into its
own state arrays when it is built, from an ``engine.setup.scene.StartDraw``. The draws are the host's
(engine.setup.scene._draw_start), in the same order:

1. the site selection (the n of the n_sites fcc sites whose 64-bit key is smallest): a histogram of the keys'
   leading bits (:func:`site_hist`), the keys of the bucket that holds the n-th smallest gathered with each
   block's count below it (:func:`site_gather`); the host sorts that bucket (a few hundred keys), finds the cut
   and each block's first particle;
2. :func:`place_draw`: one thread per site; a block scan gives each chosen site its particle i (sites in
   order, as the host's), whose position (engine.setup.scene._site_position) it draws;
3. one stream at a time, :func:`stream_draw`: each particle's rows of the stream (engine.setup.scene._stream_values)
   into a float64 scratch (dim, n), then :func:`block_moments`: each row's sums over the same fixed blocks of
   engine.setup.scene._BLOCK particles, summed in the same order; the host turns them into means
   (engine.setup.scene.stream_mean), the kernel centres the rows and sums their squares, the host takes the scales
   (engine.setup.scene.stream_scale);
4. :func:`scale_into`: the stream, scaled, into its state array in the working precision (the cast an upload
   would make on the device, K.scatter_rows).

A random start (``StartDraw.rsa``) replaces steps 1 and 2 by the rounds of engine/setup/cell_rsa.py: ``rsa_pass``
(spheres) or ``rsa_pass_spheroid`` (their orientations drawn with the centres, into the ``quat`` rows) per pass and
colour, a count per round (:func:`rsa_total`), the last round's surplus removed by a histogram of its
removal keys (:func:`rsa_last_hist`, :func:`rsa_last_gather`, a host sort of one bucket), and one thread per cell
placing its spheres (:func:`rsa_kept_counts`, a host scan, :func:`rsa_place`); the cells are freed before the first
stream's scratch is made, so the start's peak holds the cells or one stream's scratch, not both; the centres
are the host's exactly (integer tests, one rounding each; a spheroid pair within the bounding distance is tested in
floating point, engine/setup/cell_rsa.py).

The formulas are engine.setup.scene's ``@numba.njit`` functions, called by these kernels and by the host's draws alike.
Sites, blocks and host arithmetic are identical; the values are equal to rounding (libdevice's log, cos, sin and
pow against the host's libm, and fused multiply-adds). The host pays no draw, no 0.2 GB upload and no load of the
draws' compiled code; the GPU start-up thread (engine/driver/startup.py) loads these kernels (:func:`load`) beside
the job's own.
"""

from __future__ import annotations

import numpy as np
from numba import cuda

from engine.setup.cell_rsa import (RSA_Q, SPHERES, SPHEROIDS, cut_of, final_key, kept, pass_functions, pass_key,
                                   run_rounds, slot_index)
from engine.loops.cuda_cache import SIM, cache_kernels
from engine.loops.cuda_memory import device_zeros
from engine.setup.counter_rng import _bits
from engine.setup.scene import (_BLOCK, _SELECT_BITS, STREAM_QUATERNION, STREAM_SPIN, STREAM_VELOCITY, StartDraw,
                                _site_position, _stream_values, stream_mean, stream_scale)

#: sites per block of the selection and placement kernels (a compile-time size of their shared arrays)
TPB = 32 if SIM else 128
#: threads per block of the other launches (the simulator runs each thread as a Python thread)
_WIDE = 32 if SIM else 256
_NB = 1 << _SELECT_BITS
_SHIFT = np.uint64(64 - _SELECT_BITS)
_ALL = np.uint64(0xFFFFFFFFFFFFFFFF)


@cuda.jit
def site_hist(site_key, n_sites, hist):
    """hist[b] += the number of sites whose key's leading _SELECT_BITS bits are b (a block histogram in shared
    memory, then one atomic per bucket and block: integer counts, the same for any launch)."""
    sh = cuda.shared.array(_NB, np.int32)
    t = cuda.threadIdx.x
    for b in range(t, _NB, cuda.blockDim.x):
        sh[b] = 0
    cuda.syncthreads()
    for j in range(cuda.grid(1), n_sites, cuda.gridsize(1)):
        cuda.atomic.add(sh, np.int64(_bits(site_key, j, 0) >> _SHIFT), 1)
    cuda.syncthreads()
    for b in range(t, _NB, cuda.blockDim.x):
        if sh[b] > 0:
            cuda.atomic.add(hist, b, sh[b])


@cuda.jit
def site_gather(site_key, n_sites, bucket, cand_key, cand_site, cand_n, below):
    """One thread per site, TPB sites per block: the keys (and sites) in ``bucket`` go to cand_key/cand_site (in
    any order: the host sorts them), and below[block] = the block's count of keys in lower buckets."""
    cnt = cuda.shared.array(1, np.int32)
    t = cuda.threadIdx.x
    if t == 0:
        cnt[0] = 0
    cuda.syncthreads()
    j = cuda.blockIdx.x * TPB + t
    if j < n_sites:
        k = _bits(site_key, j, 0)
        b = np.int64(k >> _SHIFT)
        if b < bucket:
            cuda.atomic.add(cnt, 0, 1)
        elif b == bucket:
            at = cuda.atomic.add(cand_n, 0, 1)
            cand_key[at] = k
            cand_site[at] = j
    cuda.syncthreads()
    if t == 0:
        below[cuda.blockIdx.x] = cnt[0]


@cuda.jit
def stream_draw(key, dim, unit, out):
    """out[r, i] (r < dim) = particle i's values of one stream (engine.setup.scene ``_stream_values``, float64)."""
    for i in range(cuda.grid(1), out.shape[1], cuda.gridsize(1)):
        v0, v1, v2, v3 = _stream_values(key, i, dim, unit)
        out[0, i] = v0
        if dim > 1:
            out[1, i] = v1
        if dim > 2:
            out[2, i] = v2
        if dim > 3:
            out[3, i] = v3


@cuda.jit
def place_draw(site_key, cut, n_sites, first, m, a, half_gap, box, place_key, pos, col0):
    """One thread per site, TPB per block: a site whose key is <= ``cut`` is chosen; its particle i is the block's
    first particle (``first``) plus the chosen sites before it in the block (a shared-memory scan). Particle i's
    position goes to pos[:, col0 + i] (cast to pos's precision)."""
    flags = cuda.shared.array(TPB, np.int32)
    t = cuda.threadIdx.x
    j = cuda.blockIdx.x * TPB + t
    chosen = 0
    if j < n_sites and _bits(site_key, j, 0) <= cut:
        chosen = 1
    flags[t] = chosen
    cuda.syncthreads()
    d = 1
    while d < TPB:                     # inclusive scan (Hillis-Steele)
        v = flags[t - d] if t >= d else 0
        cuda.syncthreads()
        flags[t] += v
        cuda.syncthreads()
        d *= 2
    if chosen:
        i = first[cuda.blockIdx.x] + flags[t] - 1
        x, y, z = _site_position(j, i, m, a, half_gap, box, place_key)
        pos[0, col0 + i] = x
        pos[1, col0 + i] = y
        pos[2, col0 + i] = z


@cuda.jit
def block_moments(out, means, square, sums):
    """One thread per (row r, block of _BLOCK particles). square = 0: sums[r, block]
    = the sum of out[r, i] over the block, in particle order (as engine.setup.scene._draw_start's); square = 1: the row
    is centred, out[r, i] -= means[r], and sums[r, block] = the sum of the squares
    (engine.setup.scene._centre_and_square)."""
    g = cuda.grid(1)
    nb = sums.shape[1]
    n = out.shape[1]
    if g >= out.shape[0] * nb:
        return
    r = g // nb
    bl = g - r * nb
    acc = 0.0
    if square:
        mu = means[r]
        for i in range(bl * _BLOCK, min(n, (bl + 1) * _BLOCK)):
            x = out[r, i] - mu
            out[r, i] = x
            acc += x * x
    else:
        for i in range(bl * _BLOCK, min(n, (bl + 1) * _BLOCK)):
            acc += out[r, i]
    sums[r, bl] = acc


@cuda.jit
def scale_into(out, scale, dst, col0):
    """dst[r, col0 + i] = out[r, i] * scale, cast to dst's precision."""
    for i in range(cuda.grid(1), out.shape[1], cuda.gridsize(1)):
        for r in range(out.shape[0]):
            dst[r, col0 + i] = out[r, i] * scale


# ---- a random start: random sequential addition in cell rounds (engine/setup/cell_rsa.py) ------------------------

if SIM:
    def _raw(a):
        """The simulator's device arrays wrap NumPy arrays: engine.setup.cell_rsa's compiled functions take those."""
        return a._ary
else:
    @cuda.jit(device=True, inline=True)
    def _raw(a):
        """The array itself (on a GPU the kernels call engine.setup.cell_rsa's functions compiled for the device)."""
        return a


def _pass_kernel(kind: int):
    """The pass kernel of spheres or spheroids (engine.setup.cell_rsa.pass_functions: the shape a constant of the
    compiled code)."""
    _, cell_pass = pass_functions(kind)

    @cuda.jit
    def rsa_pass(m, colour, p, nc, thr, cdf, pos_key, count_key, quat_key, counts, slots, spass, quats, axes, unit,
                 full):
        """Pass p (its cells: the m of colour ``colour``) of a random start: engine.setup.cell_rsa's cell_pass per
        cell, with the pass's keys of the streams ``pos_key``, ``count_key`` and ``quat_key`` (cell_rsa.pass_key,
        made here: a GPU job then calls no host-compiled function, whose first call in a process costs numba's
        CPU start-up); full[0] counts the cells that lacked a slot."""
        # np.uint64: the simulator's call of the host-compiled pass_key returns a Python int
        pk, ck = np.uint64(pass_key(pos_key, p)), np.uint64(pass_key(count_key, p))
        qk = np.uint64(pass_key(quat_key, p))
        for t in range(cuda.grid(1), m, cuda.gridsize(1)):
            if cell_pass(t, colour, p, nc, thr, _raw(cdf), pk, ck, qk, _raw(counts), _raw(slots),
                         _raw(spass), _raw(quats), _raw(axes), unit):
                cuda.atomic.add(full, 0, 1)

    return rsa_pass


rsa_pass, rsa_pass_spheroid = _pass_kernel(SPHERES), _pass_kernel(SPHEROIDS)


@cuda.jit
def rsa_total(counts, total):
    """total[0] += the spheres kept in every cell (one atomic per thread)."""
    acc = 0
    for c in range(cuda.grid(1), counts.shape[0], cuda.gridsize(1)):
        acc += counts[c]
    cuda.atomic.add(total, 0, acc)


@cuda.jit
def rsa_last_hist(first_pass, trim_key, counts, spass, hist):
    """hist[b] += the spheres of the last round whose removal key's leading _SELECT_BITS bits are b."""
    for c in range(cuda.grid(1), counts.shape[0], cuda.gridsize(1)):
        for k in range(counts[c]):
            if spass[c, k] >= first_pass:
                key = final_key(trim_key, c, k, spass[c, k] - first_pass)
                cuda.atomic.add(hist, np.int64(key >> _SHIFT), 1)


@cuda.jit
def rsa_last_gather(first_pass, trim_key, bucket, counts, spass, cand_key, cand_index, cand_n):
    """The (removal key, slot number) of the last round's spheres in ``bucket`` (any order: the host sorts them)."""
    for c in range(cuda.grid(1), counts.shape[0], cuda.gridsize(1)):
        for k in range(counts[c]):
            if spass[c, k] >= first_pass:
                key = final_key(trim_key, c, k, spass[c, k] - first_pass)
                if np.int64(key >> _SHIFT) == bucket:
                    at = cuda.atomic.add(cand_n, 0, 1)
                    cand_key[at] = key
                    cand_index[at] = slot_index(c, k)


@cuda.jit
def rsa_kept_counts(first_pass, trim_key, cut_key, cut_index, counts, spass, kept_n):
    """kept_n[c] = the spheres of cell c in the start (engine.setup.cell_rsa.kept)."""
    for c in range(cuda.grid(1), counts.shape[0], cuda.gridsize(1)):
        s = 0
        for k in range(counts[c]):
            if kept(c, k, _raw(counts), _raw(spass), first_pass, trim_key, cut_key, cut_index):
                s += 1
        kept_n[c] = s


@cuda.jit
def rsa_place(nc, unit, first_pass, trim_key, cut_key, cut_index, counts, slots, spass, quats, first, pos, quat,
              col0):
    """One thread per cell: its kept particles, numbered from first[c] in slot order, get their centre in pos[:, col0 +
    i] (cast to pos's precision), a spheroid its orientation in quat[:, col0 + i] (quat has no columns for
    spheres)."""
    q = np.int64(RSA_Q)
    for c in range(cuda.grid(1), counts.shape[0], cuda.gridsize(1)):
        i = first[c]
        cx = c // (nc * nc)
        cy = (c // nc) % nc
        cz = c % nc
        for k in range(counts[c]):
            if kept(c, k, _raw(counts), _raw(spass), first_pass, trim_key, cut_key, cut_index):
                pos[0, col0 + i] = (cx * q + np.int64(slots[c, k, 0]) + 0.5) * unit
                pos[1, col0 + i] = (cy * q + np.int64(slots[c, k, 1]) + 0.5) * unit
                pos[2, col0 + i] = (cz * q + np.int64(slots[c, k, 2]) + 0.5) * unit
                if quat.shape[1] != 0:
                    for j in range(4):
                        quat[j, col0 + i] = quats[c, k, j]
                i += 1


cache_kernels({"site_hist": site_hist, "site_gather": site_gather, "place_draw": place_draw,
               "stream_draw": stream_draw, "block_moments": block_moments, "scale_into": scale_into,
               "rsa_pass": rsa_pass, "rsa_pass_spheroid": rsa_pass_spheroid, "rsa_total": rsa_total,
               "rsa_last_hist": rsa_last_hist, "rsa_last_gather": rsa_last_gather,
               "rsa_kept_counts": rsa_kept_counts, "rsa_place": rsa_place},
              ("start",))


def _blocks(work: int, tpb: int, cap: int) -> int:
    return max(1, min(cap, (work + tpb - 1) // tpb))


def _cut(d: StartDraw, site_key, stream, cap: int) -> tuple:
    """(the largest chosen key, each site block's first particle): the selection's device passes and the host's
    sort of one bucket. Every site is chosen when n = n_sites."""
    n_blocks = (d.n_sites + TPB - 1) // TPB
    if d.n >= d.n_sites:
        counts = np.full(n_blocks, TPB, np.int64)
        counts[-1] = d.n_sites - TPB * (n_blocks - 1)
        return _ALL, counts
    hist = cuda.to_device(np.zeros(_NB, np.int32), stream=stream)
    site_hist[_blocks(d.n_sites, _WIDE, cap), _WIDE, stream](site_key, d.n_sites, hist)
    h = hist.copy_to_host(stream=stream)
    stream.synchronize()
    cum = np.cumsum(h.astype(np.int64))
    bucket = int(np.searchsorted(cum, d.n))          # the first bucket whose cumulative count reaches n
    below = int(cum[bucket - 1]) if bucket else 0
    in_bucket = int(h[bucket])
    cand_key = cuda.device_array(in_bucket, np.uint64, stream=stream)
    cand_site = cuda.device_array(in_bucket, np.int64, stream=stream)
    cand_n = cuda.to_device(np.zeros(1, np.int32), stream=stream)
    blk = cuda.device_array(n_blocks, np.int32, stream=stream)
    site_gather[n_blocks, TPB, stream](site_key, d.n_sites, np.int64(bucket), cand_key, cand_site, cand_n, blk)
    ck, cs, counts = cand_key.copy_to_host(stream=stream), cand_site.copy_to_host(stream=stream), \
        blk.copy_to_host(stream=stream)
    stream.synchronize()
    cut = np.sort(ck)[d.n - below - 1]
    counts = counts.astype(np.int64)
    np.add.at(counts, cs[ck <= cut] // TPB, 1)
    return cut, counts


def _random_centres(d: StartDraw, col0: int, pos, quat, stream, cap: int) -> None:
    """A random start's centres into pos[:, col0:col0 + n] (a spheroid start's orientations into quat[:, col0:col0 +
    n]): the rounds of engine/setup/cell_rsa.py on the device, the last round's cut by a
    histogram of its removal keys and a host sort of one bucket (as :func:`_cut`), then one thread per cell places its
    particles."""
    g = d.rsa
    rsa_keys = d.rsa_keys()
    pos_key, count_key, trim_key = (np.uint64(k) for k in rsa_keys[:3])
    quat_key = np.uint64(rsa_keys[3]) if g.spheroid else np.uint64(0)
    cdf = cuda.to_device(np.array(g.cdf, np.uint64), stream=stream)
    axes = cuda.to_device(np.array(g.axes, np.float64), stream=stream)
    kernel = rsa_pass_spheroid if g.spheroid else rsa_pass
    ncell = g.nc ** 3
    m = (g.nc // 2) ** 3
    grid_cells, grid_colour = _blocks(ncell, _WIDE, cap), _blocks(m, _WIDE, cap)
    full = cuda.device_array(1, np.int64, stream=stream)
    total = cuda.device_array(1, np.int64, stream=stream)
    zero = np.zeros(1, np.int64)

    def new_arrays(per_cell: int) -> tuple:
        counts = device_zeros(ncell, np.int32, stream)   # no host zeros: 2 GB of counts at 1e9 spheres
        return (counts, cuda.device_array((ncell, per_cell, 3), np.int16, stream=stream),
                cuda.device_array((ncell, per_cell), np.int32, stream=stream),
                cuda.device_array((ncell, per_cell, 4) if g.spheroid else (1, 1, 4), np.float64, stream=stream))

    def one_round(r: int, arrays: tuple) -> tuple:
        counts, slots, spass, quats = arrays
        full.copy_to_device(zero, stream=stream)
        total.copy_to_device(zero, stream=stream)
        for colour in range(8):
            p = 8 * r + colour
            kernel[grid_colour, _WIDE, stream](m, colour, np.int64(p), g.nc, g.thr, cdf, pos_key, count_key, quat_key,
                                               counts, slots, spass, quats, axes, g.unit, full)
        rsa_total[grid_cells, _WIDE, stream](counts, total)
        f, t = full.copy_to_host(stream=stream), total.copy_to_host(stream=stream)
        stream.synchronize()
        return int(f[0]), int(t[0])

    (counts, slots, spass, quats), rounds, prev = run_rounds(g, one_round, new_arrays)
    first_pass = 8 * (rounds - 1)
    keep = d.n - prev
    hist = cuda.to_device(np.zeros(_NB, np.int32), stream=stream)
    rsa_last_hist[grid_cells, _WIDE, stream](first_pass, trim_key, counts, spass, hist)
    h = hist.copy_to_host(stream=stream)
    stream.synchronize()
    cum = np.cumsum(h.astype(np.int64))
    bucket = int(np.searchsorted(cum, keep))
    below = int(cum[bucket - 1]) if bucket else 0
    in_bucket = int(h[bucket])
    cand_key = cuda.device_array(in_bucket, np.uint64, stream=stream)
    cand_index = cuda.device_array(in_bucket, np.int64, stream=stream)
    cand_n = cuda.to_device(np.zeros(1, np.int32), stream=stream)
    rsa_last_gather[grid_cells, _WIDE, stream](first_pass, trim_key, np.int64(bucket), counts, spass, cand_key,
                                               cand_index, cand_n)
    cut_key, cut_index = cut_of(cand_key.copy_to_host(stream=stream), cand_index.copy_to_host(stream=stream),
                                keep - below)
    kept_n = cuda.device_array(ncell, np.int32, stream=stream)
    rsa_kept_counts[grid_cells, _WIDE, stream](first_pass, trim_key, cut_key, cut_index, counts, spass, kept_n)
    per = kept_n.copy_to_host(stream=stream)
    stream.synchronize()
    if int(per.sum(dtype=np.int64)) != d.n:
        raise RuntimeError(f"device random start: {int(per.sum(dtype=np.int64))} spheres kept for {d.n}")
    first = np.concatenate([[0], np.cumsum(per, dtype=np.int64)[:-1]])
    rsa_place[grid_cells, _WIDE, stream](
        g.nc, g.unit, first_pass, trim_key, cut_key, cut_index, counts, slots, spass, quats,
        cuda.to_device(first, stream=stream), pos, quat, np.int64(col0))


def draw_start(d: StartDraw, col0: int, pos, dsts: dict, stream, cap: int = 1 << 14, quat=None) -> None:
    """Draw ``d`` into columns [col0, col0 + n) of the device arrays ``pos`` (3, N) and ``dsts`` (stream number ->
    (dim, N) array, or a function that returns it, called once the centres' cells are freed; a stream missing there
    is not drawn, the others are the same), in their precisions; see the
    module docstring. ``quat`` (4, N): a random spheroid start's orientations (drawn with the centres). ``cap``:
    most blocks of a grid-stride launch."""
    n = d.n
    site_key, place_key, keys = d.keys()
    if d.rsa is not None:
        if quat is None:
            quat = cuda.device_array((4, 0), np.float64, stream=stream)
        _random_centres(d, col0, pos, quat, stream, cap)
        _free_released()    # the cells go before the streams' rows are made (the start's peak)
    else:
        cut, counts = _cut(d, site_key, stream, cap)
        if int(counts.sum()) != n:
            raise RuntimeError(f"device start: {int(counts.sum())} sites chosen for {n} particles")
        first = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        place_draw[len(first), TPB, stream](site_key, np.uint64(cut), d.n_sites, cuda.to_device(first, stream=stream),
                                            d.m, d.a, d.half_gap, d.box, place_key, pos, np.int64(col0))
    for (stream_no, dim, rms), key in zip(d.streams, keys):
        if stream_no not in dsts:       # a stream nobody holds (a sphere ensemble without orientations)
            continue
        dst = dsts[stream_no]
        _draw_stream(n, np.uint64(key), dim, rms, dst() if callable(dst) else dst, col0, stream, cap)
        _free_released()    # its scratch goes before the next stream's is made


def _free_released() -> None:
    """Free the device memory of the arrays released so far now (numba-cuda frees lazily)."""
    if not SIM:
        cuda.current_context().deallocations.clear()


def _draw_stream(n: int, key, dim: int, rms, dst, col0: int, stream, cap: int) -> None:
    """One stream's rows into dst[:, col0:col0 + n]: drawn into a float64 scratch (dim, n) (one stream at a time:
    the start's peak), centred and scaled by the means and scale the host takes from the same block sums
    (engine.setup.scene.stream_mean, stream_scale)."""
    out = cuda.device_array((dim, n), np.float64, stream=stream)
    stream_draw[_blocks(n, _WIDE, cap), _WIDE, stream](key, np.int64(dim), np.bool_(rms is None), out)
    scale = 1.0
    if rms is not None:
        n_blocks = (n + _BLOCK - 1) // _BLOCK
        sums = cuda.device_array((dim, n_blocks), np.float64, stream=stream)
        grid = _blocks(dim * n_blocks, 64, cap)      # a few thousand threads: small blocks spread them over the SMs
        means = np.zeros(dim)
        block_moments[grid, 64, stream](out, cuda.to_device(means, stream=stream), 0, sums)
        s_h = sums.copy_to_host(stream=stream)
        stream.synchronize()
        means = stream_mean(np.ascontiguousarray(s_h.T), n, rms)
        block_moments[grid, 64, stream](out, cuda.to_device(means, stream=stream), 1, sums)
        s_h = sums.copy_to_host(stream=stream)
        stream.synchronize()
        scale = stream_scale(np.ascontiguousarray(s_h.T), n, rms)
    scale_into[_blocks(n, _WIDE, cap), _WIDE, stream](out, float(scale), dst, np.int64(col0))


#: the sphere state array each stream of a sphere start goes to (engine.setup.scene.parallel_start_streams)
SPHERE_TARGETS = {STREAM_VELOCITY: "vel", STREAM_SPIN: "omega", STREAM_QUATERNION: "quat"}


def load(pos_dtype, dtype, placements=("lattice", "random")) -> None:
    """Load (or compile) every kernel of a device start into device arrays of these precisions, for the argument
    types a job's start calls them with: a start of 64 spheres of each of ``placements`` (on a lattice of 108 sites,
    random), discarded (the GPU start-up thread, engine/driver/startup.py, loads the job's own placement only)."""
    from engine.setup.params import derive
    from engine.setup.scene import parallel_start_streams
    from engine.setup.spec import SimulationSpec

    sphere = SimulationSpec()
    stream = cuda.stream()
    for protocol in placements:
        d = StartDraw.of(64, 0, parallel_start_streams(sphere, derive(sphere))[0], 20.0, 1.0, protocol)
        pos = cuda.device_array((3, d.n), pos_dtype, stream=stream)
        dsts = {k: cuda.device_array((dim, d.n), dtype, stream=stream) for k, dim, _ in d.streams}
        draw_start(d, 0, pos, dsts, stream)
    stream.synchronize()
