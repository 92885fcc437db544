"""engine/loops/cuda_launch.py without a GPU: every launch happens exactly once whatever the cache decides.

The cached path itself (bit-identical trajectories) needs the real driver: tests/gpu/test_cuda_gpu.py.
"""

from engine.loops.cuda_launch import LaunchCache


class _Kernel:
    """Stands for a numba-cuda dispatcher not launched yet in this process (no ``overloads``): ``k[config](*args)``
    launches; it has no ``compile``, so preparing a cached argument list fails, as it would with numba-cuda internals
    other than the expected ones."""

    overloads: dict = {}

    def __init__(self):
        self.calls = []

    def __getitem__(self, config):
        return lambda *args: self.calls.append((config, args))


def test_a_cache_that_cannot_prepare_turns_itself_off_and_launches_through_the_dispatcher():
    k, a, b = _Kernel(), object(), object()
    lc = LaunchCache(enabled=True)
    for step in range(5):
        lc.launch("forces", k, (4, 256, None), (100, a, b, step))
    assert [c[1][3] for c in k.calls] == [0, 1, 2, 3, 4]          # each launch once, with its own step
    assert not lc.enabled and "AttributeError" in lc.off_reason and lc.hits == 0


def test_disabled_cache_launches_directly():
    k = _Kernel()
    lc = LaunchCache(enabled=False)
    lc.launch("kick_drift", k, (1, 32, None), (1, 2.0))
    assert k.calls == [((1, 32, None), (1, 2.0))] and lc.off_reason is not None


class _Array:
    """Stands for a device array (it takes weak references, as numba-cuda's DeviceNDArray does)."""


def test_hits_replace_scalars_and_stale_arrays_are_let_go():
    """The cache's own bookkeeping, with the numba-cuda part (_prepare's flattened list and cuda.core's launch)
    stood in for by a recorder: scalars are refreshed per launch, the force-buffer swap keeps both entries for
    good (each launch passes only one of the buffers), the cache keeps no array alive, and an entry whose array
    is gone is not used again."""
    import gc
    import weakref

    launched = []

    def prepare(dispatcher, config, args):
        kargs = [a if isinstance(a, int) else id(a) for a in args]
        slots = [(i, i, None) for i, a in enumerate(args) if isinstance(a, int)]
        return (lambda stream, cfg, kern, *ka: launched.append(ka), None, None, None, kargs, slots, "no driver")

    k, a, f0, f1 = _Kernel(), _Array(), _Array(), _Array()
    lc = LaunchCache(enabled=True)
    lc._prepare = prepare
    cfg = (4, 256, None)
    lc.launch("kick", k, cfg, (100, a, f0, 0))            # miss: through the dispatcher
    lc.launch("kick", k, cfg, (100, a, f0, 1))            # hit: the recorder, with step 1
    assert len(k.calls) == 1 and launched == [(100, id(a), id(f0), 1)]
    for step in range(2, 40):                             # the swap: one buffer per launch, alternating
        lc.launch("kick", k, cfg, (100, a, (f0, f1)[step % 2], step))
    assert len(k.calls) == 2 and lc.misses == 2 and lc.hits == 38 and len(lc.entries["kick"]) == 2
    assert launched[-1] == (100, id(a), id(f1), 39)
    gone = weakref.ref(f1)
    k.calls.clear()                                       # (the recorder's own references)
    del f1
    gc.collect()
    assert gone() is None                                 # the cache held no reference to it
    f2 = _Array()
    lc.launch("kick", k, cfg, (100, a, f2, 40))           # a new buffer: a miss, and the dead entry goes
    assert len(k.calls) == 1 and len(lc.entries["kick"]) == 2
    lc.launch("kick", k, cfg, (100, a, f2, 41))
    assert launched[-1] == (100, id(a), id(f2), 41)


def test_an_entry_whose_array_died_is_not_used_even_under_a_reused_identity():
    """The key holds identities; a new array may get a dead one's id. The entry's weak reference tells them
    apart, so the launch goes through the dispatcher with the new array."""
    launched = []

    def prepare(dispatcher, config, args):
        return (lambda stream, cfg, kern, *ka: launched.append(ka), None, None, None, [args[0]], [(0, 0, None)],
                "no driver")

    k, a = _Kernel(), _Array()
    lc = LaunchCache(enabled=True)
    lc._prepare = prepare
    lc.launch("forces", k, (1, 32, None), (1, a))
    (key,) = lc.entries["forces"]
    (entry,) = lc.entries["forces"].values()
    stale = entry[:-1] + (((lambda: None),),)             # as if a had died: its reference answers None
    lc.entries["forces"][key] = stale
    lc.launch("forces", k, (1, 32, None), (2, a))         # same key, dead entry: through the dispatcher
    assert len(k.calls) == 2 and launched == [] and lc.hits == 0


def test_a_scalar_inside_a_tuple_argument_is_not_cached():
    # only top-level scalars are refilled per launch: a tuple holding one must go through numba-cuda every time
    k, a = _Kernel(), object()
    lc = LaunchCache(enabled=True)
    assert LaunchCache._prepare(k, (1, 32, None), (5, (a, 3))) is None
    for step in range(3):
        lc.launch("observe", k, (1, 32, None), (5, (a, step)))
    assert [c[1][1][1] for c in k.calls] == [0, 1, 2] and lc.hits == 0


def test_another_dispatcher_under_the_same_name_and_arrays_is_launched_itself():
    """A scene switches its kernel specialisation (a contact law turned on after the thermalisation) and launches
    the new kernel under the same name with the same arrays: the launch must be the new kernel's, not a hit on the
    old one's entry."""
    launched = []

    def prepare(dispatcher, config, args):
        return (lambda stream, cfg, kern, *ka: launched.append((kern, ka)), None, None, dispatcher, [args[0]],
                [(0, 0, None)], "no driver")

    old, new, a = _Kernel(), _Kernel(), _Array()
    lc = LaunchCache(enabled=True)
    lc._prepare = prepare
    lc.launch("forces", old, (1, 32, None), (1, a))       # miss: through the old dispatcher
    lc.launch("forces", old, (1, 32, None), (2, a))       # hit: the old kernel
    lc.launch("forces", new, (1, 32, None), (3, a))       # the new specialisation: through the new dispatcher
    lc.launch("forces", new, (1, 32, None), (4, a))       # hit: the new kernel
    assert [c[1] for c in old.calls] == [(1, a)] and [c[1] for c in new.calls] == [(3, a)]
    assert launched == [(old, (2,)), (new, (4,))]


class _CompiledKernel(_Kernel):
    """A dispatcher this process has launched before: it holds an overload (numba-cuda's ``overloads``)."""

    overloads = {"sig": object()}


def test_a_kernel_launched_before_is_launched_through_its_new_entry_alone():
    """A miss on a kernel numba-cuda has launched in this process: the flattened list is made once and the launch
    goes through it, not also through the dispatcher (which would flatten the arguments a second time); a kernel
    never launched goes through numba-cuda first, which compiles or loads it."""
    launched = []

    def prepare(dispatcher, config, args):
        return (lambda stream, cfg, kern, *ka: launched.append(ka), None, None, None, list(args), [(0, 0, None)],
                "no driver")

    seen, fresh, a, b = _CompiledKernel(), _Kernel(), _Array(), _Array()
    lc = LaunchCache(enabled=True)
    lc._prepare = prepare
    lc.launch("forces", seen, (1, 32, None), (7, a))
    lc.launch("forces", seen, (1, 32, None), (8, a))
    lc.launch("forces", seen, (1, 32, None), (9, b))      # new arrays: a miss, still no dispatcher launch
    assert seen.calls == [] and [ka[0] for ka in launched] == [7, 8, 9] and (lc.misses, lc.hits) == (2, 1)
    launched.clear()
    lc.launch("kick", fresh, (1, 32, None), (1, a))       # first launch of this kernel: numba-cuda's
    lc.launch("kick", fresh, (1, 32, None), (2, a))       # then the entry kept from it
    assert [c[1][0] for c in fresh.calls] == [1] and [ka[0] for ka in launched] == [2]


def test_a_kernel_that_cannot_be_cached_is_launched_by_its_dispatcher_once_per_launch():
    """_prepare answering None (e.g. a launch-configuration-sensitive kernel): every launch goes through numba-cuda,
    exactly once, also for a kernel launched before."""
    k, a = _CompiledKernel(), _Array()
    lc = LaunchCache(enabled=True)
    lc._prepare = lambda dispatcher, config, args: None
    for step in range(3):
        lc.launch("observe", k, (1, 32, None), (step, a))
    assert [c[1][0] for c in k.calls] == [0, 1, 2] and lc.hits == 0


def test_a_direct_launch_holds_each_argument_as_cuda_core_reads_it_and_refills_the_scalars(monkeypatch):
    """engine.numba_support.numba_internals.direct_launch with the driver call stood in for by a recorder that reads
    the parameter array back: a Python int (bool too) is an intptr_t, a float a double, a ctypes scalar keeps its
    type, a NumPy scalar takes its dtype's (as cuda.core's ParamHolder converts them); each launch refills the scalar
    slots from its own arguments and passes the kernel, grid, block and stream handles through; a cooperative
    kernel, an argument of another type and a driver error are refused."""
    import ctypes
    from types import SimpleNamespace

    import numpy as np
    import pytest

    import engine.numba_support.numba_internals as ni

    calls = []
    status = [0]

    def driver(func, gx, gy, gz, bx, by, bz, shmem, hs, params, extra):
        values = [ctypes.cast(params[i], ctypes.POINTER(t)).contents.value for i, t in enumerate(types)]
        calls.append(((func, (gx, gy, gz), (bx, by, bz), shmem, hs, extra), values))
        return status[0]

    monkeypatch.setattr(ni, "_driver_call", lambda name: driver if name == "cuLaunchKernel" else None)
    kargs = [0, 0, 1000, 8, 123456, 1000, 8, ctypes.c_int64(5), ctypes.c_double(0.5), True, np.float32(2.5),
             ctypes.c_float(1.5)]
    types = [ctypes.c_ssize_t] * 7 + [ctypes.c_int64, ctypes.c_double, ctypes.c_ssize_t, ctypes.c_float,
                                      ctypes.c_float]
    slots = [(0, 7, ctypes.c_int64), (3, 8, ctypes.c_double), (4, 9, None)]
    kernel, stream = SimpleNamespace(handle=0xABC), SimpleNamespace(handle=0x10)
    dims = ((4, 1, 1), (256, 1, 1), False)
    go = ni.direct_launch(stream, dims, kernel, kargs, slots)
    assert [type(h) for h in go.keep[0]] == types
    go((9, "array", "array", 0.25, False))
    go((10, "array", "array", -1.0, True))
    head = (0xABC, (4, 1, 1), (256, 1, 1), 0, 0x10, None)
    assert calls == [(head, [0, 0, 1000, 8, 123456, 1000, 8, 9, 0.25, 0, 2.5, 1.5]),
                     (head, [0, 0, 1000, 8, 123456, 1000, 8, 10, -1.0, 1, 2.5, 1.5])]
    assert ni.direct_launch(stream, ((4, 1, 1), (256, 1, 1), True), kernel, kargs, slots) == "a cooperative kernel"
    assert ni.direct_launch(stream, dims, kernel, kargs + [object()], slots) == "an argument of type object"
    assert "AttributeError" in ni.direct_launch(object(), dims, kernel, kargs, slots)
    status[0] = 700
    with pytest.raises(RuntimeError, match="cuLaunchKernel: CUresult 700"):
        go((11, "array", "array", 0.0, False))
    # a thread without the context current (CUDA_ERROR_INVALID_CONTEXT): numba-cuda makes it current, then the launch
    from numba import cuda

    answers, made_current = [ni.CUDA_ERROR_INVALID_CONTEXT, 0], []
    status[0] = None
    monkeypatch.setattr(ni, "_driver_call", lambda name: lambda *a: answers.pop(0))
    monkeypatch.setattr(cuda, "current_context", lambda: made_current.append(True))
    retried = ni.direct_launch(stream, dims, kernel, kargs, slots)
    retried((12, "array", "array", 0.0, False))
    assert made_current == [True] and answers == []


def test_a_cache_entry_with_a_direct_launch_launches_through_it(monkeypatch):
    """Hits of an entry prepared with a direct launch (DIRECT) go through it with the launch's own arguments, not
    through the entry's cuda.core launch; an entry prepared without one (DIRECT off, or the reason it could not be
    made) launches through cuda.core, and the cache says why."""
    import engine.loops.cuda_launch as launch

    for direct in (True, False):
        monkeypatch.setattr(launch, "DIRECT", direct)
        core, driven = [], []

        def prepare(dispatcher, config, args):
            go = (lambda a: driven.append(a)) if launch.DIRECT else "not asked for"
            return (lambda stream, cfg, kern, *ka: core.append(ka), None, None, None, list(args), [(0, 0, None)], go)

        monkeypatch.setattr(LaunchCache, "_prepare", staticmethod(prepare))
        k, a = _CompiledKernel(), _Array()
        lc = LaunchCache(enabled=True)
        for step in range(4):
            lc.launch("forces", k, (1, 32, None), (step, a))
        if direct:
            assert driven == [(step, a) for step in range(4)] and core == [] and lc.direct == 4
            assert lc.direct_off_reason is None
        else:
            assert [ka[0] for ka in core] == [0, 1, 2, 3] and driven == [] and lc.direct == 0
            assert lc.direct_off_reason == "not asked for"


def test_the_argument_key_tells_apart_what_each_arguments_identity_tells_apart():
    """engine/loops/cuda_launch.py ``_args_key`` (the cache key's part of a launch's arguments, made with builtins
    mapped over them) is equal for two launches exactly where the arguments' identities (``_ident``: a scalar by its
    type, an array by its identity, a tuple element by element) are: over every combination of scalar values and
    types, arrays and tuple contents below."""
    import itertools

    import numpy as np

    from engine.loops.cuda_launch import _args_key, _ident

    a, b, c = _Array(), _Array(), _Array()
    launches = [(n, x, t, step) for n, x, t, step in itertools.product(
        (100, np.int64(100), 7), (a, b), ((a, c), (b, c), (a,), c), (0, 1, 2.5, np.float32(1.0)))]
    for u, v in itertools.product(launches, repeat=2):
        assert (_args_key(u) == _args_key(v)) == (tuple(map(_ident, u)) == tuple(map(_ident, v))), (u, v)
