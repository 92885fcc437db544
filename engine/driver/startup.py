"""The GPU's start-up, overlapped with the host's set-up of a job (time to result).

A process's first CUDA job pays one-off costs before its first step: the CUDA driver's start-up and the primary
context (driver calls, which release the GIL), and the load of its kernels from numba-cuda's disk cache (their
modules go to the driver, which also releases the GIL). :func:`begin` starts them on a background thread on a
small stand-in scene of the job's specialisation (shape, precision, contact law, orientation: the compile-time
choices of engine/loops/cuda_loop.py), while the calling thread places the job's particles; the job's backend
then finds a live context and loaded kernels. What cannot overlap is Python work under the GIL (imports, numba's
typing registries), which either thread pays once; the thread does what needs no context first (the shape's
``prepare_kernels``: the kernel sets' dispatchers), while the driver starts, and the caller freezes the imports'
objects out of later garbage collections (:func:`_freeze_imports`).

It changes no result. The stand-in (the shape plug-in's ``standin_system``: a resting lattice, no contact) shares
no state with the job: kernels are compiled per argument types, never per values. A failure on the thread is
recorded in :attr:`GpuStartup.error` and otherwise ignored; the job then loads its kernels itself. The driver
(engine/driver/simulate.py) waits for the thread before it builds the job's backend, so the two never use the GPU at
the same time.

Two rules keep the thread safe beside the caller:
- every module the thread needs is imported by the caller before the thread starts: an import on a second thread
  could meet the caller's imports halfway, where Python's per-module import locks report a deadlock; the imports
  left to the thread (numba's target registries) happen under numba's compiler lock, which the caller's numba
  work takes too;
- the thread runs no parallel (prange) njit code: numba's default threading layer may not be entered by two
  threads at once. The stand-in is made with NumPy.

The driver's own start-up (``cuInit`` and the device's primary context) needs no Python at all: :func:`begin` hands
it to a second small thread that calls the driver library through ctypes first, so it runs while the caller
imports numba.cuda (about 0.2 s); numba-cuda then finds the driver started and retains the same primary context.
That thread's own reference to the context is released once numba-cuda holds one.

``ENABLED = False`` turns both off (for A/B timings only: ``python -m bench.e2e --off startup`` sets it in the case's
process).
"""

from __future__ import annotations

import ctypes
import gc
import os
import threading
import time
from typing import Optional

#: particles per edge of the stand-in lattice (8^3 = 512: every kernel launches with real data, in microseconds)
STANDIN_EDGE = 8
#: False: no start-up thread and no early driver start (bench/e2e.py ``--off startup`` sets it, for A/B timings)
ENABLED = True
#: False: no garbage collector freeze after the imports (:func:`_freeze_imports`; ``--off gc_freeze``, for A/B timings)
FREEZE_IMPORTS = True

_lock = threading.Lock()
#: specialisation key -> its GpuStartup (one per process and key: later jobs find the kernels loaded)
_started: dict = {}


class GpuStartup:
    """The start-up thread of one specialisation (see the module docstring)."""

    def __init__(self, shape: str, system, contacts: tuple, driver: Optional["DriverStart"] = None,
                 start_dtypes: Optional[tuple] = None):
        self.error: Optional[str] = None
        self.seconds: Optional[float] = None   # the thread's own wall time
        self._driver = driver
        self._start_dtypes = start_dtypes      # (position dtype, state dtype, placement) of a device start, or None
        self._thread = threading.Thread(target=self._work, args=(shape, system, contacts),
                                        name="demq-gpu-startup")
        self._thread.start()

    def wait(self) -> None:
        """Return when the thread has ended (at once if it has)."""
        self._thread.join()

    def _work(self, shape, system, contacts) -> None:
        from engine.backends.base import cuda_available
        from engine.backends.ensemble import make_ensemble

        t0 = time.perf_counter()
        try:
            if system is not None:      # Python work: done while the driver starts on its own thread
                from engine.shapes import host

                host(shape).cuda_ensemble().prepare_kernels(contacts)
            if not cuda_available():
                return
            if system is None:          # no stand-in for this shape: the driver and the context only
                from numba import cuda

                cuda.current_context()
                return
            ensemble = make_ensemble("cuda", [system], [contacts[0]])   # what a lone job's driver builds
            for c in contacts:          # what engine.driver.simulate.drive compiles for, in its order
                ensemble.set_contact(0, c)
                ensemble.warmup()
            ensemble.observe()
            if self._start_dtypes is not None:  # the job's large start is drawn on the device (cuda_start.py)
                from engine.shapes import host

                pos_dtype, dtype, placement = self._start_dtypes
                host(shape).load_device_start(pos_dtype, dtype, (placement,))
        except Exception as exc:  # noqa: BLE001  (the job loads its kernels itself)
            self.error = f"{type(exc).__name__}: {exc}"
        finally:
            if self._driver is not None:    # numba-cuda holds the context now (or never will): let ours go
                self._driver.release()
            self.seconds = time.perf_counter() - t0


def begin(spec, backend: str, contacts: tuple, p) -> Optional[GpuStartup]:
    """Start the GPU start-up for a job of ``spec`` on ``backend`` ('auto', 'cuda' or 'cpu', unresolved), with
    ``contacts`` the contact constants the driver compiles for (in order) and ``p`` its derived parameters.

    None when there is nothing to start: backend 'cpu', the CUDA simulator, no NVIDIA driver,
    :data:`ENABLED` False. A second job of the same specialisation in this process gets the first one's (finished
    or running) start-up.
    """
    global _early
    if not _wanted(backend):
        return None
    start_dtypes = _device_start_dtypes(spec)
    key = (spec.shape, spec.precision, bool(spec.species), start_dtypes) + tuple(
        (c.k_t is None, c.friction is None, c.orientation, c.list_mode) for c in contacts)
    with _lock:
        started = _started.get(key)
        if started is not None:
            return started
        driver = DriverStart.begin() or _early   # before the imports below, which it overlaps
        _early = None
        system = _standin(spec, p)
        # the thread's imports, here (see the module docstring)
        try:
            from engine.numba_support.numba_import import coverage_hidden

            with coverage_hidden():
                import numba.cuda  # noqa: F401
            import engine.backends.ensemble  # noqa: F401
            from engine.shapes import host
            if system is not None:
                host(spec.shape).cuda_ensemble()
            if start_dtypes is not None:
                import engine.loops.cuda_start  # noqa: F401
        except Exception:  # noqa: BLE001  (numba-cuda unusable: cuda_available() says so to the driver)
            if driver is not None:
                driver.release()
            return None
        _freeze_imports()
        started = _started[key] = GpuStartup(spec.shape, system, contacts, driver, start_dtypes)
    return started


def _freeze_imports() -> None:
    """Once per process, after the GPU path's imports: collect the garbage, then leave every object alive now out of
    the cyclic garbage collector's later passes (``gc.freeze``). numba-cuda's imports leave about 115 000 tracked
    objects that live as long as the process; every full collection walked them all (46 ms each on the H200 host),
    two or three during a job's start-up and more later (frozen, the processes of 2M- and 8M-sphere jobs ended
    0.2-0.4 s sooner: ``bench/e2e.py --off gc_freeze``). The collection here runs while the driver starts on its own
    thread. Objects frozen here are still freed when their last reference goes; only a reference cycle alive now and
    dropped later is left uncollected."""
    global _frozen
    if FREEZE_IMPORTS and not _frozen:
        _frozen = True
        gc.collect()
        gc.freeze()


_frozen = False


def start_driver(backend: str) -> None:
    """Start only the driver's start-up (:class:`DriverStart`), for a caller that asks ``cuda_available()`` before
    it can call :func:`begin` (engine.driver.ensemble.run_ensemble resolves every scene's backend first). The context
    reference it takes is released by the next :func:`begin`'s thread, or by :func:`release_early`."""
    global _early
    if _wanted(backend):
        with _lock:
            d = DriverStart.begin()
            if d is not None:
                _early = d


_early: Optional["DriverStart"] = None


def release_early() -> None:
    """Drop :func:`start_driver`'s context reference if no :func:`begin` took it over (no scene reached it)."""
    global _early
    with _lock:
        if _early is not None:
            _early.release()
            _early = None


def _wanted(backend: str) -> bool:
    return not (backend == "cpu" or os.environ.get("NUMBA_ENABLE_CUDASIM") == "1" or not ENABLED
                or not nvidia_driver())


class DriverStart:
    """``cuInit`` and a reference to device 0's primary context, through the driver library and ctypes, on a
    thread of its own (see the module docstring). Device 0 is numba-cuda's default device (after
    CUDA_VISIBLE_DEVICES). Any failure leaves everything to numba-cuda, which reports it as before."""

    _once = False           # one per process: later jobs find the driver started

    def __init__(self):
        self._lib = None
        self._ctx = ctypes.c_void_p()
        self._dev = ctypes.c_int()
        self._held = False
        self._done = threading.Lock()      # held by the thread until it has finished
        self._done.acquire()
        threading.Thread(target=self._work, name="demq-driver-start", daemon=True).start()

    @classmethod
    def begin(cls) -> Optional["DriverStart"]:
        if cls._once:
            return None
        cls._once = True
        return cls()

    def _work(self) -> None:
        try:
            lib = ctypes.CDLL("libcuda.so.1")
            if lib.cuInit(0) == 0 and lib.cuDeviceGet(ctypes.byref(self._dev), 0) == 0 \
                    and lib.cuDevicePrimaryCtxRetain(ctypes.byref(self._ctx), self._dev) == 0:
                self._lib, self._held = lib, True
        except (OSError, AttributeError):   # no driver library here: numba-cuda will say so
            pass
        finally:
            self._done.release()

    def release(self) -> None:
        """Drop this thread's reference to the primary context (after it has finished); numba-cuda's stays."""
        with self._done:
            if self._held:
                self._held = False
                try:
                    release = self._lib.cuDevicePrimaryCtxRelease_v2    # the _v2 name since CUDA 11
                except AttributeError:
                    release = self._lib.cuDevicePrimaryCtxRelease
                release(self._dev)


def nvidia_driver() -> bool:
    """An NVIDIA driver is loaded here (Linux, or WSL's GPU device): without one there is nothing to overlap,
    and the backend probe (engine.backends.base.cuda_available) answers at once."""
    from engine.backends import base

    return base.nvidia_driver()


def _device_start_dtypes(spec) -> Optional[tuple]:
    """(position dtype, state dtype, placement) when a GPU job of ``spec`` draws its start on the device (the thread
    then loads the kernels of that placement, "lattice" or "random": engine.loops.cuda_start.load), else None."""
    from engine.setup.start_kind import device_start, start_protocol

    if not device_start(spec):
        return None
    from engine.setup.precision import position_dtype, state_dtype

    return position_dtype(spec.precision), state_dtype(spec.precision), start_protocol(spec)


def _standin(spec, p):
    """The stand-in scene of ``spec``'s shape (its plug-in's ``standin_system``), or None: a species mixture (its
    multigrid lists are not those of one size), or a plug-in without that optional hook (engine/shapes/README.md)."""
    from engine.shapes import host

    if spec.species:
        return None
    try:
        make = host(spec.shape).standin_system
    except AttributeError:   # the hook is optional: the start-up then starts the driver and the context only
        return None
    return make(p, STANDIN_EDGE)
