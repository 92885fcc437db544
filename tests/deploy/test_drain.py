"""Drain mode (`demq worker --exit-when-idle`, what the Slurm array tasks run) and concurrent
start-up of many workers on a fresh PostgreSQL database (a job array starting at once)."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
import uuid

import pytest

from jobs.schema import DONE
from jobs.specs import parse_spec
from jobs.store import NewJob
from jobs.stores import open_store
from jobs.worker import Worker
from tests.deploy.deployfiles import ROOT, clean_env
from tests.jobs.conftest import TINY, make_settings, postgres_url
from tests.waiting import CEILING_S


def _run_in_thread(worker: Worker) -> threading.Thread:
    t = threading.Thread(target=worker.run_forever, kwargs={"exit_when_idle": True}, daemon=True)
    t.start()
    return t


def test_drain_worker_exits_on_an_empty_queue(tmp_path):
    settings = make_settings(tmp_path)
    worker = Worker(open_store(settings.database_url), settings)
    t = _run_in_thread(worker)
    t.join(CEILING_S)
    assert not t.is_alive()


def test_drain_worker_waits_for_a_running_job_whose_worker_dies_then_runs_it(tmp_path):
    """A job running elsewhere keeps a draining worker alive: if its worker dies, the drain worker
    reaps the expired lease, runs the job, and only then exits."""
    settings = make_settings(tmp_path, lease_s=1.0, heartbeat_s=0.2)
    store = open_store(settings.database_url)
    (job,) = store.submit([NewJob(parse_spec(TINY).to_json())])
    store.claim("ghost-worker", 1.0)  # its worker "dies": the lease is never renewed
    worker = Worker(store, settings)
    t = _run_in_thread(worker)
    time.sleep(0.5)
    assert t.is_alive(), "a drain worker must not exit while a job is running"
    t.join(CEILING_S)
    assert not t.is_alive()
    got = store.get(job.id)
    assert got.state == DONE and got.attempts == 2


def test_cli_exit_when_idle_exits_zero(tmp_path):
    # no warm-up of every kernel specialisation: this test is about drain mode, and on an empty kernel cache the
    # warm-up compiles for minutes (tests/jobs/test_warm.py tests it)
    env = clean_env(tmp_path, DEMQ_DATA_DIR=str(tmp_path / "data"), DEMQ_WORKER_WARM="off")
    r = subprocess.run([sys.executable, "-m", "service.cli", "worker", "--exit-when-idle"], cwd=ROOT, env=env,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "exiting (drain mode)" in r.stderr
    help_text = subprocess.run([sys.executable, "-m", "service.cli", "worker", "--help"], cwd=ROOT, env=env,
                               capture_output=True, text=True, timeout=60).stdout
    assert "--exit-when-idle" in help_text


@pytest.mark.postgres
def test_many_workers_starting_at_once_on_a_fresh_postgres_table():
    """Eight stores created at the same moment on a new table: CREATE TABLE is serialised (advisory
    lock), none fails with UniqueViolation/DuplicateTable."""
    url, prefix = postgres_url(), f"d{uuid.uuid4().hex[:10]}_"
    barrier, errors, stores = threading.Barrier(8), [], []

    def start():
        barrier.wait()
        try:
            stores.append(open_store(url, prefix))
        except Exception as exc:  # noqa: BLE001 - the test reports whatever went wrong
            errors.append(f"{type(exc).__name__}: {exc}")

    threads = [threading.Thread(target=start) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    try:
        assert errors == [] and len(stores) == 8
    finally:
        for s in stores[1:]:
            s.close()
        if stores:
            stores[0].drop_tables()
            stores[0].close()
