"""HDF5 result files in the H5MD 1.1 layout (nongnu.org/h5md), with a declared `dem` module.

Layout (docs/design.md §5)::

    /h5md                      version=[1,1]; author/@name; creator/@name,@version; modules/dem/@version
    /particles/all/box         @dimension=3, @boundary=[periodic]*3, edges=[L,L,L]
    /particles/all/<element>   {step, time, value[T][N][D]} for position, velocity, orientation,
                               angular_velocity (resizable, one frame per chunk)
    /particles/all/id, species, mass, radius | semi_axes       fixed per-particle data
    /observables/<name>        {step, time, value[T]} scalar time series: kinetic_energy_translational,
                               kinetic_energy_rotational, temperature_translational, temperature_rotational
                               (J), contacts, elastic_energy (J), max_overlap (/radius), and the
                               dimensionless velocity-distribution cumulants sonine_a2_translational,
                               sonine_a2_rotational, sonine_a11 (engine/physics/sonine.py), and for
                               spheres collisions (contacts begun since the scene started, cumulative)
    /parameters                @spec (JSON), derived parameters, engine version, backend, device,
                               wall time, Cundall number

The `dem` module: quaternions are scalar-first (w, x, y, z) and rotate body into space frame;
angular velocity is given in the space frame; spheres carry `radius`, spheroids `semi_axes` (a, b, c)
with a along the body x axis.

The writer works on ``<path>.part`` and renames it to ``<path>`` only in :meth:`H5MDWriter.finish`:
a reader never sees a half-written result. Non-finite values are refused before they are written.

Cost (docs/design.md §5): observables are kept in memory and written in blocks of :data:`OBSERVABLE_BLOCK` records
(one resize and one write per dataset per block, also at :meth:`H5MDWriter.flush`, at checkpoints and at
:meth:`H5MDWriter.finish`), so a record costs O(1) host work; a snapshot frame is one resize and one write
per element. With ``background=True`` the file work (creation, blocks of records, snapshot frames) runs on
one I/O thread shared by every writer of the process (HDF5 serialises its calls anyway), in submission
order, while the caller goes on (e.g. the GPU integrates): :meth:`H5MDWriter.flush`, :meth:`frame_counts`,
:meth:`truncate` and :meth:`finish` wait for it. A failure on that thread (e.g. a non-finite snapshot value)
is raised by the writer's next call, and the file is then never finished.

With ``deferred=True`` (the small scenes of a GPU ensemble, engine/driver/simulate.py) nothing touches the disk
before the end: the writer keeps its blocks of records and copies of its snapshot frames in memory, and
:meth:`H5MDWriter.finish_async` hands them to a writer process (engine/output/h5md_pool.py) that writes the same
file with this class's own code, so the files of scenes that end together are written in parallel. A
checkpoint (:meth:`flush`, :meth:`frame_counts`, :meth:`truncate`) first writes the file the usual way and
the writer goes on as a ``background`` one.
"""

from __future__ import annotations

import json
import math
import os
import threading
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import h5py
import numpy as np

from engine.errors import InstabilityError
from engine.output.pieces import FRAME_PIECE_ROWS, PIECE, map_pieces
from engine.output.xdmf import write_xdmf, xdmf_text

UNITS = {
    "position": "m", "velocity": "m s-1", "orientation": "", "angular_velocity": "s-1",
    "kinetic_energy_translational": "J", "kinetic_energy_rotational": "J",
    "temperature_translational": "J", "temperature_rotational": "J", "contacts": "",
    "elastic_energy": "J", "max_overlap": "", "momentum": "kg m s-1",
    "sonine_a2_translational": "", "sonine_a2_rotational": "", "sonine_a11": "", "collisions": "",
}
SNAPSHOT_ELEMENTS = ("position", "velocity", "orientation", "angular_velocity")
DEM_MODULE_VERSION = [1, 0]
#: observable records kept in memory before they are written (one HDF5 write per dataset per block)
OBSERVABLE_BLOCK = 512
#: the most bytes one chunk of a frame series holds: a larger frame is stored in chunks of whole particle rows
#: (HDF5 before 2.0 refuses a chunk of 4 GiB or more: a frame of 3.6e8 float32 or 1.8e8 float64 positions)
CHUNK_MAX_BYTES = 1 << 30


#: snapshot frames a background writer may hold in its queue before snapshot() waits (memory bound)
MAX_QUEUED_FRAMES = 2

_io_lock = threading.Lock()
_io_pool = None


def _records() -> tuple:
    """An empty block of observable records: ([steps], [times], [{name: value}]). Three lists, not a tuple per
    record: a record's step, time and dict of numbers are objects the cyclic garbage collector does not track, so
    the records a long run (or 256 packed scenes) keeps in memory add no work to its collections, which otherwise
    paused a packed GPU run's time loop for up to 0.1 s (docs/performance.md, "Packed ensembles")."""
    return [], [], []


def _io() -> ThreadPoolExecutor:
    """The process's one HDF5 I/O thread (background writers)."""
    global _io_pool
    with _io_lock:
        if _io_pool is None:
            _io_pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="demq-h5io")
        return _io_pool


def partial_path(path) -> Path:
    return Path(str(path) + ".part")


class H5MDWriter:
    """Appends observables and snapshots to ``<path>.part``; :meth:`finish` renames it to ``path``."""

    def __init__(self, path, *, n: int, box_length: float, spec_json: str, derived: dict,
                 radius=None, semi_axes=None, mass=None, species=None, creator_version: str = "",
                 author: str = "demq", dtype=np.float64, resume: bool = False, background: bool = False,
                 deferred: bool = False):
        """species: int (N,) species index of every particle (the position in the spec's ``species``
        list); None writes zeros (one size). background: file work on the I/O thread (module docstring);
        snapshot() then keeps the arrays it is given until they are written: do not modify them.
        deferred: keep the whole file in memory and write it in a writer process at the end (module
        docstring); snapshot() copies its arrays."""
        self.path = Path(path)
        self.tmp = partial_path(self.path)
        self.n = n
        self.dtype = np.dtype(dtype)
        self.f = None
        self._pending = _records()   # records not yet written (steps, times, {name: value} dicts)
        self._groups: dict = {}      # observable name -> its [step, time, value] datasets
        self._frame_series: dict = {}  # per-particle element name -> its _FrameSeries
        self._bg = background
        self._jobs: deque = deque()  # futures of the background file work, in order
        self._frames: deque = deque()  # futures of queued snapshot frames
        self._deferred = False
        if resume:
            self.f = h5py.File(self.tmp, "a")
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._create_args = (n, box_length, spec_json, derived, radius, semi_axes, mass, species, creator_version,
                             author)
        if deferred:
            self._deferred = True
            self._blocks: list = []       # blocks of records not yet in a file, in order
            self._frames_kept: list = []  # (step, time, arrays) snapshot frames not yet in a file
            return
        self._submit(self._create, *self._create_args)

    # ---- the I/O thread ------------------------------------------------------------------------------

    def _submit(self, fn, *args):
        """Run fn(*args) now, or on the I/O thread after the writer's earlier work (background)."""
        if not self._bg:
            return fn(*args)
        while self._jobs and self._jobs[0].done():
            self._jobs.popleft().result()  # raises a failure of earlier work here, in the caller
        fut = _io().submit(fn, *args)
        self._jobs.append(fut)
        return fut

    def _wait(self) -> None:
        """Wait for every queued piece of file work; raise the first failure."""
        first = None
        while self._jobs:
            try:
                self._jobs.popleft().result()
            except BaseException as exc:  # noqa: BLE001  (kept, raised after the queue is drained)
                first = first or exc
        self._frames.clear()
        if first is not None:
            raise first

    def _create(self, n, box_length, spec_json, derived, radius, semi_axes, mass, species, creator_version,
                author) -> None:
        self.f = f = h5py.File(self.tmp, "w")
        h5 = f.create_group("h5md")
        h5.attrs["version"] = np.array([1, 1], dtype=np.int32)
        h5.create_group("author").attrs["name"] = author
        cr = h5.create_group("creator")
        cr.attrs["name"] = "demq"
        cr.attrs["version"] = creator_version
        dem = h5.create_group("modules").create_group("dem")
        dem.attrs["version"] = np.array(DEM_MODULE_VERSION, dtype=np.int32)
        dem.attrs["quaternion_order"] = "wxyz"
        dem.attrs["quaternion_convention"] = "body-to-space, scalar first"
        dem.attrs["angular_velocity_frame"] = "space"
        dem.attrs["shape_data"] = "radius" if semi_axes is None else "semi_axes"
        part = f.create_group("particles").create_group("all")
        box = part.create_group("box")
        box.attrs["dimension"] = 3
        box.attrs["boundary"] = np.array([b"periodic"] * 3)
        edges = box.create_dataset("edges", data=np.full(3, box_length, dtype=np.float64))
        edges.attrs["unit"] = "m"
        ids = part.create_dataset("id", shape=(n,), dtype=np.int64)
        for lo in range(0, n, FRAME_PIECE_ROWS):
            ids[lo:min(n, lo + FRAME_PIECE_ROWS)] = np.arange(lo, min(n, lo + FRAME_PIECE_ROWS), dtype=np.int64)
        _per_particle(part, "species", n, np.int32, np.zeros(1, np.int32) if species is None else species)
        if mass is not None:
            _per_particle(part, "mass", n, np.float64, mass).attrs["unit"] = "kg"
        if semi_axes is not None:
            _per_particle(part, "semi_axes", n, np.float64, semi_axes).attrs["unit"] = "m"
        elif radius is not None:
            _per_particle(part, "radius", n, np.float64, radius).attrs["unit"] = "m"
        f.create_group("observables")
        par = f.create_group("parameters")
        par.attrs["spec"] = spec_json
        for key, value in derived.items():
            par.attrs[key] = _attr(value)

    # ---- appending ---------------------------------------------------------------------------------

    def _series(self, group: h5py.Group, name: str, shape_tail: tuple, dtype) -> "_FrameSeries":
        """The per-particle element ``name``'s time series (created at its first frame), its datasets' handles
        kept for the later frames."""
        series = self._frame_series.get(name)
        if series is not None:
            return series
        if name in group:  # a resumed file
            g = group[name]
        else:
            g = group.create_group(name)
            g.create_dataset("step", shape=(0,), maxshape=(None,), dtype=np.int64, chunks=(1024,))
            t = g.create_dataset("time", shape=(0,), maxshape=(None,), dtype=np.float64, chunks=(1024,))
            t.attrs["unit"] = "s"
            chunks = frame_chunks(shape_tail, np.dtype(dtype).itemsize) if shape_tail else (1024,)
            v = g.create_dataset("value", shape=(0,) + shape_tail, maxshape=(None,) + shape_tail,
                                 dtype=dtype, chunks=chunks)
            unit = UNITS.get(name, "")
            if unit:
                v.attrs["unit"] = unit
        series = self._frame_series[name] = _FrameSeries(g["step"], g["time"], g["value"])
        return series

    def observables(self, step: int, time: float, values: dict) -> None:
        """Append one record of scalar observables (kept in memory, ``values`` itself: do not modify it;
        written in blocks, see the module docstring). A non-finite value raises InstabilityError and is never
        written."""
        for name, value in values.items():
            if not math.isfinite(value):
                raise InstabilityError(f"observable {name} is not finite at step {step} (t = {time:g} s): "
                                       f"the run blew up; nothing non-finite is written", step=step)
        steps, times, rows = self._pending
        steps.append(step)
        times.append(time)
        rows.append(values)
        if len(steps) >= OBSERVABLE_BLOCK:
            self._write_pending()

    def _write_pending(self) -> None:
        """Hand the observables kept in memory to the file (now, or queued on the I/O thread)."""
        if not self._pending[0]:
            return
        rows, self._pending = self._pending, _records()
        if self._deferred:
            self._blocks.append(rows)
            return
        self._submit(self._write_block, rows)

    def _write_block(self, rows: tuple) -> None:
        """Write a block of observable records ([steps], [times], [{name: value}]): one write per dataset and name
        (a new series is created with its first block as data; later blocks resize it once)."""
        block: dict = {}  # name -> ([steps], [times], [values]), in the writer's thread, not the caller's
        for step, time, values in zip(*rows):
            for name, value in values.items():
                col = block.get(name)
                if col is None:
                    col = block[name] = ([], [], [])
                col[0].append(step)
                col[1].append(time)
                col[2].append(value)
        obs = None
        for name, (steps, times, values) in block.items():
            vals = np.asarray(values)
            dtype = np.int64 if vals.dtype.kind in "iub" else np.float64
            cols = (("step", np.asarray(steps, np.int64)), ("time", np.asarray(times, np.float64)),
                    ("value", vals.astype(dtype, copy=False)))
            g = self._groups.get(name)
            if g is None:
                obs = obs or self.f["observables"]
                if name in obs:  # a resumed file
                    g = self._groups[name] = [obs[name][key] for key in ("step", "time", "value")]
                else:
                    grp = obs.create_group(name)
                    g = self._groups[name] = [grp.create_dataset(key, data=data, maxshape=(None,), chunks=(1024,))
                                              for key, data in cols]
                    g[1].attrs["unit"] = "s"
                    if UNITS.get(name):
                        g[2].attrs["unit"] = UNITS[name]
                    continue
            k, m = g[0].shape[0], len(steps)
            for ds, (_, data) in zip(g, cols):
                ds.resize(k + m, axis=0)
                ds[k:k + m] = data

    def snapshot(self, step: int, time: float, arrays: dict) -> None:
        """Append one frame of the per-particle elements (arrays in id order). Background: queued (at most
        MAX_QUEUED_FRAMES frames wait) and the future of its write returned: the arrays must stay unmodified
        until it is done. Deferred: checked for finite values and copied (returns None). Otherwise written
        at once (returns None)."""
        if self._deferred:
            kept = {}
            for name, a in arrays.items():
                a = np.array(a, copy=True)
                _check_finite(name, a, step, time)
                kept[name] = a
            self._frames_kept.append((step, time, kept))
            return None
        if self._bg:
            while len(self._frames) >= MAX_QUEUED_FRAMES:
                self._frames.popleft().result()
            fut = self._submit(self._write_frame, step, time, arrays)
            self._frames.append(fut)
            return fut
        self._write_frame(step, time, arrays)
        return None

    def snapshot_pieces(self, step: int, time: float, n: int, pieces, left_out=()) -> None:
        """Append one frame of ``n`` particles given in pieces: (first row, {element: (m, D) array}) in row order,
        each piece's arrays valid until two more pieces are taken (engine/loops/cuda_frames.py ``_state_pieces``);
        elements named in ``left_out`` are not written. Each piece is checked for finite values and written into
        its rows of the frame (one chunk each: :func:`frame_chunks`), on the I/O thread while the next piece is
        copied (background); returns when the frame is in the file. No copy of the whole frame is made. A
        non-finite piece raises InstabilityError (the run fails, and its partial file is never a result)."""
        self._materialize()
        pending: deque = deque()
        begun = False
        for lo, arrays in pieces:
            arrays = {name: a for name, a in arrays.items() if name in SNAPSHOT_ELEMENTS and name not in left_out}
            if not begun:
                self._submit(self._begin_frame, step, time, n, {name: a.shape[1:] for name, a in arrays.items()})
                begun = True
            fut = self._submit(self._write_piece, step, time, lo, arrays)
            if fut is not None:
                pending.append(fut)
            while len(pending) >= 2:    # the next piece reuses the buffers of the oldest one in flight
                pending.popleft().result()
        while pending:
            pending.popleft().result()

    def _begin_frame(self, step: int, time: float, n: int, tails: dict) -> None:
        part = self.f["particles/all"]
        self._piece_frame = {name: (series := self._series(part, name, (n,) + tuple(tail), self.dtype),
                                    series.begin(step, time))
                             for name, tail in tails.items()}

    def _write_piece(self, step: int, time: float, lo: int, arrays: dict) -> None:
        for name, a in arrays.items():
            _check_finite(name, a, step, time)
            series, k = self._piece_frame[name]
            series.write_rows(k, lo, a)

    def _write_frame(self, step: int, time: float, arrays: dict) -> None:
        part = self.f["particles/all"]
        for name in SNAPSHOT_ELEMENTS:
            if name not in arrays:
                continue
            a = np.asarray(arrays[name])
            _check_finite(name, a, step, time)
            self._series(part, name, a.shape, self.dtype).append(step, time, a)

    def _materialize(self) -> None:
        """A deferred writer writes its file now and goes on as an ordinary (background) one."""
        if not self._deferred:
            return
        self._deferred = False
        self._submit(self._create, *self._create_args)
        for block in self._blocks:
            self._submit(self._write_block, block)
        for step, time, arrays in self._frames_kept:
            self._submit(self._write_frame, step, time, arrays)
        self._blocks, self._frames_kept = [], []

    def frame_counts(self) -> dict:
        """Number of records of every time series (for checkpoints; writes pending records first)."""
        self._materialize()
        self._write_pending()
        self._wait()
        out = {}
        for root in ("observables", "particles/all"):
            for name, g in self.f[root].items():
                if isinstance(g, h5py.Group) and "step" in g:
                    out[f"{root}/{name}"] = int(g["step"].shape[0])
        return out

    def truncate(self, counts: dict) -> None:
        """Cut every time series back to the given record counts (resume from a checkpoint)."""
        self._materialize()
        self._write_pending()
        self._wait()
        self._frame_series.clear()   # their frame counts are read again at the next append
        for key, k in counts.items():
            if key in self.f:
                for ds in ("step", "time", "value"):
                    self.f[key][ds].resize(k, axis=0)

    def flush(self) -> None:
        """Write pending records and flush the file (a copy of it is then complete, e.g. a checkpoint)."""
        self._materialize()
        self._write_pending()
        self._wait()
        self.f.flush()

    # ---- closing -----------------------------------------------------------------------------------

    def finish_async(self, run_info: dict) -> Future:
        """:meth:`finish`, as a future of the final path: a deferred writer's file is written by a writer
        process meanwhile (engine/output/h5md_pool.py); any other writer finishes now."""
        if self._deferred:
            from engine.output import h5md_pool

            self._write_pending()
            n, box_length, spec_json, derived, radius, semi_axes, mass, species, creator_version, author = \
                self._create_args
            kwargs = dict(n=n, box_length=box_length, spec_json=spec_json, derived=derived, radius=radius,
                          semi_axes=semi_axes, mass=mass, species=species, creator_version=creator_version,
                          author=author, dtype=self.dtype)
            blocks, frames = self._blocks, self._frames_kept
            self._blocks, self._frames_kept, self._deferred = [], [], False
            return h5md_pool.submit(write_whole_file, self.path, kwargs, blocks, frames, run_info)
        fut: Future = Future()
        try:
            fut.set_result(self.finish(run_info))
        except Exception as exc:  # noqa: BLE001  (the caller gets it from the future)
            fut.set_exception(exc)
        return fut

    def finish(self, run_info: dict) -> Path:
        """Write the run attributes, close, and atomically rename the file to its final name."""
        if self._deferred:
            return self.finish_async(run_info).result()
        self._write_pending()
        self._wait()
        par = self.f["parameters"]
        for key, value in run_info.items():
            par.attrs[key] = _attr(value)
        # ParaView/VisIt sidecar <stem>.xmf (engine/output/xdmf.py; a result without frames has none), read from the
        # open file (no second open of it) and written once the result has its final name
        sidecar = xdmf_text(self.path, f=self.f) if "position" in self.f["particles/all"] else None
        self.f.close()
        replace_file(self.tmp, self.path)
        if sidecar is not None:
            write_xdmf(self.path, text=sidecar)
        return self.path

    def abort(self) -> None:
        """Close and delete the partial file."""
        try:
            try:
                self._wait()
            except BaseException:  # noqa: BLE001  (the file is deleted anyway)
                pass
            if self.f is not None:
                self.f.close()
        finally:
            if self.tmp.exists():
                self.tmp.unlink()


class _FrameSeries:
    """The step, time and value datasets of one per-particle element's time series, held open: a frame of a small
    scene cost about 4 ms of h5py's Python when every append looked its datasets up by name and read the value
    dataset's creation properties again (64 spheres, 2-core VM)."""

    def __init__(self, step: h5py.Dataset, time: h5py.Dataset, value: h5py.Dataset):
        self.step, self.time, self.value = step, time, value
        self.frames = step.shape[0]
        self.plain = (value.compression is None and not value.shuffle and not value.fletcher32
                      and value.scaleoffset is None)   # no filter: a frame's bytes are its chunk's

    def append(self, step: int, time: float, value) -> None:
        """Append one frame: one chunk, or chunks of whole particle rows (:func:`frame_chunks`), written by
        :meth:`write_rows`."""
        self.write_rows(self.begin(step, time), 0, value)

    def begin(self, step: int, time: float) -> int:
        """Append a frame's step and time, and room for its values (written by :meth:`write_rows`); its index."""
        k = self.frames
        for ds in (self.step, self.time, self.value):
            ds.resize(k + 1, axis=0)
        self.step[k] = step
        self.time[k] = time
        self.frames = k + 1
        return k

    def write_rows(self, k: int, lo: int, a: np.ndarray) -> None:
        """Rows lo ... lo + len(a) - 1 of frame k: chunk by chunk as they are (H5Dwrite_chunk, a last chunk padded
        with the fill value's zeros) where the array is their bytes already (C order, the dataset's type, no filter)
        and its rows start a chunk and fill it or end the frame (218 MB took 0.07 s instead of 0.22-0.27 s through
        HDF5's copy on the H200 host); otherwise through HDF5, flushed at once (the same file either way)."""
        a = np.asarray(a)
        chunks, n = self.value.chunks, self.value.shape[1]
        rows = chunks[1]
        if not (self.plain and a.ndim >= 1 and chunks[2:] == a.shape[1:] and a.dtype == self.value.dtype
                and a.flags.c_contiguous and a.size and lo % rows == 0
                and (a.shape[0] % rows == 0 or lo + a.shape[0] == n)):
            self.value[k, lo:lo + a.shape[0]] = a
            self.value.flush()
            return
        for r0 in range(0, a.shape[0], rows):
            block = a[r0:r0 + rows]
            if block.shape[0] < rows:
                padded = np.zeros((rows,) + a.shape[1:], a.dtype)
                padded[:block.shape[0]] = block
                block = padded
            self.value.id.write_direct_chunk((k, lo + r0) + (0,) * (a.ndim - 1), block)


def _per_particle(group: h5py.Group, name: str, n: int, dtype, values) -> h5py.Dataset:
    """A per-particle constant (n rows; ``values``: an (n, ...) array, or one row for all): where every row is the
    same (one row given, a broadcast view, or all equal), a chunked dataset whose fill value is that row and of which
    no chunk is ever written, so that it takes neither disk nor a host copy (a billion spheres' radius alone would be
    8 GB of both) and reads back as the row everywhere; otherwise the values, written a piece at a time."""
    a = np.asarray(values)
    if a.ndim == 0:
        a = a.reshape(1)
    tail = a.shape[1:]
    one = a.shape[0] == 1 or (a.shape[0] == n and n > 0 and (a.strides[0] == 0 or bool(np.all(a == a[0]))))
    if one and n > 0 and not tail:
        return group.create_dataset(name, shape=(n,), dtype=dtype, chunks=(min(n, 1 << 20),),
                                    fillvalue=np.asarray(a[0], dtype))
    if one:
        a = np.broadcast_to(a[:1], (n,) + tail)
    ds = group.create_dataset(name, shape=(n,) + tail, dtype=dtype)
    for lo in range(0, n, FRAME_PIECE_ROWS):
        ds[lo:min(n, lo + FRAME_PIECE_ROWS)] = np.asarray(a[lo:lo + FRAME_PIECE_ROWS], dtype)
    return ds


def frame_chunks(shape_tail: tuple, itemsize: int) -> tuple:
    """The chunk shape of a frame series of frames ``shape_tail`` (N, D): the whole frame (1, N, D), or, above
    :data:`CHUNK_MAX_BYTES`, (1, rows, D) with as many whole rows as fit; at most FRAME_PIECE_ROWS rows (a larger
    frame is written in pieces of that many, one chunk each: :meth:`H5MDWriter.snapshot_pieces`)."""
    row = itemsize * int(np.prod(shape_tail[1:], dtype=np.int64))
    rows = min(shape_tail[0], FRAME_PIECE_ROWS)
    if rows * row > CHUNK_MAX_BYTES:
        rows = max(1, CHUNK_MAX_BYTES // row)
    return (1, rows) + tuple(shape_tail[1:])


def replace_file(src, dst) -> None:
    """os.replace(src, dst), with the file it replaces freed on a thread: the blocks and cached pages of an
    earlier result are freed when its last descriptor closes, which for a 2M-sphere file with two frames (436 MB)
    took 0.1-0.2 s on the H200 host; the new file is in place at once either way."""
    try:
        old = os.open(dst, os.O_RDONLY)
    except OSError:   # no earlier file (or not one to open): nothing to free
        old = None
    try:
        os.replace(src, dst)
    finally:
        if old is not None:
            threading.Thread(target=os.close, args=(old,), name="demq-free-old", daemon=True).start()


def writer_process_ready() -> int:
    """What a writer process runs first (engine/output/h5md_pool.prewarm): importing this module is its start-up."""
    return os.getpid()


def write_whole_file(path, kwargs: dict, blocks: list, frames: list, run_info: dict) -> Path:
    """Write a deferred writer's file at once (in a writer process): create, blocks of records, frames,
    run attributes, close, rename; a failure leaves no file."""
    w = H5MDWriter(path, **kwargs)
    try:
        for block in blocks:
            w._write_block(block)
        for step, time, arrays in frames:
            w._write_frame(step, time, arrays)
        return w.finish(run_info)
    except BaseException:
        w.abort()
        raise


#: arrays of more elements than this are checked for finite values in pieces, on several threads
_FINITE_SPLIT = PIECE


def _all_finite(a: np.ndarray) -> bool:
    """np.isfinite(a).all(), a large array in pieces on up to 8 threads (engine/output/pieces.py): one 2M-particle frame
    took 0.03-0.06 s on one thread, on the path from the last step to the closed file."""
    return all(map_pieces(a, lambda p: bool(np.isfinite(p).all()), _FINITE_SPLIT))


def _check_finite(name: str, a: np.ndarray, step: int, time: float) -> None:
    if not _all_finite(np.asarray(a)):
        raise InstabilityError(f"{name} is not finite at step {step} (t = {time:g} s): the run "
                               f"blew up; nothing non-finite is written", step=step)


def _attr(value):
    if value is None:
        return "null"
    if isinstance(value, (dict, list)) and not (isinstance(value, list) and value and
                                                 all(isinstance(x, (int, float)) for x in value)):
        return json.dumps(value)
    if isinstance(value, tuple):
        return np.asarray(value, dtype=np.float64)
    return value


def read_series(path, name: str) -> dict:
    """{step, time, value} arrays of one observable of a result file."""
    with h5py.File(path, "r") as f:
        g = f["observables"][name]
        return {"step": g["step"][()], "time": g["time"][()], "value": g["value"][()]}


def read_parameters(path) -> dict:
    """The /parameters attributes, with `spec` parsed from JSON."""
    with h5py.File(path, "r") as f:
        out = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f["parameters"].attrs.items()}
    out["spec"] = json.loads(out["spec"])
    return out


def read_frames(path):
    """The snapshot frames of a result file, one at a time (the layout above): yields dicts with ``step``,
    ``time`` (s), ``position`` (N, 3; m), ``velocity`` (N, 3; m/s), ``box`` (edge, m) and ``mass`` ((N,) kg,
    or None where the file stores none), for the frames that hold both positions and velocities. A file without
    snapshot frames raises ValueError naming it."""
    with h5py.File(path, "r") as f:
        part = f["particles/all"]
        if "position" not in part or "velocity" not in part:
            raise ValueError(f"{path}: no snapshot frames (spec 'snapshots' was 0)")
        box = float(np.asarray(part["box/edges"][()]).ravel()[0])
        mass = part["mass"][()] if "mass" in part else None
        pg, vg = part["position"], part["velocity"]
        for j in range(min(pg["value"].shape[0], vg["value"].shape[0])):
            yield {"step": int(pg["step"][j]), "time": float(pg["time"][j]), "position": pg["value"][j],
                   "velocity": vg["value"][j], "box": box, "mass": mass}
