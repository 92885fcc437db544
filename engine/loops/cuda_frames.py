"""Host copies of a CUDA ensemble's scene state (snapshots, checkpoints): :class:`StateFrames`, a part of
:class:`engine.loops.cuda_ensemble.CudaEnsembleBase`.

A kernel gathers a scene's slots into particle-id order on the device, into one reused staging buffer, and one copy
per array moves exactly that scene's rows into a reused host buffer slot. Small slots are pinned; large ones are plain
memory faulted in by threads and page-locked in place (or, where that is refused, replaced by pinned buffers made on
a thread after a few frames). The staging buffer holds at most FRAME_PIECE_ROWS particles (engine/output/pieces.py):
a larger scene is gathered a piece of ids at a time. :meth:`StateFrames._state_pieces` hands such a scene's frame out
in those pieces, through two pinned piece buffers, so that no host buffer holds the whole frame either.
"""

from __future__ import annotations

import threading
from typing import Optional

import numpy as np
from numba import cuda

from engine.loops import cuda_kernels as K
from engine.loops.cuda_cache import SIM
from engine.numba_support.numba_internals import page_lock
from engine.output.pieces import FRAME_PIECE_ROWS, map_pieces

#: a snapshot buffer slot (all state arrays of the largest scene) larger than this is pageable memory, page-locked in
#: place (StateFrames._host_slot)
PINNED_SLOT_BYTES = 32 << 20
#: ... or, where it cannot be, replaced by pinned buffers (allocated on a thread) after this many large frames
PIN_AFTER_FRAMES = 3
#: host buffers of :meth:`StateFrames._state_pieces`, used in turn: a piece stays valid until this many more are taken
PIECE_BUFFERS = 2


class StateFrames:
    """The state-copy part of a CUDA ensemble: :meth:`_scene_rows` and its host buffer slots. The ensemble provides
    ``stream``, ``starts``, ``sizes``, ``dtype``, ``pos_dtype``, ``ids``, ``_grid``, :meth:`state_arrays` and
    :meth:`_close` (velocities level with the positions)."""

    def _init_frames(self) -> None:
        """The buffers are made at their first use; a large scene's first slot on a thread during the build."""
        self._stage = None                      # device staging buffers per dtype
        self._stage_h: dict = {}                # buffer slot -> host buffers
        self._piece_h: list = []                # the pinned host buffers of _state_pieces (PIECE_BUFFERS sets)
        self._slot_prep = None                  # a first frame slot being made on a thread (_prepare_frame_slot)
        self._pinned_slots: Optional[dict] = None   # pinned replacements of pageable slots, made on a thread
        self._pageable_slots: set = set()
        self._page_locks: list = []             # the page-lock registrations (their lifetime)
        self._frames_taken = 0

    def _scene_rows(self, k: int, reuse=False) -> dict:
        """Scene k's state arrays (n_k, rows) in particle-id order, keyed as in :meth:`state_arrays`: per array
        a kernel gathers the scene's slots into id order on the device, into one reused staging buffer, and
        one copy moves exactly those n_k rows into a reused host buffer (:meth:`_host_slot`); one sync for all.
        ``reuse``: False returns copies; True or a buffer slot number returns views of that slot's host
        buffers (slot 0 for True), valid until the next call with the same slot."""
        self._close()
        s = self.stream
        a0, n_k = int(self.starts[k]), int(self.sizes[k])
        nmax = int(self.sizes.max())
        piece = self._staged(nmax)
        slot = 0 if reuse is False or reuse is True else int(reuse)
        bufs = self._host_slot(slot, nmax)
        out = {}
        for key, src in self.state_arrays().items():
            host = bufs[key][:n_k]
            for lo in range(0, n_k, piece):
                hi = min(n_k, lo + piece)
                self._gather(src, a0, n_k, lo, hi).copy_to_host(host[lo:hi], stream=s)
            out[key] = host
        s.synchronize()
        return out if reuse is not False else {key: a.copy() for key, a in out.items()}

    def _state_pieces(self, k: int, rows: int):
        """Scene k's state arrays in particle-id order, in pieces of ``rows`` particles (at most FRAME_PIECE_ROWS):
        yields (first id, {key: (m, D) host array}) in id order, each piece's arrays valid until PIECE_BUFFERS more
        are taken. Per piece a kernel gathers the slots of those ids into the staging buffer and one copy per
        array moves them into one of PIECE_BUFFERS pinned host buffers, one sync per piece: neither the device nor
        the host holds a copy of the whole frame, and the caller writes a piece while the next one is copied."""
        self._close()
        s = self.stream
        a0, n_k = int(self.starts[k]), int(self.sizes[k])
        rows = max(1, min(int(rows), self._staged(int(self.sizes.max()))))
        shapes = self._slot_shapes(min(rows, n_k))
        if not self._piece_h or any(bufs[key].shape[0] < sh[0] for bufs in self._piece_h
                                    for key, (sh, _) in shapes.items()):
            self._piece_h = [{key: cuda.pinned_array(sh, t) for key, (sh, t) in shapes.items()}
                             for _ in range(PIECE_BUFFERS)]
        for j, lo in enumerate(range(0, n_k, rows)):
            hi = min(n_k, lo + rows)
            bufs, out = self._piece_h[j % PIECE_BUFFERS], {}
            for key, src in self.state_arrays().items():
                out[key] = bufs[key][:hi - lo]
                self._gather(src, a0, n_k, lo, hi).copy_to_host(out[key], stream=s)
            s.synchronize()
            yield lo, out

    def _staged(self, nmax: int) -> int:
        """The staging buffers (per dtype, four rows of the particles of a piece) made where missing or too small;
        returns the particles a piece holds: all of the largest scene's up to FRAME_PIECE_ROWS."""
        piece = max(1, min(nmax, FRAME_PIECE_ROWS))
        types = {np.dtype(t).str: t for t in (self.dtype, self.pos_dtype)}
        if self._stage is None or any(self._stage[key].shape[0] < 4 * piece for key in types):
            self._stage = {key: cuda.device_array(4 * piece, t, stream=self.stream) for key, t in types.items()}
        return piece

    def _gather(self, src, a0: int, n_k: int, lo: int, hi: int):
        """The particles lo ... hi - 1 of the scene at a0 (n_k particles) of the (rows, N) array ``src``, in id order,
        gathered into the staging buffer: a (hi - lo, rows) device view."""
        rows = src.shape[0]
        dst = self._stage[src.dtype.str][:(hi - lo) * rows].reshape(hi - lo, rows)
        K.gather_scene[self._grid(n_k)](src, self.ids, a0, n_k, lo, hi, dst)
        return dst

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
        pinned = self._pinned_slots
        if big and pinned is not None and pinned.get(slot) is not None:
            self._stage_h[slot] = pinned.pop(slot)
        elif slot not in self._stage_h:
            prep, self._slot_prep = self._slot_prep, None
            made = {}
            if prep is not None and big and prep[2] == shapes:     # made on a thread during the build
                prep[0].join()
                made = prep[1]
            alloc = _touched_empty if big else cuda.pinned_array
            self._stage_h[slot] = bufs = made.get("bufs") or {key: alloc(sh, t) for key, (sh, t) in shapes.items()}
            if big:
                pins = made.get("pins") if "bufs" in made else _page_locked(bufs.values())
                if pins is None:
                    self._pageable_slots.add(slot)
                else:
                    self._page_locks.append(pins)   # the registrations' lifetime
        self._frames_taken += 1
        pageable = self._pageable_slots
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
        return {key: ((nmax, a.shape[0]), a.dtype) for key, a in self.state_arrays().items()}

    def _prepare_frame_slot(self) -> None:
        """A large scene's first frame slot, made on a thread while the build goes on (its state arrays exist): the
        buffers faulted in and page-locked as :meth:`_host_slot` makes them (about 30 ms for 2M spheres, which the
        first snapshot waited for), taken by the first :meth:`_host_slot` call (which waits for the thread)."""
        nmax = int(self.sizes.max())
        shapes = self._slot_shapes(nmax)
        if SIM or not _big_slot(shapes) or (nmax > FRAME_PIECE_ROWS and hasattr(self, "state_pieces")):
            return      # (the snapshots of a scene of more than FRAME_PIECE_ROWS come in pieces, without a slot)
        made: dict = {}

        def work() -> None:
            bufs = {key: _touched_empty(sh, t) for key, (sh, t) in shapes.items()}
            made["pins"] = _page_locked(bufs.values())
            made["bufs"] = bufs

        t = threading.Thread(target=work, name="demq-frame-slot", daemon=True)
        t.start()
        self._slot_prep = (t, made, shapes)


def _big_slot(shapes: dict) -> bool:
    """Whether a frame slot of these host buffers is large (over PINNED_SLOT_BYTES: not pinned-allocated)."""
    return sum(int(np.prod(sh)) * np.dtype(t).itemsize for sh, t in shapes.values()) > PINNED_SLOT_BYTES


def _page_locked(arrays) -> Optional[list]:
    """Page-lock host arrays in place (engine.numba_support.numba_internals.page_lock: cuMemHostRegister): copies to and
    from them run at pinned speed and asynchronously. The returned handles keep the registration until they are
    collected, and keep their arrays alive. None under the simulator or when the driver refuses (the arrays stay
    pageable)."""
    if SIM:
        return None
    try:
        return page_lock(arrays)
    except Exception:  # noqa: BLE001  (no page-locked memory to be had: pageable copies, as before)
        return None


def _touched_empty(shape, dtype) -> np.ndarray:
    """np.empty(shape, dtype) with every page already faulted in, in pieces on up to 8 threads
    (engine/output/pieces.py): a device copy into fresh pageable memory takes its page faults one at a time (218 MB:
    0.06-0.08 s on the H200 host, 0.02 s into touched memory)."""
    a = np.empty(shape, dtype)
    page = max(1, 4096 // a.itemsize)
    map_pieces(a, lambda p: p.__setitem__(slice(None, None, page), 0))
    return a
