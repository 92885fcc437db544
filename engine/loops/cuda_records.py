"""The observables of a CUDA ensemble: :class:`ObserveSums`, a part of
:class:`engine.loops.cuda_ensemble.CudaEnsembleBase`.

One launch of the shape's observe kernel sums every scene's energies, contacts, overlap, momentum and energy moments
into a (K, NOBS) accumulator, copied into a pinned host buffer and read once the stream has reached it. A lone
sphere scene (smooth or rough) in the per-phase loop gets the same sums from the force passes of the steps it is
observed at, one row each (``_observe_in_forces``), read once at the end of the advance call: a record then costs no
pass over the particles, no launch and no wait of its own.
"""

from __future__ import annotations

import numpy as np
from numba import cuda

from engine.loops.cuda_cache import SIM
from engine.numba_support.numba_internals import device_memset

#: records one advance call of a lone scene can sum in its force passes (:meth:`ObserveSums._observe_in_forces`;
#: a longer run of records takes several calls)
RECORD_ROWS = 256


class ObserveSums:
    """The observe part of a CUDA ensemble. The ensemble provides ``stream``, ``n_scenes``, ``sizes``, ``tpb``,
    ``max_blocks``, ``active``, ``k`` (kernels), ``_lc`` (the launch cache), ``_NOBS``, :meth:`_observe_args`,
    :meth:`_observables` and :meth:`_wait_stream`."""

    def _init_observe(self) -> None:
        self._sums = None   # the observe kernel's accumulator and host buffer (_ObserveSlot), made at the first observe
        self._rows = None   # the force passes' rows of sums (_ObserveSlot of RECORD_ROWS rows), made at first use
        self._observed_at = None    # the step whose sums the last force pass left in _last_row, or None
        self._last_row = None

    def _observe_sums(self) -> np.ndarray:
        """The observe kernel's per-scene sums (K, _NOBS) on the host, now (a copy): one zeroing of the
        accumulator, one launch with one block row per scene, one copy of K x _NOBS float64 into a pinned buffer,
        then a wait for the stream."""
        s, nk = self.stream, self.n_scenes
        if self._sums is None:
            self._sums = _ObserveSlot(nk, self._NOBS, s)
        sums = self._sums
        sums.zero()
        per_scene = (int(self.sizes.max()) + self.tpb - 1) // self.tpb
        bx = max(1, min(per_scene, max(1, self.max_blocks // nk)))
        self._lc.launch("observe", self.k["observe"], ((bx, nk), self.tpb, s), self._observe_args() + (sums.acc,))
        sums.copy_to_host()
        self._wait_stream()
        return sums.host.copy()

    def _record_rows(self) -> "_ObserveSlot":
        """The rows the force passes of one advance call sum into (:meth:`_observe_in_forces`), zeroed on the
        stream."""
        if self._rows is None:
            self._rows = _ObserveSlot(RECORD_ROWS, self._NOBS, self.stream)
        self._rows.zero()
        return self._rows

    def _observe_in_forces(self, step: int, row: int, fused: bool, par: int = 0, exact: int = 1,
                           n: int | None = None, grid=None) -> None:
        """Queue the forces of ``step`` with the observe sums of the state they complete into row ``row`` of
        :meth:`_record_rows` (one scene): cuda_loop ``forces_observe_kick_drift`` with the kick-drift of step + 1
        (``fused``; parity ``par``, ``exact`` as for ``forces_kick_drift``; the double buffers swap), else
        ``forces_observe``. The caller swaps the force buffers."""
        spin, spin_inv, rad, ext = self._step_arrays()
        obs = self._observe_args()
        tail = (obs[4], obs[5], obs[6], self._rows.acc, row)
        n = self.n if n is None else n
        grid = grid or self._grid(n)
        if fused:
            pos_out, vel_out = self._fused_out()
            self._lc.launch("forces_observe_kick_drift", self.k["forces_observe_kick_drift"], grid, (
                n, par, exact, self.pos, pos_out, self.vel, vel_out, spin, self.quat, rad, self.inv_m1, self.f_cur,
                self.f_nxt, self.torque, self.hot, spin_inv, self.x_ref, self.nbr, self.nn, self.hist, self.ids,
                self.sc, self.spd, self.spf, self.spi, self.status, step, ext) + tail)
            self._swap_fused()
        else:
            self._lc.launch("forces_observe", self.k["forces_observe"], grid, (
                n, self.pos, self.vel, spin, self.quat, rad, self.inv_m1, self.f_cur, self.f_nxt, self.torque,
                self.hot, spin_inv, self.nbr, self.nn, self.hist, self.ids, self.sc, self.spd, self.spf, self.spi,
                self.status, step, ext) + tail)

    def observe(self) -> list:
        """Per scene: the observables of :meth:`CudaBackend.observe` (:meth:`_observables`), None for an
        inactive scene."""
        if self._observed_at is not None and self._observed_at == self.steps_done:
            sums = self._last_row     # summed by the call's last force pass (_observe_in_forces)
        else:
            self._close()
            sums = self._observe_sums()
        return [self._observables(s, sums[s].tolist()) if self.active[s] else None for s in range(self.n_scenes)]


class _ObserveSlot:
    """A device accumulator (rows, NOBS) float64 and its pinned host buffer: the observe kernel's (one row per scene)
    or the force passes' (one row per record of an advance call)."""

    def __init__(self, rows: int, nobs: int, stream):
        # the simulator has no memset on a stream: zeros are copied in
        self.acc_zero = np.zeros((rows, nobs), np.float64) if SIM else None
        self.acc = cuda.device_array((rows, nobs), np.float64, stream=stream)
        self.host = cuda.pinned_array((rows, nobs), np.float64)
        self._stream = stream
        self._copier = None

    def zero(self) -> None:
        """Queue the accumulator's zeroing."""
        if SIM:
            self.acc.copy_to_device(self.acc_zero, stream=self._stream)
        else:
            device_memset(self.acc, 0, self._stream)   # all-zero bits: 0.0

    def copy_to_host(self) -> None:
        """Queue the accumulator's copy into the pinned host buffer (straight to the driver on a GPU:
        engine.numba_support.numba_internals.async_copy_and_record)."""
        if SIM:
            self.acc.copy_to_host(self.host, stream=self._stream)
            return
        if self._copier is None:
            from engine.numba_support.numba_internals import async_copy_and_record

            self._event = cuda.event(timing=False)
            self._copier = async_copy_and_record(self.acc, self.host, self._stream, self._event)
        self._copier()
