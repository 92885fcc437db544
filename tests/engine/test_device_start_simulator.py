"""Large starts drawn on the GPU (engine/loops/cuda_start.py) under the Numba CUDA simulator: the same start as the
host's draws (engine.setup.scene._parallel_draws), and the device memory a random start allocates against the memory
prediction's count of it.

Under the simulator the kernels call the same compiled engine.setup.scene functions as the host and add in Python's
float64, in the same order, so the device start must equal the host's bit for bit here; on a GPU it is equal to
rounding (tests/gpu/test_device_start_gpu.py). Runs in a simulator child (tests/cudasim.py).
"""

import sys
from pathlib import Path

import numpy as np

from tests.cudasim import run_children

ROOT = Path(__file__).resolve().parents[2]


def _streams():
    from engine.setup.scene import STREAM_QUATERNION, STREAM_SPIN, STREAM_VELOCITY

    return [(STREAM_VELOCITY, 3, 2.0), (STREAM_SPIN, 3, 40.0), (STREAM_QUATERNION, 4, None)]


def _device_arrays(d, pos_dtype, dtype, extra_cols=0, col0=0):
    from numba import cuda

    from engine.loops.cuda_start import draw_start

    n = d.n + extra_cols
    stream = cuda.stream()
    pos = cuda.to_device(np.full((3, n), -1.0, pos_dtype), stream=stream)
    dsts = {k: cuda.to_device(np.full((dim, n), -1.0, dtype), stream=stream) for k, dim, _ in d.streams}
    draw_start(d, col0, pos, dsts, stream)
    stream.synchronize()
    return pos.copy_to_host(), [dsts[k].copy_to_host() for k, _, _ in d.streams]


def _draws() -> None:
    """draw_start against the host's draws: with a site selection (n < n_sites) and without (n = n_sites), into
    columns from col0 of wider arrays (the others untouched), in float64, float32 and mixed precision."""
    from engine.setup.scene import StartDraw

    for n, box, radius in ((100, 3.0, 0.05), (256, 3.0, 0.05), (40, 1.0, 0.1)):
        d = StartDraw.of(n, 17, _streams(), box, radius)
        assert (n < d.n_sites) == (n != 256), (n, d.n_sites)
        pos_h, arrays_h = d.on_host()
        for pos_dtype, dtype in ((np.float64, np.float64), (np.float32, np.float32), (np.float64, np.float32)):
            pos, arrays = _device_arrays(d, pos_dtype, dtype, extra_cols=5, col0=3)
            assert np.array_equal(pos[:, 3:3 + n], pos_h.T.astype(pos_dtype)), (n, pos_dtype)
            assert np.all(pos[:, :3] == -1.0) and np.all(pos[:, 3 + n:] == -1.0)
            for a, h in zip(arrays, arrays_h):
                assert np.array_equal(a[:, 3:3 + n], h.T.astype(dtype)), (n, dtype)
                assert np.all(a[:, :3] == -1.0) and np.all(a[:, 3 + n:] == -1.0)
    # random starts (engine/setup/cell_rsa.py): the same centres (exact integer tests, one rounding each), a dilute one
    # and one at phi = 0.29 that takes many rounds
    for n, box, radius in ((150, 1.0, 0.05), (200, 1.0, 0.07)):
        d = StartDraw.of(n, 23, _streams(), box, radius, "random")
        pos_h, arrays_h = d.on_host()
        for pos_dtype, dtype in ((np.float64, np.float64), (np.float32, np.float32)):
            pos, arrays = _device_arrays(d, pos_dtype, dtype, extra_cols=2, col0=1)
            assert np.array_equal(pos[:, 1:1 + n], pos_h.T.astype(pos_dtype)), (n, pos_dtype)
            assert np.all(pos[:, :1] == -1.0) and np.all(pos[:, 1 + n:] == -1.0)
            for a, h in zip(arrays, arrays_h):
                assert np.array_equal(a[:, 1:1 + n], h.T.astype(dtype)), (n, dtype)
    print("draws ok")


def _ensemble() -> None:
    """A CUDA ensemble of a scene whose start is drawn on the device beside a scene with host arrays holds the
    same state as one built from host draws (their columns, the first list build and forces at t = 0)."""
    import dataclasses

    from engine.backends.base import SphereSystem
    from engine.backends.cuda import CudaEnsemble
    from engine.setup.scene import StartDraw, drawn_on_host
    from tests.engine.test_cuda_simulator import contact, tiny_system

    n, box, r = 60, 2.0, 0.05
    m, inertia = 1.0, 0.4 * r * r
    drawn = SphereSystem(box_length=box, position=None, velocity=None, angular_velocity=None, orientation=None,
                         radius=np.full(n, r), mass=np.full(n, m), inertia=np.full(n, inertia),
                         draw=StartDraw.of(n, 5, _streams(), box, r))
    assert drawn.n == n
    host = drawn_on_host(drawn)
    assert host.draw is None and host.position.shape == (n, 3)
    other = tiny_system()
    c = contact(skin=0.01)
    a = CudaEnsemble([other, drawn], [c, c])
    b = CudaEnsemble([other, dataclasses.replace(host)], [c, c])
    for k in (0, 1):
        sa, sb = a.state(k), b.state(k)
        for key in ("position", "velocity", "angular_velocity", "orientation"):
            assert np.array_equal(sa[key], sb[key]), (k, key)
    assert np.array_equal(a.f_cur.copy_to_host(), b.f_cur.copy_to_host())
    # the slots' scene index and particle ids made on the device: scenes stay in their columns, each scene's ids a
    # permutation of its own after the first list build; the kernel itself with an empty scene among others
    sizes = [other.n, n]
    assert np.array_equal(a.sc.copy_to_host(), np.repeat([0, 1], sizes))
    ids = a.ids.copy_to_host()
    assert np.array_equal(np.sort(ids[:other.n]), np.arange(other.n))
    assert np.array_equal(np.sort(ids[other.n:]), np.arange(other.n, other.n + n))
    from numba import cuda

    from engine.loops import cuda_kernels as K
    ids_d, sc_d = cuda.device_array(9, np.int32), cuda.device_array(9, np.int32)
    K.slot_ids_and_scenes[2, 32](cuda.to_device(np.cumsum([3, 0, 5, 1])), ids_d, sc_d)
    assert np.array_equal(ids_d.copy_to_host(), np.arange(9))
    assert np.array_equal(sc_d.copy_to_host(), [0, 0, 0, 2, 2, 2, 2, 2, 3])
    print("ensemble ok")


def _spheroids() -> None:
    """A spheroid ensemble of scenes drawn on the device (a rough random start, a smooth lattice start, in float64
    and float32) beside a scene with host arrays holds the state of one built from the same draws on the host: the
    random start's centres and orientations, the spins from the body-axis draws, L and the predicted spin."""
    import dataclasses

    from engine.shapes.spheroid.cuda_backend import CudaEllipsoidEnsemble
    from engine.setup.params import derive
    from engine.setup.scene import drawn_on_host, initial_ellipsoids
    from engine.setup.spec import SimulationSpec
    from tests.engine.test_cuda_ellipsoid_simulator import contact, tiny_ellipsoids

    from engine.setup import start_kind

    start_kind.PARALLEL_START_MIN = 64      # these small starts are drawn as a large one is
    scenes = []
    for start, e_t, seed in (("random", 0.8, 3), ("lattice", -1.0, 4)):
        spec = SimulationSpec(shape="ellipsoid", elongation=2.0, n_particles=80, volume_fraction=0.05, start=start,
                              e_t=e_t, seed=seed, box_length=1.0)
        drawn = initial_ellipsoids(spec, derive(spec), on_device=True)
        assert drawn.draw is not None and drawn.position is None and drawn.n == 80
        scenes.append(drawn)
    other = tiny_ellipsoids()
    for precision in ("float64", "float32"):
        c = contact(precision=precision)
        a = CudaEllipsoidEnsemble([other, *scenes], [c, c, c])
        b = CudaEllipsoidEnsemble([other] + [dataclasses.replace(drawn_on_host(s)) for s in scenes], [c, c, c])
        for k in (0, 1, 2):
            sa, sb = a.state(k), b.state(k)
            for key in ("position", "velocity", "angular_velocity", "orientation"):
                assert np.array_equal(sa[key], sb[key]), (precision, k, key)
        for name in ("angm", "omega_p", "quat", "pos_prev", "quat_prev", "vel_p"):
            assert np.array_equal(getattr(a, name).copy_to_host(), getattr(b, name).copy_to_host()), name
    from engine.shapes import host

    host("ellipsoid").load_device_start(np.float32, np.float32)     # the GPU start-up's load runs these kernels
    print("spheroids ok")


def _memory() -> None:
    """The device memory a random start drawn on the device holds at its peak (the live bytes of every device_array
    and to_device while it is drawn) is what the memory prediction counts for it (engine/loops/cuda_memory.py: the
    larger of ``random_start_bytes``, the cells, and the streams' state arrays with one stream's float64 scratch of
    START_ROWS rows: the cells are freed before the first stream is drawn, and the state arrays, handed over as
    functions that make them, are made only then), up to the fixed small arrays (the last round's key histogram of
    2^SELECT_BITS int32 and a few words)."""
    import weakref

    from numba import cuda

    from engine.loops import cuda_start
    from engine.loops.cuda_memory import START_ROWS, random_start_bytes
    from engine.setup.scene import StartDraw

    n, radius = 3000, 0.01
    box = (n * 4.0 / 3.0 * np.pi * radius ** 3 / 0.058) ** (1.0 / 3.0)
    d = StartDraw.of(n, 7, _streams(), box, radius, "random")
    stream = cuda.stream()
    pos = cuda.device_array((3, n), np.float64)
    made = []      # the state arrays, made at the draw's call (device_array is counted by then)
    dsts = {k: (lambda dim=dim: made.append(cuda.device_array((dim, n), np.float64)) or made[-1])
            for k, dim, _ in d.streams}
    live, peak = [0], [0]
    device_array, to_device = cuda.device_array, cuda.to_device

    def counted(make):
        def f(*a, **k):
            x = make(*a, **k)
            live[0] += x.nbytes
            peak[0] = max(peak[0], live[0])
            weakref.finalize(x, lambda b=x.nbytes: live.__setitem__(0, live[0] - b))
            return x
        return f

    cuda.device_array, cuda.to_device = counted(device_array), counted(to_device)
    try:
        cuda_start.draw_start(d, 0, pos, dsts, stream)
        stream.synchronize()
    finally:
        cuda.device_array, cuda.to_device = device_array, to_device
    cells, scratch = random_start_bytes(n, box, radius), 8 * START_ROWS * n
    state = sum(a.nbytes for a in made)
    assert len(made) == len(d.streams) and cells > scratch and state > 4 * cuda_start._NB + 4096
    fixed = 4 * cuda_start._NB + 4096
    assert cells <= peak[0] <= max(cells, state + scratch) + fixed, (peak[0], cells, state, scratch)
    print("memory ok")


def test_device_start_is_the_host_start_under_the_simulator():
    here = Path(__file__).resolve()
    res = run_children({part: [here, part] for part in ("draws", "ensemble", "spheroids", "memory")}, timeout=600)
    for part, (rc, out, err) in res.items():
        assert rc == 0 and f"{part} ok" in out, f"{part}:\n{out}\n{err[-3000:]}"


if __name__ == "__main__":
    from tests.cudasim import fast_block_polling

    sys.path.insert(0, str(ROOT))
    fast_block_polling()
    {"draws": _draws, "ensemble": _ensemble, "spheroids": _spheroids, "memory": _memory}[sys.argv[1]]()
