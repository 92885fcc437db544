"""CUDA backend: the whole time loop on the GPU with Numba CUDA, state resident on the device.

Same public interface and semantics as :class:`engine.backends.cpu.CpuBackend`; the kernels
(:mod:`engine.backends.cuda_kernels`) call the same njit physics functions.

Step (velocity Verlet, closing and opening half kicks fused as on the CPU):
  1. ``kick_drift``: kick (dt/2 on the first step of a call, else dt), drift with periodic wrap,
     orientation, and per-block maxima of |x - x_ref|^2 and |v|^2 folded into a device ``status``;
     an asynchronous copy of ``status`` to pinned host memory follows it in the stream.
  2. rebuild (rare) when the L_v/2 rule demands it: the host decides from the status of the
     *previous* step, which is already on the host while the GPU still runs that step's forces, so the
     time loop never waits for the GPU: it rebuilds at step s when
     sqrt(max disp^2(s-1)) + 2 max|v|(s-1) dt > L_v/2 (conservative: the true displacement at step s
     is at most disp(s-1) + |v(s)| dt). The true displacement of step s is still checked against L_v/2
     on the device and any miss is counted in ``late_rebuilds`` (expected 0).
     Rebuild = count particles per cell, scan, scatter, sort each cell by id, permute the particle
     arrays into that cell order (neighbours sit close in memory), build the full Verlet list into the
     second list buffer carrying the contact history of surviving pairs across the permutation, swap.
  3. ``forces`` over the full list: one thread per particle, each writes only its own force, torque
     and list slots; the previous forces stay in the other buffer for the predicted velocities.
A sync happens only at rebuilds (to check the list stride), at output calls and at the end of
``advance``.
"""

from __future__ import annotations

import math
import os

import numpy as np
from numba import cuda

from engine.backends.base import ContactParams, SphereSystem, cell_grid
from engine.backends import cuda_kernels as K
from engine.backends.cpu import BAD_VALUE, OVERLAP, _instability
from engine.errors import BackendUnavailable

SIM = os.environ.get("NUMBA_ENABLE_CUDASIM") == "1"


class CudaBackend:
    """The GPU time loop; see the module docstring."""

    name = "cuda"

    def __init__(self, system: SphereSystem, contact: ContactParams):
        if not SIM and not cuda.is_available():
            raise BackendUnavailable("backend = 'cuda' but no CUDA GPU is available here")
        self.dtype = np.float64 if contact.precision == "float64" else np.float32
        dt_ = self.dtype
        n = system.n
        self.n = n
        self.box = float(system.box_length)
        self.device = "CUDA simulator" if SIM else cuda.get_current_device().name
        if isinstance(self.device, bytes):
            self.device = self.device.decode()
        self.tpb = 32 if SIM else 256
        if SIM:
            self.max_blocks = 2
        else:
            self.max_blocks = cuda.get_current_device().MULTIPROCESSOR_COUNT * 16
        self.stream = cuda.stream()
        self.steps_done = 0
        self.builds = 0
        self.late_rebuilds = 0
        self._prof_events = []
        self.profile = None  # set to {} to time kick_drift / rebuild / forces with CUDA events
        rad = np.asarray(system.radius, np.float64)
        mass = np.asarray(system.mass, np.float64)
        inertia = np.asarray(system.inertia, np.float64)
        self.uniform = bool(n == 0 or (np.all(rad == rad[0]) and np.all(mass == mass[0])
                                       and np.all(inertia == inertia[0])))
        self._r0 = dt_(rad[0] if n else 0.0)
        self._m0 = dt_(mass[0] if n else 0.0)
        self._i0 = dt_(inertia[0] if n else 0.0)
        self._im0 = dt_((1.0 / mass.astype(dt_))[0] if n else 0.0)
        self._ii0 = dt_((1.0 / inertia.astype(dt_))[0] if n else 0.0)

        def up(a, rows):
            a = np.ascontiguousarray(np.asarray(a, dt_).reshape(n, rows).T)
            return cuda.to_device(a, stream=self.stream)

        self.pos = up(system.position, 3)
        self.vel = up(system.velocity, 3)
        self.omega = up(system.angular_velocity, 3)
        self.quat = up(system.orientation, 4)
        self.f_cur = cuda.to_device(np.zeros((3, n), dt_), stream=self.stream)
        self.f_nxt = cuda.device_array((3, n), dt_, stream=self.stream)
        self.torque = cuda.to_device(np.zeros((3, n), dt_), stream=self.stream)
        self.x_ref = cuda.device_array((3, n), dt_, stream=self.stream)
        self.ids = cuda.to_device(np.arange(n, dtype=np.int32), stream=self.stream)
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
        # scratch for permutations (4 rows covers the quaternion)
        self.scratch = cuda.device_array((4, n), dt_, stream=self.stream)
        self.scratch_i = cuda.device_array(n, np.int32, stream=self.stream)
        self.order = cuda.device_array(n, np.int32, stream=self.stream)
        self.inv_old = cuda.device_array(n, np.int32, stream=self.stream)
        self.status = cuda.to_device(self._fresh_status(), stream=self.stream)
        self.status_h = [cuda.pinned_array(K.S_LEN, np.float64) for _ in range(2)]
        self.events = [(cuda.event() if SIM else cuda.event(timing=False)) for _ in range(2)]
        self._status_valid = [False, False]
        self._setup_cells(float(np.max(rad)) if n else 0.0, contact.skin)
        self._alloc_lists(8)
        self.set_contact(contact)
        self._prime(system)

    # ---- set-up -----------------------------------------------------------------------------------

    @staticmethod
    def _fresh_status() -> np.ndarray:
        s = np.zeros(K.S_LEN, np.float64)
        s[[K.S_BAD_ID, K.S_BAD_STEP, K.S_OVL_ID, K.S_OVL_STEP]] = np.inf
        return s

    def _grid(self, work: int) -> tuple:
        blocks = max(1, min(self.max_blocks, (work + self.tpb - 1) // self.tpb))
        return blocks, self.tpb, self.stream

    def _setup_cells(self, rmax: float, skin: float) -> None:
        self.nc = nc = cell_grid(self.box, self.n, rmax, skin)
        self.inv_cell = nc / self.box
        self.ncell = nc**3
        self.count = cuda.device_array(self.ncell + 1, np.int32, stream=self.stream)
        self.cell_start = cuda.device_array(self.ncell + 1, np.int32, stream=self.stream)
        tile = self.tpb * 16
        nb = (self.ncell + 1 + tile - 1) // tile
        self._scan_tile = tile
        self._scan_nb = nb
        self.bsum = cuda.device_array(max(nb, 1), np.int32, stream=self.stream)
        self.bsum_scan = cuda.device_array(max(nb, 1), np.int32, stream=self.stream)
        self.bsum_tot = cuda.device_array(1, np.int32, stream=self.stream)

    def _alloc_lists(self, max_nb: int) -> None:
        n, dt_ = self.n, self.dtype
        self.max_nb = max_nb
        self.lists = []
        for _ in range(2):
            nbr = cuda.device_array((max_nb, n), np.int32, stream=self.stream)
            nn = cuda.to_device(np.zeros(n, np.int32), stream=self.stream)
            hist = cuda.device_array((K.HW, max_nb, n), dt_, stream=self.stream)
            self.lists.append([nbr, nn, hist])
        self.cur = 0

    def set_contact(self, contact: ContactParams) -> None:
        """Switch contact constants (e.g. thermalisation -> cooling); keeps lists and springs."""
        self.contact = contact
        c = self.dtype
        self.k_n = c(contact.k_n)
        self.gn_coef = c(contact.gamma_n_coef)
        self.k_t = c(0.0) if contact.k_t is None else c(contact.k_t)
        self.mu = c(0.0) if contact.friction is None else c(contact.friction)
        self.dt = c(contact.dt)
        self.skin = c(contact.skin)
        self.half = c(0.5)
        self.hp = c(self.dt * self.half)
        self.box_c = c(self.box)
        self.inv_box = c(1.0 / self.box)
        self.overlap_limit = float(contact.overlap_limit)
        self.rough = contact.k_t is not None
        self.k = K.kernels(c, self.rough, contact.friction is not None and self.rough,
                           bool(contact.orientation), self.uniform, self.tpb)

    # ---- neighbour list -----------------------------------------------------------------------------

    def _sort_and_permute(self) -> None:
        k, n, s = self.k, self.n, self.stream
        k["fill_i32"][self._grid(self.ncell + 1)](self.count, 0)
        k["count_cells"][self._grid(n)](n, self.pos, self.nc, self.inv_cell, self.count)
        # exclusive scan of ncell + 1 counts (the last is 0) -> cell_start, cell_start[ncell] = n
        m = self.ncell + 1
        k["tile_scan"][self._scan_nb, self.tpb, s](self.count, self.cell_start, m, self.bsum, 16)
        if self._scan_nb > 1:
            items = (self._scan_nb + self.tpb - 1) // self.tpb
            k["tile_scan"][1, self.tpb, s](self.bsum, self.bsum_scan, self._scan_nb, self.bsum_tot, items)
            k["add_offsets"][self._grid(m)](self.cell_start, m, self.bsum_scan, self._scan_tile)
        k["fill_i32"][self._grid(self.ncell + 1)](self.count, 0)
        k["scatter"][self._grid(n)](n, self.pos, self.nc, self.inv_cell, self.cell_start, self.count,
                                    self.order)
        k["sort_cells"][self._grid(self.ncell)](self.ncell, self.cell_start, self.order, self.ids)
        k["inverse_perm"][self._grid(n)](n, self.order, self.inv_old)
        # permute the particle arrays into cell order (forces too: the next force step reads them)
        for name in ["pos", "vel", "omega", "quat", "f_cur"] + self._per_particle:
            a = getattr(self, name)
            rows = a.shape[0]
            tmp = self.scratch[:rows]
            k["gather_rows"][self._grid(n)](n, a, tmp, self.order)
            _copy(a, tmp, s)
        k["gather_i32"][self._grid(n)](n, self.ids, self.scratch_i, self.order)
        _copy(self.ids, self.scratch_i, s)

    def _rebuild(self) -> None:
        """Sort, permute and build the list; grows the stride when a particle has more neighbours."""
        self._sort_and_permute()
        old = self.lists[self.cur]
        while True:
            new = self.lists[1 - self.cur]
            self.status[K.S_NEED_NB:K.S_NEED_NB + 1].copy_to_device(np.zeros(1), stream=self.stream)
            self.k["build"][self._grid(self.n)](
                self.n, self.pos, self.radius, self._r0, self.skin, self.box_c, self.inv_box, self.half,
                self.nc, self.inv_cell, self.cell_start, old[0], old[1], old[2], self.order, self.inv_old,
                new[0], new[1], new[2], self.x_ref, self.status)
            need = np.zeros(1)
            self.status[K.S_NEED_NB:K.S_NEED_NB + 1].copy_to_host(need, stream=self.stream)
            self.stream.synchronize()
            need = int(need[0])
            if need <= self.max_nb:
                break
            # grow the inactive buffer only; the old list is still needed for the carry-over
            max_nb = int(math.ceil((need + 2) / 4.0)) * 4
            self.max_nb = max_nb
            self.lists[1 - self.cur] = [cuda.device_array((max_nb, self.n), np.int32, stream=self.stream),
                                        cuda.to_device(np.zeros(self.n, np.int32), stream=self.stream),
                                        cuda.device_array((K.HW, max_nb, self.n), self.dtype,
                                                          stream=self.stream)]
        self.cur = 1 - self.cur
        if old[0].shape[0] != self.max_nb:  # keep both buffers the same stride
            self.lists[1 - self.cur] = [cuda.device_array((self.max_nb, self.n), np.int32, stream=self.stream),
                                        cuda.to_device(np.zeros(self.n, np.int32), stream=self.stream),
                                        cuda.device_array((K.HW, self.max_nb, self.n), self.dtype,
                                                          stream=self.stream)]
        self.builds += 1

    def _prime(self, system: SphereSystem) -> None:
        """First list build (restoring checkpointed springs) and forces at t = 0."""
        self._rebuild()
        if system.contact_pairs is not None and len(system.contact_pairs):
            self._restore_springs(np.asarray(system.contact_pairs, np.int64),
                                  np.asarray(system.contact_springs, np.float64))
        self._forces(step=0)
        self.f_cur, self.f_nxt = self.f_nxt, self.f_cur
        self._check(self._read_status_now())

    def _restore_springs(self, pairs, springs) -> None:
        nbr, nn, hist = (a.copy_to_host(stream=self.stream) for a in self.lists[self.cur])
        ids = self.ids.copy_to_host(stream=self.stream)
        self.stream.synchronize()
        slot_of = np.empty(self.n, np.int64)
        slot_of[ids] = np.arange(self.n)
        for p in range(pairs.shape[0]):
            i = slot_of[pairs[p, 0]]
            j = slot_of[pairs[p, 1]]
            for kk in range(min(nn[i], nbr.shape[0])):
                if nbr[kk, i] == j:
                    q = min(K.HW, springs.shape[1])
                    hist[0:q, kk, i] = springs[p, :q]
                    break
        self.lists[self.cur][2].copy_to_device(hist, stream=self.stream)

    def _forces(self, step: int) -> None:
        nbr, nn, hist = self.lists[self.cur]
        self.k["forces"][self._grid(self.n)](
            self.n, self.pos, self.vel, self.omega, self.radius, self.inv_m, self._r0, self._im0,
            self.f_cur, self.f_nxt, self.torque, nbr, nn, hist, self.ids, self.box_c, self.inv_box,
            self.half, self.hp, self.k_n, self.gn_coef, self.k_t, self.mu, self.dt, self.overlap_limit,
            self.status, step)

    # ---- time loop ---------------------------------------------------------------------------------

    def warmup(self) -> None:
        """Compile the kernels of the current specialisation without advancing (launches with n = 0)."""
        k, s, c = self.k, self.stream, self.dtype
        nbr, nn, hist = self.lists[self.cur]
        g = (1, self.tpb, s)
        k["kick_drift"][g](0, self.pos, self.vel, self.omega, self.quat, self.f_cur, self.torque,
                           self.inv_m, self.inv_i, self._im0, self._ii0, self.x_ref, self.ids, self.dt,
                           self.dt, self.box_c, self.inv_box, self.half, self.status, 0)
        k["forces"][g](0, self.pos, self.vel, self.omega, self.radius, self.inv_m, self._r0, self._im0,
                       self.f_cur, self.f_nxt, self.torque, nbr, nn, hist, self.ids, self.box_c,
                       self.inv_box, self.half, self.hp, self.k_n, self.gn_coef, self.k_t, self.mu,
                       self.dt, self.overlap_limit, self.status, 0)
        k["half_kick"][g](0, self.vel, self.omega, self.f_cur, self.torque, self.inv_m, self.inv_i,
                          self._im0, self._ii0, self.hp)
        k["observe"][g](0, self.pos, self.vel, self.omega, self.radius, self._r0, self.mass, self._m0,
                        self.inertia, self._i0, nbr, nn, hist, self.box_c, self.inv_box, self.half,
                        1.0, 1.0, cuda.device_array(8, np.float64, stream=s))
        # list kernels run once per build: compile them on a copy-free dry run
        k["build"][g](0, self.pos, self.radius, self._r0, self.skin, self.box_c, self.inv_box, self.half,
                      self.nc, self.inv_cell, self.cell_start, nbr, nn, hist, self.order, self.inv_old,
                      nbr, nn, hist, self.x_ref, cuda.device_array(K.S_LEN, np.float64, stream=s))
        s.synchronize()
        del c

    def advance(self, nsteps: int) -> None:
        """Advance nsteps steps; raises InstabilityError naming the step, the particle and the cause."""
        nsteps = int(nsteps)
        if nsteps <= 0:
            return
        k, s = self.k, self.stream
        limit = float(self.skin) * 0.5
        dtf = float(self.dt)
        rebuilt_prev = False
        prev = None  # slot of the previous step's status copy
        for st in range(nsteps):
            step = self.steps_done + st
            hk = self.hp if st == 0 else self.dt
            prof = self.profile is not None
            if prof:
                e0 = self._ev(); e0.record(s)
            k["kick_drift"][self._grid(self.n)](
                self.n, self.pos, self.vel, self.omega, self.quat, self.f_cur, self.torque, self.inv_m,
                self.inv_i, self._im0, self._ii0, self.x_ref, self.ids, hk, self.dt, self.box_c,
                self.inv_box, self.half, self.status, step)
            if prof:
                e1 = self._ev(); e1.record(s)
            slot = st % 2
            self.status.copy_to_host(self.status_h[slot], stream=s)
            self.events[slot].record(s)
            # decide the rebuild from the previous step's status (already on the host, no GPU stall)
            if prev is None:
                # first step of the call: the last status of the previous call is known exactly
                self.events[slot].synchronize()
                h = self.status_h[slot]
                rebuild = math.sqrt(h[K.S_DISP2]) > limit
                self._check(h)
            else:
                self.events[prev].synchronize()
                h = self.status_h[prev]
                self._check(h)
                if not rebuilt_prev and math.sqrt(h[K.S_DISP2]) > limit:
                    self.late_rebuilds += 1
                d_prev = 0.0 if rebuilt_prev else math.sqrt(h[K.S_DISP2])
                rebuild = d_prev + 2.0 * math.sqrt(h[K.S_V2]) * dtf > limit
            if prof:
                e2 = self._ev(); e2.record(s)
            if rebuild:
                self._rebuild()
            rebuilt_prev = rebuild
            if prof:
                e3 = self._ev(); e3.record(s)
            self._forces(step)
            self.f_cur, self.f_nxt = self.f_nxt, self.f_cur
            if prof:
                e4 = self._ev(); e4.record(s)
                self._prof_events.append((e0, e1, e2, e3, e4))
            prev = slot
        k["half_kick"][self._grid(self.n)](self.n, self.vel, self.omega, self.f_cur, self.torque, self.inv_m,
                                           self.inv_i, self._im0, self._ii0, self.hp)
        h = self._read_status_now()
        if not rebuilt_prev and math.sqrt(h[K.S_DISP2]) > limit:
            self.late_rebuilds += 1
        self.steps_done += nsteps
        if self.profile is not None:
            for e0, e1, e2, e3, e4 in self._prof_events:
                for name, a, b in (("kick_drift", e0, e1), ("status_copy", e1, e2), ("rebuild", e2, e3),
                                   ("forces", e3, e4)):
                    self.profile[name] = self.profile.get(name, 0.0) + cuda.event_elapsed_time(a, b)
            self._prof_events = []
        self._check(h)

    def _ev(self):
        return cuda.event(timing=True) if not SIM else cuda.event()

    def _read_status_now(self) -> np.ndarray:
        h = self.status_h[0]
        self.status.copy_to_host(h, stream=self.stream)
        self.stream.synchronize()
        return h

    def _check(self, h) -> None:
        if h[K.S_BAD_ID] < np.inf:
            step = int(h[K.S_BAD_STEP])
            self.steps_done = step
            raise _instability(BAD_VALUE, step, int(h[K.S_BAD_ID]), 0.0, self)
        if h[K.S_OVL_ID] < np.inf:
            step = int(h[K.S_OVL_STEP])
            self.steps_done = step
            raise _instability(OVERLAP, step, int(h[K.S_OVL_ID]), float(h[K.S_OVL]), self)

    # ---- host copies (output steps only) -----------------------------------------------------------

    def observe(self) -> dict:
        nbr, nn, hist = self.lists[self.cur]
        acc = cuda.to_device(np.zeros(8), stream=self.stream)
        k_t = 0.0 if self.contact.k_t is None else float(self.k_t)
        self.k["observe"][self._grid(self.n)](
            self.n, self.pos, self.vel, self.omega, self.radius, self._r0, self.mass, self._m0, self.inertia,
            self._i0, nbr, nn, hist, self.box_c, self.inv_box, self.half, float(self.k_n), k_t, acc)
        a = acc.copy_to_host(stream=self.stream)
        self.stream.synchronize()
        return {"kinetic_energy_translational": float(a[0]), "kinetic_energy_rotational": float(a[1]),
                "contacts": int(round(a[2])) // 2, "elastic_energy": float(a[3]), "max_overlap": float(a[7]),
                "momentum": (float(a[4]), float(a[5]), float(a[6]))}

    def state(self) -> dict:
        """Host copies of the state arrays in particle-id order (all copies queued, one sync)."""
        s = self.stream
        if getattr(self, "_pinned", None) is None:
            self._pinned = {name: cuda.pinned_array(getattr(self, name).shape, self.dtype)
                            for name in ("pos", "vel", "omega", "quat")}
            self._pinned_ids = cuda.pinned_array(self.n, np.int32)
        for name, buf in self._pinned.items():
            getattr(self, name).copy_to_host(buf, stream=s)
        self.ids.copy_to_host(self._pinned_ids, stream=s)
        s.synchronize()
        ids = self._pinned_ids
        out = {}
        for key, name in (("position", "pos"), ("velocity", "vel"), ("angular_velocity", "omega"),
                          ("orientation", "quat")):
            a = self._pinned[name]
            o = np.empty((self.n, a.shape[0]), self.dtype)
            o[ids] = a.T
            out[key] = o
        return out

    def contacts(self):
        """(pairs (M,2) int64 ids, history (M,HW)) of the list slots in contact (previous overlap > 0),
        ordered like the CPU backend's (by particle id, then list slot)."""
        nbr, nn, hist = (a.copy_to_host(stream=self.stream) for a in self.lists[self.cur])
        ids = self.ids.copy_to_host(stream=self.stream)
        self.stream.synchronize()
        m = nbr.shape[0]
        slot = np.arange(m)[:, None] < np.minimum(nn, m)[None, :]
        kk, ii = np.nonzero(slot & (hist[3] > 0))
        order = np.lexsort((kk, ids[ii]))
        kk, ii = kk[order], ii[order]
        pairs = np.stack([ids[ii], ids[nbr[kk, ii]]], axis=1).astype(np.int64)
        springs = np.ascontiguousarray(hist[:, kk, ii].T).astype(self.dtype)
        return pairs, springs

    # ---- introspection (bench) ----------------------------------------------------------------------

    def device_bytes(self) -> int:
        """Bytes of device memory this backend holds (all arrays)."""
        total = 0
        for v in vars(self).values():
            if isinstance(v, list):
                for x in v:
                    for y in (x if isinstance(x, list) else [x]):
                        total += getattr(y, "nbytes", 0) if _is_dev(y) else 0
            elif _is_dev(v):
                total += v.nbytes
        return total


def _is_dev(a) -> bool:
    return cuda.is_cuda_array(a) and not isinstance(a, np.ndarray)


def _copy(dst, src, stream) -> None:
    """Device-to-device copy of equal-shape arrays."""
    dst.copy_to_device(src, stream=stream)
