"""The neighbour lists of a CUDA ensemble: :class:`ListBuilds`, a part of
:class:`engine.loops.cuda_ensemble.CudaEnsembleBase`.

A rebuild keeps the contact history that must survive in a compact store, counts particles per cell (scene-major
cell ids), scans, scatters, sorts each cell by id, permutes the particle arrays into that order (only once the
particles may have drifted :data:`SORT_DRIFT_CELLS` of a cell since the last time) and builds the full Verlet list in
two passes (search the cells and count the rows, keeping the first :data:`BUILD_KEPT` neighbours of each; hand the
rows out; fill them, copying the kept rows and searching again only for longer ones: the list holds only the slots in
use, packed), taking the kept history back; the list's slots grow when a build hands out more. Scenes whose size
spread needs more than one grid level use the multigrid cells (Skorych & Dosta 2022, Algorithm 1); one scene may have
its list built on the host instead (engine/loops/cuda_listmodes.py, Skorych & Dosta 2022, §3).
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from numba import cuda

from engine.loops import cuda_kernels as K
from engine.loops.cuda_device import copy_device as _copy
from engine.loops.cuda_lists import list_kernels
from engine.loops.cuda_memory import (HIST_MARGIN, MAX_LIST_SLOTS, grown_history, lends_cell_counts,
                                      lends_cell_starts)
from engine.loops.system import SphereSystem

#: False: one grid of cell >= 2 R_max + L_v even for a spread of sizes (the one-off study bench/list_modes.py, in git
#: history, set it for the cost comparison with the multigrid build)
MULTIGRID = True
#: A rebuild permutes the particle arrays into cell order only where the particles may have moved this many cell
#: edges since they were last permuted (each rebuild comes after at most about L_v/2 of flight: the L_v/2 rule); the
#: others read the cells' particles through the sort's order (cuda_kernels.build) and leave them where they are.
#: The order is for memory locality alone (the list's rows are the same particles in the same order either way, so
#: the trajectory is the same bits); between sorts the particles stay near the cell slots they were sorted into.
#: A thin skin rebuilds often (0.03 a: every ~75 steps at phi = 0.2) and each permutation moved every particle
#: array twice (gather, copy back). 0: permute at every rebuild.
SORT_DRIFT_CELLS = 0.5
#: Neighbours per particle that a GPU list build's counting pass keeps for its filling pass (cuda_kernels.build), in
#: the list's history after the row counts, as many as it has room for: a row of at most this many is copied, not
#: found by a second search of its 27 cells (with a thin skin almost every row: the search, not the row's length,
#: is a build's cost). 0: the filling pass searches every row again.
BUILD_KEPT = 4
#: True: a rebuild's scratch lies in memory that holds nothing needed while it is used (:meth:`ListBuilds._lent`,
#: :meth:`ListBuilds._store_index`); False: arrays of its own (tests compare the two)
LEND_SCRATCH = True


class ListBuilds:
    """The list part of a CUDA ensemble. The ensemble provides its device arrays, ``stream``, ``k`` (kernels),
    ``_grid``, ``_zeros``, :meth:`_permuted_arrays` and :meth:`_permuted_i64`."""

    def _setup_scan(self) -> None:
        s = self.stream
        # the cells' first slots lie in the next force buffer where it has room beside the compact store's index
        # (:meth:`_cell_starts`), else in an array of their own
        self._cell_start_own = None
        self._cell_start_views: dict = {}
        if not (LEND_SCRATCH and lends_cell_starts(self.ncell, self.n, self.f_nxt is not self.f_cur,
                                                   np.dtype(self.dtype).itemsize)):
            self._cell_start_own = cuda.device_array(self.ncell + 1, np.int32, stream=s)
        self._scan_cells = self._scan_buffers(self.ncell + 1)
        self._scan_rows = self._scan_buffers(self.n)      # the list rows' first history slots (_gpu_rebuild)
        # the cells' counts lie in the list's history (:meth:`_cell_counts`) unless the first history is smaller than
        # them (a few particles in many cells)
        self._count_own = None
        word = np.dtype(self.dtype).itemsize
        if not LEND_SCRATCH or not lends_cell_counts(self.ncell, self.n, self.hist_words, word):
            self._count_own = cuda.device_array(self.ncell + 1, np.int32, stream=s)

    def _scan_buffers(self, m: int) -> SimpleNamespace:
        """Block-sum buffers of an exclusive scan of m int32 counts (tiles of tpb * 16)."""
        tile = self.tpb * 16
        nb = (m + tile - 1) // tile
        dev = lambda k: cuda.device_array(max(k, 1), np.int32, stream=self.stream)  # noqa: E731
        return SimpleNamespace(m=m, tile=tile, nb=nb, bsum=dev(nb), bsum_scan=dev(nb), bsum_tot=dev(1))

    def _exclusive_scan(self, src, dst, b: SimpleNamespace) -> None:
        k, s, lc = self.k, self.stream, self._lc
        lc.launch("tile_scan", k["tile_scan"], (b.nb, self.tpb, s), (src, dst, b.m, b.bsum, 16))
        if b.nb > 1:
            items = (b.nb + self.tpb - 1) // self.tpb
            lc.launch("tile_scan_sums", k["tile_scan"], (1, self.tpb, s),
                      (b.bsum, b.bsum_scan, b.nb, b.bsum_tot, items))
            lc.launch("add_offsets", k["add_offsets"], self._grid(b.m), (dst, b.m, b.bsum_scan, b.tile))

    def _alloc_list(self) -> None:
        """The list's rows (``nn``) and its first slots (:meth:`_alloc_slots`)."""
        self.nn = self._zeros(self.n + 1, np.int32)   # rows (cuda_kernels: the list's layout)
        self._nn_rows = self.nn[:self.n]     # (a view made once: the launch cache knows its arrays by identity)
        self._counts_own = None if LEND_SCRATCH else cuda.device_array(max(1, self.n), np.int32, stream=self.stream)
        self._alloc_slots(self.n + HIST_MARGIN)

    @staticmethod
    def _check_slots(slots: int) -> None:
        """The rows are int32 offsets (nn): a list of MAX_LIST_SLOTS = 2^31 slots or more is not representable
        (the memory prediction refuses a spec whose gas would need that many: cuda_memory.memory_refusal)."""
        if not 0 <= slots < MAX_LIST_SLOTS:
            raise RuntimeError(f"the Verlet list holds {slots} slots; at most 2^31 - 1 are supported (fewer particles "
                               "or a lower volume fraction)")

    def _alloc_slots(self, slots: int) -> None:
        """The list's slots: the neighbour indices ``nbr`` (int32) and their history ``hist`` (``hist_words`` x
        ``slots``), rows back to back (cuda_kernels: the list's layout). The old ones and the views lent from the
        history (:meth:`_lent`) are freed first: the kept history is in the compact store. (nbr and hist are named
        before the views: cuda_memory.device_allocations counts an allocation under the first name it meets.)"""
        s = self.stream
        self.nbr = self.hist = None
        self._list_views = {}
        self._part_views: dict = {}
        self.nbr = cuda.device_array(slots, np.int32, stream=s)
        self.hist = cuda.device_array((self.hist_words, slots), self.dtype, stream=s)

    def _list_room(self, slots: int) -> None:
        """Room for a new list of ``slots`` slots (after the kept history's compaction): the slots regrown where
        they are too few."""
        self._check_slots(slots)
        if slots > self.nbr.shape[0]:
            self._alloc_slots(grown_history(slots))

    def _alloc_store(self, cap: int) -> None:
        self.store_cap = cap
        self.cj = cuda.device_array(cap, np.int32, stream=self.stream)
        self.chist = cuda.device_array((self.hist_words, cap), self.dtype, stream=self.stream)

    def set_list_mode(self, mode: str) -> None:
        """Where the Verlet list is built: 'gpu', 'cpu-sequential', 'cpu-pipelined' or 'auto' (Skorych & Dosta
        2022, §3, :mod:`engine.loops.cuda_listmodes`); the CPU modes need one scene. 'auto' on an ensemble of
        several scenes is the GPU list."""
        from engine.loops.cuda_listmodes import MODES, HostLists
        if mode not in MODES:
            raise ValueError(f"list_mode = {mode!r} is not one of {', '.join(MODES)}")
        if self.lists is not None:
            self.lists.close()
            self.lists = None
        if mode == "gpu" or (mode == "auto" and self.n_scenes > 1):
            return
        if self.kl is None:
            self.kl = list_kernels(self.dtype, self.tpb)
        self.lists = HostLists(self, mode)

    def _sort_interval(self) -> int:
        """Rebuilds from one permutation into cell order to the next (:data:`SORT_DRIFT_CELLS`): the fewest, over
        the scenes, that may move a scene's particles that many of its cell edges at L_v/2 a rebuild; 1 for a
        multigrid ensemble (its levels' bins follow the permuted order) or a scene without a skin."""
        if SORT_DRIFT_CELLS <= 0 or self.multigrid:
            return 1
        half_skin = np.array([0.5 * float(c.skin) for c in self.contact])
        if not (half_skin > 0).all():
            return 1
        cell = self.box / self.spi_h[:, K.I_NC]
        return max(1, int(np.floor(SORT_DRIFT_CELLS * cell / half_skin).min()))

    def _sort_due(self) -> bool:
        """Whether this rebuild permutes the particles (:meth:`_sort_interval`); the first one always does."""
        if self._builds_since_sort is None or self._builds_since_sort + 1 >= self._sort_interval():
            self._builds_since_sort = 0
            self.sorts += 1
            return True
        self._builds_since_sort += 1
        return False

    def _sort_and_permute(self, permute: bool) -> None:
        """Particles into cell order (sorted by id within a cell), between the compaction of the kept history and
        the new list's build: the list's history is the scratch here (:meth:`_lent`). Not ``permute``: the order
        only (the sort's order, which the build reads the cells' particles through), the particles left in place."""
        k, n, s, lc = self.k, self.n, self.stream, self._lc
        count = self._cell_counts()
        cell_start = self._cell_starts()
        order, inv_old = self._perm_rows()
        lc.launch("fill_i32", k["fill_i32"], self._grid(self.ncell + 1), (count, 0))
        lc.launch("count_cells", k["count_cells"], self._grid(n), (n, self.pos, self.sc, self.spf, self.spi,
                                                                     count))
        # exclusive scan of ncell + 1 counts (the last is 0) -> cell_start, cell_start[ncell] = n
        self._exclusive_scan(count, cell_start, self._scan_cells)
        lc.launch("fill_i32", k["fill_i32"], self._grid(self.ncell + 1), (count, 0))
        lc.launch("scatter", k["scatter"], self._grid(n), (n, self.pos, self.sc, self.spf, self.spi,
                                                            cell_start, count, order))
        lc.launch("sort_cells", k["sort_cells"], self._grid(self.ncell), (self.ncell, cell_start, order,
                                                                           self.ids))
        if not permute:
            self._forces_unknown()      # (the next force buffer lent the cells' starts and the store's index)
            return
        lc.launch("inverse_perm", k["inverse_perm"], self._grid(n), (n, order, inv_old))
        # permute the particle arrays into cell order (forces too: the next force step reads them), each through
        # its own launch-cache name (an array and its scratch rows are the same objects at every rebuild)
        # (torque need not move: the next force step rewrites it before any kick reads it)
        for q, a in enumerate(self._permuted_arrays() + self._per_particle):
            for r, (rows, tmp) in enumerate(self._gather_parts(a)):
                lc.launch(f"gather_rows/{q}/{r}", k["gather_rows"], self._grid(n), (n, rows, tmp, order))
                _copy(rows, tmp, s)
        ints = ((self.ids, self.lvl) if self.multigrid else (self.ids,)) + tuple(self._permuted_i64())
        for q, a in enumerate(ints):   # (gather_i32 is typed at launch: the same kernel for int64)
            tmp = self._scratch_rows(a)
            lc.launch(f"gather_i32/{q}", k["gather_i32"], self._grid(n), (n, a, tmp, order))
            _copy(a, tmp, s)
        # f_nxt and the torque stay in the old order: the next force pass must store every particle's
        self._forces_unknown()

    def _scratch_rows(self, a):
        """The scratch that permuted array ``a`` (rows x N, or N) is gathered into, in the memory of the list's
        history (:meth:`_lent`)."""
        return self._lent(a.dtype, a.shape)

    def _gather_parts(self, a) -> list:
        """[(rows of ``a``, their scratch)] of a (rows, N) array's permutation: the whole array at once where its
        scratch fits in the list's history, else one row at a time (mixed precision: 3 float64 position rows, 24 B a
        particle, against a history of 5 float32 words a slot and about one slot a particle in a dilute gas). Made
        once per array and history (the launch cache knows its arrays by identity)."""
        got = self._part_views.get(id(a))
        if got is None or got[1] is not self.hist:
            if not LEND_SCRATCH or a.nbytes <= self.hist.nbytes:
                parts = [(a, self._scratch_rows(a))]
            else:
                tmp = self._lent(a.dtype, (1, a.shape[1]))
                parts = [(a[r:r + 1], tmp) for r in range(a.shape[0])]
            got = self._part_views[id(a)] = (a, self.hist, parts)
        return got[2]

    def _cell_counts(self):
        """The per-cell counts of a rebuild's sort (ncell + 1 int32), in the list's history."""
        if self._count_own is not None:
            return self._count_own
        return self._lent(np.int32, (self.ncell + 1,))

    def _cell_starts(self):
        """The cells' first slots of a rebuild (ncell + 1 int32: an exclusive scan of the cell counts), written by
        the sort and read by the build. In the next force buffer after the compact store's index
        (:meth:`_store_index`: both hold nothing the next force pass reads, and that pass runs after the build)
        where :func:`cuda_memory.lends_cell_starts`, else an array of their own. One view per buffer."""
        if self._cell_start_own is not None:
            return self._cell_start_own
        got = self._cell_start_views.get(id(self.f_nxt))
        if got is None:
            flat = self.f_nxt.reshape(self.f_nxt.size).view(np.int32)
            got = self._cell_start_views[id(self.f_nxt)] = (self.f_nxt,
                                                            flat[2 * self.n:2 * self.n + self.ncell + 1])
        return got[1]

    def _row_counts(self):
        """The per-row counts of a build's counting pass (N int32), scanned into the rows ``nn``: in the list's
        history, which holds nothing needed until the new list's history is filled (:meth:`_lent`), or an array of
        their own where ``LEND_SCRATCH`` is off."""
        if self._counts_own is not None:
            return self._counts_own
        return self._lent(np.int32, (max(1, self.n),))

    def _kept_rows(self, none: bool = False) -> tuple:
        """(kept, keep) of a build (cuda_kernels.build): the neighbours its counting pass keeps for its filling pass,
        kept[k, i] for k < keep (int32), ``keep`` = :data:`BUILD_KEPT` or fewer, as many as the list's history holds
        after the row counts (:meth:`_row_counts`; 4 in float32: 5 words a slot, N slots at least), or an array of
        its own where ``LEND_SCRATCH`` is off; keep 0 (``none``: the filling pass searches every row): a one-word
        view of the neighbour indices, never written. Made once per list allocation, among the history's views
        (:meth:`_lent`)."""
        keep = 0 if none else BUILD_KEPT
        n = max(1, self.n)
        if keep > 0 and LEND_SCRATCH:
            keep = min(keep, self.hist.nbytes // (4 * n) - 1)
        keep = max(keep, 0)
        key = ("kept", keep)
        view = self._list_views.get(key)
        if view is None:
            if keep == 0:
                view = self.nbr[:1].reshape(1, 1)
            elif LEND_SCRATCH:
                flat = self.hist.reshape(self.hist.size).view(np.uint8)
                view = flat[4 * n:4 * n * (keep + 1)].view(np.int32).reshape(keep, n)
            else:
                view = cuda.device_array((keep, n), np.int32, stream=self.stream)
            self._list_views[key] = view
        return view, keep

    def _lent(self, dtype, shape: tuple):
        """A C-contiguous device array of ``dtype`` and ``shape`` in the memory of the list's history (``hist``),
        made once per allocation (the launch cache knows its arrays by identity). Valid only between the compaction
        of the kept history and the new list's history (:meth:`_fill_history`), when the history holds nothing
        needed: a rebuild's sort, permutation and build. Its own array where ``LEND_SCRATCH`` is off. The history
        holds at least N + HIST_MARGIN slots of ``hist_words`` >= 5 words; a permuted array larger than it (mixed
        precision's float64 positions) is gathered a row at a time (:meth:`_gather_parts`), and the cell counts lie
        here only where :func:`cuda_memory.lends_cell_counts` (:meth:`_setup_scan`)."""
        dtype = np.dtype(dtype)
        key = (dtype.str, tuple(shape))
        view = self._list_views.get(key)
        if view is None:
            size = int(np.prod(shape))
            if not LEND_SCRATCH:
                view = cuda.device_array(shape, dtype, stream=self.stream)
            else:
                flat = self.hist.reshape(self.hist.size).view(np.uint8)
                if flat.size < size * dtype.itemsize:
                    raise RuntimeError(f"a rebuild's scratch of {size} x {dtype} exceeds the list history's "
                                       f"{self.hist.nbytes} B")
                view = flat[:size * dtype.itemsize].view(dtype).reshape(*shape)
            self._list_views[key] = view
        return view

    def _perm_rows(self) -> tuple:
        """(order, inv_old) of a rebuild's permutation (int32 N each: the old slot of each new one, the new slot of
        each old one), written by the sort and read until the new list's history is filled. Two rows of the torque
        where the next force pass rewrites it for every particle (:meth:`_torque_rewritten`; the torque's content
        is not kept across a rebuild anyway: it is not permuted), else arrays of their own, made at the first call."""
        if self._perm_own is None and LEND_SCRATCH and self._torque_rewritten():
            got = self._perm_views.get(id(self.torque))
            if got is None:
                flat = self.torque.reshape(self.torque.size).view(np.int32)
                got = self._perm_views[id(self.torque)] = (self.torque, flat[:self.n], flat[self.n:2 * self.n])
            return got[1], got[2]
        if self._perm_own is None:
            self._perm_own = tuple(cuda.device_array(self.n, np.int32, stream=self.stream) for _ in range(2))
        return self._perm_own

    def _torque_rewritten(self) -> bool:
        """Whether the next force pass stores every particle's torque (3 words a particle, at least two int32's),
        which a shape's ensemble says; by default no."""
        return False

    def _init_store_index(self) -> None:
        """The compact store's index (c_off, c_cnt: int32 N each) where it cannot lie in the next force buffer
        (:meth:`_store_index`): a shape with one force buffer (spheroids), or ``LEND_SCRATCH`` off."""
        self._store_views = {}
        self._c_own = None
        self.c_off = self.c_cnt = None     # set by each compaction (_compact)
        if self.f_nxt is self.f_cur or not LEND_SCRATCH:
            self._c_own = (self._zeros(self.n, np.int32), self._zeros(self.n, np.int32))
            self.c_off, self.c_cnt = self._c_own

    def _store_index(self) -> tuple:
        """(c_off, c_cnt) of a rebuild: where each particle's kept history starts in the compact store and how many
        slots it kept, written by the compaction and read by the build (or the attachment of a host-built list).
        They lie in the force buffer the next force pass writes (``f_nxt``, 3 words N): nothing reads it before
        that pass, which stores every particle's force after a rebuild (``_forces_unknown``, cuda_loop
        ``SKIP_COLD``) and runs only after the build. One pair of views per buffer (they alternate)."""
        if self._c_own is not None:
            return self._c_own
        got = self._store_views.get(id(self.f_nxt))
        if got is None:
            flat = self.f_nxt.reshape(self.f_nxt.size).view(np.int32)
            got = self._store_views[id(self.f_nxt)] = (self.f_nxt, flat[:self.n], flat[self.n:2 * self.n])
        return got[1], got[2]

    def _set_status(self, slot: int, value: float) -> None:
        """status[slot] = value, in stream order."""
        self._lc.launch("set_word", self.k["set_word"], (1, 32, self.stream), (self.status, slot, float(value)))

    def _compact(self) -> None:
        """Copy the history that must survive the rebuild into the compact store (grown when full)."""
        self.c_off, self.c_cnt = self._store_index()
        while True:
            self._set_status(K.S_NCOMP, 0.0)
            self._lc.launch("compact", self.k["compact"], self._grid(self.n), (
                self.n, self.pos, self.radius1, self.nbr, self.nn, self.hist, self.sc, self.spd, self.spi,
                self.c_off, self.c_cnt, self.cj, self.chist, self.status))
            total = int(self._read_status_now()[K.S_NCOMP])
            if total <= self.store_cap:
                return
            self._alloc_store(int(total * 1.25) + 1024)

    def _rebuild(self) -> None:
        """A list rebuild: on the GPU, or by the CPU-built list modes when they are on (Skorych & Dosta 2022, §3)."""
        if self.lists is not None:
            self.lists.rebuild()
        else:
            self._gpu_rebuild()

    def _gpu_rebuild(self) -> None:
        """Keep history, sort, permute and build: count the rows, hand them out (an exclusive scan of the counts,
        rows in particle order), make room for them, fill them, and give each slot its history."""
        permute = self._sort_due()
        self._compact()
        self._sort_and_permute(permute)
        if self.multigrid:
            self._bin_levels()
        cell_start = self._cell_starts()
        order = self._perm_rows()[0]
        kept, keep = self._kept_rows()
        searched = self.hist
        for fill in (0, 1):
            # the counts and the kept rows lie in the history, which the room may replace: the filling pass then
            # neither reads nor writes them, and searches every row again
            counts = self._row_counts()
            if self.hist is not searched:
                kept, keep = self._kept_rows(none=True)
            if self.multigrid:
                self._lc.launch("mg_build", self.kl["mg_build"], self._grid(self.n), (
                    self.n, self.pos, self.radius1, self.lvl, self.mgi, self.mgf, self.mg_start, self.mg_items,
                    self.nbr, self.nn, counts, self.x_ref, self.sc, self.spd, self.spi, fill))
            else:
                self._lc.launch("build", self.k["build"], self._grid(self.n), (
                    self.n, self.pos, self.radius1, cell_start, order, int(permute), self.nbr, self.nn, counts,
                    self.x_ref, self.sc, self.spd, self.spf, self.spi, fill, kept, keep))
            if fill == 0:
                self._exclusive_scan(counts, self._nn_rows, self._scan_rows)
                self._lc.launch("slot_total", self.k["slot_total"], (1, 32, self.stream),
                                (self.n, self.nn, counts, self.status))
                self._list_room(int(self._read_status_now()[K.S_SLOTS]))
        self._fill_history(permute)
        self.builds += 1

    def _fill_history(self, permuted: bool) -> None:
        """The new list's history (cuda_kernels.fill_history) once its rows and neighbours are in place; ``permuted``:
        the rebuild moved the particles (never for a list built on the host)."""
        order, inv_old = self._perm_rows()
        self._lc.launch("fill_history", self.k["fill_history"], self._grid(self.n), (
            self.n, self.pos, self.radius1, self.c_off, self.c_cnt, self.cj, self.chist, order, inv_old,
            int(permuted), self.nbr, self.nn, self.hist, self.sc, self.spd, self.spi))

    def _setup_multigrid(self, systems, contacts) -> None:
        """Grid levels per scene (Skorych & Dosta 2022, Algorithm 1, :mod:`engine.neighbours.multigrid`) when some
        scene's size spread needs more than one; monodisperse ensembles keep the single-grid build."""
        self.multigrid = False
        if self.uniform or not isinstance(systems[0], SphereSystem) or not MULTIGRID:
            return
        from engine.neighbours.multigrid import grid_levels, main_level
        levels = [grid_levels(self.box[s], sy.n, float(np.min(sy.radius)), float(np.max(sy.radius)),
                              contacts[s].skin) if sy.n else None for s, sy in enumerate(systems)]
        nl = max((lv.n_levels for lv in levels if lv is not None), default=1)
        if nl <= 1:
            return
        self.multigrid = True
        self.levels = levels
        self._mg_skin = [c.skin for c in contacts]
        mgi = np.zeros((self.n_scenes, nl, 3), np.int32)
        mgf = np.ones((self.n_scenes, nl), np.float64)
        lvl = np.zeros(self.n, np.int32)
        off = 0
        for s, (sy, lv) in enumerate(zip(systems, levels)):
            if lv is None:
                continue
            a0 = int(self.starts[s])
            lvl[a0:a0 + sy.n] = main_level(np.asarray(sy.radius, np.float64), lv)
            for l in range(lv.n_levels):
                nc = int(lv.nc[l])
                mgi[s, l] = (nc, off, off + nc ** 3)
                mgf[s, l] = nc / self.box[s]
                off += 2 * nc ** 3
        # the particle permutation (locality only) sorts along the finest level's cells: the coarse grid's
        # cells hold ~ (R_max/R_min)^3 small particles, which the per-cell id sort handles poorly
        coff = 0
        for s, lv in enumerate(levels):
            nc = 1 if lv is None else int(lv.nc[-1])
            self.spi_h[s, [K.I_NC, K.I_COFF]] = [nc, coff]
            self.spf_h[s, K.F_INVCELL] = nc / self.box[s]
            coff += nc ** 3
        self.ncell = coff
        self._setup_scan()
        st = self.stream
        self.mg_nbins = off
        self.mg_entries = int((lvl.astype(np.int64) + 1).sum())
        self.lvl = cuda.to_device(lvl, stream=st)
        self.mgi = cuda.to_device(mgi, stream=st)
        self.mgf = cuda.to_device(mgf, stream=st)
        self.mg_count = cuda.device_array(off + 1, np.int32, stream=st)
        self.mg_start = cuda.device_array(off + 1, np.int32, stream=st)
        self.mg_cursor = cuda.device_array(off, np.int32, stream=st)
        self.mg_items = cuda.device_array(self.mg_entries, np.int32, stream=st)
        self._scan_mg = self._scan_buffers(off + 1)
        self.kl = list_kernels(self.dtype, self.tpb)

    def _bin_levels(self) -> None:
        """Main and secondary bins of every level (counting sort by bin)."""
        k, n, lc = self.k, self.n, self._lc
        lc.launch("fill_i32", k["fill_i32"], self._grid(self.mg_nbins + 1), (self.mg_count, 0))
        lc.launch("mg_count", self.kl["mg_count"], self._grid(n), (n, self.pos, self.sc, self.spi, self.lvl, self.mgi,
                                                                     self.mgf, self.mg_count))
        self._exclusive_scan(self.mg_count, self.mg_start, self._scan_mg)
        lc.launch("fill_i32", k["fill_i32"], self._grid(self.mg_nbins), (self.mg_cursor, 0))
        lc.launch("mg_scatter", self.kl["mg_scatter"], self._grid(n), (n, self.pos, self.sc, self.spi, self.lvl,
                                                                         self.mgi, self.mgf, self.mg_start,
                                                                         self.mg_cursor, self.mg_items))

    def _restore_springs(self, pairs, springs) -> None:
        nbr, nn, hist = (a.copy_to_host(stream=self.stream) for a in (self.nbr, self.nn, self.hist))
        ids = self.ids.copy_to_host(stream=self.stream)
        self.stream.synchronize()
        slot_of = np.empty(self.n, np.int64)
        slot_of[ids] = np.arange(self.n)
        for p in range(pairs.shape[0]):
            i = slot_of[pairs[p, 0]]
            j = slot_of[pairs[p, 1]]
            for q in range(nn[i], nn[i + 1]):
                if nbr[q] == j:
                    w = min(self.hist_words, springs.shape[1])
                    hist[0:w, q] = springs[p, :w]
                    break
        self.hist.copy_to_device(hist, stream=self.stream)
