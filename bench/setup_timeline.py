"""A fresh job's timeline by thread: where the time outside the loop goes (time to result).

    python -m bench setup_timeline [--case spheres-2M-f64] [--runs 3] [--all]

Each run is one bench.e2e case (``run_case``, the public ``engine.run`` path) in a fresh Python process, after one
untimed run that fills the kernel caches. Wrappers around the engine's set-up, build, frame and file functions,
numba's CPU and CUDA disk-cache loads, and every outermost import that takes more than 10 ms record (start, end,
thread); the timeline prints them in ms from the start of the job's call (imports before it are negative).
Events shorter than 2 ms are left out unless ``--all``. A diagnostic: the wrappers cost a little, and the
end-to-end figures are bench.e2e's. Numba's internals it wraps are optional (left out when not found).
"""

from __future__ import annotations

import argparse
import builtins
import json
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
EVENTS: list = []
_patched: set = set()
_depth = threading.local()


def _wrap(owner, attr: str, label: str, first: int = 0) -> None:
    """Record the calls of owner.attr (only the first ``first`` ones when ``first``)."""
    f = getattr(owner, attr, None)
    if f is None:
        return
    seen = [0]

    def wrapped(*a, **k):
        if first and seen[0] >= first:
            return f(*a, **k)
        seen[0] += 1
        t = time.perf_counter()
        try:
            return f(*a, **k)
        finally:
            EVENTS.append((t, time.perf_counter(), threading.current_thread().name, label))

    setattr(owner, attr, wrapped)


def _patch_loaded() -> None:
    """Wrap what has been imported by now (each group once, when its module is complete)."""
    mods = sys.modules
    groups = {
        "numba-cuda": ("numba.cuda.dispatcher", "CUDACache",
                       lambda m: _wrap(m.CUDACache, "_load_overload", "CUDA kernel cache load")),
        "jitcache": ("engine.numba_support.numba_internals", "FastLoadCache",
                     lambda m: _wrap(m.FastLoadCache, "load_overload", "CPU cache load")),
        "scene": ("engine.setup.scene", "_parallel_draws", lambda m: [
            _wrap(m, n, n) for n in ("initial_spheres", "initial_ellipsoids", "_draw_start", "_centre_and_square",
                                     "_scale_streams")]),
        "cuda": ("engine.backends.cuda", "CudaBackend", lambda m: [
            _wrap(m.CudaEnsemble, "__init__", "CudaEnsemble()"), _wrap(m.CudaEnsemble, "advance", "advance", 3),
            _wrap(m.CudaEnsemble, "warmup", "warmup"), _wrap(m, "_touched_empty", "_touched_empty")] + [
            _wrap(m.CudaEnsemble, n, n, 2) for n in ("_upload_particles", "_prime", "_scene_rows", "_host_slot")]),
        "cuda-start": ("engine.loops.cuda_start", "SPHERE_TARGETS", lambda m: [
            _wrap(m, "draw_start", "device start draw"), _wrap(m, "load", "device start load")]),
        "h5md": ("engine.output.h5md", "H5MDWriter", lambda m: [
            _wrap(m.H5MDWriter, n, "h5md." + n) for n in ("_create", "_write_frame", "_write_block", "finish",
                                                          "_wait")] + [
            _wrap(m, n, "h5md." + n) for n in ("xdmf_text", "replace_file", "write_xdmf")]),
    }
    for name, (module, marker, patch) in groups.items():
        m = mods.get(module)
        if name not in _patched and m is not None and hasattr(m, marker):
            _patched.add(name)
            patch(m)


def _import(name, globals=None, locals=None, fromlist=(), level=0, _real=builtins.__import__):
    d = getattr(_depth, "d", 0)
    _depth.d = d + 1
    t = time.perf_counter()
    try:
        return _real(name, globals, locals, fromlist, level)
    finally:
        _depth.d = d
        if d == 0:
            b = time.perf_counter()
            if b - t > 0.010:
                EVENTS.append((t, b, threading.current_thread().name, "import " + "." * level + name))
            _patch_loaded()


def child(case: str, show_all: bool) -> None:
    sys.path.insert(0, str(ROOT))
    builtins.__import__ = _import
    import engine.driver.simulate as sim
    import engine.driver.startup as st

    _wrap(st.GpuStartup, "_work", "GPU start-up thread")
    _wrap(st.DriverStart, "_work", "driver start-up thread")
    _wrap(sim, "_build", "build")
    _wrap(sim.SceneRun, "__init__", "scene set-up")
    _wrap(sim.SceneRun, "open", "scene open")
    _wrap(sim.SceneRun, "finish_begin", "scene finish")
    from bench.e2e import run_case

    t0 = time.perf_counter()
    row = run_case(case, False, Path(tempfile.mkdtemp()))
    print(json.dumps({k: row.get(k) for k in ("case", "wall_s", "loop_s", "timings")}))
    print(f"{'start':>8} {'end':>8} {'ms':>7}  {'thread':18s} event")
    for a, b, thread, name in sorted(EVENTS):
        if show_all or b - a >= 0.002:
            print(f"{1e3 * (a - t0):8.1f} {1e3 * (b - t0):8.1f} {1e3 * (b - a):7.1f}  {thread[:18]:18s} {name}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", default="spheres-2M-f64", help="a bench.e2e case run through engine.run or run_ensemble")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--all", action="store_true", help="events shorter than 2 ms too")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args.case, args.all)
        return
    cmd = [sys.executable, "-m", "bench.setup_timeline", "--child", "--case", args.case] + (["--all"] * args.all)
    subprocess.run(cmd, cwd=ROOT, capture_output=True, check=True)     # fills the kernel caches
    for r in range(args.runs):
        out = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, check=True).stdout
        print(f"== run {r + 1}\n{out}")


if __name__ == "__main__":
    main()
