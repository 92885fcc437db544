"""CUDA backend: the whole time loop on the GPU with Numba CUDA, state resident on the device.

:class:`CudaEnsemble` advances K independent scenes (own box, contact constants, dt, seed, clock) stored
back to back on the device with the same kernels: the one CUDA time loop (:mod:`engine.backends.cuda_loop`)
specialised by the sphere's device functions (engine/shapes/sphere/device.py), the list kernels of
:mod:`engine.backends.cuda_kernels` and :mod:`engine.backends.cuda_lists`; all call the same njit physics
functions as the CPU backend. :class:`CudaBackend` is the one-scene case (K = 1) with the public interface of
:class:`engine.shapes.sphere.cpu_backend.CpuBackend`. This class is also the host side of every other shape (a subclass
allocates the shape's state and names its arrays for the kernels: ``shape``, ``_upload_particles``,
``_step_arrays``, ``_observe_args``, ``_observables``; engine/shapes/spheroid/cuda_backend.py is the example).

Step (velocity Verlet, closing and opening half kicks fused as on the CPU):
  1. kick + drift with periodic wrap + orientation; the largest displacement since the list build and
     the largest speed, each normalised by the scene's L_v/2, folded into a device ``status``;
  2. rebuild (rare) when some particle has moved more than L_v/2: copy the contact history that must
     survive into a compact store, count particles per cell (scene-major cell ids), scan, scatter, sort
     each cell by id, permute the particle arrays into that order (neighbours sit close in memory), build
     the full Verlet list in place taking the kept history from the compact store;
  3. forces over the full list: one thread per particle, each writes only its own force, torque and slots.

Two time loops, chosen by size (``multistep``):
  * many steps per launch (total particles <= MULTISTEP_MAX_PARTICLES, i.e. small scenes and ensembles
    of them): one cooperative kernel runs the steps with grid-wide syncs between the phases and returns
    to the host only at the end of the call or when a rebuild is due, so launch overhead is paid per
    output interval, not per step;
  * one launch per phase (large scenes): the host decides the rebuild from the *previous* step's status,
    already copied to pinned memory while the GPU runs this step, so the loop never waits for the GPU
    (rebuild at step s when d(s-1) + 2 max|v(s-1)| dt > L_v/2; misses are counted in ``late_rebuilds``).

A scene that blows up (non-finite value, overlap beyond its limit) is stopped on the device and reported
for that scene only; the others go on.
"""

from __future__ import annotations

import math
import os
import threading
import time
from types import SimpleNamespace
from typing import Callable, Optional

import numpy as np
from numba import cuda
from numba.cuda.cudadrv.driver import device_memset

from engine.backends.base import ContactParams, SphereSystem, cell_grid
from engine.backends import cuda_kernels as K
from engine.backends import cuda_loop
from engine.backends.cuda_device import copy_device as _copy
from engine.backends.cuda_lists import list_kernels
from engine.backends.cuda_launch import LaunchCache
from engine.backends.status import BAD_VALUE, OVERLAP, instability_error as _instability
from engine.errors import BackendUnavailable, InstabilityError
from engine.pieces import map_pieces
from engine.physics.sonine import DOF_ROTATION_SPHERE, sonine_sums
from engine.precision import check_shape, position_dtype, state_dtype
from engine.shapes.sphere import device as SC

SIM = os.environ.get("NUMBA_ENABLE_CUDASIM") == "1"
#: a snapshot buffer slot (all state arrays of the largest scene) larger than this is pageable memory, page-locked in
#: place (CudaEnsemble._host_slot)
PINNED_SLOT_BYTES = 32 << 20
#: ... or, where it cannot be, replaced by pinned buffers (allocated on a thread) after this many large frames
PIN_AFTER_FRAMES = 3
#: the cooperative many-steps-per-launch loop is used up to this many particles (all scenes together);
#: measured on an H200 (bench/gpu_ensemble.py): 10x faster at 4096, equal at 2^20, 25 % slower at 2^22
#: (a grid of co-resident blocks loops over many particles per thread); DEMQ_CUDA_MULTISTEP=0/1 forces it
MULTISTEP_MAX_PARTICLES = 1024 * 1024


class CudaEnsemble:
    """K scenes of spheres advanced together on the GPU; see the module docstring.

    All scenes share the precision; everything else (N, box, contact constants, dt, skin, rough or
    smooth, Coulomb, orientation) is per scene. ``advance`` returns the scenes that blew up in the call
    (each stopped at its own step, the others advanced fully); ``deactivate`` drops a scene.
    """

    name = "cuda"
    #: the particle shape (engine/shapes/SHAPES key) whose CUDA parts specialise the time loop
    shape = "sphere"
    #: the driver's work for the host while it waits for the GPU (engine/simulate.py, _Deferred: the records
    #: of the last stops): called in the waits, it runs one small unit and returns True, or False when none is left
    idle: Optional[Callable[[], bool]] = None
    #: widths of the per-scene constant tables (a subclass may append columns)
    _ND, _NF = K.ND, K.NF
    #: history words per list slot (a shape whose pair law keeps more sets its own before the lists exist)
    hist_words = K.HW
    #: device arrays permuted into cell order at a rebuild (besides the per-particle constants)
    _permuted = ("pos", "vel", "omega", "quat", "f_cur")
    #: int64 device arrays (N) permuted with them (spheres: the lazy orientations' marks)
    _permuted_i64 = ("q_last", "begun")
    #: 1-D views of other device arrays (not counted by device_bytes)
    _view_names = ("radius1", "inv_m1", "inv_i1", "mass1", "inertia1")

    def __init__(self, systems: list, contacts: list):
        if not SIM and not cuda.is_available():
            raise BackendUnavailable("backend = 'cuda' but no CUDA GPU is available here")
        if len(systems) != len(contacts) or not systems:
            raise ValueError("CudaEnsemble needs one ContactParams per scene and at least one scene")
        precisions = {c.precision for c in contacts}
        if len(precisions) != 1:
            raise ValueError(f"all scenes of an ensemble share one precision, got {sorted(precisions)}")
        check_shape(contacts[0].precision, self.shape)
        self.dtype = dt_ = state_dtype(contacts[0].precision)
        self.pos_dtype = position_dtype(contacts[0].precision)  # float64 in 'mixed' (engine/precision.py)
        self.n_scenes = nk = len(systems)
        self.sizes = np.array([s.n for s in systems], np.int64)
        self.starts = np.concatenate([[0], np.cumsum(self.sizes)[:-1]]).astype(np.int64)
        self.n = n = int(self.sizes.sum())
        self.device = "CUDA simulator" if SIM else cuda.get_current_device().name
        if isinstance(self.device, bytes):
            self.device = self.device.decode()
        self.tpb = 32 if SIM else 256
        self.sm_count = 1 if SIM else cuda.get_current_device().MULTIPROCESSOR_COUNT
        self.max_blocks = 2 if SIM else self.sm_count * 16
        env = os.environ.get("DEMQ_CUDA_MULTISTEP")
        self.multistep = (env == "1") if env in ("0", "1") else n <= MULTISTEP_MAX_PARTICLES
        self._exit_thr = 1.0  # run_steps exits when (displacement / (L_v/2))^2 exceeds it
        self.stream = cuda.stream()
        self._lc = LaunchCache()   # the per-step kernels' launches (engine/backends/cuda_launch.py)
        self.steps_done = 0
        self.builds = 0
        self.late_rebuilds = 0
        self.launches = 0
        self._prof_events = []
        self.profile = None  # set to {} to time the phases with CUDA events
        self.active = np.ones(nk, bool)
        self.contact = list(contacts)
        self.box = np.array([float(s.box_length) for s in systems])

        self.x_ref = cuda.device_array((3, n), self.pos_dtype, stream=self.stream)
        self.ids = cuda.to_device(np.arange(n, dtype=np.int32), stream=self.stream)
        self.sc = cuda.to_device(np.repeat(np.arange(nk, dtype=np.int32), self.sizes), stream=self.stream)
        self._upload_particles(systems)
        if getattr(self, "_slot_prep", None) is None:
            self._prepare_frame_slot()
        self._views()
        # scratch for permutations (4 rows covers the quaternion)
        self.scratch = cuda.device_array((4, n), dt_, stream=self.stream)
        # ... and for the positions when they are kept in another precision ('mixed')
        self.scratch_x = self.scratch if self.pos_dtype is dt_ else cuda.device_array((3, n), self.pos_dtype,
                                                                                      stream=self.stream)
        self.scratch_i = cuda.device_array(n, np.int32, stream=self.stream)
        self.scratch_l = cuda.device_array(n if self._permuted_i64 else 1, np.int64, stream=self.stream)
        self.order = cuda.device_array(n, np.int32, stream=self.stream)
        self.inv_old = cuda.device_array(n, np.int32, stream=self.stream)
        self.c_off = self._zeros(n, np.int32)
        self.c_cnt = self._zeros(n, np.int32)
        self._alloc_store(max(1024, n // 8))
        self.status = cuda.to_device(self._fresh_status(), stream=self.stream)
        self.status_h = [cuda.pinned_array(K.status_len(nk), np.float64) for _ in range(2)]
        self.events = [(cuda.event() if SIM else cuda.event(timing=False)) for _ in range(2)]

        self.spd_h = np.zeros((nk, self._ND), dt_)
        self.spf_h = np.zeros((nk, self._NF), np.float64)
        self.spi_h = np.zeros((nk, K.NI), np.int32)
        coff = 0
        for s, sy in enumerate(systems):
            c = dt_
            nc = cell_grid(self.box[s], s_n := sy.n, self._rmax[s], contacts[s].skin)
            self.spi_h[s, [K.I_NC, K.I_COFF, K.I_ACTIVE, K.I_START, K.I_N]] = [nc, coff, 1, self.starts[s], s_n]
            coff += nc ** 3
            self.spf_h[s, K.F_INVCELL] = nc / self.box[s]
            self.spd_h[s, [K.D_BOX, K.D_INVBOX]] = [c(self.box[s]), c(1.0 / self.box[s])]
            self._scene_constants(s)
        self.ncell = coff
        self._setup_scan()
        self._setup_multigrid(systems, contacts)
        self.spd = cuda.to_device(self.spd_h, stream=self.stream)
        self.spf = cuda.to_device(self.spf_h, stream=self.stream)
        self.spi = cuda.to_device(self.spi_h, stream=self.stream)
        self._alloc_list(8)
        for s, c in enumerate(contacts):
            self._set_scene_contact(s, c)
        self._upload_params()
        self._specialise()
        self._prime(systems)

    # ---- set-up -----------------------------------------------------------------------------------

    def _up(self, a, rows, dtype=None):
        """Host (N, rows) -> device (rows, N) in the working precision (or ``dtype``): :meth:`_up_into` a new array."""
        dst = cuda.device_array((rows, self.n), dtype or self.dtype, stream=self.stream)
        self._up_into(a, dst, 0)
        return dst

    def _up_into(self, a, dst, col0: int) -> None:
        """Host (n_a, rows) -> columns [col0, col0 + n_a) of the device (rows, N) array ``dst``, in its precision. The
        host array goes up as it is (float32 and float64; anything else as float64) and the device transposes and
        casts it (K.scatter_rows, the same round-to-nearest cast as NumPy's): a host transposition of a large start
        cost more than the upload itself (issue 14, set-up)."""
        a = np.asarray(a)
        if a.dtype not in (np.float32, np.float64):
            a = a.astype(np.float64)
        a = np.ascontiguousarray(a.reshape(-1, dst.shape[0]))
        if a.shape[0]:
            K.scatter_rows[self._grid(a.shape[0])](cuda.to_device(a, stream=self.stream), col0, dst)

    def _copy(self, a):
        """A device copy of device array ``a`` (on the stream; no host round trip)."""
        b = cuda.device_array(a.shape, a.dtype, stream=self.stream)
        if a.size:
            b.copy_to_device(a, stream=self.stream)
        return b

    def _zeros(self, shape, dtype):
        """A device array of zeros: a memset on the stream, no host array to copy."""
        a = cuda.device_array(shape, dtype, stream=self.stream)
        if SIM:
            a.copy_to_device(np.zeros(shape, dtype), stream=self.stream)
        elif a.size:
            device_memset(a, 0, a.nbytes, stream=self.stream)
        return a

    @staticmethod
    def _cat(systems, attr):
        """The scenes' (n_k, rows) float64 arrays of ``attr`` one after another (one scene's: not copied)."""
        parts = [np.asarray(getattr(s, attr), np.float64).reshape(s.n, -1) for s in systems]
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    def _upload_particles(self, systems) -> None:
        """Sphere state and constants on the device (uniform scenes keep their constants in spd)."""
        dt_, n = self.dtype, self.n
        rad, mass, inertia = (np.concatenate([np.asarray(getattr(s, attr), np.float64) for s in systems])
                              if len(systems) > 1 else np.asarray(getattr(systems[0], attr), np.float64)
                              for attr in ("radius", "mass", "inertia"))
        self.uniform = all(s.n == 0 or (np.all(s.radius == s.radius[0]) and np.all(s.mass == s.mass[0])
                                        and np.all(s.inertia == s.inertia[0])) for s in systems)
        self._rmax = [float(np.max(s.radius)) if s.n else 0.0 for s in systems]
        self._scene0 = [(rad[i], mass[i], inertia[i]) if s_n else (0, 0, 0)
                        for i, s_n in zip(self.starts, self.sizes)]
        up, cat = self._up, lambda attr: self._cat(systems, attr)
        if any(s.draw is not None for s in systems):
            self._draw_starts(systems)
        else:
            self.pos = up(cat("position"), 3, self.pos_dtype)
            self.vel = up(cat("velocity"), 3)
            self.omega = up(cat("angular_velocity"), 3)
            self.quat = up(cat("orientation"), 4)
        self.f_cur = self._zeros((3, n), dt_)
        self.f_nxt = cuda.device_array((3, n), dt_, stream=self.stream)
        self.torque = self._zeros((3, n), dt_)
        # the step from which each sphere's orientation turns are pending (lazy orientations, shapes/sphere/device.py)
        self.q_last = self._zeros(n, np.int64)
        # the contacts each sphere has begun (collision counter, issue 18; shapes/sphere/device.py pair)
        self.begun = self._zeros(n, np.int64)
        if self.uniform:
            dummy = cuda.device_array((1, 1), dt_, stream=self.stream)
            self.radius = self.inv_m = self.inv_i = self.mass = self.inertia = dummy
            self._per_particle = []
        else:
            self.radius = up(rad, 1)
            self.mass = up(mass, 1)
            self.inertia = up(inertia, 1)
            self.inv_m = up((1.0 / mass.astype(dt_)).astype(dt_), 1)
            self.inv_i = up((1.0 / inertia.astype(dt_)).astype(dt_), 1)
            self._per_particle = ["radius", "mass", "inertia", "inv_m", "inv_i"]

    def _draw_starts(self, systems) -> None:
        """pos, vel, omega, quat of scenes of which some hold a start to draw on the device (engine.scene.StartDraw:
        engine/backends/cuda_start.py); the others' host arrays go up into their columns."""
        from engine.backends.cuda_start import SPHERE_TARGETS, draw_start

        n, st = self.n, self.stream
        self.pos = cuda.device_array((3, n), self.pos_dtype, stream=st)
        self.vel = cuda.device_array((3, n), self.dtype, stream=st)
        self.omega = cuda.device_array((3, n), self.dtype, stream=st)
        self.quat = cuda.device_array((4, n), self.dtype, stream=st)
        self._prepare_frame_slot()     # beside the draws
        for sy, col0 in zip(systems, self.starts):
            if sy.draw is not None:
                draw_start(sy.draw, int(col0), self.pos, {k: getattr(self, a) for k, a in SPHERE_TARGETS.items()}, st,
                           self.max_blocks)
            else:
                for attr, dst in (("position", self.pos), ("velocity", self.vel), ("angular_velocity", self.omega),
                                  ("orientation", self.quat)):
                    self._up_into(getattr(sy, attr), dst, int(col0))

    def _scene_constants(self, s: int) -> None:
        """Scene s's particle constants in spd (used when its particles are uniform)."""
        c = self.dtype
        r0, m0, i0 = self._scene0[s]
        self.spd_h[s, [K.D_R0, K.D_M0, K.D_I0]] = [c(r0), c(m0), c(i0)]
        self.spd_h[s, K.D_IM0] = (1.0 / np.array([m0 or 1.0], c))[0]
        self.spd_h[s, K.D_II0] = (1.0 / np.array([i0 or 1.0], c))[0]

    def _fresh_status(self) -> np.ndarray:
        s = np.zeros(K.status_len(self.n_scenes), np.float64)
        for k in range(self.n_scenes):
            b = K.SS0 + K.NSS * k
            s[[b + K.SS_BAD_ID, b + K.SS_BAD_STEP, b + K.SS_OVL_ID, b + K.SS_OVL_STEP]] = np.inf
        return s

    def _views(self) -> None:
        """1-D views of the per-particle constants (kept as (1, N) rows for the permutation)."""
        self.radius1, self.inv_m1, self.inv_i1 = self.radius[0], self.inv_m[0], self.inv_i[0]
        self.mass1, self.inertia1 = self.mass[0], self.inertia[0]

    def _grid(self, work: int) -> tuple:
        blocks = max(1, min(self.max_blocks, (work + self.tpb - 1) // self.tpb))
        return blocks, self.tpb, self.stream

    def _setup_scan(self) -> None:
        s = self.stream
        self.count = cuda.device_array(self.ncell + 1, np.int32, stream=s)
        self.cell_start = cuda.device_array(self.ncell + 1, np.int32, stream=s)
        self._scan_cells = self._scan_buffers(self.ncell + 1)

    def _scan_buffers(self, m: int) -> SimpleNamespace:
        """Block-sum buffers of an exclusive scan of m int32 counts (tiles of tpb * 16)."""
        tile = self.tpb * 16
        nb = (m + tile - 1) // tile
        dev = lambda k: cuda.device_array(max(k, 1), np.int32, stream=self.stream)  # noqa: E731
        return SimpleNamespace(m=m, tile=tile, nb=nb, bsum=dev(nb), bsum_scan=dev(nb), bsum_tot=dev(1))

    def _exclusive_scan(self, src, dst, b: SimpleNamespace) -> None:
        k, s = self.k, self.stream
        k["tile_scan"][b.nb, self.tpb, s](src, dst, b.m, b.bsum, 16)
        if b.nb > 1:
            items = (b.nb + self.tpb - 1) // self.tpb
            k["tile_scan"][1, self.tpb, s](b.bsum, b.bsum_scan, b.nb, b.bsum_tot, items)
            k["add_offsets"][self._grid(b.m)](dst, b.m, b.bsum_scan, b.tile)

    def _alloc_list(self, max_nb: int) -> None:
        s = self.stream
        self.max_nb = max_nb
        self.nbr = cuda.device_array((max_nb, self.n), np.int32, stream=s)
        self.nn = self._zeros(self.n, np.int32)
        self.hist = cuda.device_array((self.hist_words, max_nb, self.n), self.dtype, stream=s)

    def _alloc_store(self, cap: int) -> None:
        self.store_cap = cap
        self.cj = cuda.device_array(cap, np.int32, stream=self.stream)
        self.chist = cuda.device_array((self.hist_words, cap), self.dtype, stream=self.stream)

    def _set_scene_contact(self, s: int, contact: ContactParams) -> None:
        c = self.dtype
        self.contact[s] = contact
        dt = c(contact.dt)
        skin = c(contact.skin)
        lim = float(skin) * 0.5
        self.spd_h[s, [K.D_DT, K.D_HP, K.D_KN, K.D_GN, K.D_KT, K.D_SKIN]] = [
            dt, c(dt * c(0.5)), c(contact.k_n), c(contact.gamma_n_coef),
            c(0.0) if contact.k_t is None else c(contact.k_t), skin]
        # a scene without a Coulomb limit inside a Coulomb-compiled ensemble: mu = inf never caps
        self.spd_h[s, K.D_MU] = c(np.inf) if contact.friction is None else c(contact.friction)
        self.spf_h[s, [K.F_OVL, K.F_LIM2INV, K.F_V2F, K.F_KN, K.F_KT]] = [
            float(contact.overlap_limit), 1.0 / (lim * lim), (2.0 * float(dt) / lim) ** 2, float(c(contact.k_n)),
            0.0 if contact.k_t is None else float(c(contact.k_t))]
        self.spi_h[s, K.I_ORIENT] = 1 if contact.orientation else 0

    def _specialise(self) -> None:
        act = [c for c, a in zip(self.contact, self.active) if a] or self.contact
        rough = any(c.k_t is not None for c in act)
        coulomb = rough and any(c.friction is not None for c in act)
        orient = any(c.orientation for c in act)
        if orient and not getattr(self, "_orient", True) and getattr(self, "q_last", None) is not None:
            # orientations tracked from now on: nothing is pending from the steps run without them
            self.q_last.copy_to_device(np.full(self.n, self.steps_done, np.int64), stream=self.stream)
        self._orient = orient
        self.k = cuda_loop.kernels(self.shape, self.dtype, (rough, coulomb, orient), self.uniform, self.tpb)
        self._coop_blocks = None

    def _upload_params(self) -> None:
        self.spd.copy_to_device(self.spd_h, stream=self.stream)
        self.spf.copy_to_device(self.spf_h, stream=self.stream)
        self.spi.copy_to_device(self.spi_h, stream=self.stream)

    def set_contact(self, k: int, contact: ContactParams) -> None:
        """Switch scene k's contact constants (e.g. thermalisation -> cooling); keeps lists and springs."""
        self.set_contacts({k: contact})

    def set_contacts(self, contacts: dict) -> None:
        """:meth:`set_contact` for several scenes ({scene: contact}) with one upload of the constant tables (the
        driver sets every scene's contact before the first step: one upload instead of one per scene)."""
        for k, contact in contacts.items():
            if contact.precision != self.contact[k].precision:
                raise ValueError("the precision of a scene cannot change inside an ensemble")
        self._sync_active()
        for k, contact in contacts.items():
            self._set_scene_contact(k, contact)
        self._upload_params()
        self._specialise()

    def deactivate(self, k: int) -> None:
        """Scene k drops out (finished, cancelled or failed): it is never advanced again."""
        self.deactivate_many([k])

    def deactivate_many(self, ks) -> None:
        """Scenes ks drop out together: one device round trip for all (the scenes of a packed batch end in
        the same round; one by one, 256 of them took ~1 s of syncs and parameter uploads)."""
        self._sync_active()
        for k in ks:
            self.active[k] = False
            self.spi_h[k, K.I_ACTIVE] = 0
        self._upload_params()

    def set_list_mode(self, mode: str) -> None:
        """Where the Verlet list is built: 'gpu', 'cpu-sequential', 'cpu-pipelined' or 'auto' (paper 004
        §3, :mod:`engine.backends.cuda_listmodes`); the CPU modes need one scene. 'auto' on an ensemble of
        several scenes is the GPU list."""
        from engine.backends.cuda_listmodes import MODES, HostLists
        if mode not in MODES:
            raise ValueError(f"list_mode = {mode!r} is not one of {', '.join(MODES)}")
        if self.lists is not None:
            self.lists.close()
            self.lists = None
        if mode == "gpu" or (mode == "auto" and self.n_scenes > 1):
            return
        if getattr(self, "kl", None) is None:
            self.kl = list_kernels(self.dtype, self.tpb)
        self.lists = HostLists(self, mode)

    def _sync_active(self) -> None:
        """The device clears the active flag of a scene that blows up; bring the host copy up to date."""
        spi = self.spi.copy_to_host(stream=self.stream)
        self.stream.synchronize()
        self.spi_h[:, K.I_ACTIVE] = spi[:, K.I_ACTIVE]

    # ---- neighbour list -----------------------------------------------------------------------------

    def _sort_and_permute(self) -> None:
        k, n, s = self.k, self.n, self.stream
        k["fill_i32"][self._grid(self.ncell + 1)](self.count, 0)
        k["count_cells"][self._grid(n)](n, self.pos, self.sc, self.spf, self.spi, self.count)
        # exclusive scan of ncell + 1 counts (the last is 0) -> cell_start, cell_start[ncell] = n
        self._exclusive_scan(self.count, self.cell_start, self._scan_cells)
        k["fill_i32"][self._grid(self.ncell + 1)](self.count, 0)
        k["scatter"][self._grid(n)](n, self.pos, self.sc, self.spf, self.spi, self.cell_start, self.count,
                                    self.order)
        k["sort_cells"][self._grid(self.ncell)](self.ncell, self.cell_start, self.order, self.ids)
        k["inverse_perm"][self._grid(n)](n, self.order, self.inv_old)
        # permute the particle arrays into cell order (forces too: the next force step reads them)
        # (torque need not move: the next force step rewrites it before any kick reads it)
        for name in list(self._permuted) + self._per_particle:
            a = getattr(self, name)
            tmp = (self.scratch if a.dtype == self.scratch.dtype else self.scratch_x)[:a.shape[0]]
            k["gather_rows"][self._grid(n)](n, a, tmp, self.order)
            _copy(a, tmp, s)
        for name in ("ids", "lvl") if self.multigrid else ("ids",):
            a = getattr(self, name)
            k["gather_i32"][self._grid(n)](n, a, self.scratch_i, self.order)
            _copy(a, self.scratch_i, s)
        for name in self._permuted_i64:   # (gather_i32 is typed at launch: the same kernel for int64)
            a = getattr(self, name)
            k["gather_i32"][self._grid(n)](n, a, self.scratch_l, self.order)
            _copy(a, self.scratch_l, s)

    def _set_status(self, slot: int, value: float) -> None:
        self.status[slot:slot + 1].copy_to_device(np.full(1, value), stream=self.stream)

    def _compact(self) -> None:
        """Copy the history that must survive the rebuild into the compact store (grown when full)."""
        while True:
            self._set_status(K.S_NCOMP, 0.0)
            self.k["compact"][self._grid(self.n)](self.n, self.pos, self.radius1, self.nbr, self.nn, self.hist,
                                                  self.sc, self.spd, self.spi, self.c_off, self.c_cnt, self.cj,
                                                  self.chist, self.status)
            total = np.zeros(1)
            self.status[K.S_NCOMP:K.S_NCOMP + 1].copy_to_host(total, stream=self.stream)
            self.stream.synchronize()
            if int(total[0]) <= self.store_cap:
                return
            self._alloc_store(int(total[0] * 1.25) + 1024)

    def _rebuild(self) -> None:
        """A list rebuild: on the GPU, or by the CPU-built list modes when they are on (paper 004 §3)."""
        if self.lists is not None:
            self.lists.rebuild()
        else:
            self._gpu_rebuild()

    def _gpu_rebuild(self) -> None:
        """Keep history, sort, permute and build; grows the stride when a particle has more neighbours."""
        self._compact()
        self._sort_and_permute()
        if self.multigrid:
            self._bin_levels()
        while True:
            self._set_status(K.S_NEED_NB, 0.0)
            if self.multigrid:
                self.kl["mg_build"][self._grid(self.n)](
                    self.n, self.pos, self.radius1, self.lvl, self.mgi, self.mgf, self.mg_start, self.mg_items,
                    self.c_off, self.c_cnt, self.cj, self.chist, self.order, self.inv_old, self.nbr, self.nn,
                    self.hist, self.x_ref, self.sc, self.spd, self.spi, self.status)
            else:
                self.k["build"][self._grid(self.n)](
                    self.n, self.pos, self.radius1, self.cell_start, self.c_off, self.c_cnt, self.cj,
                    self.chist, self.order, self.inv_old, self.nbr, self.nn, self.hist, self.x_ref, self.sc,
                    self.spd, self.spf, self.spi, self.status)
            need = np.zeros(1)
            self.status[K.S_NEED_NB:K.S_NEED_NB + 1].copy_to_host(need, stream=self.stream)
            self.stream.synchronize()
            need = int(need[0])
            if need <= self.max_nb:
                break
            # the kept history is in the compact store: the list can be reallocated and rebuilt
            self._alloc_list(int(math.ceil((need + 2) / 4.0)) * 4)
        self.builds += 1

    def _setup_multigrid(self, systems, contacts) -> None:
        """Grid levels per scene (paper 004 Algorithm 1, :mod:`engine.multigrid`) when some scene's size
        spread needs more than one; monodisperse ensembles keep the single-grid build."""
        self.multigrid = False
        self.lists = None
        if self.uniform or not isinstance(systems[0], SphereSystem) or os.environ.get("DEMQ_CUDA_MULTIGRID") == "0":
            return  # (DEMQ_CUDA_MULTIGRID=0: one grid of cell >= 2 R_max + L_v, for the cost comparison)
        from engine.multigrid import grid_levels, main_level
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
        k, n = self.k, self.n
        k["fill_i32"][self._grid(self.mg_nbins + 1)](self.mg_count, 0)
        self.kl["mg_count"][self._grid(n)](n, self.pos, self.sc, self.lvl, self.mgi, self.mgf, self.mg_count)
        self._exclusive_scan(self.mg_count, self.mg_start, self._scan_mg)
        k["fill_i32"][self._grid(self.mg_nbins)](self.mg_cursor, 0)
        self.kl["mg_scatter"][self._grid(n)](n, self.pos, self.sc, self.lvl, self.mgi, self.mgf, self.mg_start,
                                             self.mg_cursor, self.mg_items)

    def _prime(self, systems) -> None:
        """First list build (restoring checkpointed springs) and forces at t = 0."""
        self._rebuild()
        for s, sy in enumerate(systems):
            if sy.contact_pairs is not None and len(sy.contact_pairs):
                self._restore_springs(self.starts[s] + np.asarray(sy.contact_pairs, np.int64),
                                      np.asarray(sy.contact_springs, np.float64))
        self._forces(step=0)
        self.f_cur, self.f_nxt = self.f_nxt, self.f_cur
        # scenes that already fail at t = 0 (overlapping start): reported by the first advance
        self._pending = self._collect(self._read_status_now())

    def _restore_springs(self, pairs, springs) -> None:
        nbr, nn, hist = (a.copy_to_host(stream=self.stream) for a in (self.nbr, self.nn, self.hist))
        ids = self.ids.copy_to_host(stream=self.stream)
        self.stream.synchronize()
        slot_of = np.empty(self.n, np.int64)
        slot_of[ids] = np.arange(self.n)
        for p in range(pairs.shape[0]):
            i = slot_of[pairs[p, 0]]
            j = slot_of[pairs[p, 1]]
            for kk in range(min(nn[i], nbr.shape[0])):
                if nbr[kk, i] == j:
                    q = min(self.hist_words, springs.shape[1])
                    hist[0:q, kk, i] = springs[p, :q]
                    break
        self.hist.copy_to_device(hist, stream=self.stream)

    def _step_arrays(self) -> tuple:
        """(spin, spin_inv, list radius, ext) of the time loop's kernels (engine/backends/cuda_loop.py):
        spheres: the angular velocity, 1/I, the radius, (the lazy orientations' marks, the contacts begun)."""
        return self.omega, self.inv_i1, self.radius1, (self.q_last, self.begun)

    def _forces(self, step: int, n: int | None = None, grid=None) -> None:
        spin, _, rad, ext = self._step_arrays()
        n = self.n if n is None else n
        self._lc.launch("forces", self.k["forces"], grid or self._grid(n), (
            n, self.pos, self.vel, spin, self.quat, rad, self.inv_m1, self.f_cur, self.f_nxt, self.torque,
            self.nbr, self.nn, self.hist, self.ids, self.sc, self.spd, self.spf, self.spi, self.status, step, ext))

    # ---- time loop ---------------------------------------------------------------------------------

    def _coop_grid(self) -> tuple:
        """Blocks of the cooperative launch: all co-resident (a grid sync needs it)."""
        if self._coop_blocks is None:
            if SIM:
                self._coop_blocks = 1  # the simulator syncs a cooperative grid of one block only
            else:
                if not self.k["run_steps"].overloads:
                    self.warmup()
                kern = next(iter(self.k["run_steps"].overloads.values()))
                fit = kern.max_cooperative_grid_blocks(self.tpb)
                self._coop_blocks = max(1, min(fit, (self.n + self.tpb - 1) // self.tpb))
        return self._coop_blocks, self.tpb, self.stream

    def _kick_drift(self, first: int, step: int, n: int | None = None, grid=None) -> None:
        spin, spin_inv, _, ext = self._step_arrays()
        n = self.n if n is None else n
        self._lc.launch("kick_drift", self.k["kick_drift"], grid or self._grid(n), (
            n, first, self.pos, self.vel, spin, self.quat, self.f_cur, self.torque, self.inv_m1, spin_inv,
            self.x_ref, self.ids, self.sc, self.spd, self.spf, self.spi, self.status, step, ext))

    def _half_kick(self, n: int | None = None, grid=None) -> None:
        spin, spin_inv, _, _ = self._step_arrays()
        n = self.n if n is None else n
        self.k["half_kick"][grid or self._grid(n)](n, self.vel, spin, self.f_cur, self.torque, self.inv_m1,
                                                   spin_inv, self.sc, self.spd, self.spi)

    def _settle(self, n: int | None = None, grid=None) -> None:
        """The shape's end-of-call work (cuda_loop ``settle``), when it has some, at step ``steps_done``."""
        if "settle" in self.k:
            spin, _, _, ext = self._step_arrays()
            n = self.n if n is None else n
            self.k["settle"][grid or self._grid(n)](n, spin, self.quat, self.sc, self.spd, self.spi, self.steps_done,
                                                    ext)

    def _run_steps(self, nmax: int, first: int, step0: int, grid=None, n: int | None = None, thr=None,
                   status=None) -> None:
        spin, spin_inv, rad, ext = self._step_arrays()
        self.k["run_steps"][grid or self._coop_grid()](
            self.n if n is None else n, nmax, first, 0, self._exit_thr if thr is None else thr, self.pos, self.vel,
            spin, self.quat, self.f_cur, self.f_nxt, self.torque, self.inv_m1, spin_inv, rad, self.x_ref, self.nbr,
            self.nn, self.hist, self.ids, self.sc, self.spd, self.spf, self.spi,
            self.status if status is None else status, step0, ext)

    def warmup(self) -> None:
        """Compile the kernels of the current specialisation without advancing (launches with n = 0)."""
        s = self.stream
        g = (1, self.tpb, s)
        self._kick_drift(1, 0, n=0, grid=g)
        self._forces(0, n=0, grid=g)
        self._half_kick(n=0, grid=g)
        self._settle(n=0, grid=g)
        self._observe_sums()
        if self.multistep:
            self._run_steps(1, 1, 0, grid=g, n=0, thr=1.0, status=cuda.to_device(self._fresh_status(), stream=s))
        s.synchronize()

    def plan(self, steps: int) -> None:
        """The driver's horizon: the run goes on for about ``steps`` more steps (used by the auto list mode to
        judge whether a probe can repay itself)."""
        self._horizon = self.steps_done + int(steps)

    def steps_left(self):
        """Steps left before the later of the driver's horizon and the current advance call's end (None:
        unknown)."""
        ends = [e for e in (getattr(self, "_horizon", None), getattr(self, "_call_end", None)) if e is not None]
        return max(ends) - self.steps_done if ends else None

    def advance(self, nsteps: int) -> dict:
        """Advance every active scene nsteps steps; returns {scene: InstabilityError} of the scenes that
        blew up in this call (stopped on the device at their own step; the others went on)."""
        nsteps = int(nsteps)
        self._call_end = self.steps_done + nsteps
        failed, self._pending = dict(self._pending), {}
        if nsteps <= 0 or not self.active.any():
            return failed
        if self.multistep:
            self._advance_multistep(nsteps, failed)
        else:
            self._advance_per_phase(nsteps, failed)
        self._settle()
        self._half_kick()
        self._collect(self._read_status_now(), failed)
        return failed

    def _advance_multistep(self, nsteps: int, failed: dict) -> None:
        remaining, first = nsteps, 1
        prof = self.profile is not None
        while remaining > 0:
            t0 = time.perf_counter()
            self._exit_thr = 1.0 if self.lists is None else self.lists.exit_threshold()
            self._run_steps(remaining, first, self.steps_done)
            self.launches += 1
            first = 0
            h = self._read_status_now()
            if prof:
                self.profile["run_steps"] = self.profile.get("run_steps", 0.0) + 1e3 * (time.perf_counter() - t0)
            done = int(h[K.S_RUN_DONE])
            if done % 2 == 1:
                self.f_cur, self.f_nxt = self.f_nxt, self.f_cur
            self.steps_done += done
            remaining -= done
            self._collect(h, failed)
            if h[K.S_RUN_REBUILD] > 0 and remaining > 0:
                # this step has drifted: rebuild (or, below L_v/2, signal the pipelined CPU build), then
                # its forces complete it
                t0 = time.perf_counter()
                if self.lists is not None and max(h[K.S_D2], h[K.S_D2B]) <= 1.0:
                    self.lists.signal()
                else:
                    self._rebuild()
                self._forces(self.steps_done)
                self.f_cur, self.f_nxt = self.f_nxt, self.f_cur
                self.steps_done += 1
                remaining -= 1
                if prof:
                    self.stream.synchronize()
                    self.profile["rebuild"] = self.profile.get("rebuild", 0.0) + 1e3 * (time.perf_counter() - t0)
            if not self.active.any():
                self.steps_done += remaining
                return

    def _advance_per_phase(self, nsteps: int, failed: dict) -> None:
        s = self.stream
        rebuilt_prev = False
        prev = None  # slot of the previous step's status copy
        for st in range(nsteps):
            step = self.steps_done
            prof = self.profile is not None
            if prof:
                e0 = self._ev(); e0.record(s)
            self._kick_drift(1 if st == 0 else 0, step)
            if prof:
                e1 = self._ev(); e1.record(s)
            slot = st % 2
            self.status.copy_to_host(self.status_h[slot], stream=s)
            self.events[slot].record(s)
            # decide the rebuild from the previous step's status (already on the host, no GPU stall);
            # displacements and speeds are normalised by each scene's L_v/2
            if prev is None:
                # first step of the call: this step's displacement is known exactly
                self._wait_event(self.events[slot])
                h = self.status_h[slot]
                rebuild = math.sqrt(h[K.S_D2]) > 1.0
            else:
                self._wait_event(self.events[prev])
                h = self.status_h[prev]
                if not rebuilt_prev and math.sqrt(h[K.S_D2]) > 1.0:
                    self.late_rebuilds += 1
                d_prev = 0.0 if rebuilt_prev else math.sqrt(h[K.S_D2])
                rebuild = d_prev + math.sqrt(h[K.S_V2]) > 1.0
            self._collect(h, failed)
            if prof:
                e2 = self._ev(); e2.record(s)
            if rebuild:
                self._rebuild()
            elif self.lists is not None and self.lists.exit_threshold() < 1.0 and math.sqrt(h[K.S_D2]) > 0.5:
                self.lists.signal()  # L_v/4 passed (paper 004 B3): the pipelined CPU build starts
            rebuilt_prev = rebuild
            if prof:
                e3 = self._ev(); e3.record(s)
            self._forces(step)
            self.launches += 2
            self.f_cur, self.f_nxt = self.f_nxt, self.f_cur
            if prof:
                e4 = self._ev(); e4.record(s)
                self._prof_events.append((e0, e1, e2, e3, e4))
            prev = slot
            self.steps_done += 1
        h = self._read_status_now()
        if not rebuilt_prev and math.sqrt(h[K.S_D2]) > 1.0:
            self.late_rebuilds += 1
        if self.profile is not None:
            for e0, e1, e2, e3, e4 in self._prof_events:
                for name, a, b in (("kick_drift", e0, e1), ("status_copy", e1, e2), ("rebuild", e2, e3),
                                   ("forces", e3, e4)):
                    self.profile[name] = self.profile.get(name, 0.0) + cuda.event_elapsed_time(a, b)
            self._prof_events = []

    def _ev(self):
        return cuda.event(timing=True) if not SIM else cuda.event()

    def _read_status_now(self) -> np.ndarray:
        h = self.status_h[0]
        self.status.copy_to_host(h, stream=self.stream)
        self._wait_stream()
        return h

    def _wait_stream(self) -> None:
        """Wait for the stream by polling an event with short sleeps, which release the GIL, so that the result
        files' I/O thread (engine/h5md.py) works while the GPU does (a blocking synchronize may hold it)."""
        if SIM:
            self.stream.synchronize()
            return
        if getattr(self, "_poll_ev", None) is None:
            self._poll_ev = cuda.event(timing=False)
        self._poll_ev.record(self.stream)
        idle = self.idle
        while not self._poll_ev.query():
            if idle is None or not idle():
                time.sleep(2e-5)

    def _wait_event(self, ev) -> None:
        """``ev.synchronize()``, running the driver's idle work while the GPU has not reached ``ev``."""
        idle = self.idle
        if idle is not None and not SIM:
            while idle() and not ev.query():    # no driver call when there is no work
                pass
        ev.synchronize()

    def _collect(self, h, failed: dict | None = None) -> dict:
        """Scenes that blew up according to status h (once each): deactivated, error recorded."""
        failed = {} if failed is None else failed
        ss = h[K.SS0:].reshape(self.n_scenes, K.NSS)  # checked vectorised: this runs every step
        hit = self.active & ((ss[:, K.SS_BAD_ID] < np.inf) | (ss[:, K.SS_OVL_ID] < np.inf))
        for s in np.nonzero(hit)[0]:
            b = K.SS0 + K.NSS * s
            info = SimpleNamespace(dt=self.spd_h[s, K.D_DT], overlap_limit=self.spf_h[s, K.F_OVL])
            err = None
            if h[b + K.SS_BAD_ID] < np.inf:
                err = _instability(BAD_VALUE, int(h[b + K.SS_BAD_STEP]),
                                   int(h[b + K.SS_BAD_ID]) - int(self.starts[s]), 0.0, info)
            elif h[b + K.SS_OVL_ID] < np.inf:
                err = _instability(OVERLAP, int(h[b + K.SS_OVL_STEP]), int(h[b + K.SS_OVL_ID]) - int(self.starts[s]),
                                   float(h[b + K.SS_OVL]), info)
            if err is not None:
                self.active[s] = False
                self.spi_h[s, K.I_ACTIVE] = 0
                failed[int(s)] = err
        return failed

    # ---- host copies (output steps only) -----------------------------------------------------------

    #: the observe kernel's sums per scene (the shape's NOBS)
    _NOBS = SC.NOBS

    def _observe_args(self) -> tuple:
        """observe(pos, vel, spin, quat, rad, mass, inertia, nbr, nn, hist, spd, spf, spi, ext) (cuda_loop)."""
        return (self.pos, self.vel, self.omega, self.quat, self.radius1, self.mass1, self.inertia1, self.nbr,
                self.nn, self.hist, self.spd, self.spf, self.spi, self._step_arrays()[3])

    def _observe_sums(self) -> np.ndarray:
        """The observe kernel's per-scene sums (K, _NOBS) on the host, now (a copy)."""
        return self._observe_async().settle()

    def _observe_async(self) -> "_LateSums":
        """Queue the observe kernel's per-scene sums (K, _NOBS) on the stream (issue 14): one zeroing copy, one
        launch with one block row per scene, one copy of K x _NOBS float64 into a pinned result slot, an event.
        Nothing waits: the sums are those of the state at this point of the stream, whatever the GPU does next,
        and :meth:`_LateSums.settle` reads them. Two result slots; reusing one settles its earlier sums first."""
        s, nk = self.stream, self.n_scenes
        if getattr(self, "_acc", None) is None:
            if SIM:   # the simulator has no memset on a stream: zeros are copied in
                self._acc_zero = np.zeros((nk, self._NOBS), np.float64)
            self._acc = cuda.device_array((nk, self._NOBS), np.float64, stream=s)
            self._late = [None, None]
            self._late_h = [cuda.pinned_array((nk, self._NOBS), np.float64) for _ in range(2)]
            self._late_ev = [(cuda.event() if SIM else cuda.event(timing=False)) for _ in range(2)]
            self._late_next = 0
        k = self._late_next
        self._late_next = 1 - k
        if self._late[k] is not None:
            self._late[k].settle()
        if SIM:
            self._acc.copy_to_device(self._acc_zero, stream=s)
        else:
            device_memset(self._acc, 0, self._acc.nbytes, stream=s)   # all-zero bits: 0.0
        per_scene = (int(self.sizes.max()) + self.tpb - 1) // self.tpb
        bx = max(1, min(per_scene, max(1, self.max_blocks // nk)))
        # through the launch cache: numba-cuda's own argument handling of this 15-argument launch cost about
        # 0.8 ms of host time per stop on the H200 host, while the GPU waited for the next round
        self._lc.launch("observe", self.k["observe"], ((bx, nk), self.tpb, s), (*self._observe_args(), self._acc))
        self._acc.copy_to_host(self._late_h[k], stream=s)
        self._late_ev[k].record(s)
        self._late[k] = late = _LateSums(self._late_h[k], self._late_ev[k])
        return late

    def observe(self) -> list:
        """Per scene: the observables of :meth:`CudaBackend.observe` (:meth:`_observables`), None for an
        inactive scene."""
        f = self.observe_later()
        return [f(s) if self.active[s] else None for s in range(self.n_scenes)]

    def observe_later(self) -> Callable[[int], dict]:
        """:meth:`observe` read later: the sums are queued now (:meth:`_observe_async`); f(s) waits for them if they
        have not landed yet and builds scene s's observables (engine/simulate.py calls it in the GPU's next
        steps)."""
        late = self._observe_async()
        return lambda s: self._observables(s, late.settle()[s].tolist())

    def _observables(self, s: int, r: list) -> dict:
        """Scene s's observables from its observe sums r (engine/shapes/sphere/device.py: observe_one)."""
        return {"kinetic_energy_translational": r[0], "kinetic_energy_rotational": r[1],
                "contacts": int(round(r[2])) // 2, "elastic_energy": r[3],
                "max_overlap": r[SC.O_MAX], "momentum": (r[4], r[5], r[6]),
                "collisions": int(round(r[SC.O_COLL])) // 2,
                **sonine_sums(r[SC.O_TR2], r[SC.O_ROT2], r[SC.O_X], DOF_ROTATION_SPHERE)}

    #: state() keys and the device arrays (3 or 4 rows, particle index fastest) they are copied from
    _STATE = (("position", "pos"), ("velocity", "vel"), ("angular_velocity", "omega"), ("orientation", "quat"))
    #: state(k, reuse=...) hands out reused host buffers (engine/simulate.py keeps two slots for snapshot frames
    #: and reuses a slot only after the I/O thread has written its frame)
    reuses_state_buffers = True

    def _scene_rows(self, k: int, reuse=False) -> dict:
        """Scene k's state arrays (n_k, rows) in particle-id order, keyed as in ``_STATE`` (issue 14): per array
        a kernel gathers the scene's slots into id order on the device, into one reused staging buffer, and
        one copy moves exactly those n_k rows into a reused host buffer (:meth:`_host_slot`); one sync for all.
        ``reuse``: False returns copies; True or a buffer slot number returns views of that slot's host
        buffers (slot 0 for True), valid until the next call with the same slot."""
        s = self.stream
        a0, n_k = int(self.starts[k]), int(self.sizes[k])
        nmax = int(self.sizes.max())
        if getattr(self, "_stage", None) is None:
            self._stage = {np.dtype(t).str: cuda.device_array(max(1, 4 * nmax), t, stream=s)
                           for t in {self.dtype, self.pos_dtype}}
            self._stage_h = {}
        slot = 0 if reuse is False or reuse is True else int(reuse)
        bufs = self._host_slot(slot, nmax)
        out = {}
        for key, name in self._STATE:
            src = getattr(self, name)
            rows = src.shape[0]
            host = bufs[key][:n_k]
            if n_k:
                dst = self._stage[src.dtype.str][:n_k * rows].reshape(n_k, rows)
                K.gather_scene[self._grid(n_k)](src, self.ids, a0, n_k, dst)
                dst.copy_to_host(host, stream=s)
            out[key] = host
        s.synchronize()
        return out if reuse is not False else {key: a.copy() for key, a in out.items()}

    def _host_slot(self, slot: int, nmax: int) -> dict:
        """The host buffers {key: (nmax, rows)} of a state buffer slot (:meth:`_scene_rows`).

        Pinned at once when small (an ensemble of small scenes). Larger ones are plain memory, faulted in by
        threads (:func:`_touched_empty`) and then page-locked in place (:func:`_page_locked`): allocating pinned
        memory of that size costs more than a pageable copy of a few frames (218 MB, one 2M-sphere frame, on an
        H200 host: 0.07-0.28 s to allocate pinned, 0.03-0.06 s to copy into fresh pageable memory), registering
        touched pages does not (6-11 ms on an H100 host, bench/host_memory.py; a copy then takes 4 ms against
        16-23 ms pageable). Where they cannot be registered (the simulator; a driver that refuses) they stay
        pageable, and once the ensemble has taken PIN_AFTER_FRAMES large frames a thread allocates pinned buffers
        for those of them used so far while the run goes on; each changes over when it is next used (the caller's
        earlier frame from it is in the file by then)."""
        shapes = self._slot_shapes(nmax)
        big = _big_slot(shapes)
        pinned = getattr(self, "_pinned_slots", None)
        if big and pinned is not None and pinned.get(slot) is not None:
            self._stage_h[slot] = pinned.pop(slot)
        elif slot not in self._stage_h:
            prep, self._slot_prep = getattr(self, "_slot_prep", None), None
            made = {}
            if prep is not None and big and prep[2] == shapes:     # made on a thread during the build
                prep[0].join()
                made = prep[1]
            alloc = _touched_empty if big else cuda.pinned_array
            self._stage_h[slot] = bufs = made.get("bufs") or {key: alloc(sh, t) for key, (sh, t) in shapes.items()}
            if big:
                pins = made.get("pins") if "bufs" in made else _page_locked(bufs.values())
                if pins is None:
                    self._pageable_slots = getattr(self, "_pageable_slots", set()) | {slot}
                else:
                    self._page_locks = getattr(self, "_page_locks", []) + [pins]   # the registrations' lifetime
        self._frames_taken = getattr(self, "_frames_taken", 0) + 1
        pageable = getattr(self, "_pageable_slots", set())
        if big and pinned is None and self._frames_taken >= PIN_AFTER_FRAMES and pageable:
            self._pinned_slots = pinned = {}
            slots = sorted(pageable)

            def pin() -> None:
                try:
                    for k in slots:
                        pinned[k] = {key: cuda.pinned_array(sh, t) for key, (sh, t) in shapes.items()}
                except Exception:  # noqa: BLE001  (no pinned memory to be had: the pageable buffers stay)
                    pass

            threading.Thread(target=pin, name="demq-pin-frames", daemon=True).start()
        return self._stage_h[slot]

    def _slot_shapes(self, nmax: int) -> dict:
        """{key: ((nmax, rows), dtype)} of a frame slot's host buffers (:meth:`_host_slot`)."""
        return {key: ((nmax, getattr(self, name).shape[0]), getattr(self, name).dtype) for key, name in self._STATE}

    def _prepare_frame_slot(self) -> None:
        """A large scene's first frame slot, made on a thread while the build goes on (its state arrays exist): the
        buffers faulted in and page-locked as :meth:`_host_slot` makes them (about 30 ms for 2M spheres, which the
        first snapshot waited for), taken by the first :meth:`_host_slot` call (which waits for the thread)."""
        shapes = self._slot_shapes(int(self.sizes.max()))
        if SIM or not _big_slot(shapes):
            return
        made: dict = {}

        def work() -> None:
            bufs = {key: _touched_empty(sh, t) for key, (sh, t) in shapes.items()}
            made["pins"] = _page_locked(bufs.values())
            made["bufs"] = bufs

        t = threading.Thread(target=work, name="demq-frame-slot", daemon=True)
        t.start()
        self._slot_prep = (t, made, shapes)

    def state(self, k: int, reuse=False) -> dict:
        """Host copies of scene k's state arrays in particle-id order (``reuse``: see :meth:`_scene_rows`)."""
        return self._scene_rows(k, reuse)

    def contacts(self, k: int):
        """(pairs (M,2) int64 ids, history (M,HW)) of scene k's list slots in contact (previous overlap
        > 0), ordered like the CPU backend's (by particle id, then list slot)."""
        nbr, nn, hist = (a.copy_to_host(stream=self.stream) for a in (self.nbr, self.nn, self.hist))
        ids = self.ids.copy_to_host(stream=self.stream)
        self.stream.synchronize()
        a0, n_k = int(self.starts[k]), int(self.sizes[k])
        sl = slice(a0, a0 + n_k)
        nbr, nn, hist, ids_k = nbr[:, sl], nn[sl], hist[:, :, sl], ids[sl]
        m = nbr.shape[0]
        slot = np.arange(m)[:, None] < np.minimum(nn, m)[None, :]
        kk, ii = np.nonzero(slot & (hist[3] > 0))
        order = np.lexsort((kk, ids_k[ii]))
        kk, ii = kk[order], ii[order]
        pairs = np.stack([ids_k[ii] - a0, ids[nbr[kk, ii]] - a0], axis=1).astype(np.int64)
        springs = np.ascontiguousarray(hist[:, kk, ii].T).astype(self.dtype)
        return pairs, springs

    # ---- introspection (bench) ----------------------------------------------------------------------

    def device_bytes(self) -> int:
        """Bytes of device memory this backend holds (all arrays)."""
        views = set(self._view_names)
        return sum(v.nbytes for name, v in vars(self).items() if name not in views and _is_dev(v)
                   and not (name == "f_nxt" and v is self.f_cur))


def _big_slot(shapes: dict) -> bool:
    """Whether a frame slot of these host buffers is large (over PINNED_SLOT_BYTES: not pinned-allocated)."""
    return sum(int(np.prod(sh)) * np.dtype(t).itemsize for sh, t in shapes.values()) > PINNED_SLOT_BYTES


def _page_locked(arrays) -> Optional[list]:
    """Page-lock host arrays in place (cuMemHostRegister, through numba-cuda's Context.mempin): copies to and from
    them run at pinned speed and asynchronously. The returned handles keep the registration until they are
    collected, and keep their arrays alive. None under the simulator or when the driver refuses (the arrays stay
    pageable)."""
    if SIM:
        return None
    try:
        ctx = cuda.current_context()
        return [ctx.mempin(a, a.ctypes.data, a.nbytes, mapped=False) for a in arrays]
    except Exception:  # noqa: BLE001  (no page-locked memory to be had: pageable copies, as before)
        return None


def _touched_empty(shape, dtype) -> np.ndarray:
    """np.empty(shape, dtype) with every page already faulted in, in pieces on up to 8 threads (engine/pieces.py):
    a device copy into fresh pageable memory takes its page faults one at a time (218 MB: 0.06-0.08 s on the H200
    host, 0.02 s into touched memory)."""
    a = np.empty(shape, dtype)
    page = max(1, 4096 // a.itemsize)
    map_pieces(a, lambda p: p.__setitem__(slice(None, None, page), 0))
    return a


class _LateSums:
    """Observe sums on their way to a pinned host slot (:meth:`CudaEnsemble._observe_async`)."""

    __slots__ = ("buf", "ev", "a")

    def __init__(self, buf, ev):
        self.buf, self.ev, self.a = buf, ev, None

    def settle(self) -> np.ndarray:
        """The sums (K, NOBS), once they have landed (a copy: the slot is reused)."""
        if self.a is None:
            self.ev.synchronize()
            self.a = self.buf.copy()
        return self.a


class CudaBackend:
    """One scene on the GPU (K = 1 of :class:`CudaEnsemble`), with the CPU backend's interface."""

    name = "cuda"
    #: the ensemble class whose one scene this backend is (the ellipsoid backend sets its own)
    ensemble_class = CudaEnsemble

    def __init__(self, system: SphereSystem, contact: ContactParams):
        self.e = self.ensemble_class([system], [contact])
        self.n = system.n
        self.box = float(system.box_length)
        self.device = self.e.device
        self.set_contact(contact)
        if self.ensemble_class is CudaEnsemble:  # spheres: the list may be built on the CPU (paper 004 §3)
            self.e.set_list_mode(contact.list_mode)
        if self.e._pending:
            raise self.e._pending[0]

    def __getattr__(self, attr):  # builds, late_rebuilds, max_nb, profile, launches, dtype, ...
        return getattr(self.__dict__["e"], attr)

    def __setattr__(self, attr, value):
        if attr in ("profile", "idle"):   # the ensemble's phase timing and its hook for the driver's waits
            setattr(self.e, attr, value)
        else:
            object.__setattr__(self, attr, value)

    def set_contact(self, contact: ContactParams) -> None:
        self.contact = contact
        self.dt = contact.dt
        self.overlap_limit = float(contact.overlap_limit)
        self.e.set_contact(0, contact)

    def warmup(self) -> None:
        self.e.warmup()

    def advance(self, nsteps: int) -> None:
        """Advance nsteps steps; raises InstabilityError naming the step, the particle and the cause."""
        failed = self.e.advance(nsteps)
        if failed:
            err = failed[0]
            self.e.steps_done = err.step if isinstance(err, InstabilityError) and err.step is not None \
                else self.e.steps_done
            raise err

    @property
    def steps_done(self) -> int:
        return self.e.steps_done

    def observe(self) -> dict:
        return self.e.observe()[0]

    #: state(reuse=...) hands out reused host buffers (CudaEnsemble._scene_rows)
    reuses_state_buffers = True

    def observe_later(self) -> Callable[[], dict]:
        """:meth:`observe`, read when the returned function is called (:meth:`CudaEnsemble.observe_later`)."""
        f = self.e.observe_later()
        return lambda: f(0)

    def state(self, reuse=False) -> dict:
        return self.e.state(0, reuse)

    def contacts(self):
        return self.e.contacts(0)

    def device_bytes(self) -> int:
        return self.e.device_bytes()


def _is_dev(a) -> bool:
    return cuda.is_cuda_array(a) and not isinstance(a, np.ndarray)
