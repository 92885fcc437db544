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
        return (lambda stream, cfg, kern, *ka: launched.append(ka), None, None, None, kargs, slots)

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
        return (lambda stream, cfg, kern, *ka: launched.append(ka), None, None, None, [args[0]], [(0, 0, None)])

    k, a = _Kernel(), _Array()
    lc = LaunchCache(enabled=True)
    lc._prepare = prepare
    lc.launch("forces", k, (1, 32, None), (1, a))
    (key,) = lc.entries["forces"]
    (entry,) = lc.entries["forces"].values()
    stale = entry[:7] + (((lambda: None),),)              # as if a had died: its reference answers None
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
                [(0, 0, None)])

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
        return (lambda stream, cfg, kern, *ka: launched.append(ka), None, None, None, list(args), [(0, 0, None)])

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
