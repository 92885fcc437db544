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
