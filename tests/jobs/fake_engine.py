"""A fake engine with the contract of ``engine.driver.simulate.run``, for worker and API tests.

It takes wall time instead of computing physics, so tests can exercise the queue while the real
engine is elsewhere (or too slow for a test): ``N_STEPS`` steps, each sleeping ``spec.t_end / N_STEPS``
wall seconds, a progress report and a cancel check per step, a checkpoint (JSON) whenever
``checkpoint_interval`` has passed, resumption from that checkpoint, and an HDF5 result with the
observables layout written to a temporary name (``<output>.part``, there from the start of the run, as the
engine's writer does; removed when the run is cancelled or fails) and renamed. ``seed == FAIL_SEED`` raises an
InstabilityError half-way. Selected with ``DEMQ_ENGINE_RUN=tests.jobs.fake_engine:run``; its ensemble
counterpart :func:`run_ensemble` with ``DEMQ_ENGINE_RUN_ENSEMBLE=tests.jobs.fake_engine:run_ensemble``.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import h5py
import numpy as np

from engine.driver.simulate import Progress, RunSummary
from engine.errors import Cancelled, InstabilityError
from engine.setup.params import derive

N_STEPS = 20
FAIL_SEED = 13
TARGET = "tests.jobs.fake_engine:run"
ENSEMBLE_TARGET = "tests.jobs.fake_engine:run_ensemble"


def write_result(path, spec, n_records: int = 21) -> Path:
    """Write an HDF5 result with the engine's observables layout (Haff-like cooling curves)."""
    path = Path(path)
    p = derive(spec)
    time_ = np.linspace(0.0, spec.t_end, n_records)
    step = np.round(time_ / p.dt).astype(np.int64)
    decay = (1.0 + time_ / (0.5 * spec.t_end)) ** -2
    temps = {"temperature_translational": p.temperature0 * decay,
             "temperature_rotational": p.temperature0 * decay * 0.8}
    series = {**temps,
              "kinetic_energy_translational": 1.5 * spec.n_particles * temps["temperature_translational"],
              "kinetic_energy_rotational": 1.5 * spec.n_particles * temps["temperature_rotational"],
              "contacts": np.zeros(n_records, dtype=np.int64)}
    tmp = path.with_name(path.name + ".part")
    with h5py.File(tmp, "w") as f:
        for name, value in series.items():
            g = f.create_group(f"observables/{name}")
            g["step"], g["time"], g["value"] = step, time_, value
        params = f.create_group("parameters")
        params.attrs["spec"] = spec.to_json()
        for key in ("dt", "contact_time", "radius", "mass", "collision_rate0", "temperature0"):
            params.attrs[key] = getattr(p, key)
    os.replace(tmp, path)
    return path


def run(spec, output, *, progress=None, should_cancel=None, checkpoint_dir=None, checkpoint_interval=60.0,
        backend=None) -> RunSummary:
    ckpt = Path(checkpoint_dir) / "fake.ckpt" if checkpoint_dir else None
    start = 0
    if ckpt is not None and ckpt.exists():
        saved = json.loads(ckpt.read_text())
        if saved["spec"] == spec.to_json():
            start = saved["step"]
    t0 = last_ckpt = time.monotonic()
    partial = Path(str(output) + ".part")   # like the engine's result writer: the file grows under this name
    partial.write_bytes(b"")
    for k in range(start, N_STEPS):
        if should_cancel is not None and should_cancel():
            partial.unlink(missing_ok=True)
            raise Cancelled(f"cancelled at step {k}")
        if spec.seed == FAIL_SEED and k == N_STEPS // 2:
            partial.unlink(missing_ok=True)
            raise InstabilityError(f"overlap of particle 7 exceeds the limit at step {k}: dt too large?", k, 7)
        time.sleep(spec.t_end / N_STEPS)
        if ckpt is not None and time.monotonic() - last_ckpt >= checkpoint_interval:
            ckpt.write_text(json.dumps({"spec": spec.to_json(), "step": k + 1}))
            last_ckpt = time.monotonic()
        wall = time.monotonic() - t0
        if progress is not None:
            progress(Progress(phase="cooling", fraction=(k + 1) / N_STEPS, step=k + 1,
                              time=spec.t_end * (k + 1) / N_STEPS, eta_s=wall / (k + 1 - start) * (N_STEPS - k - 1),
                              cundall=1.0e6, loop_s=wall, resumed_from_step=start or None))
    write_result(output, spec)
    wall = max(time.monotonic() - t0, 1e-9)
    # the device names the Numba threads the worker gave this process (a lane's share: DEMQ_WORKER_LANES)
    device = f"test double, NUMBA_NUM_THREADS={os.environ.get('NUMBA_NUM_THREADS', 'unset')}"
    return RunSummary(output=Path(output), backend="fake", device=device, n_particles=spec.n_particles,
                      steps=N_STEPS - start, loop_s=wall, job_wall_s=wall,
                      cundall=spec.n_particles * (N_STEPS - start) / wall, resumed_from_step=start or None)


def run_deaf(spec, output, *, progress=None, should_cancel=None, **kwargs) -> RunSummary:
    """Like :func:`run` but never looks at the cancel check (an engine stuck in a long kernel)."""
    return run(spec, output, progress=progress, should_cancel=None, **kwargs)


def run_ensemble(specs, outputs, *, progress=None, should_cancel=None, backend=None, checkpoint_dirs=None,
                 checkpoint_interval=60.0, on_result=None) -> list:
    """The contract of ``engine.driver.ensemble.run_ensemble``: the scenes of :func:`run`, stepped together.

    Each round every active scene checks its cancel flag, takes one of its ``N_STEPS`` steps (the
    round sleeps the longest ``t_end / N_STEPS`` of the active scenes), reports progress and
    checkpoints; ``FAIL_SEED`` fails its scene alone half-way. A scene's result goes to ``on_result``
    as soon as it ends. Selected with ``DEMQ_ENGINE_RUN_ENSEMBLE=tests.jobs.fake_engine:run_ensemble``.
    """
    k_all = range(len(specs))
    dirs = list(checkpoint_dirs) if checkpoint_dirs is not None else [None] * len(specs)
    ckpts = [Path(d) / "fake.ckpt" if d else None for d in dirs]
    start = []
    for spec, ck in zip(specs, ckpts):
        saved = json.loads(ck.read_text()) if ck is not None and ck.exists() else None
        start.append(saved["step"] if saved and saved["spec"] == spec.to_json() else 0)
    results: list = [None] * len(specs)
    step = list(start)
    active = set(k_all)
    t0 = last_ckpt = time.monotonic()

    def settle(k, result):
        results[k] = result
        active.discard(k)
        if on_result is not None:
            on_result(k, result)

    while active:
        for k in sorted(active):
            if should_cancel is not None and should_cancel(k):
                settle(k, Cancelled(f"cancelled at step {step[k]}"))
            elif specs[k].seed == FAIL_SEED and step[k] == N_STEPS // 2:
                settle(k, InstabilityError(f"overlap of particle 7 exceeds the limit at step {step[k]}: dt too large?",
                                           step[k], 7))
        if not active:
            break
        time.sleep(max(specs[k].t_end for k in active) / N_STEPS)
        ck_due = time.monotonic() - last_ckpt >= checkpoint_interval
        for k in sorted(active):
            step[k] += 1
            if ckpts[k] is not None and ck_due:
                ckpts[k].write_text(json.dumps({"spec": specs[k].to_json(), "step": step[k]}))
            wall = time.monotonic() - t0
            if progress is not None:
                progress(k, Progress(phase="cooling", fraction=step[k] / N_STEPS, step=step[k],
                                     time=specs[k].t_end * step[k] / N_STEPS,
                                     eta_s=wall / (step[k] - start[k]) * (N_STEPS - step[k]), cundall=1.0e6,
                                     loop_s=wall, resumed_from_step=start[k] or None))
        if ck_due:
            last_ckpt = time.monotonic()
        for k in sorted(active):
            if step[k] >= N_STEPS:
                write_result(outputs[k], specs[k])
                wall = max(time.monotonic() - t0, 1e-9)
                settle(k, RunSummary(output=Path(outputs[k]), backend="fake", device="test double",
                                     n_particles=specs[k].n_particles, steps=N_STEPS - start[k], loop_s=wall,
                                     job_wall_s=wall, cundall=specs[k].n_particles * (N_STEPS - start[k]) / wall,
                                     resumed_from_step=start[k] or None, extra={"ensemble_size": len(specs)}))
    return results


def run_slow_exit(spec, output, **kwargs) -> RunSummary:
    """Like :func:`run`, but the process takes 3 s to exit after the run (a GPU context's teardown): a thread
    that the interpreter joins at its exit sleeps that long."""
    import threading

    summary = run(spec, output, **kwargs)
    threading.Thread(target=time.sleep, args=(3.0,)).start()
    return summary
