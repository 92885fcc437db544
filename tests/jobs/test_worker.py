"""The worker with the fake engine in a real spawned simulation process (SQLite store)."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import h5py
import pytest

from jobs.runner import TEST_CRASH_ENV
from jobs.schema import CANCELLED, DONE, FAILED, QUEUED, RUNNING
from jobs.specs import parse_spec
from jobs.store import NewJob
from jobs.stores import open_store
from jobs.worker import Worker, describe_exit
from tests.jobs.conftest import TINY
from tests.jobs.fake_engine import FAIL_SEED


def _enqueue(store, **keys):
    (job,) = store.submit([NewJob(parse_spec({**TINY, **keys}).to_json())])
    return job


@pytest.fixture
def local(settings):
    store = open_store(settings.database_url)
    yield store, Worker(store, settings)
    store.close()


def _wait(cond, timeout=30.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return
        time.sleep(0.05)
    raise AssertionError("condition not reached in time")


def test_job_runs_to_done_with_result_and_timings(local, settings):
    store, worker = local
    job = _enqueue(store, t_end=0.5)
    seen = []
    worker.on_progress = lambda j, p: seen.append(p["fraction"])
    assert worker.execute(store.claim(worker.owner, settings.lease_s)) == DONE
    got = store.get(job.id)
    assert got.state == DONE and got.progress == 1.0 and got.error is None
    assert got.wall_s > 0.4 and got.cundall > 0 and got.backend == "fake"
    assert Path(got.result_path) == settings.result_path(job.id)
    with h5py.File(got.result_path) as f:
        assert f["observables/kinetic_energy_translational/value"].shape[0] > 1
    assert seen and seen == sorted(seen) and seen[-1] == 1.0
    assert not settings.checkpoint_dir(job.id).exists()


def test_engine_error_fails_the_job_and_the_next_runs(local, settings):
    store, worker = local
    bad, good = _enqueue(store, seed=FAIL_SEED), _enqueue(store)
    worker.execute(store.claim(worker.owner, settings.lease_s))
    worker.execute(store.claim(worker.owner, settings.lease_s))
    assert store.get(bad.id).state == FAILED
    assert store.get(bad.id).error.startswith("InstabilityError: overlap of particle 7")
    assert store.get(good.id).state == DONE


def test_crashing_simulation_fails_readably_and_the_next_runs(local, settings, monkeypatch):
    store, worker = local
    monkeypatch.setenv(TEST_CRASH_ENV, "99")
    crash, good = _enqueue(store, seed=99), _enqueue(store)
    assert worker.execute(store.claim(worker.owner, settings.lease_s)) == FAILED
    assert worker.execute(store.claim(worker.owner, settings.lease_s)) == DONE
    assert store.get(crash.id).error == "simulation process killed by signal SIGSEGV"
    assert store.get(good.id).state == DONE


def test_describe_exit():
    assert describe_exit(-9).startswith("simulation process killed by signal SIGKILL (out of memory?")
    assert describe_exit(3) == "simulation process exited with code 3 without reporting a result"


def test_cancel_of_running_job(local, settings):
    store, worker = local
    job = _enqueue(store, t_end=30.0)  # the fake engine sleeps 30 s unless stopped
    thread = threading.Thread(target=worker.run_forever)
    thread.start()
    try:
        _wait(lambda: store.get(job.id).progress > 0)
        assert store.request_cancel(job.id).cancel_requested
        _wait(lambda: store.get(job.id).state == CANCELLED, timeout=10)
    finally:
        worker.stop()
        thread.join(30)
    assert store.get(job.id).finished_at is not None
    assert not settings.checkpoint_dir(job.id).exists()


def test_stop_releases_running_job_without_counting_the_attempt(local, settings):
    store, worker = local
    job = _enqueue(store, t_end=30.0)
    thread = threading.Thread(target=worker.run_forever)
    thread.start()
    _wait(lambda: store.get(job.id).progress > 0)
    worker.stop()
    thread.join(15)
    assert not thread.is_alive()
    got = store.get(job.id)
    assert (got.state, got.attempts, got.lease_owner) == (QUEUED, 0, None)
    assert (settings.checkpoint_dir(job.id) / "fake.ckpt").exists()  # kept for the next attempt


def test_unresponsive_simulation_is_killed_after_grace(tmp_path, monkeypatch):
    """A simulation that ignores the cancel check is killed after the grace period; job cancelled."""
    from tests.jobs.conftest import make_settings

    settings = make_settings(tmp_path, cancel_grace_s=0.5, engine_run="tests.jobs.fake_engine:run_deaf")
    store = open_store(settings.database_url)
    worker = Worker(store, settings)
    job = _enqueue(store, t_end=30.0)
    thread = threading.Thread(target=worker.run_forever)
    thread.start()
    try:
        _wait(lambda: store.get(job.id).state == RUNNING and store.get(job.id).progress > 0)
        t0 = time.monotonic()
        store.request_cancel(job.id)
        _wait(lambda: store.get(job.id).state == CANCELLED, timeout=10)
        assert time.monotonic() - t0 < 5
    finally:
        worker.stop()
        thread.join(30)
