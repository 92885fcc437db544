"""The time loop of a CUDA ensemble: :class:`TimeLoop`, a part of :class:`engine.loops.cuda_ensemble.CudaEnsembleBase`.

Two loops, chosen by size (``multistep``): many steps per cooperative launch (small scenes and ensembles of them),
returning to the host only at the end of the call or when a rebuild is due; or one launch per phase (large scenes),
the rebuild decided from the previous step's status already copied to pinned memory. A scene that blows up is stopped on the device and reported alone.
"""

from __future__ import annotations

import math
import time
from types import SimpleNamespace

import numpy as np
from numba import cuda

from engine.loops import cuda_kernels as K
from engine.loops.cuda_cache import SIM
from engine.loops.status import BAD_VALUE, OVERLAP, instability_error as _instability

#: False: every kick_drift measures the displacements since the list build against x_ref (bench/e2e.py --off
#: displacement_bound); True: only where the bound max|v| dt summed over the steps nears L_v/2
DISPLACEMENT_BOUND = True


class TimeLoop:
    """The stepping part of a CUDA ensemble. The ensemble provides its device arrays and tables, ``k`` (kernels),
    ``_lc`` (the launch cache of the per-step kernels, engine/loops/cuda_launch.py), ``stream``, ``lists`` and
    :meth:`_step_arrays`."""

    def _forces(self, step: int, n: int | None = None, grid=None) -> None:
        spin, _, rad, ext = self._step_arrays()
        n = self.n if n is None else n
        self._lc.launch("forces", self.k["forces"], grid or self._grid(n), (
            n, self.pos, self.vel, spin, self.quat, rad, self.inv_m1, self.f_cur, self.f_nxt, self.torque,
            self.nbr, self.nn, self.hist, self.ids, self.sc, self.spd, self.spf, self.spi, self.status, step, ext))

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

    def _kick_drift(self, first: int, step: int, n: int | None = None, grid=None, exact: int = 1) -> None:
        spin, spin_inv, _, ext = self._step_arrays()
        n = self.n if n is None else n
        self._lc.launch("kick_drift", self.k["kick_drift"], grid or self._grid(n), (
            n, first, exact, self.pos, self.vel, spin, self.quat, self.f_cur, self.torque, self.inv_m1, spin_inv,
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
        ends = [e for e in (self._horizon, self._call_end) if e is not None]
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
        """One launch per phase. The rebuild before the forces of step t is decided from step t-1's status
        (copied to pinned memory while step t's kick-drift runs): with B an upper bound of the largest
        displacement at step t-1 and u = 2 max|v| dt of step t-1 (both in units of L_v/2), the list is rebuilt
        when B + u > 1. B is exact where kick_drift measured the displacements against x_ref (the first step
        of a call, CPU-built lists, and the steps where the bound nears the limit); elsewhere B grows by
        u/2 = max|v| dt a step, which bounds every particle's displacement (``DISPLACEMENT_BOUND``; x_ref is
        then not read: 24 bytes a particle-step in float64)."""
        s = self.stream
        rebuilt_prev = False
        prev = None  # slot of the previous step's status copy
        bound = 0.0     # the largest displacement at the step of the status last read, or an upper bound of it
        u_last = 1.0    # 2 max|v| dt of that step
        exact_of = [1, 1]  # whether the kick_drift of the step whose status sits in slot 0 / 1 measured exactly
        for st in range(nsteps):
            step = self.steps_done
            prof = self.profile is not None
            if prof:
                e0 = self._ev(); e0.record(s)
            # measure exactly where the bound (known up to step t-2) could decide the next rebuild: bound + u
            # after two more steps of at most u/2, plus the margin u of the rule, with half a step to spare;
            # and always while a pipelined CPU build waits for its L_v/4 signal
            bounded = DISPLACEMENT_BOUND and (self.lists is None or self.lists.exit_threshold() >= 1.0)
            exact = 1 if (st == 0 or not bounded or bound + 2.5 * u_last > 1.0) else 0
            self._kick_drift(1 if st == 0 else 0, step, exact=exact)
            if prof:
                e1 = self._ev(); e1.record(s)
            slot = st % 2
            exact_of[slot] = exact
            self.status.copy_to_host(self.status_h[slot], stream=s)
            self.events[slot].record(s)
            # decide the rebuild from the previous step's status (already on the host, no GPU stall);
            # displacements and speeds are normalised by each scene's L_v/2
            if prev is None:
                # first step of the call: this step's displacement is known exactly
                self.events[slot].synchronize()
                h = self.status_h[slot]
                bound = math.sqrt(h[K.S_D2])
                rebuild = bound > 1.0
            else:
                self.events[prev].synchronize()
                h = self.status_h[prev]
                u_last = math.sqrt(h[K.S_V2])
                if rebuilt_prev:
                    bound = 0.0
                elif exact_of[prev]:
                    bound = math.sqrt(h[K.S_D2])
                    if bound > 1.0:
                        self.late_rebuilds += 1
                else:
                    bound += 0.5 * u_last
                rebuild = bound + u_last > 1.0
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
        if self._poll_ev is None:
            self._poll_ev = cuda.event(timing=False)
        self._poll_ev.record(self.stream)
        while not self._poll_ev.query():
            time.sleep(2e-5)

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
