"""Time to result: whole jobs, from spec to closed HDF5 file, through the public path.

``python -m bench e2e`` (or ``python -m bench e2e``) times each case in a fresh Python process (so kernel
compilation or its disk-cache load is part of the figure, as for a user who starts a job) and prints:

* the end-to-end Cundall number: N x steps / wall seconds of the whole call (``engine.run``,
  ``engine.driver.ensemble.run_ensemble``, or, for the worker, from the HTTP submission of the batch until the
  last result is downloadable);
* the loop Cundall number: N x steps / wall seconds of the time loop (thermalisation and cooling steps,
  rebuilds, no output) — a diagnostic, printed beside the end-to-end figure;
* where the rest went (RunSummary.extra["timings"], engine/driver/simulate.py TIMINGS): setup (spec, placement,
  velocities), build (device upload, first list), compile (or cache load), loop, records, snapshots,
  checkpoints, open and close of the file, and "other" (imports excluded: the clock starts at the call);
* the process's seconds (``process_s``): the fresh process from its start to its exit, the interpreter, every
  import and the exit included (what a user's ``python -c`` of the job takes; with ``--off``, whose switches import
  their modules before the call's clock starts, the fair figure to compare).

``--off NAME ...`` turns latency machinery of the GPU path off in the process that runs each case, before the case
starts, for side-by-side A/B timings (see SWITCHES): ``startup`` (the start-up thread, engine/driver/startup.py),
``gc_freeze`` (the garbage collector's freeze after the GPU path's imports, engine/driver/startup.py),
``device_start`` (large starts drawn on the GPU, engine/setup/start_kind.py), ``kernel_cache`` (the kernels' disk
cache, engine/loops/cuda_cache.py), ``multigrid`` (the multigrid list build), ``multistep`` (the many-steps-per-launch
loop: the per-phase loop at every size), ``launch_cache`` (engine/loops/cuda_launch.py), ``displacement_bound`` (every
kick-drift measures displacements against x_ref, engine/loops/cuda_stepping.py), ``fused`` (two launches a step
instead of the fused force-and-kick-drift kernel, engine/loops/cuda_stepping.py), ``multistep_fused`` (two passes
and two grid syncs a step in the many-steps kernel instead of one, engine/loops/cuda_stepping.py),
``observe_in_forces`` (a lone smooth-sphere scene's records by the closing half kick and the observe kernel instead of
the last force pass of each advance call, engine/loops/cuda_stepping.py), ``direct_launch`` (the launch cache hands its
argument lists to cuda.core's launch instead of calling the driver's cuLaunchKernel itself,
engine/loops/cuda_launch.py), ``sort_interval`` (every list rebuild permutes the particles into cell order,
engine/loops/cuda_rebuild.py ``SORT_DRIFT_CELLS``), ``build_kept`` (a list build's filling pass searches every row's
cells again instead of copying the rows its counting pass kept, engine/loops/cuda_rebuild.py ``BUILD_KEPT``). Not for
the worker cases, whose jobs run in processes of the service.

Cases (``--cases``; N x steps, phi = 0.058 unless said, default records = t_end/200, no thermalisation so
that the step count is exact):

  spheres-2M-f64 / -f32     2 097 152 spheres x 5000 steps, 2 snapshots       
  spheres-8M-f64 / -f32     8 388 608 spheres x 2000 steps, 2 snapshots       
  batch-256x4096-2k / -20k  256 scenes x 4096 spheres x 2000 / 20 000 steps, one run_ensemble (b)
  worker-256x4096-20k       the same batch submitted over HTTP to `demq serve` (embedded worker)  (b)
  worker-2M-f64             spheres-2M-f64 as one job submitted over HTTP to `demq serve`
                            (DEMQ_E2E_WORKER_IDLE_S: seconds the worker idles before the submit, default 0;
                            DEMQ_WORKER_STANDBY=off|on: its standby simulation process, jobs/worker.py)
  quickstart                the README quick-start default spec, through engine.run       (c)
  ellipsoids-2M             2 097 152 ellipsoids, xi = 2 x 2000 steps, 2 snapshots    (d)
  ellipsoids-rough-2M       the same with rough contacts (e_t = 0.8, the spec default)
  ellipsoids-rough-1M       1 048 576 rough ellipsoids, xi = 2 x 2000 steps, 2 snapshots
  cpu-16x512                CPU: 16 x 512 spheres x 3000 steps with default records through run_ensemble,
                            against one such scene with 4 records, in the same process (the issue's
                            must-show ratio)

``--trace`` prints, for each timed run of a case with one job, when each step of its set-up and build ran and on which
thread (the GPU start-up thread's driver start, kernel loads, stand-in and device-start loads beside the job's
own set-up, build, device draw and first list; the file's writes and close): where the time outside the loop goes.

``--public`` calls ``engine.run`` / ``engine.run_ensemble`` with nothing of engine.driver imported before the clock
starts: the call's wall time then includes the runner's import (numba, h5py, the kernels' modules), as a user's first
call in a fresh process does, and the CUDA driver's start (engine/driver/startup.py) runs beside that import.

``--quick`` shrinks every case (for the smoke test). ``--reps`` runs each case several times (median of the
end-to-end wall time). Writes ``--out``/e2e.json and e2e.md.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

BREAKDOWN = ("setup", "build", "compile", "loop", "records", "snapshots", "checkpoints", "open", "close")
GPU_CASES = ("spheres-2M-f64", "spheres-2M-f32", "spheres-2M-mixed", "spheres-8M-f64", "spheres-8M-f32",
             "spheres-8M-mixed", "batch-256x4096-2k",
             "batch-256x4096-20k", "worker-256x4096-20k", "worker-2M-f64", "ellipsoids-2M", "ellipsoids-rough-2M",
             "ellipsoids-rough-1M")
CPU_CASES = ("quickstart", "cpu-16x512")


#: --off name -> (module, setting, value when off): module-level settings of the engine, on by default
SWITCHES = {
    "startup": ("engine.driver.startup", "ENABLED", False),
    "gc_freeze": ("engine.driver.startup", "FREEZE_IMPORTS", False),
    "device_start": ("engine.setup.start_kind", "DEVICE_START", False),
    "kernel_cache": ("engine.loops.cuda_cache", "ENABLED", False),
    "multigrid": ("engine.loops.cuda_rebuild", "MULTIGRID", False),
    "multistep": ("engine.loops.cuda_ensemble", "MULTISTEP", False),
    "launch_cache": ("engine.loops.cuda_launch", "ENABLED", False),
    "displacement_bound": ("engine.loops.cuda_stepping", "DISPLACEMENT_BOUND", False),
    "fused": ("engine.loops.cuda_stepping", "FUSED", False),
    "multistep_fused": ("engine.loops.cuda_stepping", "MULTISTEP_FUSED", False),
    "observe_in_forces": ("engine.loops.cuda_stepping", "OBSERVE_IN_FORCES", False),
    "skip_cold": ("engine.loops.cuda_loop", "SKIP_COLD", False),
    "keep_velocity": ("engine.loops.cuda_loop", "KEEP_VELOCITY", False),
    "direct_launch": ("engine.loops.cuda_launch", "DIRECT", False),
    "sort_interval": ("engine.loops.cuda_rebuild", "SORT_DRIFT_CELLS", 0.0),
    "build_kept": ("engine.loops.cuda_rebuild", "BUILD_KEPT", 0),
}


def switch_off(names) -> None:
    """Set the engine settings of ``names`` (keys of SWITCHES) to their off values in this process."""
    import importlib

    for name in names:
        if name not in SWITCHES:
            raise ValueError(f"--off: unknown switch {name!r}; known: {', '.join(SWITCHES)}")
        module, setting, value = SWITCHES[name]
        mod = importlib.import_module(module)
        if not hasattr(mod, setting):
            raise AttributeError(f"--off {name}: {module} has no setting {setting}")
        setattr(mod, setting, value)


def case_specs(case: str, quick: bool) -> dict:
    """{"specs": [spec dicts], "path": "run" | "ensemble" | "worker"} of a case."""
    n2m, n8m, k, nk = (2_097_152, 8_388_608, 256, 4096) if not quick else (4096, 8192, 4, 512)
    s5k, s2k, s20k = (5000, 2000, 20_000) if not quick else (50, 40, 80)

    def sph(n, steps, precision="float64", snapshots=2, seed=0, **kw):
        return dict(n_particles=n, volume_fraction=0.058, box_length=2.0 * (n / 4096) ** (1.0 / 3.0),
                    precision=precision, snapshots=snapshots, seed=seed, thermalization=0, _steps=steps, **kw)

    if case.startswith("spheres-"):
        n, steps = (n2m, s5k) if "-2M-" in case else (n8m, s2k)
        prec = {"f64": "float64", "f32": "float32", "mixed": "mixed"}[case.rsplit("-", 1)[1]]
        return {"path": "run", "specs": [sph(n, steps, prec)]}
    if case == "worker-2M-f64":   # spheres-2M-f64 as one job through the service
        return {"path": "worker", "specs": [sph(n2m, s5k)]}
    if case.startswith("batch-") or case.startswith("worker-"):
        steps = s20k if case.endswith("20k") else s2k
        return {"path": "worker" if case.startswith("worker") else "ensemble",
                "specs": [sph(nk, steps, snapshots=0, seed=i, backend="auto") for i in range(k)]}
    if case.startswith("ellipsoids-"):
        e_t = 0.8 if "rough" in case else -1.0
        n = n2m if case.endswith("2M") else n2m // 2
        return {"path": "run", "specs": [sph(n, s2k, shape="ellipsoid", elongation=2.0, e_t=e_t)]}
    if case == "quickstart":
        return {"path": "run",
                "specs": [{} if not quick else {"n_particles": 512, "t_end": 0.002, "thermalization": 0}]}
    if case == "cpu-16x512":
        steps = 3000 if not quick else 60
        return {"path": "cpu-ratio", "specs": [sph(512, steps, snapshots=0, seed=i, backend="cpu") for i in range(16)]}
    raise ValueError(f"unknown case {case!r}; cases: {', '.join(GPU_CASES + CPU_CASES)}")


def to_spec(d: dict):
    """A SimulationSpec from a case dict; ``_steps`` sets t_end to exactly that many time steps."""
    from engine.setup.params import derive
    from engine.setup.spec import SimulationSpec

    d = dict(d)
    steps = d.pop("_steps", None)
    spec = SimulationSpec(**d)
    if steps is not None:
        dt = derive(spec).dt
        spec = SimulationSpec(**{**d, "t_end": steps * dt, "dt": dt})
    return spec


def _row(label: str, n_total: int, steps: int, wall: float, loop: float, timings: dict, extra=None) -> dict:
    other = wall - sum(timings.get(k, 0.0) for k in BREAKDOWN)
    return {"case": label, "particles": n_total, "steps": steps, "wall_s": wall, "loop_s": loop,
            "e2e_cundall": n_total * steps / wall if wall > 0 else 0.0,
            "loop_cundall": n_total * steps / loop if loop > 0 else 0.0,
            "e2e_over_loop": loop / wall if wall > 0 else 0.0,
            "timings": {**{k: timings.get(k, 0.0) for k in BREAKDOWN}, "other": other}, **(extra or {})}


def _sum_timings(summaries) -> dict:
    """Ensemble breakdown: scene-own phases summed over the scenes, shared ones (build, compile) once, the
    loop as the longest scene's (the scenes advance together)."""
    from engine.driver.simulate import SHARED_TIMINGS

    out = dict.fromkeys(BREAKDOWN, 0.0)
    for s in summaries:
        for k, v in s.extra["timings"].items():
            if k in SHARED_TIMINGS or k == "loop":
                out[k] = max(out[k], v)
            else:
                out[k] += v
    # run_ensemble's set-up as a whole (its scenes are set up on several threads, whose own times overlap)
    setup = [s.extra["ensemble_setup_s"] for s in summaries if "ensemble_setup_s" in s.extra]
    if setup:
        out["setup"] = max(setup)
    return out


#: what ``--trace`` times: (module, class or None, attribute) of the set-up and build steps of one job
TRACED = (
    ("engine.driver.simulate", "SceneRun", "__init__"), ("engine.driver.simulate", None, "_build"),
    ("engine.driver.simulate", None, "_compile"), ("engine.driver.simulate", "SceneRun", "finish_begin"),
    ("engine.driver.startup", None, "begin"), ("engine.driver.startup", "GpuStartup", "wait"),
    ("engine.driver.startup", "GpuStartup", "_work"), ("engine.driver.startup", "DriverStart", "_work"),
    ("engine.backends.base", None, "cuda_available"), ("engine.backends.ensemble", None, "make_ensemble"),
    ("engine.loops.cuda_memory", None, "refuse_oversize"), ("engine.shapes.sphere.host", None, "initial_system"),
    ("engine.shapes.sphere.host", None, "load_device_start"),
    ("engine.loops.cuda_ensemble", "CudaEnsembleBase", "_init_host"),
    ("engine.shapes.sphere.cuda_backend", "CudaEnsemble", "_upload_particles"),
    ("engine.loops.cuda_rebuild", "ListBuilds", "_rebuild"), ("engine.loops.cuda_stepping", "TimeLoop", "warmup"),
    ("engine.output.h5md", "H5MDWriter", "_create"), ("engine.output.h5md", "H5MDWriter", "_write_frame"),
    ("engine.output.h5md", "H5MDWriter", "finish_async"),
)


def trace_steps(log: list, origin: list) -> None:
    """Wrap the :data:`TRACED` steps: each call appends (start, end in s after ``origin[0]``, thread name, step) to
    ``log``. Only a step's first 40 calls are kept (list rebuilds recur through the loop). The traced modules are
    imported here, before the call's clock starts (their imports then leave the call's set-up, as with ``--off``)."""
    import functools
    import importlib
    import threading

    for mod_name, cls_name, attr in TRACED:
        owner = importlib.import_module(mod_name)
        if cls_name is not None:
            owner = getattr(owner, cls_name)
        f = getattr(owner, attr)
        name = f"{cls_name or mod_name.rsplit('.', 1)[-1]}.{attr}"
        calls = [0]

        def timed(*a, __f=f, __name=name, __calls=calls, **k):
            t = time.perf_counter()
            try:
                return __f(*a, **k)
            finally:
                __calls[0] += 1
                if __calls[0] <= 40:
                    log.append((round(t - origin[0], 4), round(time.perf_counter() - origin[0], 4),
                                threading.current_thread().name, __name))
        setattr(owner, attr, functools.wraps(f)(timed))


def run_case(case: str, quick: bool, workdir: Path, off=(), start=None, trace: bool = False,
             public: bool = False) -> dict:
    """Time one case in this process (the caller gives it a fresh one), with the SWITCHES ``off`` turned off and,
    when ``start`` is given, every scene started that way (the spec's ``start``: "lattice" or "random"). ``public``:
    the call is ``engine.run`` / ``engine.run_ensemble`` with nothing of engine.driver imported before it (the
    call's clock then includes the runner's import, as a user's first call in a fresh process does)."""
    info = case_specs(case, quick)
    path, raw = info["path"], info["specs"]
    if start is not None:
        raw = [dict(d, start=start) for d in raw]
    if off and path == "worker":
        raise ValueError(f"--off does not reach the jobs of case {case} (they run in the service's processes)")
    if public and (off or trace or path not in ("run", "ensemble")):
        raise ValueError(f"--public: case {case} with --off or --trace, or a case that is not one engine.run or "
                         "run_ensemble call (their imports would come before the call)")
    switch_off(off)
    if path == "worker":
        return _run_worker(case, raw, workdir)
    if path == "cpu-ratio":
        return _run_cpu_ratio(case, raw, workdir)
    if public:
        from engine import run, run_ensemble
    else:
        from engine.driver.ensemble import run_ensemble
        from engine.driver.simulate import run

    specs = [to_spec(d) for d in raw]   # the bench's own step arithmetic: not the user's time
    log: list = []
    origin = [0.0]
    if trace and path == "run":
        trace_steps(log, origin)
    runner_imported = "engine.driver.simulate" in sys.modules     # before the clock (False with --public)
    t0 = origin[0] = time.perf_counter()    # the trace's times count from the call's start
    if path == "run":
        summary = run(specs[0], workdir / "out.h5")
        wall = time.perf_counter() - t0
        tm = dict(summary.extra["timings"])
        row = _row(case, summary.n_particles, summary.steps, wall, summary.loop_s, tm,
                   {"backend": summary.backend, "device": summary.device,
                    "records": int(specs[0].t_end / (specs[0].output_interval or specs[0].t_end / 200)) + 1,
                    "precision": specs[0].precision, "shape": specs[0].shape,
                    "list_mode": summary.extra.get("list_mode"),
                    # engine/driver/startup.py's thread (None: off, --off startup, or no GPU)
                    "gpu_startup": summary.extra.get("gpu_startup"), "runner_imported": runner_imported})
        if trace:
            row["trace"] = sorted(log)
        return row
    outs = [workdir / f"s{k}.h5" for k in range(len(specs))]
    results = run_ensemble(specs, outs)
    wall = time.perf_counter() - t0
    bad = [r for r in results if isinstance(r, BaseException)]
    if bad:
        raise RuntimeError(f"{len(bad)} scenes failed: {bad[0]!r}")
    tm = _sum_timings(results)
    n_total = sum(r.n_particles for r in results)
    steps = results[0].steps
    records = int(round(specs[0].t_end / specs[0].output_interval)) + 1 if specs[0].output_interval else 201
    row = _row(case, n_total, steps, wall, tm["loop"], tm,
               {"backend": results[0].backend, "device": results[0].device, "scenes": len(specs),
                "precision": specs[0].precision, "shape": specs[0].shape, "runner_imported": runner_imported})
    row["records_per_scene"] = records
    row["record_host_ms_per_scene"] = 1e3 * tm["records"] / (len(specs) * records)
    return row


def _run_cpu_ratio(case: str, raw: list, workdir: Path) -> dict:
    """16 x 512 spheres with default records through run_ensemble against one such scene with 4 records
    (both end to end, after a warm-up run that compiles)."""
    from engine.driver.ensemble import run_ensemble
    from engine.driver.simulate import run

    specs = [to_spec(d) for d in raw]
    run(specs[0].model_copy(update={"t_end": specs[0].t_end / 10}), workdir / "warm.h5")  # compile
    one = specs[0].model_copy(update={"output_interval": specs[0].t_end / 4})
    t0 = time.perf_counter()
    s1 = run(one, workdir / "one.h5")
    wall1 = time.perf_counter() - t0
    t0 = time.perf_counter()
    results = run_ensemble(specs, [workdir / f"e{k}.h5" for k in range(len(specs))])
    wall = time.perf_counter() - t0
    tm = _sum_timings(results)
    n_total = sum(r.n_particles for r in results)
    row = _row(case, n_total, results[0].steps, wall, tm["loop"], tm,
               {"backend": results[0].backend, "device": results[0].device, "scenes": len(specs)})
    one_rate = s1.n_particles * s1.steps / wall1
    records = int(round(specs[0].t_end / (specs[0].output_interval or specs[0].t_end / 200))) + 1
    row.update(one_scene_4_records_cundall=one_rate, ratio_to_one_scene=row["e2e_cundall"] / one_rate,
               record_host_ms_per_scene=1e3 * tm["records"] / (len(specs) * records))
    return row


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _run_worker(case: str, raw: list, workdir: Path) -> dict:
    """The batch submitted over HTTP to `demq serve` (API + embedded worker, SQLite) until the last result is
    downloadable; the worker packs the batch into one ensemble."""
    import httpx

    port = _free_port()
    env = {**os.environ, "DEMQ_DATA_DIR": str(workdir / "data"), "DEMQ_PORT": str(port),
           "DEMQ_HOST": "127.0.0.1", "DEMQ_MAX_PARTICLE_STEPS": "1e15"}
    log = open(workdir / "server.log", "w")   # a file, not a pipe nobody reads: a full pipe would stall the server
    server = subprocess.Popen([sys.executable, "-c", "from service.cli import main; main()", "serve"],
                              cwd=str(ROOT), env=env, stdout=log, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    try:
        with httpx.Client(base_url=url, timeout=60.0) as c:
            for _ in range(600):
                try:
                    if c.get("/healthz").status_code == 200:
                        break
                except httpx.HTTPError:
                    pass
                time.sleep(0.1)
            # a service is usually up for a while before a submit: DEMQ_E2E_WORKER_IDLE_S seconds of idle worker
            # (its standby simulation process starts up meanwhile, jobs/worker.py); 0: submit at once
            time.sleep(float(os.environ.get("DEMQ_E2E_WORKER_IDLE_S", "0")))
            base = to_spec(raw[0]).model_dump(mode="json")
            base.pop("seed")
            t0 = time.perf_counter()
            r = c.post("/batches", json={"base": base, "sweep": {"seed": [d["seed"] for d in raw]}})
            r.raise_for_status()
            batch = r.json()
            bid = batch["batch_id"]
            while True:
                page = c.get("/jobs", params={"batch_id": bid, "limit": 1000}).json()
                states = [j["state"] for j in page["items"]]
                if len(states) == len(raw) and all(s in ("done", "failed", "cancelled") for s in states):
                    break
                time.sleep(0.05)
            last = max(page["items"], key=lambda j: j.get("finished_at") or "")
            got = c.get(f"/jobs/{last['id']}/result")
            wall = time.perf_counter() - t0
            if any(s != "done" for s in states) or got.status_code != 200:
                raise RuntimeError(f"batch did not finish cleanly: {sorted(set(states))}, result {got.status_code}")
            n_total = sum(d["n_particles"] for d in raw)
            steps = int(round(base["t_end"] / base["dt"]))
            loop = max(j.get("loop_s") or 0.0 for j in page["items"])
            return _row(case, n_total, steps, wall, loop, {"loop": loop},
                        {"scenes": len(raw), "path": "worker", "jobs": len(states)})
    finally:
        server.terminate()
        try:
            server.wait(timeout=30)
        except subprocess.TimeoutExpired:
            server.kill()
        log.close()
        keep = os.environ.get("DEMQ_E2E_SERVER_LOG")   # every run's server log, appended, where asked for
        if keep:
            with open(keep, "a") as f:
                f.write(f"==== {case} in {workdir}\n" + (workdir / "server.log").read_text())


def fresh_process(case: str, quick: bool, off=(), start=None, trace: bool = False, public: bool = False) -> dict:
    """run_case in a new Python process (compilation / cache load counted, as for a user's first call)."""
    with tempfile.TemporaryDirectory(prefix="demq-e2e-") as d:
        code = ("import json,sys; sys.path.insert(0, %r); from bench.e2e import run_case; from pathlib import Path; "
                "print('E2E-ROW ' + json.dumps(run_case(%r, %r, Path(%r), %r, %r, %r, %r)))"
                % (str(ROOT), case, quick, d, tuple(off), start, trace, public))
        t0 = time.perf_counter()
        p = subprocess.run([sys.executable, "-c", code], cwd=str(ROOT), capture_output=True, text=True)
        process_s = time.perf_counter() - t0
        for line in p.stdout.splitlines():
            if line.startswith("E2E-ROW "):
                return {**json.loads(line[8:]), "process_s": process_s}
        raise RuntimeError(f"case {case} failed (exit {p.returncode}):\n{p.stderr[-3000:]}")


def table(rows: list) -> str:
    head = ("| case | particles x steps | end-to-end Cundall | loop Cundall (diagnostic) | e2e/loop | wall s | "
            + " | ".join(BREAKDOWN + ("other",)) + " |")
    lines = [head, "|" + "---|" * (6 + len(BREAKDOWN) + 1)]
    for r in rows:
        t = r["timings"]
        lines.append(f"| {r['case']} | {r['particles']} x {r['steps']} | {r['e2e_cundall']:.3g} | "
                     f"{r['loop_cundall']:.3g} | {r['e2e_over_loop']:.2f} | {r['wall_s']:.2f} | "
                     + " | ".join(f"{t.get(k, 0.0):.2f}" for k in BREAKDOWN + ("other",)) + " |")
    return "\n".join(lines)


def main(argv=None, out_dir=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--off", nargs="+", default=[], choices=sorted(SWITCHES), metavar="NAME",
                    help="turn latency machinery off in each case's process, for A/B timings: "
                    + ", ".join(f"{k} ({m}.{s} = {v})" for k, (m, s, v) in SWITCHES.items()))
    ap.add_argument("--cases", nargs="*", default=None, help="cases to run (default: the GPU cases when a GPU "
                    "is present, and the CPU cases)")
    ap.add_argument("--start", choices=("lattice", "random"), default=None,
                    help="start every scene this way (default: the spec's default start; 'lattice' for a comparison "
                         "with code older than the random start)")
    ap.add_argument("--reps", type=int, default=1, help="runs per case (median of the end-to-end wall time)")
    ap.add_argument("--quick", action="store_true", help="small scenes (smoke test)")
    ap.add_argument("--out", type=Path, default=out_dir or Path("bench-out") / "e2e",
                    help="report folder (default ./bench-out/e2e/)")
    ap.add_argument("--same-process", action="store_true", help="run the cases in this process (warm caches)")
    ap.add_argument("--trace", action="store_true", help="print when each set-up and build step of a one-job case "
                    "ran, and on which thread (module docstring)")
    ap.add_argument("--public", action="store_true", help="call engine.run / engine.run_ensemble with nothing of "
                    "engine.driver imported first: the call's figures include the runner's import (a user's first "
                    "call); the process's seconds compare with the default's")
    ap.add_argument("--prime", action="store_true", help="run each case once first, untimed (fills the kernel "
                    "disk cache; its wall time is reported as the first run)")
    args = ap.parse_args(argv)
    if args.cases is None:
        from engine.backends.base import cuda_available

        args.cases = (list(GPU_CASES) if cuda_available() else []) + list(CPU_CASES)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    def once(case):
        if args.same_process:
            with tempfile.TemporaryDirectory(prefix="demq-e2e-") as d:
                return run_case(case, args.quick, Path(d), args.off, args.start, args.trace, args.public)
        return fresh_process(case, args.quick, args.off, args.start, args.trace, args.public)

    for case in args.cases:
        first = once(case) if args.prime else None
        reps = [once(case) for _ in range(max(1, args.reps))]
        row = sorted(reps, key=lambda r: r["wall_s"])[(len(reps) - 1) // 2]   # median (lower for even)
        row["walls"] = [r["wall_s"] for r in reps]
        row["off"] = list(args.off)
        row["public"] = args.public
        row["runs"] = [{"wall_s": r["wall_s"], "loop_s": r["loop_s"], "process_s": r.get("process_s"),
                        "timings": r["timings"], "gpu_startup": r.get("gpu_startup")} for r in reps]
        if first is not None:
            row["first_run"] = {"wall_s": first["wall_s"], "timings": first["timings"]}
        rows.append(row)
        for k, r in enumerate(reps):
            for a, b, thread, step in r.get("trace", []):
                print(f"  {case} run {k + 1}: {a:7.3f} {b:7.3f} s {b - a:6.3f} s  {thread:20.20s} {step}")
        procs = [r["process_s"] for r in reps if r.get("process_s") is not None]
        print(f"{case}: wall {row['wall_s']:.2f} s (runs {', '.join(f'{w:.2f}' for w in row['walls'])}"
              + (f"; processes {', '.join(f'{w:.2f}' for w in procs)} s" if procs else "")
              + (f"; first run {first['wall_s']:.2f} s" if first else "") + "), "
              f"end-to-end {row['e2e_cundall']:.3g}, loop {row['loop_cundall']:.3g} particle-steps/s, "
              f"e2e/loop {row['e2e_over_loop']:.2f}; " + ", ".join(f"{k} {v:.2f}" for k, v in row["timings"].items()),
              flush=True)
    (args.out / "e2e.json").write_text(json.dumps(rows, indent=1, default=str))
    md = table(rows)
    (args.out / "e2e.md").write_text(md + "\n")
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
