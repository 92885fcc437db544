"""Time to result (docs/design.md §9): parallel starts, the buffered / background result writer, the auto list mode's
probe rule. The speed itself is measured by bench/e2e.py, not here."""

from __future__ import annotations

import ast
import gc
import math
import types

import h5py
import numba
import numpy as np
import pytest

import engine.setup.start_kind as start_kind
from engine.errors import InstabilityError
from engine.loops.system import rows_equal
from engine.output.h5md import OBSERVABLE_BLOCK, H5MDWriter, partial_path
from engine.setup.params import derive
from engine.setup.scene import (PARALLEL_GENERATOR, PARALLEL_RSA_GENERATOR, PARALLEL_START_MIN, SEQUENTIAL_GENERATOR,
                                STREAM_QUATERNION, STREAM_SITES, STREAM_SPIN, STREAM_SPIN_AXIS, STREAM_VELOCITY, _bits,
                                _parallel_draws, _smallest_sites, _stream_key, device_start, initial_ellipsoids,
                                initial_spheres, start_generator)
from engine.setup.spec import SimulationSpec


def _big(n=PARALLEL_START_MIN, start="lattice", **kw):
    """A large start (the lattice protocol unless ``start`` says otherwise: engine/setup/cell_rsa.py's random one is
    tested in tests/engine/test_cell_rsa.py)."""
    return SimulationSpec(n_particles=n, volume_fraction=0.058, box_length=2.0 * (n / 4096) ** (1.0 / 3.0),
                          thermalization=0, start=start, **kw)


def test_which_starts_are_drawn_in_parallel():
    assert start_generator(_big(PARALLEL_START_MIN - 1)) == SEQUENTIAL_GENERATOR
    assert start_generator(_big()) == PARALLEL_GENERATOR
    assert start_generator(_big(start=None)) == PARALLEL_RSA_GENERATOR                # the default: random
    assert start_generator(SimulationSpec()) == SEQUENTIAL_GENERATOR
    species = [{"radius_ratio": 1.0, "number_fraction": 0.5}, {"radius_ratio": 0.5, "number_fraction": 0.5}]
    assert start_generator(_big(species=species, start=None)) == SEQUENTIAL_GENERATOR  # RSA placement stays sequential


def test_a_gpu_jobs_large_sphere_start_is_left_to_the_device_and_drawn_on_the_host_if_the_job_runs_on_the_cpu(
        monkeypatch, tmp_path):
    """engine.setup.scene.initial_spheres(on_device=True) leaves a large sphere start to the GPU backend (a StartDraw,
    no host arrays: engine/loops/cuda_start.py); a job whose backend resolves to the CPU after all draws it on the
    host, the same start as always; with start_kind.DEVICE_START False and for other shapes the host draws."""
    import engine.driver.simulate as sim

    spec = _big(seed=9)
    p = derive(spec)
    host = initial_spheres(spec, p)
    left = initial_spheres(spec, p, on_device=True)
    assert left.draw is not None and left.position is None and left.velocity is None and left.n == spec.n_particles
    assert left.draw.n_sites >= spec.n_particles and np.array_equal(left.radius, host.radius)
    # its one-size constants are broadcast views (no N-long host arrays), which rows_equal knows without a scan
    for attr in ("radius", "mass", "inertia"):
        a = getattr(left, attr)
        assert a.strides == (0,) and not a.flags.writeable and np.array_equal(a, getattr(host, attr)), attr
    assert rows_equal(left.radius) and rows_equal(np.zeros((0, 3))) and rows_equal(np.ones((4, 3)))
    assert not rows_equal(np.array([1.0, 1.0, 2.0])) and not rows_equal(np.array([[1.0, 2.0], [1.0, 3.0]]))
    assert initial_spheres(_big(PARALLEL_START_MIN - 1), p, on_device=True).draw is None     # a small start

    class Started:                 # stands for a GPU start-up (engine/driver/startup.py), as on a machine with a GPU
        def wait(self):
            pass

    monkeypatch.setattr(sim, "begin_gpu_startup", lambda *a: Started())
    scene = sim.SceneRun(spec.model_copy(update={"backend": "cpu"}), tmp_path / "x.h5")
    assert scene.backend == "cpu" and scene.system.draw is None
    for attr in ("position", "velocity", "angular_velocity", "orientation", "radius", "mass", "inertia"):
        assert np.array_equal(getattr(scene.system, attr), getattr(host, attr)), attr
    # the CPU loops get writable arrays of their own
    assert all(getattr(scene.system, a).flags.writeable and getattr(scene.system, a).flags.c_contiguous
               for a in ("radius", "mass", "inertia"))
    assert device_start(spec) and device_start(_big(shape="ellipsoid", elongation=2.0))     # spheroids alike
    assert not device_start(_big(PARALLEL_START_MIN - 1))
    # a job that runs on the GPU leaves its start to the device, unless start_kind.DEVICE_START is False
    monkeypatch.setattr(sim, "resolve_backend", lambda name, shape: "cuda")
    gpu = sim.SceneRun(spec, tmp_path / "y.h5")
    assert gpu.backend == "cuda" and gpu.system.draw == left.draw and gpu.system.position is None
    monkeypatch.setattr(start_kind, "DEVICE_START", False)
    assert not device_start(spec)
    gpu = sim.SceneRun(spec, tmp_path / "z.h5")
    assert gpu.system.draw is None and np.array_equal(gpu.system.position, host.position)


def test_parallel_start_is_a_valid_homogeneous_gas():
    from engine.analysis.pairs import periodic_pairs

    spec = _big()
    p = derive(spec)
    sy = initial_spheres(spec, p)
    box = spec.box_length
    v, w, q, x = sy.velocity, sy.angular_velocity, sy.orientation, sy.position
    assert np.all((x >= 0.0) & (x < box))
    # no two spheres overlap (periodic box)
    close = periodic_pairs(x, box, 2.0 * p.radius)                 # pairs at distance <= 2a: only touching ones
    r = x[close[:, 1]] - x[close[:, 0]]
    r -= box * np.round(r / box)
    assert np.all(np.sum(r * r, axis=1) >= (2.0 * p.radius) ** 2)
    # zero momentum and exactly the requested rms speed (to rounding)
    assert np.abs(v.mean(axis=0)).max() < 1e-12 * spec.velocity_rms
    assert math.sqrt(np.mean(np.sum(v * v, axis=1))) == pytest.approx(spec.velocity_rms, rel=1e-12)
    assert np.abs(w.mean(axis=0)).max() < 1e-12 * np.sqrt(np.mean(w * w))
    assert np.abs(np.linalg.norm(q, axis=1) - 1.0).max() < 1e-14
    # Gaussian components: kurtosis 3 within ~6 standard errors of sqrt(24/n) = 0.005 for n = 2^20
    kurt = np.mean(v ** 4, axis=0) / np.mean(v ** 2, axis=0) ** 2
    assert np.abs(kurt - 3.0).max() < 0.03
    # isotropic: the three components carry the same energy within ~6 standard errors (sqrt(2/n) = 0.0014)
    var = np.mean(v ** 2, axis=0)
    assert np.abs(var / var.mean() - 1.0).max() < 0.01
    # uniform orientations: <q_k^2> = 1/4 for each component
    assert np.abs(np.mean(q ** 2, axis=0) - 0.25).max() < 0.005
    # the same seed gives the same start, another seed another one
    again = initial_spheres(spec, p)
    assert np.array_equal(again.position, x) and np.array_equal(again.velocity, v)
    other = initial_spheres(spec.model_copy(update={"seed": 1}), p)
    assert not np.array_equal(other.velocity, v)


@pytest.mark.parametrize("kw", [{}, {"start": None}, {"shape": "ellipsoid", "elongation": 2.0, "e_t": -1.0},
                                {"shape": "ellipsoid", "elongation": 2.0},
                                {"shape": "ellipsoid", "elongation": 2.0, "e_t": -1.0, "start": None},
                                {"shape": "ellipsoid", "elongation": 2.0, "start": None}])
def test_loading_a_start_kind_covers_every_compiled_call_of_its_large_starts(monkeypatch, kw):
    """engine.setup.scene.load_parallel_start (the worker's standby, warm_process) calls every compiled function of a
    large start of the spec's kind (spheres; smooth and rough ellipsoids, 3 and 4 streams; lattice and random) with
    the argument types the start calls it with, so the start loads nothing more."""
    import engine.setup.cell_rsa as rsa
    import engine.setup.scene as sc
    from engine.shapes import host

    calls = {}
    for module, name in ((sc, "_draw_start"), (sc, "_centre_and_square"), (sc, "_scale_streams"),
                         (sc, "_space_spins_parallel"), (rsa, "_round"), (rsa, "_last_round"), (rsa, "_gather")):
        f = getattr(module, name)

        def spy(*args, _f=f, _name=name):
            calls.setdefault(_name, []).append(tuple(numba.typeof(a) for a in args))
            return _f(*args)

        monkeypatch.setattr(module, name, spy)
    spec = _big(**kw)
    p = derive(spec)
    assert sc.load_parallel_start(spec.model_copy(update={"n_particles": 1000}), p)   # N is not read
    loaded = {k: set(v) for k, v in calls.items()}
    calls.clear()
    host(spec.shape).initial_system(spec, p)
    assert set(calls) == set(loaded) and all(set(v) <= loaded[k] for k, v in calls.items())
    species = [{"radius_ratio": 1.0, "number_fraction": 0.5}, {"radius_ratio": 0.5, "number_fraction": 0.5}]
    assert not sc.load_parallel_start(_big(species=species, start=None), p)      # species starts are NumPy's


def test_warm_process_loads_only_the_start_functions_its_specs_job_calls(monkeypatch):
    """The standby's warm-up loads the host's start functions a job of its spec calls (a large start drawn on the
    host, a spheroid's start), and none for a start NumPy or the device draws: on an empty cache their compile held
    the claim handed to the standby behind numba's compiler lock."""
    import engine.setup.scene as sc
    from engine.driver import simulate

    monkeypatch.setattr(simulate, "begin_gpu_startup", lambda *a: None)     # the GPU part: engine/driver/startup.py
    loaded = []
    load = sc.load_parallel_start
    monkeypatch.setattr(sc, "load_parallel_start",
                        lambda spec, p: loaded.append((spec.shape, spec.n_particles)) or load(spec, p))
    simulate.warm_process(SimulationSpec(shape="ellipsoid", elongation=2.0))
    assert loaded == [("ellipsoid", 4096)]
    loaded.clear()
    simulate.warm_process()                                   # the default job: a NumPy start
    species = [{"radius_ratio": 1.0, "number_fraction": 0.5}, {"radius_ratio": 0.5, "number_fraction": 0.5}]
    simulate.warm_process(SimulationSpec(species=species, volume_fraction=0.1))
    simulate.warm_process(SimulationSpec(shape="ellipsoid", elongation=2.0, start="lattice"))   # NumPy's too
    assert loaded == []
    simulate.warm_process(_big())                            # a large start drawn on the host (no GPU)
    assert loaded == [("sphere", PARALLEL_START_MIN)]
    # on a GPU (its start-up begun) a spec whose start the device draws loads no host start; a small spheroid does
    monkeypatch.setattr(simulate, "begin_gpu_startup", lambda *a: types.SimpleNamespace(wait=lambda: None))
    loaded.clear()
    for shape, kw in (("sphere", {}), ("ellipsoid", dict(elongation=2.0))):
        simulate.warm_process(SimulationSpec(shape=shape, n_particles=1 << 21, **kw))
    simulate.warm_process()
    assert loaded == []
    simulate.warm_process(SimulationSpec(shape="ellipsoid", elongation=2.0))
    assert loaded == [("ellipsoid", 4096)]


_DRAWS_ON_TWO_THREADS = """
import sys
import numba
import numpy as np
from engine.setup.scene import STREAM_QUATERNION, STREAM_SPIN, STREAM_VELOCITY, _parallel_draws
assert numba.get_num_threads() == 2, numba.get_num_threads()
pos, arrays = _parallel_draws(50_000, 7, [(STREAM_VELOCITY, 3, 2.0), (STREAM_SPIN, 3, 5.0), (STREAM_QUATERNION, 4, None)],
                              place=(4.6, 0.05))
np.savez(sys.argv[1], pos, *arrays)
"""


def test_parallel_start_does_not_depend_on_the_thread_count(tmp_path):
    # 50 000 of the 55 296 sites of a 24^3-cell lattice: the site selection runs too. Here on one thread
    # (tests/conftest.py), in a child process on two.
    import os
    import subprocess
    import sys
    from pathlib import Path

    streams = [(STREAM_VELOCITY, 3, 2.0), (STREAM_SPIN, 3, 5.0), (STREAM_QUATERNION, 4, None)]
    threads = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = _parallel_draws(50_000, 7, streams, place=(4.6, 0.05))
        # the velocities with other companions (spheroid spins, in another order), no positions: as many streams
        # as above, so the compiled draw of three streams serves both
        others = _parallel_draws(50_000, 7, [(STREAM_VELOCITY, 3, 2.0), (STREAM_SPIN_AXIS, 1, 3.0),
                                             (STREAM_QUATERNION, 4, None)])[1]
        vel_one = others[0]
    finally:
        numba.set_num_threads(threads)
    root = Path(__file__).resolve().parents[2]
    p = subprocess.run([sys.executable, "-c", _DRAWS_ON_TWO_THREADS, str(tmp_path / "two.npz")],
                       capture_output=True, text=True, timeout=600, cwd=str(tmp_path),
                       env={**os.environ, "NUMBA_NUM_THREADS": "2", "PYTHONPATH": str(root)})
    assert p.returncode == 0, p.stderr[-3000:]
    with np.load(tmp_path / "two.npz") as f:
        many = (f["arr_0"], [f[f"arr_{k}"] for k in (1, 2, 3)])
    assert np.array_equal(one[0], many[0])
    assert all(np.array_equal(a, b) for a, b in zip(one[1], many[1]))
    # a stream's draws do not depend on the other streams drawn with it
    assert np.array_equal(vel_one, many[1][0]) and np.array_equal(others[2], many[1][2])
    with pytest.raises(ValueError, match="quaternions only"):    # unit rows are quaternions (quat_unit)
        _parallel_draws(10, 7, [(STREAM_QUATERNION, 3, None)])


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_unit_quaternions_are_numpys_normalisation(dtype):
    """Both ellipsoid backends normalise the start's quaternions with one compiled loop; it must give NumPy's
    ``orient / np.linalg.norm(orient, axis=1)[:, None]`` (what they used before) bit for bit."""
    from engine.shapes.spheroid.cpu_backend import unit_quaternions

    orient = np.random.default_rng(5).normal(size=(200_000, 4)) * 3.0
    out = np.empty_like(orient, dtype=dtype)
    unit_quaternions(orient, out)
    assert np.array_equal(out, (orient / np.linalg.norm(orient, axis=1)[:, None]).astype(dtype))


@numba.njit(parallel=True)
def _select_in_parallel(key, n_sites, n):
    return _smallest_sites(key, n_sites, n)     # inlined, as in engine.setup.scene._draw_start: its pranges run


@numba.njit
def _site_keys(key, n_sites):
    out = np.empty(n_sites, np.uint64)
    for j in range(n_sites):
        out[j] = _bits(key, j, 0)
    return out


@pytest.mark.parametrize("n, n_sites", [(1, 4), (3, 32), (255, 256), (5000, 6912), (27_000, 32_000)])
def test_site_selection_takes_the_sites_of_smallest_key(n, n_sites):
    """The radix select of the large starts picks what a sort of all keys picks (the choice before it replaced
    np.argpartition + np.sort; 64-bit keys never tie here, so the set is unique)."""
    key = _stream_key(11, STREAM_SITES)
    keys = _site_keys(key, n_sites)
    assert len(np.unique(keys)) == n_sites
    chosen = _select_in_parallel(key, n_sites, n)
    assert np.array_equal(chosen, np.sort(np.argpartition(keys, n - 1)[:n]))


def test_stream_keys_are_splitmix64_of_seed_and_stream():
    """The Python-integer stream key against SplitMix64 written out in NumPy's wrapping uint64 arithmetic."""
    def mix(x):
        with np.errstate(over="ignore"):
            x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
            x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
            return x ^ (x >> np.uint64(31))
    for seed, stream in [(0, 0), (7, 3), (2**63 + 5, 1), (-1, 5)]:
        with np.errstate(over="ignore"):
            x = np.uint64(seed % 2**64) * np.uint64(0x9E3779B97F4A7C15) + np.uint64(stream + 1)
        assert _stream_key(seed, stream) == mix(np.array([x]))[0]


def test_parallel_ellipsoid_start_spins_only_about_the_perpendicular_axes():
    spec = _big(shape="ellipsoid", elongation=2.0, e_t=-1.0)
    p = derive(spec)
    sy = initial_ellipsoids(spec, p)
    w, q = sy.angular_velocity, sy.orientation
    wq, xq, yq, zq = q.T
    e1 = np.stack([1 - 2 * (yq * yq + zq * zq), 2 * (xq * yq + wq * zq), 2 * (xq * zq - wq * yq)], 1)
    assert np.abs(np.sum(w * e1, axis=1)).max() < 1e-9 * np.abs(w).max()   # no spin about the symmetry axis
    # T per perpendicular dof = m <v^2>/3 (equipartition at the start)
    e_perp = 0.5 * p.inertia[1] * np.mean(np.sum(w * w, axis=1))
    t_tr = p.mass * np.mean(np.sum(sy.velocity ** 2, axis=1)) / 3.0
    assert e_perp == pytest.approx(t_tr, rel=1e-9)


# ---- the result writer --------------------------------------------------------------------------------

def _write(path, background: bool, records: int, frames=(), nan_frame=None, deferred=False):
    w = H5MDWriter(path, n=5, box_length=1.0, spec_json="{}", derived={"dt": 1e-3}, radius=np.ones(5),
                   mass=np.ones(5), background=background, deferred=deferred)
    rng = np.random.default_rng(0)
    for r in range(records):
        w.observables(r, r * 1e-3, {"a": float(r), "contacts": np.int64(r % 3)})
        if r in frames:
            pos = rng.random((5, 3))
            if r == nan_frame:
                pos[2, 1] = np.nan
            w.snapshot(r, r * 1e-3, {"position": pos})
    return w


def _datasets(path) -> dict:
    out = {}
    with h5py.File(path) as f:
        f.visititems(lambda name, o: out.__setitem__(name, o[()]) if isinstance(o, h5py.Dataset) else None)
    return out


@pytest.mark.parametrize("background", [False, True])
def test_writer_blocks_and_counts(tmp_path, background):
    records = 2 * OBSERVABLE_BLOCK + 17  # three blocks
    w = _write(tmp_path / "r.h5", background, records, frames=(0, 5, records - 1))
    counts = w.frame_counts()  # what a checkpoint records: pending records included
    assert counts["observables/a"] == records and counts["particles/all/position"] == 3
    w.finish({"wall_time": 1.0})
    d = _datasets(tmp_path / "r.h5")
    assert np.array_equal(d["observables/a/step"], np.arange(records))
    assert np.array_equal(d["observables/a/value"], np.arange(records, dtype=float))
    assert d["observables/contacts/value"].dtype == np.int64
    assert d["particles/all/position/value"].shape == (3, 5, 3)


def test_background_and_synchronous_writers_write_the_same_file(tmp_path):
    for bg in (False, True):
        _write(tmp_path / f"{bg}.h5", bg, 700, frames=(0, 300, 699)).finish({"wall_time": 1.0})
    a, b = _datasets(tmp_path / "False.h5"), _datasets(tmp_path / "True.h5")
    assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


def test_a_deferred_file_written_by_a_writer_process_is_the_same_file(tmp_path):
    """engine/output/h5md_pool.py: the whole file kept in memory and written at the end in another process."""
    records, frames = 2 * OBSERVABLE_BLOCK + 5, (0, 300, 2 * OBSERVABLE_BLOCK + 4)
    _write(tmp_path / "bg.h5", True, records, frames=frames).finish({"wall_time": 1.0})
    w = _write(tmp_path / "def.h5", True, records, frames=frames, deferred=True)
    assert not partial_path(tmp_path / "def.h5").exists()  # nothing on disk before the end
    fut = w.finish_async({"wall_time": 1.0})
    assert fut.result(timeout=120) == tmp_path / "def.h5"
    a, b = _datasets(tmp_path / "bg.h5"), _datasets(tmp_path / "def.h5")
    assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
    with h5py.File(tmp_path / "def.h5") as f:
        assert f["parameters"].attrs["wall_time"] == 1.0
    assert not partial_path(tmp_path / "def.h5").exists()


def test_a_deferred_writer_writes_its_file_at_a_checkpoint_and_goes_on(tmp_path):
    w = _write(tmp_path / "c.h5", True, 30, frames=(2,), deferred=True)
    counts = w.frame_counts()  # a checkpoint needs the file: it is written now, in this process
    assert counts["observables/a"] == 30 and counts["particles/all/position"] == 1
    assert partial_path(tmp_path / "c.h5").exists()
    w.observables(30, 0.03, {"a": 30.0, "contacts": np.int64(0)})
    w.finish({"wall_time": 1.0})
    assert np.array_equal(_datasets(tmp_path / "c.h5")["observables/a/value"], np.arange(31, dtype=float))


def test_a_deferred_writer_refuses_a_non_finite_frame_at_once_and_a_failed_write_leaves_no_file(tmp_path):
    with pytest.raises(InstabilityError, match="position is not finite at step 10"):
        _write(tmp_path / "n2.h5", True, 20, frames=(3, 10), nan_frame=10, deferred=True)
    # the writer process fails (the target's folder is a file by then): the error comes back, no file stays
    target = tmp_path / "gone" / "r.h5"
    w = _write(target, True, 3, deferred=True)
    (tmp_path / "gone").rmdir()
    (tmp_path / "gone").write_text("not a folder")
    with pytest.raises(Exception):
        w.finish_async({"wall_time": 1.0}).result(timeout=120)
    assert not target.exists()


def test_a_non_finite_frame_on_the_io_thread_never_reaches_a_result(tmp_path):
    path = tmp_path / "bad.h5"
    w = _write(path, True, 20, frames=(3, 10), nan_frame=10)
    with pytest.raises(InstabilityError, match="position is not finite at step 10"):
        w.finish({"wall_time": 1.0})
    w.abort()
    assert not path.exists() and not partial_path(path).exists()


def _chunked_and_copied(tmp_path, frames) -> dict:
    """The files of 40 particles with ``frames`` written as they are ("chunk": C order, written as chunks where the
    dtype fits) and as Fortran-ordered copies ("copy": through HDF5's write)."""
    paths = {}
    for label, conv in (("chunk", lambda a: a), ("copy", np.asfortranarray)):
        w = H5MDWriter(tmp_path / f"{label}.h5", n=40, box_length=1.0, spec_json="{}", derived={},
                       radius=np.ones(40))
        for k, fr in enumerate(frames):
            w.snapshot(k, 0.1 * k, {name: conv(a) for name, a in fr.items()})
        paths[label] = w.finish({"wall_time": 1.0})
    return paths


def test_a_frame_written_as_its_chunk_is_the_same_file_as_through_hdf5s_copy(tmp_path):
    """A frame series (engine.output.h5md._FrameSeries.append) writes a C-ordered frame of the dataset's type as its
    chunk (H5Dwrite_chunk); any other array (here Fortran-ordered copies, float32 into a float64 file) goes through
    HDF5's write. Same bytes."""
    rng = np.random.default_rng(5)
    frames = [{"position": rng.random((40, 3)), "orientation": rng.random((40, 4)),
               "velocity": rng.random((40, 3)).astype(np.float32)} for _ in range(3)]
    paths = _chunked_and_copied(tmp_path, frames)
    assert paths["chunk"].read_bytes() == paths["copy"].read_bytes()
    d = _datasets(paths["chunk"])
    assert np.array_equal(d["particles/all/position/value"], np.stack([f["position"] for f in frames]))
    assert np.array_equal(d["particles/all/velocity/value"],
                          np.stack([f["velocity"] for f in frames]).astype(np.float64))


def test_a_frame_above_the_chunk_limit_is_written_in_chunks_of_whole_rows(tmp_path, monkeypatch):
    """A frame larger than h5md.CHUNK_MAX_BYTES is stored in chunks of whole particle rows (HDF5 before 2.0 refuses a
    chunk of 4 GiB or more), each written as it is, the last one padded: the same file as through HDF5's copy and the
    same values."""
    from engine.output import h5md

    monkeypatch.setattr(h5md, "CHUNK_MAX_BYTES", 7 * 3 * 8)     # 7 rows of float64 positions, 5 of orientations
    rng = np.random.default_rng(6)
    frames = [{"position": rng.random((40, 3)), "orientation": rng.random((40, 4))} for _ in range(2)]
    paths = _chunked_and_copied(tmp_path, frames)
    assert paths["chunk"].read_bytes() == paths["copy"].read_bytes()
    with h5py.File(paths["chunk"], "r") as f:
        assert f["particles/all/position/value"].chunks == (1, 7, 3)
        assert f["particles/all/orientation/value"].chunks == (1, 5, 4)
    d = _datasets(paths["chunk"])
    for name in ("position", "orientation"):
        assert np.array_equal(d[f"particles/all/{name}/value"], np.stack([f[name] for f in frames])), name


def test_pieces_cover_the_array_and_write_through_to_it():
    from engine.backends.cuda import _touched_empty
    from engine.output.pieces import map_pieces

    a = np.zeros((25, 4))
    sizes = map_pieces(a, lambda p: (p.__setitem__(slice(None), p.size), p.size)[1], piece=7)
    assert sum(sizes) == a.size and len(sizes) == 15 and set(a.reshape(-1)) == set(sizes)
    assert map_pieces(a, lambda p: p.size) == [a.size]              # one piece: on the caller's thread
    b = _touched_empty((3000, 4), np.float64)                       # every page written once (0 at its start)
    assert b.shape == (3000, 4) and b.dtype == np.float64 and np.all(b.reshape(-1)[::512] == 0)


def test_a_large_frame_is_checked_for_finite_values_in_pieces(monkeypatch):
    from engine.output import h5md

    monkeypatch.setattr(h5md, "_FINITE_SPLIT", 7)   # 10 x 3 values: five pieces, on engine/output/pieces.py's pool
    a = np.arange(30.0).reshape(10, 3)
    assert h5md._all_finite(a)
    for bad in (np.nan, np.inf, -np.inf):
        for where in ((0, 0), (4, 1), (9, 2)):
            b = a.copy()
            b[where] = bad
            assert not h5md._all_finite(b), (bad, where)
    with pytest.raises(InstabilityError, match="velocity is not finite at step 3"):
        h5md._check_finite("velocity", b, 3, 0.1)


def test_a_result_replaces_an_earlier_one_and_frees_it_off_the_callers_thread(tmp_path):
    import os
    import threading

    from engine.output.h5md import replace_file

    fds = lambda: len(os.listdir("/proc/self/fd"))  # noqa: E731
    base = fds()
    (tmp_path / "new").write_bytes(b"new")
    replace_file(tmp_path / "new", tmp_path / "r.h5")          # no earlier file
    (tmp_path / "newer").write_bytes(b"newer")
    replace_file(tmp_path / "newer", tmp_path / "r.h5")        # the earlier one is closed on a thread
    for t in threading.enumerate():
        if t.name == "demq-free-old":
            t.join()
    assert (tmp_path / "r.h5").read_bytes() == b"newer" and not (tmp_path / "newer").exists()
    assert fds() == base


def test_frame_slots_reuse_a_free_slot_and_else_wait_for_the_older_one():
    from concurrent.futures import Future

    from engine.driver.simulate import _FrameSlots

    slots = _FrameSlots()
    assert slots.take() == 0
    slots.busy[0] = done = Future()
    done.set_result(None)
    assert slots.take() == 0                 # its frame is written: the same buffers again
    slots.busy[0] = pending0 = Future()
    assert slots.take() == 1                 # slot 0 still being written
    slots.busy[1] = pending1 = Future()
    pending0.set_result(None)
    assert slots.take() == 0
    slots.busy[0] = Future()
    pending1.set_result(None)                # both busy would wait for the less recently used one: slot 1
    assert slots.take() == 1


# ---- the auto list mode's probe rule ---------------------------------------------------------------------

def _lists(steps_left, per_step=1e-3, steps_per_stage=20):
    from engine.loops.cuda_listmodes import HostLists

    fake = types.SimpleNamespace(
        stages=[{"mode": "gpu", "steps": steps_per_stage}] * 5, decisions=[],
        ens=types.SimpleNamespace(steps_left=lambda: steps_left, steps_done=100),
        _means=lambda mode: {"per_step": per_step, "wall": per_step * steps_per_stage})
    return HostLists._worth_probing(fake), fake.decisions


def test_auto_probes_only_when_the_rest_of_the_run_can_repay_it():
    from engine.loops.cuda_listmodes import MIN_STAGES_LEFT, MIN_WALL_LEFT_S

    per_step, stage = 1e-3, 20
    enough = int(max(MIN_STAGES_LEFT * stage, MIN_WALL_LEFT_S / per_step)) + 1
    assert _lists(enough, per_step, stage)[0]
    ok, decisions = _lists(enough // 4, per_step, stage)  # too short: no probe, and the decision says why
    assert not ok and "skipped probe" in str(decisions)
    assert not _lists(MIN_STAGES_LEFT * stage * 10, per_step=1e-6, steps_per_stage=stage)[0]  # stages, not seconds
    assert not _lists(None)[0]  # unknown length: never probe


# ---- the GPU output path under the CUDA simulator (a child process: the simulator must be on before numba.cuda
# is imported) -------------------------------------------------------------------------------------------------

_SIM_HEAD = r"""
from tests.cudasim import fast_block_polling
fast_block_polling()
import sys, h5py, numpy as np
from engine.driver.simulate import run
from engine.driver.ensemble import run_ensemble
out = sys.argv[1]
spec = dict(n_particles=27, volume_fraction=0.05, box_length=0.6, t_end=4e-4, output_interval=4e-5,
            snapshots=4, thermalization=0, seed=3)
"""

# the CPU reference runs (seed 3; seed 4 with 3 snapshots; seeds 4, 5) and the CUDA runs are two children that
# run side by side
_SIM_CPU = _SIM_HEAD + r"""
run({**spec, "backend": "cpu"}, f"{out}/cpu.h5")
run({**spec, "snapshots": 7, "backend": "cpu"}, f"{out}/cpu7.h5")
run({**spec, "seed": 4, "snapshots": 3, "backend": "cpu"}, f"{out}/cpu1.h5")
for s in (4, 5):
    run({**spec, "seed": s, "backend": "cpu"}, f"{out}/cpu{s}.h5")
"""

_SIM_CUDA = _SIM_HEAD + r"""
run({**spec, "backend": "cuda"}, f"{out}/gpu.h5")                 # one scene: its own CudaEnsemble
# frames of a large scene: plain host buffers for the first frames, then buffers a thread pinned meanwhile
import engine.backends.cuda as cb
import engine.loops.cuda_frames as cf
cf.PINNED_SLOT_BYTES, _slot, _pinned_used = 0, cb.CudaEnsemble._host_slot, []
def _spy(self, slot, nmax):
    ready = dict(getattr(self, "_pinned_slots", None) or {})
    bufs = _slot(self, slot, nmax)
    _pinned_used.append(any(bufs is b for b in ready.values()))
    return bufs
cb.CudaEnsemble._host_slot = _spy
run({**spec, "snapshots": 7, "backend": "cuda"}, f"{out}/p7.h5")
print("PINNED-FRAMES", _pinned_used)
cf.PINNED_SLOT_BYTES, cb.CudaEnsemble._host_slot = 32 << 20, _slot
run_ensemble([{**spec, "seed": 3}, {**spec, "seed": 4, "snapshots": 3}], [f"{out}/e0.h5", f"{out}/e1.h5"],
             backend="cuda")                                       # packed CudaEnsemble
import engine.driver.simulate
engine.driver.simulate.DEFER_MIN_SCENES = 2                               # files written by writer processes
run_ensemble([{**spec, "seed": 3}, {**spec, "seed": 4, "snapshots": 3}], [f"{out}/d0.h5", f"{out}/d1.h5"],
             backend="cuda")
# frames of several scenes at the same steps while the I/O thread lags: the ensemble's shared buffer slots
import time
from engine.output.h5md import H5MDWriter
_write_frame = H5MDWriter._write_frame
H5MDWriter._write_frame = lambda self, *a: (time.sleep(0.2), _write_frame(self, *a))[1]
engine.driver.simulate.DEFER_MIN_SCENES = 100
run_ensemble([{**spec, "seed": s} for s in (3, 4, 5)], [f"{out}/s{s}.h5" for s in (3, 4, 5)], backend="cuda")
"""


def test_snapshot_frames_through_reused_buffers_match_the_cpu_run(tmp_path):
    """Frames taken through the two reused buffer slots (one scene and a packed ensemble) are the
    CPU run's frames: the simulated CUDA backend is bit-identical to the CPU one (orientations: to rounding), so
    any frame written from a buffer that was overwritten too early would differ."""
    from tests.cudasim import run_children

    res = run_children({"cpu": ["-c", _SIM_CPU, tmp_path], "cuda": ["-c", _SIM_CUDA, tmp_path]}, timeout=900)
    for part, (rc, _, err) in res.items():
        assert rc == 0, (part, err[-3000:])
    # p7: a scene whose frames are "large" (PINNED_SLOT_BYTES = 0): the first ones through plain host buffers,
    # later ones through the buffers the thread pinned after the third
    used = ast.literal_eval(res["cuda"][1].split("PINNED-FRAMES", 1)[1].splitlines()[0].strip())
    assert len(used) == 7 and not any(used[:3]) and any(used[3:]), used
    for gpu, cpu in (("gpu", "cpu"), ("e0", "cpu"), ("e1", "cpu1"), ("d0", "cpu"), ("d1", "cpu1"), ("s3", "cpu"),
                     ("s4", "cpu4"), ("s5", "cpu5"), ("p7", "cpu7")):
        a, b = _datasets(tmp_path / f"{gpu}.h5"), _datasets(tmp_path / f"{cpu}.h5")
        for el in ("position", "velocity", "angular_velocity", "orientation"):
            key = f"particles/all/{el}/value"
            assert a[key].shape == b[key].shape and a[key].shape[0] in (3, 4, 7)
            if el == "orientation":
                # the CPU turns a sphere's quaternion lazily (closed form of the Fincham steps since its last
                # update), the CUDA loop step by step: equal to rounding; a stale or foreign frame is off by O(1)
                assert np.abs(a[key] - b[key]).max() < 1e-12, (gpu, el)
            else:
                assert np.array_equal(a[key], b[key]), (gpu, el)
        # the records are reduced on the device in another order: equal to rounding
        assert np.allclose(a["observables/kinetic_energy_translational/value"],
                           b["observables/kinetic_energy_translational/value"], rtol=1e-12, atol=0)
    for deferred, ordinary in (("d0", "e0"), ("d1", "e1")):  # a deferred file holds the same data
        a, b = _datasets(tmp_path / f"{deferred}.h5"), _datasets(tmp_path / f"{ordinary}.h5")
        assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a), deferred


# ---- the CUDA kernels' disk-cache key ----------------------------------------------------------------------

def _factory(flag):
    from numba import cuda

    @cuda.jit(device=True)
    def helper(x):
        return x * 2.0 if flag else x

    @cuda.jit
    def kern(a):
        i = cuda.grid(1)
        if i < a.shape[0]:
            a[i] = helper(a[i])

    return {"kern": kern, "helper": helper}


def test_factory_kernels_get_a_cache_key_that_is_stable_across_rebuilds():
    """A new process rebuilds the closures; numba-cuda's own key pickles the closure's dispatchers, which is not
    stable, so engine.loops.cuda_cache keys by (engine sources, specialisation, name): equal for a rebuild
    of the same specialisation, different for another one. No GPU needed (nothing is compiled)."""
    from engine.loops import cuda_cache

    if cuda_cache.SIM:
        pytest.skip("the CUDA simulator caches nothing")
    from numba.cuda.dispatcher import CUDACache

    codegen = types.SimpleNamespace(magic_tuple=lambda: ("sm_90", "x86_64"))
    keys = []
    for flag in (True, True, False):
        ks = cuda_cache.cache_kernels(_factory(flag), ("test", flag))
        assert isinstance(ks["kern"]._cache, CUDACache)
        assert not isinstance(ks["helper"]._cache, CUDACache)  # device functions compile into the kernels
        keys.append(ks["kern"]._cache._index_key(("float64[:]",), codegen))
    assert keys[0] == keys[1] and keys[0] != keys[2]


def test_cuda_kernel_cache_loads_without_refreshing_the_target():
    """numba-cuda refreshes every CUDA registry before a disk-cache load (about 0.3 s once per process); the
    stable-key cache loads without it. No GPU needed: the load itself is replaced."""
    from engine.loops import cuda_cache

    if cuda_cache.SIM:
        pytest.skip("the CUDA simulator caches nothing")
    cache = cuda_cache.cache_kernels(_factory(True), ("test-load", True))["kern"]._cache

    class NoRefresh:
        def refresh(self):
            raise AssertionError("the target context was refreshed")

    cache._load_overload = lambda sig, ctx: ("loaded", sig)
    assert cache.load_overload("sig", NoRefresh()) == ("loaded", "sig")


# ---- the CPU kernels' disk-cache loads ---------------------------------------------------------------------

_ENGINE_JIT_MODULES = ("engine.setup.scene", "engine.setup.cell_rsa", "engine.setup.counter_rng",
                       "engine.neighbours.multigrid", "engine.loops.cpu", "engine.loops.cpu_shared",
                       "engine.shapes.sphere.kernels", "engine.shapes.spheroid.kernels",
                       "engine.shapes.spheroid.cpu_backend", "engine.validation.encounter_dsmc",
                       "engine.validation.sonine")


def test_every_cached_engine_kernel_loads_without_the_target_refresh():
    """Every ``cache=True`` njit function of the engine gets engine.numba_support.jitcache's fast-load cache; a module
    that defines one without calling fast_loads(globals()) fails here."""
    import importlib
    import pkgutil

    import engine
    from engine.numba_support.numba_internals import FastLoadCache
    from numba.core.caching import FunctionCache

    found = set()
    for info in pkgutil.walk_packages(engine.__path__, "engine."):
        if info.name.startswith("engine.validation.") and info.name not in _ENGINE_JIT_MODULES:
            continue   # scripts with heavy imports; the jit ones are listed
        mod = importlib.import_module(info.name)
        for name, obj in vars(mod).items():
            cache = getattr(obj, "_cache", None)
            if isinstance(cache, FunctionCache) and getattr(obj, "__module__", None) == info.name:
                assert isinstance(cache, FastLoadCache), f"{info.name}.{name}: call fast_loads(globals())"
                found.add(info.name)
    assert found == set(_ENGINE_JIT_MODULES)


def test_the_source_digest_is_the_sources_at_import_and_is_not_taken_again(monkeypatch):
    """Kernel cache keys name the code this process imported (a hash taken after an edit on disk would file old
    machine code under the new sources), and a kernel set's key costs no re-hash."""
    import engine.numba_support.jitcache as jc

    assert jc.source_digest() == jc._hash_sources()     # the sources have not changed since the import
    monkeypatch.setattr(jc, "_hash_sources", lambda: pytest.fail("the sources were hashed again"))
    assert jc.source_digest() == jc._DIGEST


_FRESH_JOB = """
import sys
from engine.driver.simulate import run
from engine.setup.spec import SimulationSpec
run(SimulationSpec(**{spec!r}), sys.argv[1])
print(sorted(m for m in ("numba.np.arraymath", "scipy.linalg") if m in sys.modules))
"""


def test_a_fresh_process_loads_the_cpu_kernels_without_numbas_registries_and_writes_the_same_file(tmp_path):
    """A fresh process whose kernels are on disk runs a CPU job without installing numba's lowering registries
    (nor scipy.linalg, numba's BLAS check): the refresh before every cache load is skipped. Its file equals this
    process's, dataset for dataset (same spec, CPU: bit for bit)."""
    import subprocess
    import sys

    from engine.driver.simulate import run

    d = dict(n_particles=256, t_end=0.002, thermalization=0, snapshots=2, backend="cpu", seed=3)
    run(SimulationSpec(**d), tmp_path / "here.h5")       # compiles or loads, and leaves the kernels on disk
    p = subprocess.run([sys.executable, "-c", _FRESH_JOB.format(spec=d), str(tmp_path / "fresh.h5")],
                       capture_output=True, text=True, timeout=600, cwd=str(tmp_path),
                       env={**__import__("os").environ, "PYTHONPATH": str(__import__("pathlib").Path(__file__)
                                                                             .resolve().parents[2])})
    assert p.returncode == 0, p.stderr[-3000:]
    assert p.stdout.strip().splitlines()[-1] == "[]", p.stdout
    with h5py.File(tmp_path / "here.h5") as a, h5py.File(tmp_path / "fresh.h5") as b:
        names = []
        a.visit(lambda n: names.append(n) if isinstance(a[n], h5py.Dataset) else None)
        compared = 0
        for n in names:
            x = a[n][()]
            if isinstance(x, np.ndarray) and x.dtype.kind in "fiu":
                assert np.array_equal(x, b[n][()], equal_nan=True), n
                compared += 1
        assert compared > 10


@pytest.mark.parametrize("deferred", [False, True])
def test_records_kept_in_memory_add_nothing_for_the_garbage_collector_to_scan(tmp_path, deferred):
    """A record held until its block is written (a deferred writer: until the end of the run) is a step, a time and
    a dict of numbers, none of them tracked by the cyclic garbage collector: 256 packed scenes' records added no
    work to its collections (a full one paused a packed GPU run's time loop for 0.1 s when each record was a
    tuple). The records still reach the file in order."""
    w = H5MDWriter(tmp_path / "r.h5", n=4, box_length=1.0, spec_json="{}", derived={}, radius=np.ones(4),
                   deferred=deferred)
    tracked = len(gc.get_objects())
    for k in range(300):
        w.observables(k, 0.5 * k, {"kinetic_energy_translational": 1.0 + k, "contacts": np.int64(k)})
    assert len(gc.get_objects()) - tracked < 10
    path = w.finish({"wall_time": 1.0})
    with h5py.File(path, "r") as f:
        g = f["observables/contacts"]
        assert np.array_equal(g["step"][:], np.arange(300)) and np.array_equal(g["value"][:], np.arange(300))
        assert np.array_equal(f["observables/kinetic_energy_translational/time"][:], 0.5 * np.arange(300))
