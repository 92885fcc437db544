"""The CUDA ensemble base: K independent scenes of one shape stored back to back on the GPU and advanced with the
same kernel launches, the state resident on the device.

:class:`CudaEnsembleBase` holds what every shape shares: the per-scene constant tables (box, contact constants, dt,
skin, cell grid), the scene index per particle, the status words and the host-side bookkeeping, and it is made of
parts by responsibility, each in its own module:

- :class:`~engine.loops.cuda_rebuild.ListBuilds`: cells, permutation, Verlet list, compact history store, multigrid;
- :class:`~engine.loops.cuda_stepping.TimeLoop`: the kick-drift / forces / half-kick launches, the two time loops,
  the waits for the GPU, instability reports;
- :class:`~engine.loops.cuda_records.ObserveSums`: the observe kernel's per-scene sums (records);
- :class:`~engine.loops.cuda_frames.StateFrames`: host copies of a scene's state (snapshots, checkpoints).

A shape's subclass (engine/shapes/<pkg>/cuda_backend.py) allocates its state and names its arrays for the kernels:
the abstract hooks below (``_upload_particles``, ``_scene_constants``, ``_views``, ``_permuted_arrays``,
``_permuted_i64``, ``state_arrays``, ``_specialise``, ``_prime``, ``_step_arrays``, ``_observe_args``,
``_observables``). The kernels are the one CUDA time loop (engine/loops/cuda_loop.py) specialised by the shape's
device functions, and the list kernels of engine/loops/cuda_kernels.py and cuda_lists.py; all call the same njit
physics as the CPU backend.

Step (velocity Verlet, closing and opening half kicks fused as on the CPU):
  1. kick + drift with periodic wrap + orientation; the largest displacement since the list build and
     the largest speed, each normalised by the scene's L_v/2, folded into a device ``status``;
  2. rebuild (rare) when some particle has moved more than L_v/2;
  3. forces over the full list: one thread per particle, each writes only its own force, torque and slots.
For a shape that declares its pair evaluator ``FUSABLE`` (smooth spheres), the per-phase loop runs 3 and the next
step's 1 in one launch (cuda_loop ``forces_kick_drift``; the shape's :meth:`_fused_out` / :meth:`_swap_fused`
hold the other halves of the double-buffered positions and velocities).

:class:`CudaSceneBackend` is one scene (K = 1) behind the single :class:`~engine.backends.protocol.Backend`
interface, for code that drives one backend by hand (tests, bench).
"""

from __future__ import annotations

import abc
from typing import Optional

import numpy as np
from numba import cuda

from engine.backends.protocol import Backend, Ensemble
from engine.errors import BackendUnavailable, InstabilityError
from engine.loops import cuda_kernels as K
from engine.loops.cuda_cache import SIM
from engine.loops.cuda_frames import StateFrames
from engine.loops.cuda_launch import LaunchCache
from engine.loops.cuda_memory import device_zeros, xref_dtype, xref_margin
from engine.loops.cuda_records import ObserveSums
from engine.loops.cuda_rebuild import ListBuilds
from engine.loops.cuda_stepping import TimeLoop
from engine.loops.system import ContactParams, cell_grid, ensemble_many_steps_loop
from engine.numba_support.numba_internals import device_memset
from engine.setup.precision import check_shape, position_dtype, state_dtype

#: None: the loop by size and density (engine.loops.system.many_steps_loop); True / False forces the many-steps or
#: the per-phase loop (tests and bench set it, for comparisons)
MULTISTEP = None

#: threads per block of the ensemble's launches
TPB = 32 if SIM else 256


class CudaEnsembleBase(TimeLoop, ListBuilds, ObserveSums, StateFrames, Ensemble):
    """K scenes of one shape advanced together on the GPU; see the module docstring.

    All scenes share the precision; everything else (N, box, contact constants, dt, skin, rough or
    smooth, Coulomb, orientation) is per scene. ``advance`` returns the scenes that blew up in the call
    (each stopped at its own step, the others advanced fully); ``deactivate`` drops a scene.
    """

    name = "cuda"
    #: the particle shape (engine/shapes/SHAPES key) whose CUDA parts specialise the time loop (set by the subclass)
    shape: str
    #: the Ensemble interface's capabilities: one observe launch serves every scene; all scenes advance together
    shares_observation = True
    #: the Verlet list of a lone scene may be built on the host (cuda_listmodes.HostLists; spheres)
    host_lists = False
    #: widths of the per-scene constant tables (a subclass may append columns)
    _ND, _NF = K.ND, K.NF
    #: history words per list slot (a shape whose pair law keeps more sets its own before the lists exist)
    hist_words = K.HW
    #: 1-D views of other device arrays (not counted by device_bytes)
    _view_names: tuple = ()
    #: the observe kernel's sums per scene (the shape's NOBS)
    _NOBS: int

    def __init__(self, systems: list, contacts: list, reads_state: bool = True, orientations: bool = True):
        """``reads_state``: whether the driver will copy scenes' state to the host (snapshots, checkpoints); a large
        scene's first host frame slot is then made on a thread during the build (:meth:`_prepare_frame_slot`).
        ``orientations`` False: no scene wants its particles' orientations (spheres only: the shape decides)."""
        self.reads_state = reads_state
        self.orientations_wanted = orientations
        if not SIM and not cuda.is_available():
            raise BackendUnavailable("backend = 'cuda' but no CUDA GPU is available here")
        if len(systems) != len(contacts) or not systems:
            raise ValueError("CudaEnsemble needs one ContactParams per scene and at least one scene")
        precisions = {c.precision for c in contacts}
        if len(precisions) != 1:
            raise ValueError(f"all scenes of an ensemble share one precision, got {sorted(precisions)}")
        check_shape(contacts[0].precision, self.shape)
        self._init_host(systems, contacts)
        self._init_frames()
        self._init_observe()
        self._upload_particles(systems)
        if self._slot_prep is None and reads_state:
            self._prepare_frame_slot()
        self._views()
        self._init_scratch()
        self._init_tables(systems, contacts)
        self._alloc_list()
        for s, c in enumerate(contacts):
            self._set_scene_contact(s, c)
        self._upload_params()
        self._specialise()
        self._prime(systems)

    def _init_host(self, systems: list, contacts: list) -> None:
        """Sizes, launch geometry, counters and the host-side state of the run."""
        self.dtype = state_dtype(contacts[0].precision)
        self.pos_dtype = position_dtype(contacts[0].precision)  # float64 in 'mixed' (engine/setup/precision.py)
        self.n_scenes = nk = len(systems)
        self.sizes = np.array([s.n for s in systems], np.int64)
        self.starts = np.concatenate([[0], np.cumsum(self.sizes)[:-1]]).astype(np.int64)
        self.n = n = int(self.sizes.sum())
        self.device = "CUDA simulator" if SIM else cuda.get_current_device().name
        if isinstance(self.device, bytes):
            self.device = self.device.decode()
        self.tpb = TPB
        self.sm_count = 1 if SIM else cuda.get_current_device().MULTIPROCESSOR_COUNT
        self.max_blocks = 2 if SIM else self.sm_count * 16
        self.multistep = ensemble_many_steps_loop(systems) if MULTISTEP is None else MULTISTEP
        self._exit_thr = 1.0  # run_steps exits when (displacement / (L_v/2))^2 exceeds it
        self._horizon: Optional[int] = None     # the driver's plan: the run ends about here (plan())
        self._call_end: Optional[int] = None    # the current advance call ends here
        self._status_copiers = None             # per pinned status slot: copy + event record (TimeLoop._status_copy)
        self._status_waits = None               # per pinned status slot: the wait for its event (TimeLoop._wait_status)
        self._carry = None                      # (step, builds, bound, speed) at the last per-phase call's end
        self._last_kick = None                  # what _close_call reads of that call's last kick-drift
        self._open = False                      # velocities half a step behind the positions (TimeLoop._close)
        self._lc = LaunchCache()                # the per-step kernels' launches (engine/loops/cuda_launch.py)
        self._orient = True                     # the compiled specialisation tracks orientations
        self.lists = None                       # host-built Verlet lists (set_list_mode), None: built on the GPU
        self.kl = None                          # the multigrid / host-list kernels, where used
        self._coop_blocks = None                # blocks of the cooperative launch (made at its first use)
        self._pending: dict = {}                # scenes that failed at t = 0, reported by the first advance
        self.stream = cuda.stream()
        self.steps_done = 0
        self.builds = 0
        self.sorts = 0                          # the rebuilds that permuted the particles (cuda_rebuild)
        self._builds_since_sort = None
        self.late_rebuilds = 0
        self.launches = 0
        self._prof_events = []
        self.profile = None  # set to {} to time the phases with CUDA events
        self.active = np.ones(nk, bool)
        self.contact = list(contacts)
        self.box = np.array([float(s.box_length) for s in systems])
        self.x_ref = None           # made after the state (_init_scratch): a start drawn on the device peaks before
        self.ids = cuda.device_array(n, np.int32, stream=self.stream)
        self.sc = cuda.device_array(n if nk > 1 else 1, np.int32, stream=self.stream)   # (cuda_kernels.scene_of)
        if n:
            K.slot_ids_and_scenes[self._grid(n)](cuda.to_device(np.cumsum(self.sizes), stream=self.stream), self.ids,
                                                 self.sc)

    def _init_scratch(self) -> None:
        """The compact store's index, the compact store and the status words. (The permutation's order and inverse
        lie in the torque or arrays of their own, its scratch rows and the cells' counts in the list's history, the
        compact store's index in the next force buffer: ListBuilds._perm_rows, _lent, _store_index.)"""
        n, nk = self.n, self.n_scenes
        xref = xref_dtype(self.pos_dtype, self.box, [float(c.skin) for c in self.contact])
        self.x_ref = cuda.device_array((3, n), xref, stream=self.stream)
        # per scene, x_ref's rounding bound in units of the rule's limit (_set_scene_contact); the largest is the
        # displacement the rule measures right after a build (TimeLoop's bound, _rebuilt_bound)
        self._xref_gaps = np.zeros(nk)
        self._rebuilt_bound = 0.0
        self._perm_own = None
        self._perm_views = {}
        self._init_store_index()
        # which particles' force buffers may hold something other than zero (cuda_loop SKIP_COLD)
        self.hot = cuda.device_array(n, np.uint8, stream=self.stream)
        self._forces_unknown()
        self._alloc_store(max(1024, n // 8))
        self.status = cuda.to_device(self._fresh_status(), stream=self.stream)
        # pinned status copies: the per-step slots 0 and 1 of the per-phase loop, and 2 for a wait-now read
        # (TimeLoop._read_status_now), which must not overwrite a step's status still to be read
        self.status_h = [cuda.pinned_array(K.status_len(nk), np.float64) for _ in range(3)]
        self.events = [(cuda.event() if SIM else cuda.event(timing=False)) for _ in range(3)]   # one per slot

    def _init_tables(self, systems: list, contacts: list) -> None:
        """The per-scene constant tables (spd: working precision, spf: float64, spi: int32) with the cell grids."""
        dt_, nk = self.dtype, self.n_scenes
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

    # ---- the shape's hooks ----------------------------------------------------------------------------

    @abc.abstractmethod
    def _upload_particles(self, systems) -> None:
        """The shape's state and per-particle constants on the device; sets ``uniform``, ``_rmax``, ``_scene0``,
        ``f_cur``/``f_nxt``, ``torque``, ``radius``, ``inv_m`` and ``_per_particle`` (the arrays permuted at a
        rebuild besides :meth:`_permuted_arrays`)."""

    @abc.abstractmethod
    def _scene_constants(self, s: int) -> None:
        """Scene s's particle constants in spd (used when its particles are uniform)."""

    @abc.abstractmethod
    def _views(self) -> None:
        """1-D views of the per-particle constants (``radius1``, ``inv_m1``, ...)."""

    @abc.abstractmethod
    def _permuted_arrays(self) -> tuple:
        """The device arrays permuted into cell order at a rebuild, besides the per-particle constants."""

    @abc.abstractmethod
    def _permuted_i64(self) -> tuple:
        """The int64 device arrays (N) permuted with them."""

    @abc.abstractmethod
    def state_arrays(self) -> dict:
        """{state key: device array (rows, N), particle index fastest} that :meth:`_scene_rows` copies out."""

    @abc.abstractmethod
    def _specialise(self) -> None:
        """Pick the kernels of the active scenes' contact laws (engine/loops/cuda_loop.kernels)."""

    @classmethod
    def prepare_kernels(cls, contacts: tuple) -> None:
        """Make the kernel sets that a lone one-size scene switches through with ``contacts`` (their dispatchers:
        nothing compiled or loaded), where the shape can say them without an ensemble; Python work that needs no
        CUDA context, which the GPU start-up thread does while the driver starts (engine/driver/startup.py)."""

    @abc.abstractmethod
    def _prime(self, systems) -> None:
        """First list build (restoring checkpointed springs) and forces at t = 0; sets ``_pending``."""

    @abc.abstractmethod
    def _step_arrays(self) -> tuple:
        """(spin, spin_inv, list radius, ext) of the time loop's kernels (engine/loops/cuda_loop.py)."""

    def _fused_out(self) -> tuple:
        """(pos_out, vel_out): the other halves of the double buffer that cuda_loop's
        ``forces_kick_drift`` writes; called only for a shape whose kernel set has it (``FUSABLE``)."""
        raise NotImplementedError(f"{type(self).__name__}: the shape's kernels have no fused step")

    def _swap_fused(self) -> None:
        """After a fused launch: the halves :meth:`_fused_out` returned become the current state arrays."""
        raise NotImplementedError(f"{type(self).__name__}: the shape's kernels have no fused step")

    def _multistep_out(self) -> tuple:
        """(pos_b, vel_b, spin_b): the other halves of the double buffer of cuda_loop's ``run_steps_fused``; called
        only for a shape whose kernel set has it (``MULTISTEP_FUSABLE``)."""
        raise NotImplementedError(f"{type(self).__name__}: the shape's kernels have no fused many-steps loop")

    def _swap_multistep(self) -> None:
        """After a fused many-steps launch that ended in the second halves: they become the current state."""
        raise NotImplementedError(f"{type(self).__name__}: the shape's kernels have no fused many-steps loop")

    @abc.abstractmethod
    def _observe_args(self) -> tuple:
        """observe(pos, vel, spin, quat, rad, mass, inertia, nbr, nn, hist, spd, spf, spi, ext) (cuda_loop)."""

    @abc.abstractmethod
    def _observables(self, s: int, r: list) -> dict:
        """Scene s's observables (the keys of the shape's CPU backend) from its observe sums r."""

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
        cost more than the upload itself."""
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

    def _forces_unknown(self) -> None:
        """Mark every particle's force and torque buffers as possibly not zero (``hot`` = 0xFF,
        engine/loops/cuda_loop.py ``SKIP_COLD``), after they were written outside the force passes or the kernels
        that write them changed (allocation, a rebuild's permutation, a new specialisation): the next two force
        passes store every particle's force and torque, every kick reads them."""
        if not self.n:
            return
        if SIM:
            self.hot.copy_to_device(np.full(self.n, 0xFF, np.uint8), stream=self.stream)
        else:
            device_memset(self.hot, 0xFF, self.stream)

    def _zeros(self, shape, dtype):
        """A device array of zeros on the ensemble's stream (:func:`cuda_memory.device_zeros`)."""
        return device_zeros(shape, dtype, self.stream)

    @staticmethod
    def _cat(arrays):
        """The scenes' arrays as (n_k, rows) float64, one after another (one scene's: not copied)."""
        parts = [np.asarray(a, np.float64).reshape(len(a), -1) for a in arrays]
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    def _fresh_status(self) -> np.ndarray:
        s = np.zeros(K.status_len(self.n_scenes), np.float64)
        for k in range(self.n_scenes):
            b = K.SS0 + K.NSS * k
            s[[b + K.SS_BAD_ID, b + K.SS_BAD_STEP, b + K.SS_OVL_ID, b + K.SS_OVL_STEP]] = np.inf
        return s

    def _grid(self, work: int) -> tuple:
        blocks = max(1, min(self.max_blocks, (work + self.tpb - 1) // self.tpb))
        return blocks, self.tpb, self.stream

    def _set_scene_contact(self, s: int, contact: ContactParams) -> None:
        c = self.dtype
        skin = c(contact.skin)
        # the Verlet rule's limit L_v / 2 less what x_ref's rounding may hide (cuda_memory.xref_margin)
        margin = xref_margin(self.box[s], self.x_ref.dtype, self.pos_dtype)
        lim = float(skin) * 0.5 - margin
        if not lim > 0.0:
            raise ValueError(f"verlet_skin = {float(skin):g} m is too small for the float32 list reference of a box "
                             f"of {self.box[s]:g} m: its rounding takes the whole Verlet limit L_v / 2")
        self._xref_gaps[s] = margin / lim
        self._rebuilt_bound = float(self._xref_gaps.max())
        self.contact[s] = contact
        dt = c(contact.dt)
        self.spd_h[s, [K.D_DT, K.D_HP, K.D_KN, K.D_GN, K.D_KT, K.D_SKIN]] = [
            dt, c(dt * c(0.5)), c(contact.k_n), c(contact.gamma_n_coef),
            c(0.0) if contact.k_t is None else c(contact.k_t), skin]
        # a scene without a Coulomb limit inside a Coulomb-compiled ensemble: mu = inf never caps
        self.spd_h[s, K.D_MU] = c(np.inf) if contact.friction is None else c(contact.friction)
        self.spf_h[s, [K.F_OVL, K.F_LIM2INV, K.F_V2F, K.F_KN, K.F_KT]] = [
            float(contact.overlap_limit), 1.0 / (lim * lim), (2.0 * float(dt) / lim) ** 2, float(c(contact.k_n)),
            0.0 if contact.k_t is None else float(c(contact.k_t))]
        self.spi_h[s, K.I_ORIENT] = 1 if contact.orientation else 0

    def _upload_params(self) -> None:
        self._carry = None      # dt, skin or contact changed: the next call measures its first step again
        self._observed_at = None    # the force pass's sums were of the old constants
        self.spd.copy_to_device(self.spd_h, stream=self.stream)
        self.spf.copy_to_device(self.spf_h, stream=self.stream)
        self.spi.copy_to_device(self.spi_h, stream=self.stream)

    # ---- the Ensemble interface ------------------------------------------------------------------------

    def set_contact(self, k: int, contact: ContactParams) -> None:
        """Switch scene k's contact constants (e.g. thermalisation -> cooling); keeps lists and springs."""
        self.set_contacts({k: contact})

    def set_contacts(self, contacts: dict) -> None:
        """:meth:`set_contact` for several scenes ({scene: contact}) with one upload of the constant tables (the
        driver sets every scene's contact before the first step: one upload instead of one per scene)."""
        for k, contact in contacts.items():
            if contact.precision != self.contact[k].precision:
                raise ValueError("the precision of a scene cannot change inside an ensemble")
        self._close()   # with the kernels of the constants that computed the forces it kicks with
        self._sync_active()
        for k, contact in contacts.items():
            self._set_scene_contact(k, contact)
        self._upload_params()
        self._specialise()
        self._forces_unknown()     # a smooth specialisation leaves the torque alone: stale where it turns rough

    def deactivate(self, k: int) -> None:
        """Scene k drops out (finished, cancelled or failed): it is never advanced again."""
        self.deactivate_many([k])

    def deactivate_many(self, ks) -> None:
        """Scenes ks drop out together: one device round trip for all (the scenes of a packed batch end in
        the same round; one by one, 256 of them took ~1 s of syncs and parameter uploads)."""
        self._close()   # before the flags stop the half kick (a finished scene's state is read after)
        self._sync_active()
        for k in ks:
            self.active[k] = False
            self.spi_h[k, K.I_ACTIVE] = 0
        self._upload_params()

    def start_alone(self, contact: ContactParams) -> None:
        """This ensemble is one scene of its own (a lone job, :class:`CudaBackend`): its Verlet list is built where
        ``contact.list_mode`` says (spheres; Skorych & Dosta 2022, §3), and a start that already fails at t = 0
        (overlapping particles) raises its InstabilityError now, as a CPU backend's constructor does."""
        if self.host_lists:
            self.set_list_mode(contact.list_mode)
        if self._pending:
            raise self._pending[0]

    def scene_info(self, k: int) -> dict:
        """Where scene k's Verlet lists were built, when on the host (Skorych & Dosta 2022, §3: final mode, stages,
        restarts, mean tau_CPU / tau_GPU / tau_exch per mode, q, G_max); {} for lists built on the GPU."""
        if self.lists is None:
            return {}
        summary = self.lists.summary()
        return {"list_mode": summary["final_mode"], "list_modes": summary}

    def _sync_active(self) -> None:
        """The device clears the active flag of a scene that blows up; bring the host copy up to date."""
        spi = self.spi.copy_to_host(stream=self.stream)
        self.stream.synchronize()
        self.spi_h[:, K.I_ACTIVE] = spi[:, K.I_ACTIVE]

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
        count, ids_k = np.diff(nn[a0:a0 + n_k + 1]), ids[sl]
        # the scene's rows lie back to back from its first particle's (cuda_kernels: the list's layout)
        ii = np.repeat(np.arange(n_k), count)             # the particle of each of the scene's slots
        q = (int(nn[a0]) if n_k else 0) + np.arange(len(ii))
        touching = hist[3, q] > 0
        ii, q = ii[touching], q[touching]
        order = np.lexsort((q, ids_k[ii]))                # by particle id, then list slot
        ii, q = ii[order], q[order]
        pairs = np.stack([ids_k[ii] - a0, ids[nbr[q]] - a0], axis=1).astype(np.int64)
        springs = np.ascontiguousarray(hist[:, q].T).astype(self.dtype)
        return pairs, springs

    # ---- introspection (bench) ----------------------------------------------------------------------

    def device_bytes(self) -> int:
        """Bytes of device memory this backend holds (all arrays)."""
        views = set(self._view_names)
        return sum(v.nbytes for name, v in vars(self).items() if name not in views and _is_dev(v)
                   and not (name == "f_nxt" and v is self.f_cur)) + sum(
            slot.acc.nbytes for slot in (self._sums, self._rows) if slot is not None)


def _is_dev(a) -> bool:
    return cuda.is_cuda_array(a) and not isinstance(a, np.ndarray)


class CudaSceneBackend(Backend):
    """One scene on the GPU (K = 1 of the shape's :class:`CudaEnsembleBase` subclass, ``ensemble_class``) with the
    single :class:`~engine.backends.protocol.Backend` interface, for code that drives one backend by hand (tests,
    bench). A job does not use it: its driver runs the ensemble itself (engine.backends.ensemble.make_ensemble).
    ``e`` is the one-scene ensemble; what else is read of it here is named below."""

    name = "cuda"
    #: the ensemble class whose one scene this backend is (the shape's subclass sets it)
    ensemble_class: type

    def __init__(self, system, contact: ContactParams):
        self.e = self.ensemble_class([system], [contact])
        self.n = system.n
        self.box = float(system.box_length)
        self.device = self.e.device
        self.e.start_alone(contact)
        self.contact = contact
        self.dt = contact.dt
        self.overlap_limit = float(contact.overlap_limit)

    # ---- the one-scene ensemble's counters and switches ---------------------------------------------

    @property
    def builds(self) -> int:
        return self.e.builds

    @property
    def late_rebuilds(self) -> int:
        return self.e.late_rebuilds

    @property
    def launches(self) -> int:
        return self.e.launches

    @property
    def list_slots(self) -> int:
        """The slots the Verlet list has room for (neighbour indices and their history, all particles' rows)."""
        return int(self.e.nbr.shape[0])

    @property
    def dtype(self):
        return self.e.dtype

    @property
    def steps_done(self) -> int:
        return self.e.steps_done

    @property
    def profile(self) -> Optional[dict]:
        """Phase timings with CUDA events (set to {} to collect them)."""
        return self.e.profile

    @profile.setter
    def profile(self, value: Optional[dict]) -> None:
        self.e.profile = value

    # ---- the Backend interface ------------------------------------------------------------------------

    def set_contact(self, contact: ContactParams) -> None:
        self.contact = contact
        self.dt = contact.dt
        self.overlap_limit = float(contact.overlap_limit)
        self.e.set_contact(0, contact)

    def warmup(self) -> None:
        self.e.warmup()

    def plan(self, steps: int) -> None:
        self.e.plan(steps)

    def advance(self, nsteps: int) -> None:
        """Advance nsteps steps; raises InstabilityError naming the step, the particle and the cause."""
        failed = self.e.advance(nsteps)
        if failed:
            err = failed[0]
            self.e.steps_done = err.step if isinstance(err, InstabilityError) and err.step is not None \
                else self.e.steps_done
            raise err

    def observe(self) -> dict:
        return self.e.observe()[0]

    def state(self, reuse=False) -> dict:
        return self.e.state(0, reuse)

    def contacts(self):
        return self.e.contacts(0)

    def list_info(self) -> dict:
        return self.e.scene_info(0)

    def device_bytes(self) -> int:
        return self.e.device_bytes()
