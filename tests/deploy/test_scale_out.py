"""Scaling out, exercised: the API and three workers as separate processes on loopback against the
real local PostgreSQL, started with exactly the command lines of deploy/ (compose file, Slurm
script). 30 real-engine jobs (CPU backend, no GPU here); one worker is stopped with SIGTERM and one
killed with SIGKILL while each runs a job; every job still ends done exactly once with a valid HDF5.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import time
from collections import Counter

import h5py
import httpx
import pytest

from engine.setup.spec import SimulationSpec
from jobs.schema import DONE, QUEUED, RUNNING
from tests.deploy.conftest import SPEC, free_port, process_env, wait_for
from tests.deploy.deployfiles import SBATCH, compose, compose_workers, sbatch_exec

pytestmark = [pytest.mark.heavy,   # an API, three workers and real-engine jobs: over a minute of CPU
              pytest.mark.postgres]

N_JOBS = 30
#: The documented log line: "<date> <time>,<ms> <logger> <LEVEL> <message>".
LOG_LINE = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3} demq\.[\w.]+ (DEBUG|INFO|WARNING|ERROR|CRITICAL) \S")


def _mid_run(store, owner: str):
    """A job leased to ``owner`` that is computing (0 < progress < 0.6), or None."""
    for job in store.list(state=RUNNING, limit=1000)[0]:
        if job.lease_owner == owner and 0.0 < job.progress < 0.6:
            return job
    return None


def test_api_and_three_workers_on_postgres_sigterm_sigkill_every_job_done_once(
        tmp_path, pg, procs, bin_dir, warm_jit):
    url, prefix, store = pg
    for seed in range(N_JOBS):  # the specs are valid before anything starts
        SimulationSpec.model_validate({**SPEC, "seed": seed})
    data, port = tmp_path / "data", free_port()
    # one job per claim: this test follows single jobs across workers (a pack of tiny jobs would drain
    # the queue before a worker can be caught mid-job); packing has its own tests (tests/jobs/test_packing.py)
    env = process_env(bin_dir, DEMQ_DATABASE_URL=url, DEMQ_TABLE_PREFIX=prefix, DEMQ_DATA_DIR=str(data),
                      DEMQ_HOST="127.0.0.1", DEMQ_PORT=str(port), DEMQ_ENSEMBLE_MAX_JOBS="1")
    doc = compose()
    base = f"http://127.0.0.1:{port}"
    t0 = time.monotonic()

    # ---- the API, exactly as the compose file (and api.Dockerfile) runs it ------------------------
    api_cmd = doc["services"]["api"]["command"]
    assert api_cmd == ["demq", "serve", "--no-worker"]
    api = procs.start("api", api_cmd, env)
    wait_for(lambda: _healthz(base) == 200, "the API's /healthz", {"api": api})
    healthcheck = doc["services"]["api"]["healthcheck"]["test"]
    assert healthcheck[0] == "CMD"
    assert subprocess.run(healthcheck[1:], env=env, timeout=60).returncode == 0, "compose API healthcheck"

    # ---- two workers as the compose file runs them, one as the Slurm array task runs it -----------
    workers = compose_workers(doc)
    w_term = procs.start("w-term", workers["worker-gpu0"]["command"], {**env, "DEMQ_WORKER_ID": "w-term"})
    w_kill = procs.start("w-kill", workers["worker-gpu1"]["command"], {**env, "DEMQ_WORKER_ID": "w-kill"})
    with httpx.Client(base_url=base, timeout=30) as c:
        ids = []
        for seed in range(N_JOBS):
            r = c.post("/jobs", json={**SPEC, "seed": seed})
            assert r.status_code == 201, r.text
            ids.append(r.json()["id"])
    assert sbatch_exec() == ("demq", "worker", "--exit-when-idle")
    slurm_env = {**env, "SLURM_ARRAY_JOB_ID": "4242", "SLURM_ARRAY_TASK_ID": "2", "SLURM_CPUS_PER_TASK": "1",
                 "CUDA_VISIBLE_DEVICES": ""}
    drain = procs.start("slurm-task", ["bash", str(SBATCH)], slurm_env)
    alive = {"api": api, "w-term": w_term, "w-kill": w_kill, "slurm-task": drain}

    # ---- SIGTERM one worker while it computes a job: the job is released, the worker exits 0 ------
    # (after a third of the jobs, so that three workers share the work for a while)
    wait_for(lambda: store.counts().get(DONE, 0) >= N_JOBS // 3, f"{N_JOBS // 3} jobs done", alive)
    held = wait_for(lambda: _mid_run(store, "w-term"), "w-term computing a job", alive)
    del alive["w-term"]
    assert procs.stop("w-term", 40) == 0, procs.log("w-term")
    after = store.get(held.id)
    assert after.lease_owner != "w-term" and after.state in (QUEUED, RUNNING, DONE), after
    assert f"job {held.id}: released to the queue" in procs.log("w-term")

    # ---- SIGKILL another while it computes a job: its lease expires, the reaper requeues it -------
    wait_for(lambda: store.counts().get(DONE, 0) >= N_JOBS // 2, f"{N_JOBS // 2} jobs done", alive)
    killed = wait_for(lambda: _mid_run(store, "w-kill"), "w-kill computing a job", alive)
    os.kill(w_kill.pid, signal.SIGKILL)
    assert w_kill.wait(10) == -signal.SIGKILL
    del alive["w-kill"]
    row = store.get(killed.id)
    assert (row.state, row.lease_owner) == (RUNNING, "w-kill"), "the kill must hit the job mid-run"
    # every job of the killed worker's claim (a pack of compatible jobs, docs/design.md §7) loses its lease with it
    lost = {j.id for j in store.list(state=RUNNING, limit=1000)[0] if j.lease_owner == "w-kill"}
    assert killed.id in lost

    # ---- the Slurm task drains the queue and exits 0 by itself ------------------------------------
    try:
        rc = drain.wait(300)
    except subprocess.TimeoutExpired:
        raise AssertionError(f"the drain worker did not finish the queue; counts {store.counts()}\n"
                             f"{procs.log('slurm-task')[-3000:]}") from None
    assert rc == 0, procs.log("slurm-task")
    drain_log = procs.log("slurm-task")
    assert "no queued or running job left; exiting (drain mode)" in drain_log
    assert re.search(rf"reaper: requeued \[[^\]]*'{killed.id}'", drain_log), drain_log[-3000:]

    # ---- every job done exactly once, seen through the API -----------------------------------------
    with httpx.Client(base_url=base, timeout=30) as c:
        listed = c.get("/jobs", params={"limit": 1000}).json()
        assert c.get("/healthz").json()["jobs"] == {"done": N_JOBS}
        r = c.get(f"/jobs/{killed.id}/result")
        assert r.status_code == 200 and r.content[:8] == b"\x89HDF\r\n\x1a\n"
    assert listed["total"] == N_JOBS and sorted(j["id"] for j in listed["items"]) == sorted(ids)
    by_id = {j["id"]: j for j in listed["items"]}
    assert all(j["state"] == DONE and j["error"] is None for j in by_id.values()), \
        [(j["id"], j["state"], j["error"]) for j in by_id.values() if j["state"] != DONE]
    assert all(by_id[i]["attempts"] == 2 for i in lost), [(i, by_id[i]["attempts"]) for i in lost]
    assert by_id[held.id]["attempts"] == 1  # a released attempt is not counted
    assert all(j["attempts"] == 1 for i, j in by_id.items() if i not in lost)

    # one "done" per job across all worker logs (a job run twice to completion would log it twice)
    logs = {name: procs.log(name) for name in ("w-term", "w-kill", "slurm-task")}
    done_lines = Counter(m for text in logs.values() for m in re.findall(r"job (\S+): done$", text, re.M))
    assert done_lines == Counter({i: 1 for i in ids}), done_lines
    for name, text in logs.items():
        demq_lines = [ln for ln in text.splitlines() if " demq." in ln]
        assert demq_lines and all(LOG_LINE.match(ln) for ln in demq_lines), (name, demq_lines[:5])

    # ---- each result: <data_dir>/results/<id>.h5, a valid HDF5 with the energy series -------------
    for job_id in ids:
        got = store.get(job_id)
        assert got.result_path == str(data / "results" / f"{job_id}.h5") and got.backend == "cpu"
        with h5py.File(got.result_path) as f:
            values = f["observables/kinetic_energy_translational/value"][()]
            times = f["observables/kinetic_energy_translational/time"][()]
        assert len(values) > 1 and (values > 0).all() and times[-1] == pytest.approx(SPEC["t_end"], rel=1e-3)
        assert (times[1:] > times[:-1]).all(), f"job {job_id}: repeated or unordered records"
    assert sorted(p.name for p in (data / "results").glob("*.h5")) == sorted(f"{i}.h5" for i in ids)
    leftover = list((data / "checkpoints").iterdir()) if (data / "checkpoints").exists() else []
    assert leftover == [], f"checkpoints of finished jobs left behind: {leftover}"

    # ---- the API stops on SIGTERM too (uvicorn shuts down cleanly, then re-raises the signal) -------
    assert procs.stop("api", 30) in (0, -signal.SIGTERM)
    assert "Application shutdown complete." in procs.log("api")
    print(f"scale-out test: {N_JOBS} jobs in {time.monotonic() - t0:.0f} s after warm-up")


def _healthz(base: str) -> int:
    try:
        return httpx.get(f"{base}/healthz", timeout=2).status_code
    except httpx.HTTPError:
        return 0
