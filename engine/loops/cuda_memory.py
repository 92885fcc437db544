"""Device memory of a CUDA ensemble: what it holds (:func:`device_allocations`, read off a live ensemble) and what
a sphere scene will hold (:func:`sphere_account`, the same arrays predicted from the spec before anything is
allocated). The test suite checks the two against each other array by array (CUDA simulator), and
bench/large_scenes.py checks the prediction against the allocator's peak on a GPU.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Optional

import numpy as np

from engine.setup.precision import float32_copy_error, float32_reference_fits


def _allocation(a):
    """(key, bytes) of the allocation that device array ``a`` lives in (a view counts as its base), or None
    when ``a`` is not a device array."""
    ary = getattr(a, "_ary", None)       # the CUDA simulator's FakeCUDAArray wraps a NumPy array
    if ary is not None and type(a).__name__ == "FakeCUDAArray":
        base = ary
        while isinstance(base.base, np.ndarray):
            base = base.base
        return id(base), int(base.nbytes)
    data = getattr(a, "gpu_data", None)  # numba.cuda DeviceNDArray: a MemoryPointer, views own a parent
    if data is None or not hasattr(a, "copy_to_host"):
        return None
    owner = getattr(data, "owner", data)
    return id(owner), int(getattr(owner, "size", a.nbytes))


def device_allocations(root, prefix: str = "") -> dict[str, int]:
    """{attribute path: bytes} of every distinct device allocation reachable from ``root``'s attributes (views
    and aliases counted once, under the first path met in attribute order)."""
    found: dict[str, int] = {}
    seen_alloc: set = set()
    seen_obj: set = set()

    def walk(obj, path: str) -> None:
        alloc = _allocation(obj)
        if alloc is not None:
            if alloc[0] not in seen_alloc:
                seen_alloc.add(alloc[0])
                found[path] = alloc[1]
            return
        if id(obj) in seen_obj or isinstance(obj, (str, bytes, int, float, np.ndarray, np.generic)):
            return
        seen_obj.add(id(obj))
        if isinstance(obj, dict):
            for k, v in obj.items():
                walk(v, f"{path}[{k!r}]")
        elif isinstance(obj, (list, tuple)):
            for k, v in enumerate(obj):
                walk(v, f"{path}[{k}]")
        elif isinstance(obj, SimpleNamespace) or type(obj).__module__.startswith("engine."):
            for k, v in vars(obj).items():
                walk(v, f"{path}.{k}" if path else k)

    walk(root, prefix)
    return found


#: slots a particle's row has in a CUDA list built on the host (engine/loops/cuda_listmodes.py: its host buffers, packed
#: for the device on upload); a build that finds more widens them to ceil((need + 2) / 4) * 4
FIRST_STRIDE = 8


#: list slots (neighbour indices and their history) a CUDA list holds beyond its rows' (engine/loops/cuda_rebuild.py
#: ``_alloc_slots``): it starts with N + HIST_MARGIN and is regrown to 5/4 of the slots a build hands out plus
#: HIST_MARGIN when they do not fit
HIST_MARGIN = 1024


def device_zeros(shape, dtype, stream):
    """A device array of zeros, set by a memset queued on ``stream``: no host array of zeros to copy up (under the
    CUDA simulator, which has no memset, one is copied)."""
    from numba import cuda

    from engine.loops.cuda_cache import SIM
    from engine.numba_support.numba_internals import device_memset

    a = cuda.device_array(shape, dtype, stream=stream)
    if SIM:
        a.copy_to_device(np.zeros(shape, dtype), stream=stream)
    elif a.size:
        device_memset(a, 0, stream)
    return a


def grown_history(slots: int) -> int:
    """The list's slots after a build that handed out ``slots`` (more than it held)."""
    return int(1.25 * slots) + HIST_MARGIN


def grown_stride(need: int) -> int:
    """The host list's row width after a build that found ``need`` neighbours in one particle's row."""
    return max(FIRST_STRIDE, int(math.ceil((need + 2) / 4.0)) * 4) if need > FIRST_STRIDE else FIRST_STRIDE


def lends_cell_counts(ncell: int, n: int, hist_words: int, word: int) -> bool:
    """Whether a rebuild's per-cell counts (ncell + 1 int32) fit in the first list history of n particles
    (engine/loops/cuda_rebuild.py ``_lent``); a scene of few particles in many cells gives them their own array."""
    return 4 * (ncell + 1) <= hist_words * (n + HIST_MARGIN) * word


def xref_margin(box: float, xref_dtype, pos_dtype) -> float:
    """Bound (m) on the distance between a position in [0, box) and x_ref's copy of it: 0 where x_ref has the
    positions' type, else sqrt(3) 2^-24 box for float32 (engine.setup.precision ``float32_copy_error``). The Verlet
    rule subtracts it from its limit: a displacement measured against the rounded x_ref below L_v / 2 - margin leaves
    the true one below L_v / 2."""
    if np.dtype(xref_dtype) == np.dtype(pos_dtype):
        return 0.0
    return float32_copy_error(box)


def xref_dtype(pos_dtype, boxes, skins):
    """The type of the list's reference positions x_ref: float32 where the positions are float64 (float64 and mixed
    precision: 12 B a particle less) and its rounding takes at most XREF_MARGIN_SHARE of the Verlet rule's limit
    L_v / 2 in every scene (boxes, skins: m), else the positions' own type."""
    pos_dtype = np.dtype(pos_dtype)
    if pos_dtype != np.float64:
        return pos_dtype
    if all(float32_reference_fits(b, v) for b, v in zip(boxes, skins)):
        return np.dtype(np.float32)
    return pos_dtype


def lends_cell_starts(ncell: int, n: int, two_force_buffers: bool, word: int) -> bool:
    """Whether a rebuild's cell starts (ncell + 1 int32) fit in the next force buffer (3 words of n particles) after
    the compact store's index (2 n int32) (engine/loops/cuda_rebuild.py ``_cell_starts``): in float64 for gases of up
    to about 4 cells a particle; a shape with one force buffer (spheroids) has none to lend."""
    return two_force_buffers and 4 * (2 * n + ncell + 1) <= 3 * n * word


def mean_list_neighbours(volume_fraction: float, reach_over_diameter: float) -> float:
    """Mean count of neighbours within the list's reach r_c = sigma (1 + L_v / sigma) of a sphere in an equilibrium
    gas of equal spheres: n g(sigma) (4 pi / 3)(r_c^3 - sigma^3) = 8 phi g(sigma) ((r_c / sigma)^3 - 1), with the
    Carnahan-Starling contact value g(sigma) = (1 - phi / 2) / (1 - phi)^3 over the whole shell (an upper bound: g
    falls towards 1 across it)."""
    from engine.setup.params import carnahan_starling_g

    return 8.0 * volume_fraction * carnahan_starling_g(volume_fraction) * (reach_over_diameter ** 3 - 1.0)


@dataclass(frozen=True)
class SphereLayout:
    """What sizes a sphere ensemble's device arrays (engine/shapes/sphere/cuda_backend.py, engine/loops/): N in all,
    the state and position word (bytes) and the list reference's (``xref_word``, 0: the position's), rough or
    smooth, equal spheres or not, the list's slots (neighbour indices and their history), the compact store's
    capacity, the cells, the scenes, the threads per block, whether the many-steps loop and the state staging of
    snapshots are used, and the per-scene tables' sizes."""

    n: int
    word: int
    pos_word: int
    rough: bool
    uniform: bool
    hist_slots: int
    store_cap: int
    ncell: int
    n_scenes: int = 1
    tpb: int = 256
    multistep: bool = False
    reads_state: bool = False
    #: orientations and their marks on the device (engine/shapes/sphere/cuda_backend.py ``orientations_held``)
    orientations: bool = True
    hist_words: int = 5
    nobs: int = 12
    record_rows: int = 256
    #: words per scene of the constant tables spd, spf, spi and of the status array (engine/loops/cuda_kernels.py
    #: ND, NF, NI, status_len): an upper bound by default, exact where the kernels module is at hand
    scene_words: tuple = (64, 64, 64, 64)
    xref_word: int = 0


def sphere_account(L: SphereLayout) -> dict[str, int]:
    """{array: bytes} of a sphere ensemble on the device, named as :func:`device_allocations` finds them: the state,
    forces, the permutation's order, the Verlet list with its contact history, the cells, the compact store, the
    records' accumulators and (when used) the double buffers and the state staging. A rebuild's scratch takes no
    memory of its own: the permutation's rows, the cells' counts and the list rows' counts lie in the list's history,
    the compact store's index and (where :func:`lends_cell_starts`) the cells' starts in the next force buffer, and
    for a lone scene of rough spheres the permutation's order and inverse in the torque
    (engine/loops/cuda_rebuild.py ``LEND_SCRATCH``)."""
    n, w, pw = L.n, L.word, L.pos_word
    a = {
        "x_ref": 3 * n * (L.xref_word or pw), "ids": 4 * n, "sc": 4 * (n if L.n_scenes > 1 else 1),
        "pos": 3 * n * pw, "vel": 3 * n * w, "omega": 3 * n * w, "quat": 4 * (n if L.orientations else 1) * w,
        "f_cur": 3 * n * w, "f_nxt": 3 * n * w, "torque": 3 * n * w,
        "q_last": 8 * (n if L.orientations else 1), "begun": 4 * n, "hot": n,
        "cj": 4 * L.store_cap, "chist": L.hist_words * L.store_cap * w,
        "nbr": 4 * L.hist_slots, "nn": 4 * (n + 1), "hist": L.hist_words * L.hist_slots * w,
        "_sums.acc": 8 * L.n_scenes * L.nobs, "_rows.acc": 8 * L.record_rows * L.nobs,
    }
    nd, nf, ni, status = L.scene_words
    a.update({"spd": L.n_scenes * nd * w, "spf": L.n_scenes * nf * 8, "spi": L.n_scenes * ni * 4, "status": 8 * status})
    tile = L.tpb * 16
    for name, m in (("_scan_cells", L.ncell + 1), ("_scan_rows", n)):     # the cells' and the list rows' scans
        blocks = max(1, (m + tile - 1) // tile)
        a.update({f"{name}.bsum": 4 * blocks, f"{name}.bsum_scan": 4 * blocks, f"{name}.bsum_tot": 4})
    if not lends_cell_counts(L.ncell, n, L.hist_words, w):
        a["_count_own"] = 4 * (L.ncell + 1)
    if not lends_cell_starts(L.ncell, n, True, w):
        a["_cell_start_own"] = 4 * (L.ncell + 1)
    if not (L.rough and L.n_scenes == 1):     # the permutation's order and inverse, where the torque cannot lend them
        a["_perm_own[0]"], a["_perm_own[1]"] = 4 * n, 4 * n
    if L.uniform:
        a["radius"] = w
    else:
        a.update({k: n * w for k in ("radius", "mass", "inertia", "inv_m", "inv_i")})
    if L.multistep or not L.rough:     # the fused step's (smooth) and the many-steps loop's double buffers
        a["_alt[0]"], a["_alt[1]"] = 3 * n * pw, 3 * n * w
    if L.multistep:
        a["_alt_spin"] = 3 * n * w
    if L.reads_state:     # four rows of a piece of at most FRAME_PIECE_ROWS particles (engine/loops/cuda_frames.py)
        from engine.output.pieces import FRAME_PIECE_ROWS

        for word in sorted({w, pw}):
            a[f"_stage['<f{word}']"] = 4 * max(1, min(n, FRAME_PIECE_ROWS)) * word
    return a


#: rows of a device-drawn sphere start's float64 scratch: one stream's at a time, the largest the orientation's 4
#: (engine/loops/cuda_start.py ``draw_start``)
START_ROWS = 4
#: the slots a CUDA list can address (its rows' offsets are int32: engine/loops/cuda_rebuild.py ``_check_slots``)
MAX_LIST_SLOTS = 2 ** 31
#: part of the free device memory a run may plan to use: the CUDA context, the kernels' local memory and the
#: allocator's rounding take the rest
USABLE_FRACTION = 0.95


def random_start_bytes(n: int, box: float, radius: float) -> int:
    """Device bytes of the cells of a random start of n spheres drawn on the device (engine/loops/cuda_start.py
    ``_random_centres``; engine/setup/cell_rsa.py): per cell the count, the kept count and the first index (4 + 4 + 8
    B), and per slot the grid centre (3 int16) and the pass that placed it (int32)."""
    from engine.setup.cell_rsa import CellRsa

    g = CellRsa.of(n, box, radius)
    return g.nc ** 3 * (4 + 4 + 8 + g.slots * (3 * 2 + 4))


@dataclass(frozen=True)
class DevicePrediction:
    """A sphere spec's predicted device memory: the per-array table of the running loop (bytes), the start's
    transient arrays, the peak (the larger of the loop and the start), the list slots assumed and the slots an
    equilibrium gas's rows take (the mean neighbour count times N)."""

    table: dict
    start_bytes: int
    slots: int
    rows_slots: int

    @property
    def loop_bytes(self) -> int:
        return sum(self.table.values())

    @property
    def peak_bytes(self) -> int:
        return max(self.loop_bytes, self.start_bytes)


def predict_sphere_device(spec, p, *, reads_state: bool = False, tpb: int = 256) -> DevicePrediction:
    """The device memory of a sphere spec run as one scene on the GPU (:func:`sphere_account` with the list slots
    an equilibrium gas needs, :func:`mean_list_neighbours`), from the spec and its derived parameters ``p``
    (engine.setup.params.derive, with the run's skin). ``reads_state``: snapshots or checkpoints copy the state out."""
    from engine.loops.system import cell_grid, many_steps_loop
    from engine.setup.precision import position_dtype, state_dtype
    from engine.setup.start_kind import RANDOM, device_start, start_protocol

    n = int(spec.n_particles)
    word = np.dtype(state_dtype(spec.precision)).itemsize
    pos_word = np.dtype(position_dtype(spec.precision)).itemsize
    uniform = len(p.species_radius) <= 1
    reach = (2.0 * p.radius_max + p.skin) / (2.0 * p.radius_max)
    mean = mean_list_neighbours(spec.volume_fraction, reach)
    # the list starts with N + HIST_MARGIN slots and grows when a build hands out more (cuda_rebuild._list_room)
    slots = n + HIST_MARGIN if mean * n <= n + HIST_MARGIN else grown_history(int(math.ceil(mean * n)))
    layout = SphereLayout(
        n=n, word=word, pos_word=pos_word, rough=not spec.smooth, uniform=uniform, hist_slots=slots,
        store_cap=max(1024, n // 8), ncell=cell_grid(spec.box_length, n, p.radius_max, p.skin) ** 3, tpb=tpb,
        multistep=many_steps_loop(n, spec.volume_fraction if spec.shape == "sphere" else None),
        reads_state=reads_state,
        orientations=spec.orientations and (reads_state or spec.snapshots > 0),
        xref_word=xref_dtype(position_dtype(spec.precision), [spec.box_length], [p.skin]).itemsize)
    table = sphere_account(layout)
    start = sum(table[k] for k in ("ids", "sc", "pos", "vel", "omega", "quat"))
    if device_start(spec):
        # the centres are placed beside the positions alone (the other state arrays are made once the random
        # start's cells are freed), then each stream is drawn into a float64 scratch of its own rows, one at a time
        rows = START_ROWS if layout.orientations else START_ROWS - 1
        cells = random_start_bytes(n, spec.box_length, p.radius) if start_protocol(spec) == RANDOM else 0
        start = max(start + 8 * rows * n, sum(table[k] for k in ("ids", "sc", "pos")) + cells)
    return DevicePrediction(table=table, start_bytes=start, slots=slots, rows_slots=int(math.ceil(mean * n)))


def largest_fitting(spec, p_of, budget: float, **kw) -> int:
    """The largest n_particles (same volume fraction and everything else) whose predicted peak fits ``budget``
    bytes; ``p_of(spec)`` derives a spec's parameters. 0 when not even one particle fits."""
    def peak(n: int) -> int:
        s = spec.model_copy(update={"n_particles": n})
        return predict_sphere_device(s, p_of(s), **kw).peak_bytes

    lo, hi = 0, max(1, int(spec.n_particles))
    while peak(hi) <= budget:
        lo, hi = hi, hi * 2
    while hi - lo > max(1, lo // 1000):
        mid = (lo + hi) // 2
        lo, hi = (mid, hi) if peak(mid) <= budget else (lo, mid)
    return lo


def device_memory() -> Optional[tuple[int, int, str]]:
    """(free bytes, total bytes, device name) of the current CUDA device (the CUDA simulator: the host's memory);
    None when no CUDA device can be used here (the run then fails where the device is first needed)."""
    from numba import cuda

    from engine.loops.cuda_cache import SIM

    if SIM:
        import os

        pages, size = os.sysconf("SC_AVPHYS_PAGES"), os.sysconf("SC_PAGE_SIZE")
        return pages * size, os.sysconf("SC_PHYS_PAGES") * size, "CUDA simulator"
    if not cuda.is_available():
        return None
    free, total = cuda.current_context().get_memory_info()
    name = cuda.get_current_device().name
    return int(free), int(total), name.decode() if isinstance(name, bytes) else str(name)


def _down3(x: float) -> float:
    """x rounded down to three significant digits (a largest N that still fits when printed with :.3g)."""
    if x < 1:
        return 0.0
    unit = 10.0 ** (math.floor(math.log10(x)) - 2)
    return math.floor(x / unit) * unit


def _gb(b: float) -> str:
    return f"{b / 1e9:.3g} GB"


def memory_refusal(spec, p, free_bytes: float, device: str, p_of, *, reads_state: bool = False) -> str | None:
    """Why a sphere spec will not fit ``free_bytes`` of device memory (None when it does): the predicted peak
    (:func:`predict_sphere_device`), the device's free memory and the largest n_particles that fits (``p_of(spec)``
    derives a spec's parameters)."""
    budget = USABLE_FRACTION * free_bytes
    pred = predict_sphere_device(spec, p, reads_state=reads_state)
    if pred.rows_slots >= MAX_LIST_SLOTS:
        return (f"n_particles = {spec.n_particles}: its Verlet list would hold about {pred.rows_slots:.3g} slots "
                f"({pred.rows_slots / spec.n_particles:.2f} a particle at volume_fraction = {spec.volume_fraction:g}); "
                f"at most {MAX_LIST_SLOTS - 1} are supported (int32 row offsets): the largest n_particles is about "
                f"{_down3((MAX_LIST_SLOTS - 1) * spec.n_particles / pred.rows_slots):.3g}")
    if pred.peak_bytes <= budget:
        return None
    fits = largest_fitting(spec, p_of, budget, reads_state=reads_state)
    why = (f"n_particles = {spec.n_particles}: the run needs about {_gb(pred.peak_bytes)} of device memory "
           f"({pred.peak_bytes / spec.n_particles:.0f} B per particle, {spec.precision}); "
           f"{device} has {_gb(free_bytes)} free, of which {USABLE_FRACTION:.0%} may be planned; "
           f"the largest n_particles that fits is about {fits:.3g}")
    if spec.orientations:    # the orientations a sphere's snapshots hold are its largest optional arrays
        bare = predict_sphere_device(spec.model_copy(update={"orientations": False}), p, reads_state=reads_state)
        if bare.peak_bytes < pred.peak_bytes:
            why += (f"; without orientations in the snapshots (orientations = false) it needs about "
                    f"{_gb(bare.peak_bytes)}{' and fits' if bare.peak_bytes <= budget else ''}")
    return why


def refuse_oversize(spec, p, *, reads_state: bool = False) -> None:
    """Raise :class:`engine.errors.SpecError` before anything is allocated when a sphere spec's predicted device
    memory exceeds what the current device has free (:func:`memory_refusal`)."""
    from engine.errors import SpecError
    from engine.setup.params import derive

    got = device_memory()
    if got is None:
        return
    free, _total, device = got
    why = memory_refusal(spec, p, free, device, derive, reads_state=reads_state)
    if why is not None:      # an earlier run's arrays in this process may only await collection: free them, ask again
        release_unreferenced()
        free, _total, device = device_memory()
        why = memory_refusal(spec, p, free, device, derive, reads_state=reads_state)
    if why is not None:
        raise SpecError(why)


def release_unreferenced() -> None:
    """Collect unreachable Python objects and free the device memory Numba still holds for released arrays."""
    import gc

    from numba import cuda

    from engine.loops.cuda_cache import SIM

    gc.collect()
    if not SIM and cuda.is_available():
        cuda.current_context().deallocations.clear()
