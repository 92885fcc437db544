"""The GPU start-up thread (engine/driver/startup.py) and the reordered set-up it overlaps with.

The time it saves is measured by bench/e2e.py on a GPU (``--off startup`` against the default); that a run with it
writes the same file as one without is tests/gpu/test_startup_gpu.py. Here: when it starts, that its stand-in scenes
are valid starts of their shape, that its kernel warm-up runs through the CUDA simulator for every shape, and
that the start of a spec does not depend on the Verlet skin (the driver places before it resolves the
backend and the skin).
"""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

import engine.driver.startup as startup
import engine.setup.start_kind as start_kind
from engine.driver.simulate import run_contacts
from engine.setup.params import derive
from engine.setup.spec import SimulationSpec
from engine.shapes import host
from tests.cudasim import ROOT, child_env


def _contacts(spec, p):
    return run_contacts(spec, p)


@pytest.mark.parametrize("shape", ["sphere", "ellipsoid"])
def test_standin_is_a_resting_lattice_without_contacts(shape):
    kw = {"elongation": 2.0} if shape == "ellipsoid" else {}
    spec = SimulationSpec(shape=shape, n_particles=4096, volume_fraction=0.3, verlet_skin=4.0, **kw)
    p = derive(spec)
    sy = host(shape).standin_system(p, startup.STANDIN_EDGE)
    n = startup.STANDIN_EDGE ** 3
    assert sy.n == n and type(sy) is host(shape).SYSTEM
    a = p.radius if shape == "sphere" else p.semi_axes[0]      # bounding radius
    x = sy.position
    assert np.all((x > 0) & (x < sy.box_length))
    d = np.abs(x[:, None, :] - x[None, :, :])
    d = np.minimum(d, sy.box_length - d)
    r = np.sqrt((d ** 2).sum(-1)) + np.eye(n) * 1e9
    assert r.min() >= 2.5 * a * (1 - 1e-12)        # bounding spheres 0.5 a apart: no contact
    assert sy.box_length >= 3.0 * p.cutoff          # the largest skin a spec allows still fits 3 cells
    assert not sy.velocity.any() and not sy.angular_velocity.any()
    assert np.allclose(np.linalg.norm(sy.orientation, axis=1), 1.0)


def test_when_the_startup_thread_starts(monkeypatch):
    spec = SimulationSpec()
    p = derive(spec)
    c = _contacts(spec, p)
    monkeypatch.setattr(startup, "nvidia_driver", lambda: True)
    monkeypatch.setattr(startup, "_started", {})
    monkeypatch.delenv("NUMBA_ENABLE_CUDASIM", raising=False)
    assert startup.begin(spec, "cpu", c, p) is None
    monkeypatch.setattr(startup, "ENABLED", False)
    assert startup.begin(spec, "auto", c, p) is None
    monkeypatch.setattr(startup, "ENABLED", True)
    monkeypatch.setenv("NUMBA_ENABLE_CUDASIM", "1")
    assert startup.begin(spec, "cuda", c, p) is None
    monkeypatch.delenv("NUMBA_ENABLE_CUDASIM")
    monkeypatch.setattr(startup, "nvidia_driver", lambda: False)
    assert startup.begin(spec, "auto", c, p) is None


def test_one_startup_per_specialisation(monkeypatch):
    """A second job of the same specialisation gets the first one's start-up; another precision its own.
    (No real thread runs: GpuStartup is replaced by a recorder.)"""
    made = []

    class Recorder:
        def __init__(self, shape, system, contacts, driver=None, start_dtypes=None):
            made.append((shape, system.n if system is not None else None, contacts, start_dtypes))

        def wait(self):
            pass

    monkeypatch.setattr(startup, "nvidia_driver", lambda: True)
    monkeypatch.setattr(startup, "_started", {})
    monkeypatch.setattr(startup, "GpuStartup", Recorder)
    monkeypatch.setattr(startup.DriverStart, "begin", classmethod(lambda cls: None))
    monkeypatch.delenv("NUMBA_ENABLE_CUDASIM", raising=False)
    a, b = SimulationSpec(seed=1), SimulationSpec(seed=2)
    pa, pb = derive(a), derive(b)
    s1 = startup.begin(a, "auto", _contacts(a, pa), pa)
    s2 = startup.begin(b, "cuda", _contacts(b, pb), pb)
    assert s1 is s2 and len(made) == 1
    assert made[0][1] == startup.STANDIN_EDGE ** 3
    f32 = SimulationSpec(precision="float32")
    p32 = derive(f32)
    assert startup.begin(f32, "auto", _contacts(f32, p32), p32) is not s1 and len(made) == 2
    species = SimulationSpec(species=[{"radius_ratio": 1.0, "number_fraction": 0.5},
                                      {"radius_ratio": 0.5, "number_fraction": 0.5}])
    ps = derive(species)
    startup.begin(species, "auto", _contacts(species, ps), ps)
    assert made[-1][1] is None      # a mixture: the driver and the context only, no stand-in scene
    assert all(m[3] is None for m in made)      # no start drawn on the device: no such kernels to load
    # a large one-size sphere start is drawn on the device: its own start-up, which loads the kernels of its own
    # placement too (another placement: another start-up)
    big = SimulationSpec(n_particles=1 << 20, precision="mixed")
    pg = derive(big)
    s_big = startup.begin(big, "auto", _contacts(big, pg), pg)
    assert s_big is not s1 and made[-1][3] == (np.float64, np.float32, "random")
    lattice = big.model_copy(update={"start": "lattice"})
    s_lattice = startup.begin(lattice, "auto", _contacts(lattice, pg), pg)
    assert s_lattice is not s_big and made[-1][3] == (np.float64, np.float32, "lattice")
    monkeypatch.setattr(start_kind, "DEVICE_START", False)
    s_off = startup.begin(big, "auto", _contacts(big, pg), pg)
    assert s_off is not s_big and len(made) == 6 and made[-1][3] is None     # drawn on the host: no such load


class _FakeDriver:
    """The four driver calls DriverStart makes, recorded; ``fail`` names one that returns an error."""

    def __init__(self, fail=None):
        self.calls, self.fail = [], fail

    def __getattr__(self, name):
        if not name.startswith("cu"):
            raise AttributeError(name)

        def call(*args):
            self.calls.append(name)
            return 1 if name == self.fail else 0
        return call


@pytest.mark.parametrize("fail", [None, "cuInit", "cuDevicePrimaryCtxRetain"])
def test_the_driver_start_holds_the_context_until_released_once(monkeypatch, fail):
    fake = _FakeDriver(fail)
    monkeypatch.setattr(startup.ctypes, "CDLL", lambda name: fake)
    d = startup.DriverStart()
    d.release()                  # waits for the thread
    d.release()                  # a second release does nothing
    if fail is None:
        assert fake.calls == ["cuInit", "cuDeviceGet", "cuDevicePrimaryCtxRetain", "cuDevicePrimaryCtxRelease_v2"]
    else:
        assert "cuDevicePrimaryCtxRelease_v2" not in fake.calls and fake.calls[-1] == fail


def test_the_imports_are_frozen_once_per_process(monkeypatch):
    calls = []
    monkeypatch.setattr(startup.gc, "collect", lambda: calls.append("collect"))
    monkeypatch.setattr(startup.gc, "freeze", lambda: calls.append("freeze"))
    monkeypatch.setattr(startup, "_frozen", False)
    monkeypatch.setattr(startup, "FREEZE_IMPORTS", False)
    startup._freeze_imports()
    assert calls == []                              # switched off (bench/e2e.py --off gc_freeze)
    monkeypatch.setattr(startup, "FREEZE_IMPORTS", True)
    startup._freeze_imports()
    startup._freeze_imports()
    assert calls == ["collect", "freeze"]           # the garbage first, then the rest frozen, once


def test_the_driver_start_without_a_driver_library_does_nothing(monkeypatch):
    def missing(name):
        raise OSError(f"{name}: cannot open shared object file")

    monkeypatch.setattr(startup.ctypes, "CDLL", missing)
    d = startup.DriverStart()
    d.release()
    assert not d._held
    monkeypatch.setattr(startup.DriverStart, "_once", False)
    assert startup.DriverStart.begin() is not None and startup.DriverStart.begin() is None   # once per process


_SIM_CHILD = """
import sys
from tests.cudasim import fast_block_polling
fast_block_polling()
import engine.backends.base as base
import engine.driver.startup as startup
from engine.setup.params import derive
from engine.driver.simulate import run_contacts
from engine.shapes import host
from engine.setup.spec import SimulationSpec
base.cuda_available = lambda: True          # the simulator stands in for the GPU
shape = sys.argv[1]
kw = {"elongation": 2.0} if shape == "ellipsoid" else {}
spec = SimulationSpec(shape=shape, n_particles=512, volume_fraction=0.1, e_t=0.5, snapshots=2, **kw)
p = derive(spec)
contacts = run_contacts(spec, p)
import engine.loops.cuda_loop as loop
host(shape).cuda_ensemble().prepare_kernels(contacts)
prepared = dict(loop._cache)
s = startup.GpuStartup(shape, host(shape).standin_system(p, 3), contacts)
s.wait()
print("PREPARED", len(prepared), "ERROR", s.error, "KERNEL SETS", len(loop._cache))
"""


@pytest.mark.parametrize("shape", ["sphere", "ellipsoid"])
def test_kernel_warmup_runs_for_every_shape_in_the_simulator(shape):
    """The thread's work (stand-in backend, warm-up per contact, observe) runs without error on each shape."""
    p = subprocess.run([sys.executable, "-c", _SIM_CHILD, shape], env=child_env(), cwd=ROOT, capture_output=True,
                       text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    # it built the loop's kernels: for spheres the set made ahead without a context (prepare_kernels), no other
    prepared = 1 if shape == "sphere" else 0
    assert f"PREPARED {prepared} ERROR None KERNEL SETS 1" in p.stdout, p.stdout + p.stderr[-3000:]


@pytest.mark.parametrize("kw", [{}, {"shape": "ellipsoid", "elongation": 2.5},
                                {"species": [{"radius_ratio": 1.0, "number_fraction": 0.3},
                                             {"radius_ratio": 0.4, "number_fraction": 0.7}]}])
def test_the_start_does_not_depend_on_the_skin(kw):
    """SceneRun places the particles with the unresolved skin and resolves the backend afterwards."""
    spec = SimulationSpec(n_particles=500, volume_fraction=0.1, seed=7, **kw)
    shape = host(spec.shape)
    a = shape.initial_system(spec, derive(spec.model_copy(update={"verlet_skin": 0.2})))
    b = shape.initial_system(spec, derive(spec.model_copy(update={"verlet_skin": 3.0})))
    for f in ("position", "velocity", "angular_velocity", "orientation", "mass", "inertia"):
        assert np.array_equal(getattr(a, f), getattr(b, f)), f


def test_an_unknown_backend_is_refused_before_the_placement(tmp_path, monkeypatch):
    """The set-up now places before it resolves the backend; a misspelt backend still costs nothing."""
    from engine.errors import BackendUnavailable
    from engine.driver.simulate import run

    placed = []
    monkeypatch.setattr(host("sphere"), "initial_system", lambda *a: placed.append(a))
    with pytest.raises(BackendUnavailable, match="unknown backend 'gpu'"):
        run(SimulationSpec(), tmp_path / "out.h5", backend="gpu")
    assert placed == [] and list(tmp_path.iterdir()) == []


def test_an_early_driver_start_is_released_when_no_startup_took_it(monkeypatch):
    released = []

    class Early:
        def release(self):
            released.append(1)

    monkeypatch.setattr(startup, "_early", Early())
    startup.release_early()
    startup.release_early()
    assert released == [1] and startup._early is None


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the driver's files are Linux's")
def test_without_an_nvidia_driver_the_gpu_probe_does_not_import_numba_cuda(monkeypatch):
    """A CPU machine's jobs ('auto' backend) do not pay numba-cuda's import (0.2 s) to learn there is no GPU."""
    import engine.backends.base as base

    monkeypatch.setattr(base, "NVIDIA_DRIVER_PATHS", ("/nonexistent/nvidiactl",))
    assert base.no_nvidia_driver()
    monkeypatch.setattr(base, "NVIDIA_DRIVER_PATHS", ("/proc/self",))   # a path that exists: a driver is loaded
    assert not base.no_nvidia_driver()
    monkeypatch.undo()
    if not base.no_nvidia_driver():
        pytest.skip("this machine has an NVIDIA driver")
    code = ("import sys; from engine.backends.base import cuda_available; "
            "print(cuda_available(), 'numba.cuda' in sys.modules)")
    env = {k: v for k, v in child_env().items() if k != "NUMBA_ENABLE_CUDASIM"}
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "False"]


@pytest.mark.parametrize("jit_coverage", ["", "1"])
def test_numba_is_imported_without_coverage_unless_it_measures_coverage(tmp_path, jit_coverage):
    """engine.numba_support.numba_import.coverage_hidden: numba's first import does not import ``coverage`` (70 ms of a
    GPU job's start-up) unless NUMBA_JIT_COVERAGE=1, and ``coverage`` stays importable afterwards. A stand-in
    ``coverage`` package on the path records its import."""
    fake = tmp_path / "coverage"
    fake.mkdir()
    (fake / "__init__.py").write_text("from . import types\n")
    (fake / "types.py").write_text("def __getattr__(name):\n    return object\n")
    code = ("import sys, engine.setup.scene; during = 'coverage' in sys.modules; import coverage; "
            "print('RESULT', during, 'coverage' in sys.modules)")
    path = [str(tmp_path), str(ROOT)] + [x for x in [os.environ.get("PYTHONPATH")] if x]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(path), "NUMBA_JIT_COVERAGE": jit_coverage}
    p = subprocess.run([sys.executable, "-c", code], env=env, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
    line = [x for x in p.stdout.splitlines() if x.startswith("RESULT")][-1]
    assert line == f"RESULT {jit_coverage == '1'} True", line
