"""The one module of the engine that touches private internals of numba and numba-cuda.

Everything here works with numba 0.68 and numba-cuda 0.30; tests/engine/test_numba_internals.py checks each
internal against the installed versions and names the internal and the version when one has changed. Where a
cache internal is missing at run time the engine compiles instead of loading a cached kernel, and where page-locking
fails its frames stay in pageable memory: slower, never different.

numba (the CPU kernels, engine/numba_support/jitcache.py):

- ``numba.core.caching.FunctionCache``, the on-disk cache of a ``cache=True`` njit function. Its
  ``load_overload(sig, target_context)`` refreshes the CPU target context before every load (every lowering
  registry, and scipy.linalg for numba's BLAS check: 0.25-0.4 s of Python under the GIL, once per process).
  :class:`FastLoadCache` loads without it, through the private ``_guard_against_spurious_io_errors()`` and
  ``_load_overload(sig, target_context)``, after what a load of linked machine code does need: the NRT
  (``numba.core.runtime.rtsys.initialize``) and the hash secret (``numba.cpython.hashing``).
- the private ``_index_key(sig, codegen)`` of a cache: the key of one compiled signature, by default (signature,
  ``codegen.magic_tuple()``, the source file's time stamp and size). :class:`StableKeyCache` replaces the stamp by
  a key the caller gives (numba keys a cached closure by a pickle of its cells, which changes in every process).
- a dispatcher's private ``_cache`` attribute, where it keeps its cache object (:func:`set_cache`).
- a cache's private ``_cache_file`` (numba's ``IndexDataCacheFile``; numba-cuda has its own copy of the class) with
  ``_index_path``, ``_load_index()``, ``_save_index(overloads)``, ``_save_data(name, data)`` and
  ``_data_name(number)``: :func:`lock_saves` gives it a ``save`` that holds a lock file across processes (or leaves
  the overload uncached after :data:`SAVE_LOCK_WAIT_S`) and writes an overload's data before the index entry that
  names it. numba's own reads the index, picks the first data file name the index does not use, writes the index
  and then the data, with nothing held between: two processes saving new overloads of one function at once (the
  warm-up compiles in up to 8 processes, jobs/warm.py) could each keep only its own entry, or leave one's entry
  naming a file the other wrote last, and a later load would take that file's machine code for the entry's
  signature.

numba-cuda (the CUDA kernels, engine/loops/):

- ``numba.cuda.dispatcher.CUDACache``: the same private methods as numba's cache, plus ``_launch_config_key``
  (part of the key of a launch-configuration-sensitive kernel) and ``numba.cuda.utils.numba_target_override``
  (the context manager its ``load_overload`` enters before the target refresh that :func:`cuda_stable_key_cache`
  skips: a kernel is rebuilt from its linked code without the context).
- ``CUDADispatcher.targetoptions["device"]`` (a device function has no cache of its own).
- ``numba.cuda.cudadrv.driver.device_memset(dst, val, size, stream)``: a memset on a stream (no public API).
- ``Context.mempin(owner, pointer, size, mapped)`` of ``numba.cuda.current_context()``: page-lock existing host
  memory in place (cuMemHostRegister); the public API only allocates new pinned arrays.
- a device array's ``device_ctypes_pointer`` and the ``handle`` of a numba-cuda ``Stream`` and ``Event``, given to
  the driver library directly through ctypes (cuda-python's ``cuda.bindings.driver`` where the library is not found
  by name; :func:`async_copy_and_record`, :func:`event_waiter`: the time loop's per-step status copy and its wait,
  where numba-cuda's checked wrappers cost more host time than the step takes on the GPU).
- a kernel launch without the dispatcher (:func:`prepare_launch`, used by engine/loops/cuda_launch.py): a compiled
  kernel's ``argument_types``, its private ``_prepare_args`` (numba-cuda 0.30 flattens each array argument into
  meminfo, parent, size, itemsize, pointer, shape and strides, and each scalar into one ctypes value), its
  ``_codelibrary.get_cufunc()``, the dispatcher's ``configure`` (its ``griddim``, ``blockdim``, ``stream``,
  ``pre_launch_callbacks`` and ``sharedmem``) and ``_launch_config_sensitive``, and the module-level
  ``LaunchConfig``, ``launch`` and ``CUDA_CORE_GE_1_0`` of ``numba.cuda.dispatcher`` (cuda.core's).
- the driver's ``cuLaunchKernel`` called through ctypes with a parameter array built once (:func:`direct_launch`),
  given the ``handle`` of the cuda.core kernel and stream of :func:`prepare_launch` and its argument list read the
  way cuda.core's ``ParamHolder`` reads it (a Python int as an ``intptr_t``, a float as a double, a ctypes or NumPy
  scalar as its own type): cuda.core converts every argument at every launch, about 20 us of Python for the time
  loop's 200-odd flattened arguments, which at 2^20 particles is more host time than a step takes on the GPU.

The CUDA parts import numba.cuda only when called (a CPU job never imports it).
"""

from __future__ import annotations

import contextlib
import time

from engine.numba_support.numba_import import coverage_hidden

#: what the engine was written against (the test reports these beside the installed versions)
NUMBA_VERSION = "0.68"
NUMBA_CUDA_VERSION = "0.30"

try:
    with coverage_hidden():
        from numba.core.caching import FunctionCache
        from numba.core.runtime import rtsys as _rtsys

    class FastLoadCache(FunctionCache):
        """numba's FunctionCache, whose loads skip the target refresh and whose saves are locked (module
        docstring)."""

        def __init__(self, py_func):
            super().__init__(py_func)
            lock_saves(self)

        def load_overload(self, sig, target_context):
            _rtsys.initialize(target_context)      # the parts of the refresh a load needs
            import numba.cpython.hashing  # noqa: F401
            with self._guard_against_spurious_io_errors():
                return self._load_overload(sig, target_context)

    class StableKeyCache(FastLoadCache):
        """A :class:`FastLoadCache` keyed by (signature, codegen magic tuple, ``stable``) instead of the source
        file's stamp."""

        def __init__(self, py_func, stable: tuple):
            self._stable = stable
            super().__init__(py_func)

        def _index_key(self, sig, codegen):
            return (sig, codegen.magic_tuple(), self._stable)
except ImportError:  # another numba layout: no fast loads, closures compile in every process
    FunctionCache = FastLoadCache = StableKeyCache = None


def get_cache(dispatcher):
    """The cache object of a numba or numba-cuda dispatcher (None: not cached)."""
    return getattr(dispatcher, "_cache", None)


def set_cache(dispatcher, cache) -> None:
    """Give a dispatcher ``cache`` as its on-disk cache (used by its next compile or load)."""
    dispatcher._cache = cache


def make_fast_loading(dispatcher) -> bool:
    """Turn the plain FunctionCache of a ``cache=True`` njit dispatcher into a :class:`FastLoadCache` (same state, one
    method different); False where it has another cache, none, or this numba lacks the internals."""
    cache = get_cache(dispatcher)
    if FastLoadCache is None or type(cache) is not FunctionCache:
        return False
    cache.__class__ = FastLoadCache
    lock_saves(cache)
    return True


#: Seconds a cache save waits for its index's lock before it leaves its overload out of the cache (a later process
#: compiles it again): the holder may be the worker's warm-up process, which the worker stops (SIGSTOP) while a
#: claim runs (jobs/warm.py), and a claim must not wait for it.
SAVE_LOCK_WAIT_S = 5.0


@contextlib.contextmanager
def _held(lock_path: str, wait_s: float):
    """An exclusive lock on the file ``lock_path`` (made if missing) across processes, held for the block, which gets
    True; False if another holder kept it ``wait_s`` seconds. True and no lock where the platform has no ``fcntl``
    (not Linux or macOS) or the file system refuses the lock file or the lock (numba's unlocked save then, as
    before)."""
    try:
        import fcntl

        f = open(lock_path, "ab")
    except (ImportError, OSError):
        yield True
        return
    with f:
        deadline = time.monotonic() + wait_s
        while True:
            try:
                fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    yield False
                    return
                time.sleep(0.005)
            except OSError:       # no locks on this file system (an old NFS mount)
                yield True
                return
        try:
            yield True
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def _locked_save(self, key, data) -> None:
    """``IndexDataCacheFile.save`` under the index's lock file, the data written before the index that names it
    (module docstring): a reader that finds the entry finds its file complete, and no saver picks a name another one
    is about to write. Left out of the cache if the lock stays held :data:`SAVE_LOCK_WAIT_S` seconds."""
    with _held(self._index_path + ".lock", SAVE_LOCK_WAIT_S) as locked:
        if not locked:
            return
        overloads = self._load_index()
        name = overloads.get(key)
        if name is None:
            used = set(overloads.values())
            number = 1
            while self._data_name(number) in used:
                number += 1
            name = self._data_name(number)
            self._save_data(name, data)
            overloads[key] = name
            self._save_index(overloads)
        else:
            self._save_data(name, data)


_locked_file_classes: dict = {}


def lock_saves(cache) -> None:
    """Give ``cache``'s index-and-data file (numba's or numba-cuda's ``IndexDataCacheFile``) :func:`_locked_save` as
    its ``save``; nothing where the cache has no such file."""
    cache_file = getattr(cache, "_cache_file", None)
    if cache_file is None:
        return
    cls = type(cache_file)
    if cls.save is _locked_save:
        return
    locked = _locked_file_classes.get(cls)
    if locked is None:
        locked = _locked_file_classes[cls] = type("Locked" + cls.__name__, (cls,), {"save": _locked_save})
    cache_file.__class__ = locked


def stable_key_cache(dispatcher, stable: tuple) -> bool:
    """Give an njit dispatcher a :class:`StableKeyCache` keyed by ``stable``; False where it cannot have one (this
    numba lacks the internals, or no cache locator fits the function's file, e.g. a read-only install)."""
    if StableKeyCache is None:
        return False
    try:
        set_cache(dispatcher, StableKeyCache(dispatcher.py_func, stable))
    except Exception:  # noqa: BLE001  (no cache locator: compile as numba does without a cache)
        return False
    return True


_cuda_cache_class = None


def cuda_stable_key_cache_class():
    """numba-cuda's CUDACache keyed by (signature, codegen magic tuple, numba-cuda version, ``stable``[, launch
    configuration]) instead of the source file's stamp, whose loads skip the CUDA target refresh; None where this
    numba-cuda lacks the internals. Made once (it imports numba.cuda)."""
    global _cuda_cache_class
    if _cuda_cache_class is not None:
        return _cuda_cache_class or None
    try:
        import numba_cuda
        from numba.cuda.dispatcher import CUDACache
        from numba.cuda.utils import numba_target_override
    except ImportError:
        _cuda_cache_class = False
        return None

    class CudaStableKeyCache(CUDACache):
        def __init__(self, py_func, stable: tuple):
            self._stable = stable
            super().__init__(py_func)
            lock_saves(self)

        def _index_key(self, sig, codegen):
            k = (sig, codegen.magic_tuple(), numba_cuda.__version__, self._stable)
            return k if self._launch_config_key is None else k + (("launch_config", self._launch_config_key),)

        def load_overload(self, sig, target_context):
            with numba_target_override(), self._guard_against_spurious_io_errors():
                return self._load_overload(sig, target_context)

    _cuda_cache_class = CudaStableKeyCache
    return CudaStableKeyCache


def cuda_stable_key_cache(dispatcher, stable: tuple) -> bool:
    """Give a CUDA kernel dispatcher (not a device function) the cache of :func:`cuda_stable_key_cache_class`;
    False where it is not one, this numba-cuda lacks the internals, or no cache locator fits its file."""
    cls = cuda_stable_key_cache_class()
    if cls is None:
        return False
    from numba.cuda.dispatcher import CUDADispatcher

    if not isinstance(dispatcher, CUDADispatcher) or dispatcher.targetoptions.get("device", False):
        return False
    try:
        set_cache(dispatcher, cls(dispatcher.py_func, stable))
    except Exception:  # noqa: BLE001  (no cache locator for this file: compile as before)
        return False
    return True


def device_memset(array, value: int, stream) -> None:
    """Set every byte of a device array to ``value`` (0-255), queued on ``stream``."""
    from numba.cuda.cudadrv.driver import device_memset as memset

    memset(array, value, array.nbytes, stream=stream)


def async_copy_device(dst, src, stream) -> None:
    """Queue, on ``stream``, the copy of the whole contiguous device array ``src`` into the contiguous device array
    ``dst`` of the same shape and type, straight through cuda-python's ``cuMemcpyDtoDAsync``. numba-cuda's
    ``copy_to_device`` checks, views and converts both arrays at every call (about 0.2 ms of Python each): a list
    rebuild copies every permuted particle array back from its scratch, which at a few thousand particles cost
    more host time than the rebuild's kernels take on the GPU. Raises ValueError for a size or layout it does not
    handle and RuntimeError naming the call where the driver refuses."""
    from cuda.bindings import driver as cu

    if dst.shape != src.shape or dst.dtype != src.dtype or not (dst.is_c_contiguous() and src.is_c_contiguous()):
        raise ValueError(f"device copy of {src.shape} {src.dtype} into {dst.shape} {dst.dtype}: both must be "
                         "contiguous, of one shape and one type")
    if src.nbytes == 0:
        return
    err, = cu.cuMemcpyDtoDAsync(int(dst.device_ctypes_pointer.value), int(src.device_ctypes_pointer.value),
                                int(src.nbytes), int(stream.handle))
    if err != cu.CUresult.CUDA_SUCCESS:
        raise RuntimeError(f"cuMemcpyDtoDAsync: {err}")


def async_copy_and_record(device_array, host_array, stream, event):
    """A function that queues, on ``stream``, the copy of the whole ``device_array`` into the pinned ``host_array``
    (same size), then records ``event``: straight through the driver's ``cuMemcpyDtoHAsync`` and ``cuEventRecord``
    with the pointers and handles resolved once, called through ctypes (about a microsecond each; cuda-python's
    driver bindings where the driver library is not found by name: a few). numba-cuda's ``copy_to_host`` and
    ``Event.record`` check and convert their arguments at every call (about 40 us of Python for a copy of 100
    bytes): the per-step status copy of the GPU time loop then costs more host time than the step takes on the GPU.
    The arrays, stream and event must outlive the function. Raises RuntimeError naming the call where the driver
    refuses."""
    if device_array.nbytes != host_array.nbytes:
        raise ValueError(f"copy of {device_array.nbytes} bytes into a buffer of {host_array.nbytes}")
    src = int(device_array.device_ctypes_pointer.value)
    dst = int(host_array.ctypes.data)
    nbytes = int(host_array.nbytes)
    hs = int(stream.handle)
    he = int(event.handle)
    copy, record = _driver_call("cuMemcpyDtoHAsync_v2"), _driver_call("cuEventRecord")
    if copy is not None and record is not None:
        def copy_and_record() -> None:
            err = copy(dst, src, nbytes, hs)
            if err:
                raise RuntimeError(f"cuMemcpyDtoHAsync: CUresult {err}")
            err = record(he, hs)
            if err:
                raise RuntimeError(f"cuEventRecord: CUresult {err}")

        return copy_and_record
    from cuda.bindings import driver as cu

    copy, record, success = cu.cuMemcpyDtoHAsync, cu.cuEventRecord, cu.CUresult.CUDA_SUCCESS

    def copy_and_record_bindings() -> None:
        err, = copy(dst, src, nbytes, hs)
        if err != success:
            raise RuntimeError(f"cuMemcpyDtoHAsync: {err}")
        err, = record(he, hs)
        if err != success:
            raise RuntimeError(f"cuEventRecord: {err}")

    return copy_and_record_bindings


def event_waiter(event):
    """A function that waits for numba-cuda ``event`` (``event.synchronize()``) through the driver's
    ``cuEventSynchronize`` called with its handle through ctypes (numba-cuda's wrapper checks its argument and the
    result in Python at every call: a few microseconds, paid every step of the per-phase loop); the event's own
    ``synchronize`` where the driver library is not found by name. The event must outlive the function. Raises
    RuntimeError with the driver's error code where the wait fails."""
    wait = _driver_call("cuEventSynchronize")
    if wait is None:
        return event.synchronize
    he = int(event.handle)

    def synchronize() -> None:
        err = wait(he)
        if err:
            raise RuntimeError(f"cuEventSynchronize: CUresult {err}")

    return synchronize


#: the driver calls made through ctypes, with their argument types (CUresult as the return value)
_DRIVER_ARGS = {"cuMemcpyDtoHAsync_v2": ("p", "u64", "size", "p"), "cuEventRecord": ("p", "p"),
                "cuEventSynchronize": ("p",),
                "cuLaunchKernel": ("p", "u", "u", "u", "u", "u", "u", "u", "p", "p", "p")}
#: the calls that wait (ctypes lets go of the GIL during them, so that the result files' I/O thread works meanwhile);
#: the others only queue work and return: they keep the GIL, which a thread that let it go may have to wait up to
#: Python's switch interval to get back while another thread runs
_DRIVER_WAITS = {"cuEventSynchronize"}
_driver_calls: dict = {}


def _driver_call(name: str):
    """The driver library's ``name`` as a ctypes function with its argument types (:data:`_DRIVER_ARGS`), or None
    where the library or the symbol is not found; a call of :data:`_DRIVER_WAITS` lets go of the GIL, the others
    keep it."""
    if name not in _driver_calls:
        import ctypes

        kinds = {"p": ctypes.c_void_p, "u64": ctypes.c_uint64, "size": ctypes.c_size_t, "u": ctypes.c_uint}
        loader = ctypes.CDLL if name in _DRIVER_WAITS else ctypes.PyDLL
        try:
            fn = getattr(loader("libcuda.so.1"), name)
            fn.argtypes = [kinds[k] for k in _DRIVER_ARGS[name]]
            fn.restype = ctypes.c_int
        except (OSError, AttributeError):
            fn = None
        _driver_calls[name] = fn
    return _driver_calls[name]


def page_lock(arrays) -> list:
    """Page-lock host arrays in place in the current CUDA context; the returned handles keep the registration (and
    their arrays) alive until they are collected. Raises where the driver refuses."""
    from numba import cuda

    ctx = cuda.current_context()
    return [ctx.mempin(a, a.ctypes.data, a.nbytes, mapped=False) for a in arrays]


def prepare_launch(dispatcher, config: tuple, args: tuple, scalar_types: tuple, direct: bool = False):
    """What numba-cuda's own launch of ``dispatcher[config](*args)`` hands to cuda.core, kept for later launches with
    the same arrays: ``(launch, stream, launch_config, kernel, kargs, slots, go)``, where ``launch(stream,
    launch_config, kernel, *kargs)`` launches, ``slots`` lists ``(position in args, index in kargs, ctypes type or
    None)`` of each top-level scalar argument (its value is refilled per launch) and ``go`` the same launch through the
    driver (:func:`direct_launch`, with ``direct``) or, where there is none, a string that says why. None where such a
    launch would not be numba-cuda's (a launch-configuration-sensitive or debug kernel, pre-launch callbacks, dynamic
    shared memory, host arrays copied per launch, a scalar inside a tuple). A cooperative kernel keeps its cooperative
    launch. The kernel must have been launched once in this process (numba-cuda then knows whether it is
    launch-configuration sensitive); argument types it has not been launched with are compiled or loaded here."""
    import ctypes

    from numba.cuda import dispatcher as nd

    if any(isinstance(a, tuple) and any(isinstance(x, scalar_types) for x in a) for a in args):
        return None
    griddim, blockdim, stream = config
    if getattr(dispatcher, "_launch_config_sensitive", False):
        return None
    kernel = dispatcher.compile(tuple(dispatcher.typeof_pyval(a) for a in args))
    if kernel.debug:
        return None
    lc = dispatcher.configure(griddim, blockdim, stream)    # normalised dimensions, cuda.core stream
    if lc.pre_launch_callbacks or lc.sharedmem:
        return None
    stream = lc.stream
    kargs, retr, slots = [], [], []
    for pos, (t, v) in enumerate(zip(kernel.argument_types, args)):
        start = len(kargs)
        kernel._prepare_args(t, v, stream, retr, kargs)
        if isinstance(v, scalar_types):
            if len(kargs) != start + 1:
                return None
            first = kargs[start]
            slots.append((pos, start, type(first) if isinstance(first, ctypes._SimpleCData) else None))
    if retr:
        return None
    if nd.CUDA_CORE_GE_1_0:
        launch_config = nd.LaunchConfig(grid=lc.griddim, block=lc.blockdim, shmem_size=0,
                                       is_cooperative=bool(kernel.cooperative))
    else:
        launch_config = nd.LaunchConfig(grid=lc.griddim, block=lc.blockdim, shmem_size=0,
                                       cooperative_launch=bool(kernel.cooperative))
    cufunc = kernel._codelibrary.get_cufunc().kernel
    go = "not asked for"
    if direct:
        try:
            go = direct_launch(stream, (lc.griddim, lc.blockdim, bool(kernel.cooperative)), cufunc, kargs, slots)
        except Exception as exc:  # noqa: BLE001  (cuda.core's launch then, as before)
            go = f"{type(exc).__name__}: {exc}"
    return (nd.launch, stream, launch_config, cufunc, kargs, slots, go)


#: the driver's CUresult of a call made on a thread where no context is current
CUDA_ERROR_INVALID_CONTEXT = 201


def direct_launch(stream, dims: tuple, kernel, kargs: list, slots: list):
    """A function ``go(args)`` that launches what ``launch(stream, launch_config, kernel, *kargs)`` of
    :func:`prepare_launch` launches, through the driver's ``cuLaunchKernel`` with one parameter array built here:
    each argument of ``kargs`` held in a ctypes value of the type cuda.core's ``ParamHolder`` gives it (a Python int,
    bool included, an ``intptr_t``; a float a double; a ctypes scalar its own type; a NumPy scalar its dtype's), and
    ``go`` sets the values of the scalar ``slots`` (``(position in args, index in kargs, ...)``) from ``args`` before
    each launch. ``dims``: (grid, block, cooperative), the grid and block as 3-tuples. The same kernel, arguments
    and stream: the same launch, without cuda.core's conversion of every argument (module docstring). Where this
    cannot be done the same way, a string that says why instead (a cooperative kernel, an argument of another type,
    no driver library or handle). ``go`` raises RuntimeError naming the driver's error code where a launch fails."""
    import ctypes

    import numpy as np

    grid, block, cooperative = dims
    if cooperative:
        return "a cooperative kernel"
    fn = _driver_call("cuLaunchKernel")
    if fn is None:
        return "no driver library libcuda.so.1 with cuLaunchKernel"
    holders = []
    for a in kargs:
        if isinstance(a, ctypes._SimpleCData):
            holders.append(type(a)(a.value))
        elif isinstance(a, int):                  # bool included: cuda.core tests int first
            holders.append(ctypes.c_ssize_t(a))
        elif isinstance(a, float):
            holders.append(ctypes.c_double(a))
        elif isinstance(a, np.generic) and a.dtype.kind in "biuf":
            holders.append(np.ctypeslib.as_ctypes_type(a.dtype)(a.item()))
        else:
            return f"an argument of type {type(a).__name__}"
    try:
        func = int(kernel.handle)
        hs = int(stream.handle)
        grid = tuple(int(x) for x in grid)
        block = tuple(int(x) for x in block)
    except (AttributeError, TypeError, ValueError) as exc:
        return f"{type(exc).__name__}: {exc}"
    if len(grid) != 3 or len(block) != 3:
        return f"grid {grid}, block {block}"
    params = (ctypes.c_void_p * max(1, len(holders)))(*[ctypes.addressof(h) for h in holders])
    refill = [(pos, holders[slot]) for pos, slot, _ in slots]
    gx, gy, gz = grid
    bx, by, bz = block

    def go(args) -> None:
        for pos, holder in refill:
            holder.value = args[pos]
        err = fn(func, gx, gy, gz, bx, by, bz, 0, hs, params, None)
        if err == CUDA_ERROR_INVALID_CONTEXT:   # a thread without the context current: numba-cuda makes it so
            from numba import cuda

            cuda.current_context()
            err = fn(func, gx, gy, gz, bx, by, bz, 0, hs, params, None)
        if err:
            raise RuntimeError(f"cuLaunchKernel: CUresult {err}")

    go.keep = (holders, params)     # the parameter array points into the holders: both live as long as go
    return go
