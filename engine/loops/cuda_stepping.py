"""The time loop of a CUDA ensemble: :class:`TimeLoop`, a part of :class:`engine.loops.cuda_ensemble.CudaEnsembleBase`.

Two loops, chosen by size (``multistep``): many steps per cooperative launch (small scenes and ensembles of them),
returning to the host only at the end of the call or when a rebuild is due; or one launch per phase (large scenes),
the rebuild decided from the previous step's status already copied to pinned memory. A scene that blows up is stopped on
the device and reported alone.
"""

from __future__ import annotations

import math
import time
from types import SimpleNamespace

import numpy as np
from numba import cuda

from engine.backends.protocol import check_observation_steps
from engine.loops import cuda_kernels as K
from engine.loops.cuda_cache import SIM
from engine.loops.cuda_records import RECORD_ROWS
from engine.loops.status import BAD_VALUE, OVERLAP, instability_error as _instability

#: False: every kick_drift measures the displacements since the list build against x_ref (bench/e2e.py --off
#: displacement_bound); True: only where the bound max|v| dt summed over the steps nears L_v/2
DISPLACEMENT_BOUND = True
#: True: the many-steps loop runs a step's forces and the next kick-drift in one pass, one grid sync a step, where the
#: shape's kernels allow it (cuda_loop ``run_steps_fused``); False: two passes a step (bench/e2e.py --off
#: multistep_fused, the tests)
MULTISTEP_FUSED = True
#: True: the per-phase loop runs a step's forces and the next kick-drift in one launch where the shape's kernels
#: allow it (cuda_loop ``forces_kick_drift``); False: two launches a step (bench/e2e.py --off fused, the tests)
FUSED = True
#: True: a lone scene of spheres (smooth or rough) in the per-phase loop sums its observables in the force pass of
#: each step it is observed at (cuda_loop ``forces_observe``, ``forces_observe_kick_drift``: the end of an advance
#: call, and the records :meth:`TimeLoop.advance_observing` passes inside one) and leaves its velocities (and spins)
#: half a step behind until the state is read (:meth:`TimeLoop._close`); False: every call ends with the closing
#: half kick, and observe() launches the observe kernel and waits for it (bench/e2e.py --off observe_in_forces)
OBSERVE_IN_FORCES = True
#: what :meth:`TimeLoop.warmup` has warmed in this process: (kernel set, position and state types, loop kind)
_WARMED: set = set()


def _maxima(h, odd: bool) -> tuple:
    """(squared displacement, squared speed) maxima of a status copy h: the slots of parity 1 (S_D2B, S_V2B) for a
    kick-drift run in a fused launch of odd parity, else those of parity 0."""
    return (h[K.S_D2B], h[K.S_V2B]) if odd else (h[K.S_D2], h[K.S_V2])


class TimeLoop:
    """The stepping part of a CUDA ensemble. The ensemble provides its device arrays and tables, ``k`` (kernels),
    ``_lc`` (the launch cache of the per-step kernels, engine/loops/cuda_launch.py), ``stream``, ``lists`` and
    :meth:`_step_arrays`."""

    def _forces(self, step: int, n: int | None = None, grid=None) -> None:
        spin, _, rad, ext = self._step_arrays()
        n = self.n if n is None else n
        self._lc.launch("forces", self.k["forces"], grid or self._grid(n), (
            n, self.pos, self.vel, spin, self.quat, rad, self.inv_m1, self.f_cur, self.f_nxt, self.torque, self.hot,
            self.nbr, self.nn, self.hist, self.ids, self.sc, self.spd, self.spf, self.spi, self.status, step, ext))

    def _forces_kick_drift(self, step: int, par: int, exact: int, n: int | None = None, grid=None) -> None:
        """The forces of ``step`` and the kick-drift of step + 1 in one launch (cuda_loop ``forces_kick_drift``);
        the double buffers swap: the new state becomes the current one."""
        spin, spin_inv, rad, ext = self._step_arrays()
        pos_out, vel_out = self._fused_out()
        self._lc.launch("forces_kick_drift", self.k["forces_kick_drift"], grid or self._grid(self.n), (
            self.n if n is None else n, par, exact, self.pos, pos_out, self.vel, vel_out, spin, self.quat, rad,
            self.inv_m1, self.f_cur, self.f_nxt, self.torque, self.hot, spin_inv, self.x_ref, self.nbr, self.nn,
            self.hist, self.ids, self.sc, self.spd, self.spf, self.spi, self.status, step, ext))
        self._swap_fused()
        self.f_cur, self.f_nxt = self.f_nxt, self.f_cur

    def _coop_grid(self, name: str = "run_steps") -> tuple:
        """Blocks of the cooperative launch of kernel ``name``: all co-resident (a grid sync needs it)."""
        if self._coop_blocks is None:
            self._coop_blocks = {}
        if name not in self._coop_blocks:
            if SIM:
                self._coop_blocks[name] = 1  # the simulator syncs a cooperative grid of one block only
            else:
                if not self.k[name].overloads:
                    self._warm_launches()
                kern = next(iter(self.k[name].overloads.values()))
                fit = kern.max_cooperative_grid_blocks(self.tpb)
                self._coop_blocks[name] = max(1, min(fit, (self.n + self.tpb - 1) // self.tpb))
        return self._coop_blocks[name], self.tpb, self.stream

    def _kick_drift(self, first: int, step: int, n: int | None = None, grid=None, exact: int = 1) -> None:
        spin, spin_inv, _, ext = self._step_arrays()
        n = self.n if n is None else n
        self._lc.launch("kick_drift", self.k["kick_drift"], grid or self._grid(n), (
            n, first, exact, self.pos, self.vel, spin, self.quat, self.f_cur, self.torque, self.hot, self.inv_m1,
            spin_inv, self.x_ref, self.ids, self.sc, self.spd, self.spf, self.spi, self.status, step, ext))

    def _half_kick(self, n: int | None = None, grid=None) -> None:
        spin, spin_inv, _, _ = self._step_arrays()
        n = self.n if n is None else n
        self._lc.launch("half_kick", self.k["half_kick"], grid or self._grid(n), (
            n, self.vel, spin, self.f_cur, self.torque, self.inv_m1, spin_inv, self.sc, self.spd, self.spi))

    def _settle(self, n: int | None = None, grid=None) -> None:
        """The shape's end-of-call work (cuda_loop ``settle``), when it has some, at step ``steps_done``."""
        if "settle" in self.k:
            spin, _, _, ext = self._step_arrays()
            n = self.n if n is None else n
            self._lc.launch("settle", self.k["settle"], grid or self._grid(n), (
                n, spin, self.quat, self.sc, self.spd, self.spi, self.steps_done, ext))

    def _multistep_fused(self) -> bool:
        return MULTISTEP_FUSED and "run_steps_fused" in self.k

    def _run_steps(self, nmax: int, first: int, step0: int, grid=None, n: int | None = None, thr=None,
                   status=None) -> None:
        """The many-steps kernel: cuda_loop ``run_steps_fused`` where the shape's kernels have it (the caller swaps
        the double buffer's halves where the launch ended in the second), else ``run_steps``."""
        spin, spin_inv, rad, ext = self._step_arrays()
        if self._multistep_fused():
            pos_b, vel_b, spin_b = self._multistep_out()
            grid = grid or self._coop_grid("run_steps_fused")
            self._lc.launch("run_steps_fused", self.k["run_steps_fused"], grid, (
                self.n if n is None else n, nmax, first, float(self._exit_thr if thr is None else thr), self.pos,
                pos_b, self.vel, vel_b, spin, spin_b, self.quat, self.f_cur, self.f_nxt, self.torque, self.hot,
                self.inv_m1, spin_inv, rad, self.x_ref, self.nbr, self.nn, self.hist, self.ids, self.sc, self.spd,
                self.spf, self.spi, self.status if status is None else status, step0, ext))
            return
        self._lc.launch("run_steps", self.k["run_steps"], grid or self._coop_grid(), (
            self.n if n is None else n, nmax, first, 0, float(self._exit_thr if thr is None else thr), self.pos,
            self.vel, spin, self.quat, self.f_cur, self.f_nxt, self.torque, self.hot, self.inv_m1, spin_inv, rad,
            self.x_ref, self.nbr, self.nn, self.hist, self.ids, self.sc, self.spd, self.spf, self.spi,
            self.status if status is None else status, step0, ext))

    def warmup(self) -> None:
        """Compile (or load) the kernels of the current specialisation without advancing (:meth:`_warm_launches`). A
        process does it once per kernel set, array types and kind of loop: a later ensemble of the same kind (the
        next job of a worker) finds them loaded and skips the launches, each of which costs about half a millisecond
        of host time for its arguments."""
        key = (id(self.k), np.dtype(self.pos_dtype).str, np.dtype(self.dtype).str, self.multistep,
               self.multistep and self._multistep_fused(), self.n_scenes == 1)
        if key not in _WARMED:
            self._warm_launches()
            _WARMED.add(key)

    def _warm_launches(self) -> None:
        """Launch every kernel of the time loop with n = 0 (compiled or loaded at the first launch), then wait."""
        s = self.stream
        g = (1, self.tpb, s)
        self._kick_drift(1, 0, n=0, grid=g)
        self._forces(0, n=0, grid=g)
        self._half_kick(n=0, grid=g)
        self._settle(n=0, grid=g)
        self._observe_sums()
        if "forces_kick_drift" in self.k:      # the fused step (n = 0: the buffers swap twice, state unchanged)
            for par in (1, 0):
                self._forces_kick_drift(0, par, 1, n=0, grid=g)
        # also for a small scene in the many-steps loop: a worker warms every specialisation with tiny scenes, and a
        # large lone scene of the same specialisation runs these
        if "forces_observe" in self.k and self.n_scenes == 1:
            self._record_rows()
            for fused in (True, False) if "forces_observe_kick_drift" in self.k else (False,):
                self._observe_in_forces(0, 0, fused, n=0, grid=g)
                if fused:
                    self._observe_in_forces(0, 0, fused, n=0, grid=g)     # the buffers swap back
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
        return self._advance(int(nsteps), (int(nsteps),))[0]

    def advance_observing(self, nsteps: int, at) -> tuple:
        """:meth:`Ensemble.advance_observing`: a lone sphere scene in the per-phase loop (``_ends_calls_open``)
        sums the observables in the force passes of the steps in ``at``, in calls of up to RECORD_ROWS of them with
        one wait each; other ensembles advance to each and observe."""
        check_observation_steps(nsteps, at)
        nsteps, at = int(nsteps), [int(k) for k in at]
        if not self._ends_calls_open():
            return super().advance_observing(nsteps, at)
        failed, out, done = {}, [], 0
        for c in range(0, len(at), RECORD_ROWS):
            chunk = [k - done for k in at[c:c + RECORD_ROWS]]
            f, rows = self._advance(chunk[-1], chunk)
            failed.update(f)
            if rows is None:     # nothing active
                break
            out += [[self._observables(s, r.tolist()) if self.active[s] else None for s in range(self.n_scenes)]
                    for r in rows]
            done = at[c:c + RECORD_ROWS][-1]
        out += [[None] * self.n_scenes for _ in at[len(out):]]
        return failed, out

    def observes_in_loop(self) -> bool:
        """:meth:`Ensemble.observes_in_loop`: where :meth:`advance_observing` sums in the force passes."""
        return self._ends_calls_open()

    def _advance(self, nsteps: int, at: tuple) -> tuple:
        """advance(nsteps); where the call ends open (``_ends_calls_open``), the observe sums of the state after each
        count of steps in ``at`` (1 <= k <= nsteps, increasing) are summed in that step's force pass: returns
        (failed, their rows (len(at), NOBS) on the host, or None), and the last row answers observe() until the
        state moves."""
        self._call_end = self.steps_done + nsteps
        failed, self._pending = dict(self._pending), {}
        if nsteps <= 0 or not self.active.any():
            return failed, None
        self._observed_at = None
        keep_open = self._ends_calls_open()
        if not keep_open:
            self._close()
        if self.multistep:
            self._advance_multistep(nsteps, failed)
        else:
            self._advance_per_phase(nsteps, failed, at if keep_open else ())
        if keep_open:
            self._open = True
            self._rows.copy_to_host()
        else:
            self._settle()
            self._half_kick()
        self._collect(self._read_status_now(), failed)
        rows = None
        if keep_open:
            rows = self._rows.host[:len(at)].copy()
            self._last_row = rows[-1:]
            self._observed_at = self.steps_done
        if not self.multistep:
            self._close_call()
        return failed, rows

    def _ends_calls_open(self) -> bool:
        """Whether an advance call sums its observables in its force passes (cuda_loop ``forces_observe``) and ends
        with the velocities half a step behind (``OBSERVE_IN_FORCES``: one scene in the per-phase loop, a shape whose
        force pass leaves the spins alone, ``OBSERVES_AFTER_FORCES``)."""
        return OBSERVE_IN_FORCES and not self.multistep and self.n_scenes == 1 and "forces_observe" in self.k

    def _close(self) -> None:
        """The velocities brought level with the positions where a call left them half a step behind (the deferred
        closing half kick, and the shape's end-of-call work before it): before the state is read, the scene's
        constants change or it drops out. The next call then starts with the opening half kick."""
        if self._open:
            self._settle()
            self._half_kick()
            self._open = False

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
            # the fused kernel leaves the state in the half of the last drift: step `done` after an exit, else done - 1
            if self._multistep_fused() and (done if h[K.S_RUN_REBUILD] > 0 else done - 1) % 2 == 1:
                self._swap_multistep()
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

    def _advance_per_phase(self, nsteps: int, failed: dict, observe_at=()) -> None:
        """One launch per phase, or, for a shape whose kernels fuse them (``forces_kick_drift``, with ``FUSED``),
        one launch per step: the forces of step t and the kick-drift of step t + 1 in one pass, positions and
        velocities double-buffered. A call that starts with the velocities half a step behind (``_open``) starts
        with a whole kick. ``observe_at``: after each of these counts of steps the force pass also sums the
        observables into the next row of ``_record_rows`` (``_observe_in_forces``).

        The rebuild before the forces of step t is decided from step t-1's status (copied to pinned memory while
        the GPU runs on): with B an upper bound of the largest displacement at step t-1 and u = 2 max|v| dt of
        step t-1 (both in units of L_v/2), the list is rebuilt when B + u > 1. B is exact where the kick-drift
        measured the displacements against x_ref (the first step of a call, CPU-built lists, and the steps where
        the bound nears the limit); elsewhere B grows by u/2 = max|v| dt a step, which bounds every particle's
        displacement (``DISPLACEMENT_BOUND``; x_ref is then not read: 24 bytes a particle-step in float64)."""
        s = self.stream
        fused = FUSED and "forces_kick_drift" in self.k
        # the bound at the previous call's last kick-drift (_close_call), valid while nothing has moved, rebuilt or
        # changed the scenes' constants since: the first step's rebuild is then decided without waiting for the GPU
        carry, self._carry = self._carry, None
        if carry is not None and (self.lists is not None or carry[:2] != (self.steps_done, self.builds)):
            carry = None
        rebuilt_prev = False
        prev = None  # slot of the previous step's status copy
        bound = 0.0     # the largest displacement at the step of the status last read, or an upper bound of it
        u_last = 1.0    # 2 max|v| dt of that step
        exact_of = [1, 1]  # whether the kick-drift whose status sits in slot 0 / 1 measured exactly
        prof = self.profile is not None
        # the kick-drift of step 0 of the call; later ones run here too (one-phase launches) or in the fused
        # launch of the previous step's forces. Its status goes to pinned slot st % 2, read from the device slots
        # of parity st % 2 (the fused kernel alternates them; the one-phase kernels use parity 0)
        rows = {k: r for r, k in enumerate(observe_at)}
        if rows:
            self._record_rows()
        self._kick_drift(0 if self._open else 1, self.steps_done)
        self._status_copy(0)
        for st in range(nsteps):
            step = self.steps_done
            if prof:
                e0 = self._ev(); e0.record(s)
            # the bound decides only where the lists are not waiting for a pipelined CPU build's L_v/4 signal
            bounded = DISPLACEMENT_BOUND and (self.lists is None or self.lists.exit_threshold() >= 1.0)
            if st > 0 and not fused:
                exact = 1 if (not bounded or bound + 2.5 * u_last > 1.0) else 0
                self._kick_drift(0, step, exact=exact)
                exact_of[st % 2] = exact
                self._status_copy(st % 2)
            if prof:
                e1 = self._ev(); e1.record(s)
            slot = st % 2
            par = slot if fused else 0
            # decide the rebuild from the previous step's status (already on the host, no GPU stall);
            # displacements and speeds are normalised by each scene's L_v/2
            if prev is None and carry is not None:
                # first step of the call: the bound and speed at the previous call's last step, one step back
                h = None
                bound, u_last = carry[2], carry[3]
                d2 = bound * bound
                rebuild = bound + u_last > 1.0
            elif prev is None:
                # first step of the call: this step's displacement is known exactly (the GPU catches up first)
                self._wait_status(slot)
                h = self.status_h[slot]
                d2 = h[K.S_D2]
                bound = math.sqrt(d2)
                rebuild = bound > 1.0
            else:
                self._wait_status(prev)
                h = self.status_h[prev]
                d2, v2 = _maxima(h, fused and prev == 1)
                u_last = math.sqrt(v2)
                if rebuilt_prev:
                    bound = self._rebuilt_bound
                elif exact_of[prev]:
                    bound = math.sqrt(d2)
                    if bound > 1.0:
                        self.late_rebuilds += 1
                else:
                    bound += 0.5 * u_last
                rebuild = bound + u_last > 1.0
            if h is not None:
                self._collect(h, failed)
            if prof:
                e2 = self._ev(); e2.record(s)
            if rebuild:
                self._rebuild()
            elif self.lists is not None and self.lists.exit_threshold() < 1.0 and math.sqrt(d2) > 0.5:
                self.lists.signal()  # L_v/4 passed (Skorych & Dosta 2022, B3): the pipelined CPU build starts
            rebuilt_prev = rebuild
            if prof:
                e3 = self._ev(); e3.record(s)
            row = rows.get(st + 1)
            if fused and st + 1 < nsteps:
                # measure exactly where the bound (known up to step t-1) could decide a rebuild: bound + u after
                # two more steps of at most u/2, plus the margin u of the rule, with half a step to spare
                exact = 1 if (not bounded or bound + 2.5 * u_last > 1.0) else 0
                if row is None:
                    self._forces_kick_drift(step, 1 - par, exact)
                else:
                    self._observe_in_forces(step, row, True, 1 - par, exact)
                    self.f_cur, self.f_nxt = self.f_nxt, self.f_cur
                exact_of[1 - slot] = exact
                self._status_copy(1 - slot)
                self.launches += 1
            else:
                if row is None:
                    self._forces(step)
                else:
                    self._observe_in_forces(step, row, False)
                self.launches += 2
                self.f_cur, self.f_nxt = self.f_nxt, self.f_cur
            if prof:
                e4 = self._ev(); e4.record(s)
                self._prof_events.append((e0, e1, e2, e3, e4))
            prev = slot
            self.steps_done += 1
        last = (nsteps - 1) % 2
        self._last_kick = (last, fused and last == 1, exact_of[last], rebuilt_prev, bound)
        if self.profile is not None:
            names = ("kick_drift", "status_copy", "rebuild", "forces_kick_drift" if fused else "forces")
            for e0, e1, e2, e3, e4 in self._prof_events:
                for name, a, b in zip(names, (e0, e1, e2, e3), (e1, e2, e3, e4)):
                    self.profile[name] = self.profile.get(name, 0.0) + cuda.event_elapsed_time(a, b)
            self._prof_events = []

    def _close_call(self) -> None:
        """After a per-phase call, once the stream has finished: the last kick-drift's status (its pinned slot)
        gives the displacement bound B and speed u the next call starts from (``_carry``), and counts a late
        rebuild when the last step's forces ran on a list its displacements had outgrown."""
        slot, odd, exact, rebuilt, bound = self._last_kick
        d2, v2 = _maxima(self.status_h[slot], odd)
        u, d = math.sqrt(v2), math.sqrt(d2)
        if rebuilt:
            # rebuilt before the last forces: x_ref holds the last kick-drift's positions (rounded: _rebuilt_bound)
            b = self._rebuilt_bound
        elif exact:
            b = d
            if d > 1.0:
                self.late_rebuilds += 1
        else:
            b = bound + 0.5 * u
        self._carry = (self.steps_done, self.builds, b, u)

    def _status_copy(self, slot: int) -> None:
        """The status words to pinned slot ``slot`` after what the stream holds, and the slot's event (through
        engine.numba_support.numba_internals.async_copy_and_record on a GPU: numba-cuda's copy and record cost about as
        much host time as a step of 2M spheres takes on an H100). Slots 0 and 1: the per-phase loop's steps; 2: a
        wait-now read (:meth:`_read_status_now`)."""
        if self._status_copiers is None:
            if SIM:
                self._status_copiers = [
                    (lambda k=k: (self.status.copy_to_host(self.status_h[k], stream=self.stream),
                                  self.events[k].record(self.stream))) for k in range(3)]
            else:
                from engine.numba_support.numba_internals import async_copy_and_record

                self._status_copiers = [async_copy_and_record(self.status, self.status_h[k], self.stream,
                                                              self.events[k]) for k in range(3)]
        self._status_copiers[slot]()

    def _wait_status(self, slot: int) -> None:
        """Wait for the status copy of pinned slot ``slot`` (its event; through
        engine.numba_support.numba_internals.event_waiter on a GPU: the driver's wait called straight, which the
        per-phase loop does every step)."""
        if self._status_waits is None:
            if SIM:
                self._status_waits = [self.events[k].synchronize for k in range(3)]
            else:
                from engine.numba_support.numba_internals import event_waiter

                self._status_waits = [event_waiter(self.events[k]) for k in range(3)]
        self._status_waits[slot]()

    def _ev(self):
        return cuda.event(timing=True) if not SIM else cuda.event()

    def _read_status_now(self) -> np.ndarray:
        """The status words once the stream has run all it holds (pinned slot 2)."""
        self._status_copy(2)
        self._poll(self.events[2])
        return self.status_h[2]

    def _wait_stream(self) -> None:
        """Wait until the stream has run all it holds."""
        self.events[2].record(self.stream)
        self._poll(self.events[2])

    @staticmethod
    def _poll(event) -> None:
        """Wait for ``event`` by polling it with short sleeps, which release the GIL, so that the result files' I/O
        thread (engine/output/h5md.py) works while the GPU does (a blocking synchronize may hold it)."""
        if SIM:
            event.synchronize()
            return
        while not event.query():
            time.sleep(2e-5)

    def _collect(self, h, failed: dict | None = None) -> dict:
        """Scenes that blew up according to status h (once each): deactivated, error recorded."""
        failed = {} if failed is None else failed
        # this runs every step: first whether any scene has recorded a failure at all (its offender's id is finite),
        # in scalars for one scene, in two strided minima for several
        if self.n_scenes == 1:
            if not (h[K.SS0 + K.SS_BAD_ID] < np.inf or h[K.SS0 + K.SS_OVL_ID] < np.inf):
                return failed
        elif not (h[K.SS0 + K.SS_BAD_ID::K.NSS].min() < np.inf or h[K.SS0 + K.SS_OVL_ID::K.NSS].min() < np.inf):
            return failed
        ss = h[K.SS0:].reshape(self.n_scenes, K.NSS)
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
