"""engine/backends/cuda_launch.py without a GPU: every launch happens exactly once whatever the cache decides.

The cached path itself (bit-identical trajectories) needs the real driver: tests/gpu/test_cuda_gpu.py.
"""

from engine.backends.cuda_launch import LaunchCache


class _Kernel:
    """Stands for a numba-cuda dispatcher: ``k[config](*args)`` launches; it has no ``compile``, so preparing a
    cached argument list fails, as it would with numba-cuda internals other than the expected ones."""

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


def test_hits_replace_scalars_and_stale_arrays_are_let_go():
    """The cache's own bookkeeping, with the numba-cuda part (_prepare's flattened list and cuda.core's launch)
    stood in for by a recorder: scalars are refreshed per launch, the force-buffer swap keeps both entries,
    and an entry whose array was replaced is dropped (its device memory can then be freed)."""
    launched = []

    def prepare(dispatcher, config, args):
        kargs = [a if isinstance(a, int) else id(a) for a in args]
        slots = [(i, i, None) for i, a in enumerate(args) if isinstance(a, int)]
        return (lambda stream, cfg, kern, *ka: launched.append(ka), None, None, None, kargs, slots, args)

    k, a, b, c = _Kernel(), object(), object(), object()
    lc = LaunchCache(enabled=True)
    lc._prepare = prepare
    cfg = (4, 256, None)
    lc.launch("forces", k, cfg, (100, a, b, 0))           # miss: through the dispatcher
    lc.launch("forces", k, cfg, (100, a, b, 1))           # hit: the recorder, with step 1
    assert len(k.calls) == 1 and launched == [(100, id(a), id(b), 1)]
    lc.launch("forces", k, cfg, (100, b, a, 2))           # the swap: a second entry, the first one kept
    lc.launch("forces", k, cfg, (100, a, b, 3))           # hit again
    assert len(k.calls) == 2 and launched[-1] == (100, id(a), id(b), 3) and len(lc.entries["forces"]) == 2
    lc.launch("forces", k, cfg, (100, a, c, 4))           # b replaced by c: the entries holding b go
    assert len(k.calls) == 3 and len(lc.entries["forces"]) == 1
    lc.launch("forces", k, cfg, (100, a, c, 5))
    assert launched[-1] == (100, id(a), id(c), 5) and lc.hits == 3 and lc.misses == 3


def test_a_scalar_inside_a_tuple_argument_is_not_cached():
    # only top-level scalars are refilled per launch: a tuple holding one must go through numba-cuda every time
    k, a = _Kernel(), object()
    lc = LaunchCache(enabled=True)
    assert LaunchCache._prepare(k, (1, 32, None), (5, (a, 3))) is None
    for step in range(3):
        lc.launch("observe", k, (1, 32, None), (5, (a, step)))
    assert [c[1][1][1] for c in k.calls] == [0, 1, 2] and lc.hits == 0
