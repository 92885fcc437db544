"""The observables of a CUDA ensemble: :class:`ObserveSums`, a part of
:class:`engine.loops.cuda_ensemble.CudaEnsembleBase`.

One launch of the shape's observe kernel sums every scene's energies, contacts, overlap, momentum and energy moments
into a (K, NOBS) accumulator, copied into one of two pinned host slots; :class:`_LateSums` reads them when they have
landed, so the driver can build the records while the GPU runs the next steps.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
from numba import cuda
from numba.cuda.cudadrv.driver import device_memset

from engine.loops.cuda_cache import SIM


class ObserveSums:
    """The observe part of a CUDA ensemble. The ensemble provides ``stream``, ``n_scenes``, ``sizes``, ``tpb``,
    ``max_blocks``, ``active``, ``k`` (kernels), ``_lc`` (launch cache), ``_NOBS``, :meth:`_observe_args` and
    :meth:`_observables`."""

    def _init_observe(self) -> None:
        self._sums = None    # the observe kernel's result slots (_ObserveSlots), made at the first observe

    def _observe_sums(self) -> np.ndarray:
        """The observe kernel's per-scene sums (K, _NOBS) on the host, now (a copy)."""
        return self._observe_async().settle()

    def _observe_async(self) -> "_LateSums":
        """Queue the observe kernel's per-scene sums (K, _NOBS) on the stream (issue 14): one zeroing copy, one
        launch with one block row per scene, one copy of K x _NOBS float64 into a pinned result slot, an event.
        Nothing waits: the sums are those of the state at this point of the stream, whatever the GPU does next,
        and :meth:`_LateSums.settle` reads them. Two result slots; reusing one settles its earlier sums first."""
        s, nk = self.stream, self.n_scenes
        if self._sums is None:
            self._sums = _ObserveSlots(nk, self._NOBS, s)
        sums = self._sums
        k = sums.next
        sums.next = 1 - k
        if sums.late[k] is not None:
            sums.late[k].settle()
        if SIM:
            sums.acc.copy_to_device(sums.acc_zero, stream=s)
        else:
            device_memset(sums.acc, 0, sums.acc.nbytes, stream=s)   # all-zero bits: 0.0
        per_scene = (int(self.sizes.max()) + self.tpb - 1) // self.tpb
        bx = max(1, min(per_scene, max(1, self.max_blocks // nk)))
        # through the launch cache: numba-cuda's own argument handling of this 15-argument launch cost about
        # 0.8 ms of host time per stop on the H200 host, while the GPU waited for the next round
        self._lc.launch("observe", self.k["observe"], ((bx, nk), self.tpb, s), (*self._observe_args(), sums.acc))
        sums.acc.copy_to_host(sums.host[k], stream=s)
        sums.events[k].record(s)
        sums.late[k] = late = _LateSums(sums.host[k], sums.events[k])
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


class _ObserveSlots:
    """The observe kernel's device accumulator (K, NOBS) and two pinned host result slots with their events
    (:meth:`CudaEnsemble._observe_async`)."""

    def __init__(self, n_scenes: int, nobs: int, stream):
        # the simulator has no memset on a stream: zeros are copied in
        self.acc_zero = np.zeros((n_scenes, nobs), np.float64) if SIM else None
        self.acc = cuda.device_array((n_scenes, nobs), np.float64, stream=stream)
        self.late: list = [None, None]
        self.host = [cuda.pinned_array((n_scenes, nobs), np.float64) for _ in range(2)]
        self.events = [(cuda.event() if SIM else cuda.event(timing=False)) for _ in range(2)]
        self.next = 0


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
