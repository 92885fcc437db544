"""The observables of a CUDA ensemble: :class:`ObserveSums`, a part of
:class:`engine.loops.cuda_ensemble.CudaEnsembleBase`.

One launch of the shape's observe kernel sums every scene's energies, contacts, overlap, momentum and energy moments
into a (K, NOBS) accumulator, copied into a pinned host buffer and read once the stream has reached it.
"""

from __future__ import annotations

import numpy as np
from numba import cuda

from engine.loops.cuda_cache import SIM
from engine.numba_internals import device_memset


class ObserveSums:
    """The observe part of a CUDA ensemble. The ensemble provides ``stream``, ``n_scenes``, ``sizes``, ``tpb``,
    ``max_blocks``, ``active``, ``k`` (kernels), ``_lc`` (the launch cache), ``_NOBS``, :meth:`_observe_args`,
    :meth:`_observables` and :meth:`_wait_stream`."""

    def _init_observe(self) -> None:
        self._sums = None    # the observe kernel's accumulator and host buffer (_ObserveSlot), made at the first observe

    def _observe_sums(self) -> np.ndarray:
        """The observe kernel's per-scene sums (K, _NOBS) on the host, now (a copy): one zeroing of the
        accumulator, one launch with one block row per scene, one copy of K x _NOBS float64 into a pinned buffer,
        then a wait for the stream."""
        s, nk = self.stream, self.n_scenes
        if self._sums is None:
            self._sums = _ObserveSlot(nk, self._NOBS, s)
        sums = self._sums
        if SIM:
            sums.acc.copy_to_device(sums.acc_zero, stream=s)
        else:
            device_memset(sums.acc, 0, s)   # all-zero bits: 0.0
        per_scene = (int(self.sizes.max()) + self.tpb - 1) // self.tpb
        bx = max(1, min(per_scene, max(1, self.max_blocks // nk)))
        self._lc.launch("observe", self.k["observe"], ((bx, nk), self.tpb, s), self._observe_args() + (sums.acc,))
        sums.acc.copy_to_host(sums.host, stream=s)
        self._wait_stream()
        return sums.host.copy()

    def observe(self) -> list:
        """Per scene: the observables of :meth:`CudaBackend.observe` (:meth:`_observables`), None for an
        inactive scene."""
        sums = self._observe_sums()
        return [self._observables(s, sums[s].tolist()) if self.active[s] else None for s in range(self.n_scenes)]


class _ObserveSlot:
    """The observe kernel's device accumulator (K, NOBS) and its pinned host buffer
    (:meth:`ObserveSums._observe_sums`)."""

    def __init__(self, n_scenes: int, nobs: int, stream):
        # the simulator has no memset on a stream: zeros are copied in
        self.acc_zero = np.zeros((n_scenes, nobs), np.float64) if SIM else None
        self.acc = cuda.device_array((n_scenes, nobs), np.float64, stream=stream)
        self.host = cuda.pinned_array((n_scenes, nobs), np.float64)
