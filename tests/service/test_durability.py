"""Durability with real processes: `demq worker` killed with SIGKILL or stopped with SIGTERM, an API
restarted with jobs queued and running, a crashing simulation. Each runs with the fake engine
(fast, always) and, where it matters, with the real engine on a tiny scene."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest
from fastapi.testclient import TestClient

from jobs.runner import TEST_CRASH_ENV
from jobs.schema import DONE, FAILED, QUEUED, RUNNING
from jobs.specs import parse_spec
from jobs.store import NewJob
from jobs.stores import open_store
from jobs.worker import Worker
from service.app import create_app
from tests import waiting
from tests.extras import assert_figure
from tests.jobs.conftest import ROOT, TINY, make_settings
from tests.jobs.fake_engine import TARGET

REAL = "engine.driver.simulate:run"
#: A real-engine job of a few seconds on one CPU core (~5e5 steps of 64 particles): long enough to
#: write several checkpoints at a 0.3 s interval before the worker is killed.
REAL_LONG = {**TINY, "t_end": 1.0}


def start_worker(settings, engine_run=TARGET, **env) -> subprocess.Popen:
    """`demq worker` in its own process (session), configured through DEMQ_* variables; like ``settings`` (from
    make_settings) it does not warm every kernel specialisation first: a real-engine job compiles only its own."""
    full_env = {**os.environ, "PYTHONPATH": str(ROOT), "DEMQ_ENGINE_RUN": engine_run,
                "DEMQ_WORKER_WARM": settings.warm, "DEMQ_DATA_DIR": str(settings.data_dir), "DEMQ_POLL_SECONDS": "0.05",
                "DEMQ_LEASE_SECONDS": str(settings.lease_s), "DEMQ_HEARTBEAT_SECONDS": str(settings.heartbeat_s),
                "DEMQ_CHECKPOINT_INTERVAL": "0.3", "DEMQ_PROGRESS_SECONDS": "0.1", **env}
    full_env.pop("DEMQ_DATABASE_URL", None)
    return subprocess.Popen([sys.executable, "-m", "service.cli", "worker"], cwd=ROOT, env=full_env,
                            start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def wait_for(cond, what):
    """Wait for an event; the limits only catch hangs (tests/waiting.py)."""
    return waiting.wait_for(cond, what)


def stop(proc) -> int:
    proc.send_signal(signal.SIGTERM)
    try:
        return proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()


def _checkpointed_past_start(ckpt) -> bool:
    """A checkpoint beyond step 0 of the cooling run exists (the real engine's state.npz or the fake
    engine's JSON): the first checkpoint may be taken at step 0, and a fast run may reach 5 % before the
    next one, so progress alone does not promise a resume point past the start."""
    try:
        if (ckpt / "state.npz").exists():
            with np.load(ckpt / "state.npz") as saved:
                return str(saved["phase"]) == "cooling" and int(saved["step_done"]) > 0
        if (ckpt / "fake.ckpt").exists():
            return json.loads((ckpt / "fake.ckpt").read_text())["step"] > 0
    except (OSError, ValueError, KeyError, EOFError):  # replaced while being read: look again
        pass
    return False


def _enqueue(store, spec):
    (job,) = store.submit([NewJob(parse_spec(spec).to_json())])
    return job


@pytest.mark.parametrize("engine_run, spec", [(TARGET, {**TINY, "t_end": 8.0}), (REAL, REAL_LONG)],
                         ids=["fake-engine", "real-engine"])
def test_sigkilled_worker_job_is_resumed_from_checkpoint(tmp_path, engine_run, spec):
    settings = make_settings(tmp_path, lease_s=2.0, heartbeat_s=0.3)
    store = open_store(settings.database_url)
    job = _enqueue(store, spec)
    first = start_worker(settings, engine_run)
    ckpt = settings.checkpoint_dir(job.id)
    try:
        wait_for(lambda: _checkpointed_past_start(ckpt) and store.get(job.id).progress > 0.05,
                 "a checkpoint after the start")
    finally:
        os.kill(first.pid, signal.SIGKILL)
        first.wait(10)
    assert store.get(job.id).state == RUNNING  # the row still says running: only the lease can tell
    second = start_worker(settings, engine_run)
    try:
        wait_for(lambda: store.get(job.id).state in (DONE, FAILED), "the resumed job")
    finally:
        assert stop(second) == 0
    got = store.get(job.id)
    assert got.state == DONE, got.error
    assert got.attempts == 2 and got.resumed_from_step and got.resumed_from_step > 0
    with h5py.File(got.result_path) as f:
        values = f["observables/kinetic_energy_translational/value"][()]
        times = f["observables/kinetic_energy_translational/time"][()]
    assert len(values) > 1 and (times[1:] > times[:-1]).all()  # one series, no repeated frames


def test_sigterm_releases_the_job_and_exits_zero(tmp_path):
    settings = make_settings(tmp_path)
    store = open_store(settings.database_url)
    job = _enqueue(store, {**TINY, "t_end": 30.0})
    proc = start_worker(settings)
    wait_for(lambda: store.get(job.id).progress > 0, "the job to start")
    t0 = time.monotonic()
    assert stop(proc) == 0
    assert time.monotonic() - t0 < 10
    got = store.get(job.id)
    assert (got.state, got.attempts, got.lease_owner) == (QUEUED, 0, None)


def test_job_that_keeps_killing_its_worker_ends_failed(tmp_path):
    settings = make_settings(tmp_path, lease_s=1.0, heartbeat_s=0.2, max_attempts=2)
    store = open_store(settings.database_url)
    (job,) = store.submit([NewJob(parse_spec({**TINY, "t_end": 30.0}).to_json())], max_attempts=2)
    for attempt in (1, 2):
        proc = start_worker(settings)
        wait_for(lambda: store.get(job.id).attempts == attempt and store.get(job.id).state == RUNNING, "claim")
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
        time.sleep(1.2)  # the lease expires
        store.reap_expired()
    got = store.get(job.id)
    assert got.state == FAILED and "every attempt, 2 of 2" in got.error


@pytest.mark.parametrize("engine_run", [TARGET, REAL], ids=["fake-engine", "real-engine"])
def test_crashing_simulation_fails_its_job_and_the_next_runs(tmp_path, monkeypatch, engine_run):
    monkeypatch.setenv(TEST_CRASH_ENV, "4242")
    settings = make_settings(tmp_path, engine_run=engine_run)
    store = open_store(settings.database_url)
    crash, good = _enqueue(store, {**TINY, "seed": 4242}), _enqueue(store, TINY)
    worker = Worker(store, settings)
    worker.execute(store.claim(worker.owner, settings.lease_s))
    worker.execute(store.claim(worker.owner, settings.lease_s))
    assert store.get(crash.id).state == FAILED
    assert store.get(crash.id).error == "simulation process killed by signal SIGSEGV"
    assert store.get(good.id).state == DONE, store.get(good.id).error


def test_api_restart_loses_nothing(tmp_path):
    """Jobs queued and one running when the API process (with its embedded worker) dies: a new
    process on the same data directory shows them all and finishes them all."""
    settings = make_settings(tmp_path, lease_s=1.0, heartbeat_s=0.2)
    first = create_app(settings)
    with TestClient(first) as c:
        ids = [c.post("/jobs", json={**TINY, "seed": i}).json()["id"] for i in range(4)]
        first.state.store.claim("dead-worker", 1.0, job_id=ids[0])  # it was running when the process died
    first.state.store.close()

    second = create_app(settings, embedded_worker=True)
    with TestClient(second) as c:
        listed = {j["id"]: j["state"] for j in c.get("/jobs").json()["items"]}
        assert set(listed) == set(ids) and listed[ids[0]] in ("running", "queued")
        wait_for(lambda: all(c.get(f"/jobs/{i}").json()["state"] == "done" for i in ids), "all jobs done")
        assert c.get(f"/jobs/{ids[0]}").json()["attempts"] == 2
        assert c.get("/healthz").json()["jobs"] == {"done": 4}


def test_end_to_end_real_engine_submit_done_download(tmp_path):
    """Submit over HTTP, the embedded worker runs the real engine, download the HDF5."""
    settings = make_settings(tmp_path, engine_run=REAL)
    with TestClient(create_app(settings, embedded_worker=True)) as c:
        job_id = c.post("/jobs", json=TINY).json()["id"]
        wait_for(lambda: c.get(f"/jobs/{job_id}").json()["state"] in ("done", "failed"), "the real run")
        status = c.get(f"/jobs/{job_id}").json()
        assert status["state"] == "done", status["error"]
        assert status["cundall"] > 0 and status["backend"] in ("cpu", "cuda") and status["progress"] == 1.0
        r = c.get(f"/jobs/{job_id}/result")
        assert r.status_code == 200
        out = tmp_path / "downloaded.h5"
        out.write_bytes(r.content)
        with h5py.File(out) as f:
            for name in ("kinetic_energy_translational", "kinetic_energy_rotational",
                         "temperature_translational", "temperature_rotational"):
                assert f[f"observables/{name}/value"].shape[0] > 1
        energy = c.get(f"/jobs/{job_id}/energy").json()
        assert energy["kinetic_energy_translational"][0] > 0
        assert_figure(c.get(f"/jobs/{job_id}/plot.png"))


def test_cli_local_submit_wait_writes_result(tmp_path):
    """The quick start: `demq submit --local --wait -o result.h5`, no server (tiny scene via --set)."""
    sets = [arg for k, v in TINY.items() for arg in ("--set", f"{k}={v}")]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    r = subprocess.run([sys.executable, "-m", "service.cli", "submit", "--local", "--wait", "-o", "result.h5", *sets],
                       cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    with h5py.File(tmp_path / "result.h5") as f:
        assert f["observables/temperature_translational/value"].shape[0] > 1
    assert (tmp_path / "demq-data" / "demq.sqlite3").exists()
    # the ParaView sidecar beside the copy, naming it (not the file in the data directory)
    assert 'result.h5:/particles/all/position/value' in (tmp_path / "result.xmf").read_text()
    # stdout: the job id first; stderr is a pipe here: plain progress lines, the last one at 100 %
    job_id = r.stdout.splitlines()[0]
    assert len(job_id) == 32 and "wrote result.h5 and result.xmf" in r.stdout
    progress = [line for line in r.stderr.splitlines() if line.startswith(f"job {job_id[:8]}:")]
    assert "\r" not in r.stderr and progress and "100.0%" in progress[-1], r.stderr
    r = subprocess.run([sys.executable, "-m", "service.cli", "submit", "--local", "--wait", "--set", "e_n=3"],
                       cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "e_n = 3" in r.stderr


def test_a_submit_wakes_the_embedded_worker(tmp_path):
    """With a 60 s idle wait, jobs submitted over HTTP (one, then a batch) still start at once: the submit wakes
    `demq serve`'s worker."""
    settings = make_settings(tmp_path, poll_s=60.0)
    with TestClient(create_app(settings, embedded_worker=True)) as c:
        time.sleep(0.5)                        # the worker has found the queue empty and waits
        t0 = time.monotonic()
        job_id = c.post("/jobs", json=TINY).json()["id"]
        wait_for(lambda: c.get(f"/jobs/{job_id}").json()["state"] == "done", "the job")
        ids = c.post("/batches", json={"base": TINY, "sweep": {"seed": [1, 2]}}).json()["job_ids"]
        wait_for(lambda: all(c.get(f"/jobs/{i}").json()["state"] == "done" for i in ids), "the batch")
        assert time.monotonic() - t0 < 30
