"""Graceful shutdown never loses work: SIGTERM to a worker started the way deploy/ starts it (the
Slurm array task; `demq serve` of the systemd workstation unit) while it computes a real-engine job
stops the simulation, keeps its checkpoint, releases the lease without counting the attempt and
exits; the next worker resumes the job from that checkpoint and the result has every record once."""

from __future__ import annotations

import signal
import time

import h5py
import httpx
import numpy as np
import pytest

from engine.setup.spec import SimulationSpec
from jobs.schema import DONE, QUEUED, RUNNING
from jobs.specs import parse_spec
from jobs.store import NewJob
from jobs.stores import open_store
from tests.deploy.conftest import SPEC, free_port, process_env, wait_for
from tests.deploy.deployfiles import (SBATCH, WORKSTATION_UNIT, env_file, sbatch_exec, seconds, unit,
                                      unit_exec)
from tests.waiting import CEILING_S

#: Several seconds of one CPU core: long enough for a few checkpoints at DEMQ_CHECKPOINT_INTERVAL=0.3 s.
LONG = {**SPEC, "t_end": 1.5}


def _checkpoint_step(directory) -> int:
    """Cooling step of the checkpoint in ``directory`` (-1 if none yet)."""
    try:
        with np.load(directory / "state.npz") as ck:
            return int(ck["step_done"])
    except (OSError, KeyError, ValueError):
        return -1


def _mid_run_with_checkpoint(store, job_id, ckpt_dir) -> int:
    """The checkpoint step once the job runs past 20 % with a checkpoint beyond step 0, else 0."""
    job = store.get(job_id)
    if job.state == RUNNING and job.progress > 0.2:
        step = _checkpoint_step(ckpt_dir)
        return step if step > 0 else 0
    return 0


def _check_complete_result(path, t_end: float) -> None:
    with h5py.File(path) as f:
        times = f["observables/kinetic_energy_translational/time"][()]
        values = f["observables/kinetic_energy_translational/value"][()]
    assert len(values) == len(times) > 100 and (values > 0).all()
    assert (times[1:] > times[:-1]).all(), "a record was written twice"
    assert times[0] == 0.0 and times[-1] == pytest.approx(t_end, rel=1e-3), "records missing"


@pytest.mark.postgres
def test_slurm_task_sigterm_releases_the_job_and_the_next_task_resumes_it(tmp_path, pg, procs, bin_dir, warm_jit):
    """scancel / the time limit (--signal=B:TERM@120) -> SIGTERM to the exec'd worker."""
    url, prefix, store = pg
    spec = parse_spec(LONG)
    (job,) = store.submit([NewJob(spec.to_json())])
    data = tmp_path / "data"
    env = process_env(bin_dir, DEMQ_DATABASE_URL=url, DEMQ_TABLE_PREFIX=prefix, DEMQ_DATA_DIR=str(data),
                      SLURM_ARRAY_JOB_ID="77", SLURM_CPUS_PER_TASK="1", CUDA_VISIBLE_DEVICES="")
    assert sbatch_exec() == ("demq", "worker", "--exit-when-idle")
    ckpt = data / "checkpoints" / job.id

    first = procs.start("task-0", ["bash", str(SBATCH)], {**env, "SLURM_ARRAY_TASK_ID": "0"})
    step = wait_for(lambda: _mid_run_with_checkpoint(store, job.id, ckpt), "a checkpoint past step 0",
                    {"task-0": first})
    t0 = time.monotonic()
    assert procs.stop("task-0", 60) == 0, procs.log("task-0")
    stop_s = time.monotonic() - t0
    assert stop_s < float(env["DEMQ_CANCEL_GRACE_SECONDS"]), f"stopping took {stop_s:.1f} s"
    released = store.get(job.id)
    assert (released.state, released.attempts, released.lease_owner) == (QUEUED, 0, None)
    assert _checkpoint_step(ckpt) >= step, "the checkpoint must survive the shutdown"
    log = procs.log("task-0")
    assert f"job {job.id}: stopping the simulation (shutdown)" in log
    assert f"job {job.id}: released to the queue (worker stopping); checkpoints kept" in log
    assert not (data / "results" / f"{job.id}.h5").exists()

    second = procs.start("task-1", ["bash", str(SBATCH)], {**env, "SLURM_ARRAY_TASK_ID": "1"})
    assert second.wait(CEILING_S) == 0, procs.log("task-1")  # drains the queue and exits by itself
    done = store.get(job.id)
    assert done.state == DONE and done.error is None, done.error
    assert done.attempts == 1, "the released attempt must not count"
    assert done.resumed_from_step is not None and done.resumed_from_step >= step > 0
    _check_complete_result(done.result_path, LONG["t_end"])
    assert not ckpt.exists(), "checkpoints are removed once the job is done"


def test_workstation_serve_sigterm_releases_the_job_and_restart_resumes_it(tmp_path, procs, bin_dir, warm_jit):
    """`systemctl stop demq` -> SIGTERM (KillSignal) to `demq serve`: its embedded worker releases
    the job before TimeoutStopSec; `systemctl start demq` finishes it from the checkpoint."""
    service = unit(WORKSTATION_UNIT)["Service"]
    assert service["KillSignal"] == ["SIGTERM"]
    timeout_stop = seconds(service["TimeoutStopSec"][0])
    argv = unit_exec(WORKSTATION_UNIT)
    assert argv == ("demq", "serve")
    port = free_port()
    # /etc/demq/demq.env as shipped, with this test's data directory, port and fast timings
    env = process_env(bin_dir, **{**env_file(), "DEMQ_DATA_DIR": str(tmp_path / "data"), "DEMQ_PORT": str(port),
                                  "DEMQ_CHECKPOINT_INTERVAL": "0.3", "DEMQ_CANCEL_GRACE_SECONDS": "20"})
    base = f"http://127.0.0.1:{port}"
    SimulationSpec.model_validate(LONG)

    serve = procs.start("serve-1", argv, env)
    wait_for(lambda: _healthz(base), "demq serve", {"serve-1": serve})
    job_id = httpx.post(f"{base}/jobs", json=LONG, timeout=30).json()["id"]
    store = open_store(f"sqlite:///{tmp_path / 'data' / 'demq.sqlite3'}")
    ckpt = tmp_path / "data" / "checkpoints" / job_id
    step = wait_for(lambda: _mid_run_with_checkpoint(store, job_id, ckpt), "a checkpoint past step 0",
                    {"serve-1": serve})
    t0 = time.monotonic()
    assert procs.stop("serve-1", timeout_stop) in (0, -signal.SIGTERM)  # uvicorn re-raises SIGTERM after a clean
                                                                        # shutdown
    assert time.monotonic() - t0 < min(timeout_stop, 30)
    assert "Application shutdown complete." in procs.log("serve-1")
    released = store.get(job_id)
    assert (released.state, released.attempts, released.lease_owner) == (QUEUED, 0, None)
    assert _checkpoint_step(ckpt) >= step

    serve = procs.start("serve-2", argv, env)
    wait_for(lambda: _healthz(base) and httpx.get(f"{base}/jobs/{job_id}", timeout=5).json()["state"] == DONE,
             "the resumed job", {"serve-2": serve})
    job = httpx.get(f"{base}/jobs/{job_id}", timeout=5).json()
    assert job["attempts"] == 1 and job["resumed_from_step"] >= step > 0
    _check_complete_result(tmp_path / "data" / "results" / f"{job_id}.h5", LONG["t_end"])
    assert procs.stop("serve-2", timeout_stop) in (0, -signal.SIGTERM)
    store.close()


def _healthz(base: str) -> bool:
    try:
        return httpx.get(f"{base}/healthz", timeout=2).status_code == 200
    except httpx.HTTPError:
        return False
