"""engine/numba_support/numba_internals.py against the installed numba and numba-cuda: every private internal the engine
relies on is still there, with the same parameters, and does what the engine assumes. A failure names the internal and
the installed versions: the engine then silently compiles in every process (or worse), so this is where it must show.

The CPU parts run for real (a function compiled into a cache in tmp_path, loaded back by a second dispatcher). The
CUDA cache's key and load need a device (codegen.magic_tuple() asks the driver), and the CUDA simulator caches
nothing: without a GPU its parts are checked as far as numba-cuda goes without a driver (classes, parameters, the
cache attached to a real kernel dispatcher, the key's layout, the load's steps)."""

from __future__ import annotations

import importlib
import importlib.util
import inspect
import os

import numba
import pytest

from engine.numba_support import numba_internals as ni

SIM = os.environ.get("NUMBA_ENABLE_CUDASIM") == "1"


def _versions() -> str:
    try:
        import numba_cuda

        cuda_version = numba_cuda.__version__
    except ImportError:
        cuda_version = "not installed"
    return (f"installed numba {numba.__version__}, numba-cuda {cuda_version}; "
            "engine/numba_support/numba_internals.py was written "
            f"for numba {ni.NUMBA_VERSION}, numba-cuda {ni.NUMBA_CUDA_VERSION}")


def _check(ok: bool, internal: str, what: str) -> None:
    if not ok:
        pytest.fail(f"numba internal {internal} changed: {what} ({_versions()})", pytrace=False)


def _params(fn) -> list:
    return list(inspect.signature(fn).parameters)


def _module(tmp_path, name: str, source: str, file: str | None = None):
    """A module ``name`` of ``source`` in the file ``file`` (default: its own; a cache locator needs the function's
    file), imported anew even where that file was imported before under another name."""
    path = tmp_path / f"{file or name}.py"
    if not path.exists():
        path.write_text(source)
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


# ---- numba (CPU) -------------------------------------------------------------------------------------------------

def test_numba_cache_internals_have_the_expected_shape():
    _check(ni.FunctionCache is not None, "numba.core.caching.FunctionCache / numba.core.runtime.rtsys",
           "no longer importable")
    fc = ni.FunctionCache
    for name, params in (("load_overload", ["self", "sig", "target_context"]),
                         ("_load_overload", ["self", "sig", "target_context"]),
                         ("_index_key", ["self", "sig", "codegen"]),
                         ("_guard_against_spurious_io_errors", ["self"]),
                         ("__init__", ["self", "py_func"])):
        _check(hasattr(fc, name), f"FunctionCache.{name}", "missing")
        _check(_params(getattr(fc, name)) == params, f"FunctionCache.{name}",
               f"parameters {_params(getattr(fc, name))}, expected {params}")
    from numba.core.runtime import rtsys

    _check(callable(getattr(rtsys, "initialize", None)), "numba.core.runtime.rtsys.initialize", "missing")
    importlib.import_module("numba.cpython.hashing")
    # the load that FastLoadCache replaces: a target refresh, then the guarded private load
    src = inspect.getsource(fc.load_overload)
    _check("target_context.refresh()" in src and "self._guard_against_spurious_io_errors()" in src
           and "self._load_overload(sig, target_context)" in src, "FunctionCache.load_overload",
           "no longer refresh + _guard_against_spurious_io_errors + _load_overload")


def test_a_fast_loading_cache_loads_the_compiled_function_without_the_target_refresh(tmp_path, monkeypatch):
    from numba.core.registry import cpu_target

    monkeypatch.setattr(numba.config, "CACHE_DIR", str(tmp_path / "cache"))
    src = "from numba import njit\n\n@njit(cache=True)\ndef triple(x):\n    return 3 * x + 1\n"
    first = _module(tmp_path, "ni_cached_a", src)
    _check(first.triple(4) == 13 and first.triple.stats.cache_misses, "FunctionCache", "first call did not compile")
    _check(type(ni.get_cache(first.triple)) is ni.FunctionCache, "Dispatcher._cache",
           f"a cache=True dispatcher's _cache is {type(ni.get_cache(first.triple))!r}, not FunctionCache")
    # the same file under another module name: a new dispatcher whose cache finds the first one's machine code
    second = _module(tmp_path, "ni_cached_b", src, file="ni_cached_a")
    _check(ni.make_fast_loading(second.triple), "Dispatcher._cache", "make_fast_loading found no FunctionCache")
    _check(type(ni.get_cache(second.triple)) is ni.FastLoadCache, "Dispatcher._cache", "class not replaced")
    refreshes = []
    orig_refresh = type(cpu_target.target_context).refresh
    monkeypatch.setattr(type(cpu_target.target_context), "refresh",
                        lambda self: refreshes.append(1) or orig_refresh(self))
    _check(second.triple(5) == 16, "FunctionCache._load_overload", "the loaded function computes something else")
    _check(dict(second.triple.stats.cache_hits) and not dict(second.triple.stats.cache_misses),
           "FunctionCache._load_overload", f"no cache hit (hits {dict(second.triple.stats.cache_hits)}, "
           f"misses {dict(second.triple.stats.cache_misses)})")
    _check(not refreshes, "FunctionCache.load_overload", "the fast load still refreshed the target")


def test_a_stable_key_cache_serves_a_closure_rebuilt_with_new_cells(tmp_path, monkeypatch):
    """numba keys a closure by a pickle of its cells; a StableKeyCache keys it by the caller's key, so a closure
    built again (here: over another dispatcher object, as the engine's factories do) loads the first one's code."""
    monkeypatch.setattr(numba.config, "CACHE_DIR", str(tmp_path / "cache"))
    mod = _module(tmp_path, "ni_factory", (
        "from numba import njit\n\n"
        "def make():\n"
        "    @njit\n"
        "    def inner(x):\n"
        "        return x * x\n\n"
        "    @njit\n"
        "    def outer(x):\n"
        "        return inner(x) + 2\n"
        "    return outer\n"))
    a, b = mod.make(), mod.make()
    _check(ni.stable_key_cache(a, ("test", 1)) and ni.stable_key_cache(b, ("test", 1)), "StableKeyCache",
           "could not be attached")
    _check(a(3) == 11 and dict(a.stats.cache_misses), "StableKeyCache", "first call did not compile")
    _check(b(3) == 11, "StableKeyCache._index_key", "the loaded closure computes something else")
    _check(dict(b.stats.cache_hits) and not dict(b.stats.cache_misses), "FunctionCache._index_key",
           f"the rebuilt closure did not load (hits {dict(b.stats.cache_hits)}, misses {dict(b.stats.cache_misses)})")


def _index_data_file_internals(cls) -> None:
    for name, params in (("save", ["self", "key", "data"]), ("load", ["self", "key"]), ("_load_index", ["self"]),
                         ("_save_index", ["self", "overloads"]), ("_save_data", ["self", "name", "data"]),
                         ("_data_name", ["self", "number"])):
        _check(hasattr(cls, name), f"{cls.__module__}.IndexDataCacheFile.{name}", "missing")
        _check(_params(getattr(cls, name)) == params, f"{cls.__module__}.IndexDataCacheFile.{name}",
               f"parameters {_params(getattr(cls, name))}, expected {params}")


def test_cache_saves_are_locked_and_write_the_data_before_its_index_entry(tmp_path, monkeypatch):
    """Two saves of new overloads of one function at once: each holds the index's lock file from its read of the
    index to its writes, so neither loses the other's entry or names the other's data file, and an overload's data
    is written before the index entry that names it. Two threads stand in for two processes (flock locks an open
    file, so two opens in one process exclude each other as two processes do); a pause after each read of the index
    makes the saves overlap, and numba's own save then keeps one entry of the two."""
    import threading
    import time
    import types

    from numba.core.caching import IndexDataCacheFile

    _index_data_file_internals(IndexDataCacheFile)
    for locked in (True, False):
        folder = tmp_path / f"locked-{locked}"
        folder.mkdir()
        cache_file = IndexDataCacheFile(cache_path=str(folder), filename_base="f", source_stamp=(1.0, 2))
        if locked:
            ni.lock_saves(types.SimpleNamespace(_cache_file=cache_file))
        read = cache_file._load_index
        cache_file._load_index = lambda: (read(), time.sleep(0.5))[0]
        writes = []
        for name in ("_save_data", "_save_index"):
            write = getattr(cache_file, name)
            setattr(cache_file, name, lambda *a, _w=write, _n=name: (writes.append(_n), _w(*a))[1])
        saves = [threading.Thread(target=cache_file.save, args=(("sig", k), ("code", k))) for k in (1, 2)]
        for t in saves:
            t.start()
        for t in saves:
            t.join()
        index = read()
        if not locked:      # the race the lock closes: both saves read an empty index and took the same name
            assert len(index) == 1, index
            continue
        _check(sorted(index) == [("sig", 1), ("sig", 2)] and len(set(index.values())) == 2, "IndexDataCacheFile.save",
               f"locked saves left the index {index}")
        _check([cache_file.load(("sig", k)) for k in (1, 2)] == [("code", 1), ("code", 2)], "IndexDataCacheFile.load",
               "an entry loads another overload's data")
        _check(writes == ["_save_data", "_save_index"] * 2, "IndexDataCacheFile.save", f"writes in order {writes}")
    # a save whose lock another holder keeps (a warm-up process stopped while a claim runs) gives up and caches nothing
    import fcntl

    monkeypatch.setattr(ni, "SAVE_LOCK_WAIT_S", 0.2)
    folder = tmp_path / "held"
    folder.mkdir()
    cache_file = IndexDataCacheFile(cache_path=str(folder), filename_base="f", source_stamp=(1.0, 2))
    ni.lock_saves(types.SimpleNamespace(_cache_file=cache_file))
    with open(cache_file._index_path + ".lock", "ab") as holder:
        fcntl.flock(holder, fcntl.LOCK_EX)
        t0 = time.monotonic()
        cache_file.save(("sig", 3), ("code", 3))
        waited = time.monotonic() - t0
        fcntl.flock(holder, fcntl.LOCK_UN)
    _check(cache_file._load_index() == {} and 0.2 <= waited < 5.0, "IndexDataCacheFile.save",
           f"a save under a held lock waited {waited:.2f} s and left {cache_file._load_index()}")
    # a file system that refuses the lock: the save goes on unlocked (numba's, data first), as it did before
    def refuse(*a):
        raise OSError(37, "No locks available")

    monkeypatch.setattr(fcntl, "flock", refuse)
    cache_file.save(("sig", 4), ("code", 4))
    _check(cache_file.load(("sig", 4)) == ("code", 4), "IndexDataCacheFile.save", "a refused lock lost the save")
    monkeypatch.undo()
    # the engine's caches get the locked save: numba's (fast loading, stable key) here, numba-cuda's in its test below
    monkeypatch.setattr(numba.config, "CACHE_DIR", str(tmp_path / "cache"))
    mod = _module(tmp_path, "ni_locked",
                  "from numba import njit\n\n@njit(cache=True)\ndef twice(x):\n    return 2 * x\n")
    _check(ni.make_fast_loading(mod.twice), "Dispatcher._cache", "make_fast_loading found no FunctionCache")
    _check(type(ni.get_cache(mod.twice)._cache_file).save is ni._locked_save, "FunctionCache._cache_file",
           "the fast-loading cache's file has numba's save")
    _check(ni.stable_key_cache(mod.twice, ("test", 2)), "StableKeyCache", "could not be attached")
    _check(type(ni.get_cache(mod.twice)._cache_file).save is ni._locked_save, "FunctionCache._cache_file",
           "the stable-key cache's file has numba's save")
    _check(mod.twice(4) == 8, "StableKeyCache", "the locked cache's function computes something else")


# ---- numba-cuda ------------------------------------------------------------------------------------------------

cuda_only = pytest.mark.skipif(SIM, reason="the CUDA simulator replaces numba.cuda; the engine caches nothing there")


@cuda_only
def test_numba_cuda_internals_have_the_expected_shape():
    _check(ni.cuda_stable_key_cache_class() is not None,
           "numba.cuda.dispatcher.CUDACache / numba.cuda.utils.numba_target_override / numba_cuda.__version__",
           "no longer importable")
    from numba.cuda.cudadrv import driver
    from numba.cuda.dispatcher import CUDACache

    for name, params in (("load_overload", ["self", "sig", "target_context"]),
                         ("_load_overload", ["self", "sig", "target_context"]),
                         ("_index_key", ["self", "sig", "codegen"]),
                         ("_guard_against_spurious_io_errors", ["self"]),
                         ("__init__", ["self", "py_func"])):
        _check(hasattr(CUDACache, name), f"CUDACache.{name}", "missing")
        _check(_params(getattr(CUDACache, name)) == params, f"CUDACache.{name}",
               f"parameters {_params(getattr(CUDACache, name))}, expected {params}")
    _check(_params(driver.device_memset) == ["dst", "val", "size", "stream"], "numba.cuda.cudadrv.driver.device_memset",
           f"parameters {_params(driver.device_memset)}")
    _check(_params(driver.Context.mempin) == ["self", "owner", "pointer", "size", "mapped"],
           "numba.cuda.cudadrv.driver.Context.mempin", f"parameters {_params(driver.Context.mempin)}")
    # the load that the engine's cache replaces: the target override, then the base load's refresh + guarded load
    own = inspect.getsource(CUDACache.load_overload)
    base = inspect.getsource(CUDACache.__mro__[1].load_overload)
    _check("numba_target_override()" in own and "super().load_overload(sig, target_context)" in own,
           "CUDACache.load_overload", "no longer numba_target_override + the base load")
    _check("target_context.refresh()" in base and "self._load_overload(sig, target_context)" in base,
           f"{CUDACache.__mro__[1].__module__}.Cache.load_overload", "no longer refresh + _load_overload")


@cuda_only
def test_a_kernel_gets_the_stable_key_cache_and_its_key_keeps_numba_cudas_layout(tmp_path, monkeypatch):
    from numba import cuda
    from numba.core.registry import cpu_target

    monkeypatch.setattr(numba.config, "CACHE_DIR", str(tmp_path / "cache"))
    mod = _module(tmp_path, "ni_kernels", (
        "def kernel(a):\n    a[0] = 1\n\n"
        "def device(x):\n    return x + 1\n"))
    kern = cuda.jit(mod.kernel)
    dev = cuda.jit(device=True)(mod.device)
    cls = ni.cuda_stable_key_cache_class()
    _check(ni.cuda_stable_key_cache(kern, ("test", "kernel")), "CUDADispatcher._cache", "could not be attached")
    cache = ni.get_cache(kern)
    _check(isinstance(cache, cls), "CUDADispatcher._cache", f"holds {type(cache)!r}")
    _check(not ni.cuda_stable_key_cache(dev, ("test", "device")), "CUDADispatcher.targetoptions['device']",
           "a device function was given a cache")
    _check(hasattr(cache, "_launch_config_key") and cache._launch_config_key is None, "CUDACache._launch_config_key",
           "missing or not None on a new cache")
    with cache._guard_against_spurious_io_errors():
        pass
    _index_data_file_internals(type(cache._cache_file).__mro__[1])
    _check(type(cache._cache_file).save is ni._locked_save, "CUDACache._cache_file", "the kernel's cache file has "
           "numba-cuda's save")
    # numba-cuda's key: (sig, codegen magic, numba-cuda version, source hashes) [+ launch configuration]; the
    # engine's replaces only the hashes (a codegen stands in that needs no driver: only its magic_tuple is read)
    codegen = cpu_target.target_context.codegen()
    sig = (numba.types.float64[:],)
    base = super(cls, cache)._index_key(sig, codegen)
    ours = cache._index_key(sig, codegen)
    _check(len(base) == 4 and base[:3] == ours[:3] and ours[3] == ("test", "kernel"), "CUDACache._index_key",
           f"layout {base!r}")
    cache._launch_config_key = ("lc",)
    base, ours = super(cls, cache)._index_key(sig, codegen), cache._index_key(sig, codegen)
    _check(base[-1] == ("launch_config", ("lc",)) and ours[-1] == base[-1], "CUDACache._index_key",
           f"launch-configuration part {base[-1]!r}")


@cuda_only
def test_the_driver_bindings_of_the_status_copy_are_there():
    """engine.numba_support.numba_internals.async_copy_and_record and async_copy_device call cuda-python's driver with
    the handles of numba-cuda's stream and event and device arrays' pointers (the copies themselves are checked on a
    GPU, tests/gpu/test_cuda_gpu.py)."""
    from cuda.bindings import driver as cu
    from numba.cuda.cudadrv import devicearray, driver

    for name in ("cuMemcpyDtoHAsync", "cuMemcpyDtoDAsync", "cuEventRecord"):
        _check(hasattr(cu, name), f"cuda.bindings.driver.{name}", "missing")
    _check(hasattr(cu.CUresult, "CUDA_SUCCESS"), "cuda.bindings.driver.CUresult.CUDA_SUCCESS", "missing")
    for cls in (driver.Stream, driver.Event):
        _check("self.handle = handle" in inspect.getsource(cls.__init__), f"numba.cuda.cudadrv.driver.{cls.__name__}",
               "no longer keeps its driver handle in .handle")
    _check(hasattr(devicearray.DeviceNDArrayBase, "device_ctypes_pointer"),
           "numba.cuda.cudadrv.devicearray.DeviceNDArrayBase.device_ctypes_pointer", "missing")
    _check(hasattr(devicearray.DeviceNDArray, "is_c_contiguous"),
           "numba.cuda.cudadrv.devicearray.DeviceNDArray.is_c_contiguous", "missing")


@cuda_only
def test_the_launch_internals_of_prepare_launch_have_the_expected_shape():
    """engine.numba_support.numba_internals.prepare_launch replays numba-cuda's own kernel launch: the compiled kernel's
    argument flattening and launch, the dispatcher's configuration and cuda.core's launch entry (the cached path's
    results are checked bit for bit on a GPU, tests/gpu/test_cuda_gpu.py)."""
    from numba.cuda import dispatcher as nd

    for name in ("LaunchConfig", "launch", "CUDA_CORE_GE_1_0"):
        _check(hasattr(nd, name), f"numba.cuda.dispatcher.{name}", "missing")
    kernel_class = nd._Kernel
    _check(_params(kernel_class._prepare_args) == ["self", "ty", "val", "stream", "retr", "kernelargs"],
           "numba.cuda.dispatcher._Kernel._prepare_args", f"parameters {_params(kernel_class._prepare_args)}")
    launch_src = inspect.getsource(kernel_class.launch)
    _check("self._prepare_args(t, v, stream, retr, kernelargs)" in launch_src
           and "launch(stream, config, kernel, *kernelargs)" in launch_src and "cufunc.kernel" in launch_src,
           "numba.cuda.dispatcher._Kernel.launch", "no longer _prepare_args per argument, then cuda.core's launch")
    for name in ("argument_types", "debug", "cooperative"):
        _check(name in inspect.getsource(kernel_class), f"numba.cuda.dispatcher._Kernel.{name}", "missing")
    for name in ("configure", "compile", "typeof_pyval"):
        _check(hasattr(nd.CUDADispatcher, name), f"numba.cuda.dispatcher.CUDADispatcher.{name}", "missing")
