"""Claims that serve each job as its own scene needs: CPU claims run as a sequence (cheapest first, each job ends
with its own run), fair shares between workers, cancels that reach a running job at once, and the resume step on
the row while a resumed job runs.

The fake engine (tests/jobs/fake_engine.py) runs in real spawned simulation processes; one case runs the real
engine. Waits are for events, with ceilings that only catch hangs (timings belong to bench/; the cancel latency was the
one-off study bench/cancel_latency.py, in git history).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import subprocess
import sys
import threading
import time
import uuid

import pytest

from jobs.packing import Packer, fair_share, particle_steps, sequence_order
from jobs.schema import CANCELLED, DONE, FAILED, QUEUED, RUNNING
from jobs.specs import parse_spec
from jobs.store import NewJob
from jobs.stores import open_store
from jobs.worker import Worker
from tests.jobs.conftest import ROOT, TINY, make_settings, postgres_url
from tests.jobs.fake_engine import ENSEMBLE_TARGET, TARGET


def _enqueue(store, *specs, priority=0):
    return store.submit([NewJob(parse_spec({**TINY, **s}).to_json(), priority) for s in specs])


def _wait(cond, timeout=60.0, what="condition"):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return
        time.sleep(0.02)
    raise AssertionError(f"{what} not reached in time")


@pytest.fixture
def sequencing(tmp_path):
    """A worker with packing on (the fake engine and its ensemble counterpart) on this CPU-only host: CPU claims
    run as sequences (DEMQ_CPU_PACKS=sequence, the default)."""
    settings = make_settings(tmp_path, engine_run_ensemble=ENSEMBLE_TARGET)
    store = open_store(settings.database_url)
    yield store, Worker(store, settings), settings
    store.close()


class _Executing:
    """execute_pack of a claim on a thread; joined on exit."""

    def __init__(self, worker, claim):
        self.outcome: dict = {}
        self.thread = threading.Thread(target=lambda: self.outcome.update(worker.execute_pack(claim)))

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.thread.join(120)
        assert not self.thread.is_alive()


# ---- selection -------------------------------------------------------------------------------------------

def test_a_cpu_claim_takes_any_cpu_job_and_runs_the_cheapest_first(sequencing):
    store, _, _ = sequencing
    jobs = _enqueue(store, {"t_end": 0.4}, {"t_end": 0.1, "precision": "float32"}, {"t_end": 0.2, "n_particles": 80},
                    {"shape": "ellipsoid", "elongation": 1.5, "t_end": 0.05}, {"backend": "cuda"})
    packer = Packer(256, 100, resolve=lambda name, shape: "cuda" if name == "cuda" else "cpu")
    # any shape, precision and size go together on the CPU (one scene in memory at a time: no particle bound);
    # a job for another backend does not
    picked = packer.select(jobs[0], jobs[1:])
    assert [j.id for j in picked] == [j.id for j in jobs[1:4]]
    assert packer.mode([jobs[0], *picked]) == "sequence" and packer.mode([jobs[0]]) == "one"
    assert Packer(256, 100, packer._resolve, "ensemble").mode([jobs[0], *picked]) == "ensemble"
    assert [j.id for j in packer.select(jobs[0], jobs[1:], max_jobs=2)] == [jobs[1].id]
    # cheapest (particle-steps) first; a higher priority before any cost
    assert [j.id for j in sequence_order(jobs[:4])] == [jobs[3].id, jobs[1].id, jobs[2].id, jobs[0].id]
    (urgent,) = _enqueue(store, {"t_end": 0.8}, priority=5)
    assert sequence_order(jobs[:4] + [urgent])[0].id == urgent.id
    # N x steps: the same N and dt, four times the simulated time (rel: the step counts are rounded)
    assert particle_steps(jobs[0]) == pytest.approx(4 * particle_steps(jobs[1]), rel=1e-3)
    assert particle_steps(dataclasses.replace(jobs[0], spec={"n_particles": -1})) == 0.0  # fails at once anyway


def test_fair_share():
    assert fair_share(12, 2) == 6 and fair_share(13, 2) == 7 and fair_share(1, 4) == 1 and fair_share(5, 0) == 5


def test_a_claim_is_capped_at_the_fair_share_of_the_live_workers(sequencing):
    store, worker, _ = sequencing
    jobs = _enqueue(store, *[{"seed": i} for i in range(10)])
    store.register_worker("other-cpu-worker", "elsewhere", 1, ["cpu"])
    store.register_worker("gpu-only-worker", "elsewhere", 2, ["cuda"])   # runs no CPU job: not counted
    claim = worker._next(None)
    assert len(claim) == 5                       # ceil(10 / 2 CPU workers)
    assert len(worker._next(None)) == 3          # ceil(5 / 2)
    store.unregister_worker("other-cpu-worker")
    assert len(worker._next(None)) == 2          # alone: the rest
    assert store.counts().get(QUEUED, 0) == 0 and len(jobs) == 10


# ---- a sequence ------------------------------------------------------------------------------------------

def test_each_job_of_a_cpu_claim_ends_with_its_own_run_cheapest_first(sequencing, caplog):
    store, worker, settings = sequencing
    long, *short = _enqueue(store, {"t_end": 3.0}, {"t_end": 0.4, "seed": 1}, {"t_end": 0.4, "seed": 2},
                            {"t_end": 0.6, "seed": 3})
    claim = worker._next(None)
    assert {j.id for j in claim} == {long.id, *(j.id for j in short)}
    with caplog.at_level(logging.INFO, logger="demq.worker"), _Executing(worker, claim) as run:
        # the short jobs are done, each with its result, while the long one has not started: it waits with the
        # ETA of its own end, not the claim's
        _wait(lambda: all(store.get(j.id).state == DONE for j in short), what="the short jobs done")
        got = store.get(long.id)
        assert got.state == RUNNING and got.phase in ("waiting", "starting", "cooling")
        assert all(settings.result_path(j.id).exists() for j in short)
    assert run.outcome == {j.id: DONE for j in claim}
    assert "running 4 jobs one after another, cheapest first" in caplog.text
    # cheapest first: the short jobs ended in the order of their cost, all before the long one
    ends = {j.id: store.get(j.id).finished_at for j in claim}
    assert ends[short[0].id] < ends[short[2].id] < ends[long.id] and ends[short[1].id] < ends[short[2].id]


def test_a_waiting_job_gets_the_eta_of_its_own_end(sequencing):
    store, worker, _ = sequencing
    first, second, third = _enqueue(store, {"t_end": 2.0}, {"t_end": 3.0, "seed": 1}, {"t_end": 6.0, "seed": 2})
    claim = worker._next(None)
    with _Executing(worker, claim):
        _wait(lambda: store.get(first.id).progress > 0.2 and store.get(third.id).eta_s is not None,
              what="progress of the first job and the ETAs of the others")
        a, b, c = (store.get(j.id) for j in (first, second, third))
        assert (b.phase, c.phase) == ("waiting", "waiting") and b.progress == 0.0
        # each waits for the runs before it: the ETAs grow along the sequence by the jobs' estimated costs
        assert a.eta_s < b.eta_s < c.eta_s
        store.request_cancel(second.id)
        store.request_cancel(third.id)


def test_cancel_of_a_job_waiting_in_a_sequence_ends_it_at_once(sequencing):
    store, worker, settings = sequencing
    running, waiting = _enqueue(store, {"t_end": 2.0}, {"t_end": 4.0, "seed": 1})
    with _Executing(worker, worker._next(None)) as run:
        _wait(lambda: store.get(running.id).progress > 0, what="the first job running")
        store.request_cancel(waiting.id)
        _wait(lambda: store.get(waiting.id).state == CANCELLED, what="the waiting job cancelled")
        assert store.get(running.id).state == RUNNING   # undisturbed
    assert run.outcome == {running.id: DONE, waiting.id: CANCELLED}
    assert not settings.result_path(waiting.id).exists() and not settings.checkpoint_dir(waiting.id).exists()


def test_a_crash_in_a_sequence_fails_the_running_job_only(sequencing, monkeypatch):
    """The process dies (SIGSEGV) in the second job of a sequence: that one is the culprit (it was running), it
    fails; the job done before keeps its result, the one after goes back to the queue to run as usual."""
    from jobs.packing import is_solo
    from jobs.runner import TEST_CRASH_ENV

    store, worker, _ = sequencing
    monkeypatch.setenv(TEST_CRASH_ENV, "4242")
    done, crash, after = _enqueue(store, {"t_end": 0.2}, {"t_end": 0.4, "seed": 4242}, {"t_end": 0.8, "seed": 2})
    assert worker.execute_pack(worker._next(None)) == {done.id: DONE, crash.id: "failed", after.id: "requeued"}
    assert store.get(crash.id).error == "simulation process killed by signal SIGSEGV"
    got = store.get(after.id)
    assert (got.state, got.attempts) == (QUEUED, 0) and not is_solo(got)
    assert store.get(done.id).state == DONE


def test_stop_releases_the_running_and_the_waiting_jobs_of_a_sequence(sequencing):
    store, worker, _ = sequencing
    jobs = _enqueue(store, {"t_end": 30.0}, {"t_end": 40.0, "seed": 1})
    thread = threading.Thread(target=worker.run_forever)
    thread.start()
    try:
        _wait(lambda: store.get(jobs[0].id).progress > 0, what="the first job running")
    finally:
        worker.stop()
        thread.join(60)
    assert not thread.is_alive()
    for j in jobs:
        got = store.get(j.id)
        assert (got.state, got.attempts, got.lease_owner) == (QUEUED, 0, None)


# ---- cancel of a running job --------------------------------------------------------------------------------

def test_a_cancelled_run_deaf_until_its_end_is_killed_its_partial_file_removed_the_rest_requeued(tmp_path):
    """The engine's cancel checks come at its stops, which can be seconds apart (a 20 000-sphere CPU job): the
    worker kills a process that runs no other job's scene after DEMQ_CANCEL_KILL_SECONDS; the job ends cancelled
    with no partial result, and the sequence's jobs that had not started go back to the queue."""
    settings = make_settings(tmp_path, engine_run="tests.jobs.fake_engine:run_deaf",
                             engine_run_ensemble=ENSEMBLE_TARGET, cancel_grace_s=300.0)
    store = open_store(settings.database_url)
    worker = Worker(store, settings)
    deaf, after = _enqueue(store, {"t_end": 60.0}, {"t_end": 90.0, "seed": 1})
    with _Executing(worker, worker._next(None)) as run:
        _wait(lambda: store.get(deaf.id).progress > 0, what="the deaf job running")
        assert (settings.result_path(deaf.id).parent / f"{deaf.id}.h5.part").exists()
        store.request_cancel(deaf.id)
        _wait(lambda: store.get(deaf.id).state == CANCELLED, what="the deaf job cancelled")  # far within the grace
    assert run.outcome == {deaf.id: CANCELLED, after.id: "requeued"}
    assert not (settings.result_path(deaf.id).parent / f"{deaf.id}.h5.part").exists()
    assert not settings.result_path(deaf.id).exists() and not settings.checkpoint_dir(deaf.id).exists()
    got = store.get(after.id)
    assert (got.state, got.attempts, got.error) == (QUEUED, 0, None)
    store.close()


def test_real_engine_cancel_of_a_running_cpu_job_leaves_no_file(tmp_path):
    """A real CPU job of a few thousand spheres, cancelled while its time loop runs: cancelled, no result, no
    partial file, no checkpoints (how soon, for 20 000 spheres, was measured by the one-off study
    bench/cancel_latency.py)."""
    settings = make_settings(tmp_path, engine_run="engine.driver.simulate:run")
    store = open_store(settings.database_url)
    worker = Worker(store, settings)
    (job,) = _enqueue(store, {"n_particles": 3000, "volume_fraction": 0.05, "box_length": 1.0, "t_end": 5.0,
                              "thermalization": 1.0, "backend": "cpu"})
    part = settings.result_path(job.id).parent / f"{job.id}.h5.part"
    with _Executing(worker, worker._next(None)) as run:
        _wait(lambda: store.get(job.id).progress > 0 and part.exists(), timeout=600, what="the job's time loop")
        store.request_cancel(job.id)
        _wait(lambda: store.get(job.id).state == CANCELLED, what="the job cancelled")
    assert run.outcome == {job.id: CANCELLED}
    assert not part.exists() and not settings.result_path(job.id).exists()
    assert not settings.checkpoint_dir(job.id).exists()
    store.close()


# ---- the resume step while running ------------------------------------------------------------------------

def test_resumed_from_step_is_on_the_row_and_in_the_api_json_while_the_resumed_job_runs(tmp_path):
    from service.schemas import JobOut

    settings = make_settings(tmp_path, checkpoint_interval=0.1)
    store = open_store(settings.database_url)
    (job,) = _enqueue(store, {"t_end": 20.0})
    first = Worker(store, settings)
    thread = threading.Thread(target=first.run_forever)
    thread.start()
    try:
        _wait(lambda: (settings.checkpoint_dir(job.id) / "fake.ckpt").exists(), what="a checkpoint")
        assert store.get(job.id).resumed_from_step is None     # a fresh start
    finally:
        first.stop()
        thread.join(60)
    assert store.get(job.id).state == QUEUED
    second = Worker(store, settings)
    thread = threading.Thread(target=second.run_forever)
    thread.start()
    try:
        _wait(lambda: store.get(job.id).resumed_from_step is not None, what="the resume step on the row")
        got = store.get(job.id)
        assert got.state == RUNNING and got.resumed_from_step > 0
        assert JobOut.of(got).model_dump()["resumed_from_step"] == got.resumed_from_step
    finally:
        second.stop()
        thread.join(60)
    store.close()


# ---- several worker processes on one PostgreSQL queue --------------------------------------------------------

def _worker_process(settings, prefix: str, url: str, worker_id: str) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "DEMQ_DATABASE_URL": url, "DEMQ_TABLE_PREFIX": prefix,
           "DEMQ_DATA_DIR": str(settings.data_dir), "DEMQ_ENGINE_RUN": TARGET,
           "DEMQ_ENGINE_RUN_ENSEMBLE": ENSEMBLE_TARGET, "DEMQ_WORKER_ID": worker_id, "DEMQ_POLL_SECONDS": "0.05",
           "DEMQ_HEARTBEAT_SECONDS": "0.3", "DEMQ_LEASE_SECONDS": "5", "DEMQ_PROGRESS_SECONDS": "0.1",
           "DEMQ_WORKER_STANDBY": "off"}
    return subprocess.Popen([sys.executable, "-m", "service.cli", "worker"], cwd=ROOT, env=env,
                            start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


@pytest.mark.postgres
def test_two_worker_processes_share_twelve_cpu_jobs_on_postgresql(tmp_path):
    """12 CPU jobs, two `demq worker` processes on one PostgreSQL queue: neither runs more than 8 of them (before
    the fair share, the first worker packed 11 and the second ran one)."""
    import signal

    url, prefix = postgres_url(), f"t{uuid.uuid4().hex[:10]}_"
    settings = make_settings(tmp_path)
    store = open_store(url, prefix)
    store.create_tables()
    procs = [_worker_process(settings, prefix, url, f"w{i}") for i in range(2)]
    try:
        _wait(lambda: {w.worker_id for w in store.live_workers(60)} == {"w0", "w1"}, timeout=120,
              what="both workers registered")
        jobs = _enqueue(store, *[{"t_end": 0.3 + 0.05 * i, "seed": i} for i in range(12)])
        _wait(lambda: store.counts().get(DONE, 0) == 12, timeout=120, what="every job done")
    finally:
        for p in procs:
            p.send_signal(signal.SIGTERM)
        logs = [p.communicate(timeout=60)[1] for p in procs]
    assert all(p.returncode == 0 for p in procs), logs
    ran = [{j.id for j in jobs if f"job {j.id}: done" in log} for log in logs]
    assert len(ran[0]) + len(ran[1]) == 12 and not ran[0] & ran[1]
    assert max(len(r) for r in ran) <= 8, [len(r) for r in ran]
    assert store.live_workers(60) == []      # both unregistered on their clean exit
    store.drop_tables()
    store.close()


# ---- the store's cancel poll and the new settings ----------------------------------------------------------

def test_cancel_requests_reads_the_requested_ones_of_the_given_jobs(store):
    jobs = store.submit([NewJob(parse_spec({**TINY, "seed": i}).to_json()) for i in range(4)])
    store.claim_ids("w", 10, [j.id for j in jobs])
    store.request_cancel(jobs[1].id)
    store.request_cancel(jobs[3].id)
    assert store.cancel_requests([j.id for j in jobs[:3]]) == {jobs[1].id}
    assert store.cancel_requests([j.id for j in jobs]) == {jobs[1].id, jobs[3].id}
    assert store.cancel_requests([]) == set() and store.cancel_requests(["nope"]) == set()


def test_settings_of_claims_cancels_and_warm_up():
    from jobs.settings import Settings

    s = Settings.from_env(environ={})
    assert (s.cpu_packs, s.ensemble_cost_ratio, s.cancel_kill_s, s.cancel_poll_s, s.warm) == \
        ("sequence", 4.0, 0.3, 0.2, "on")
    assert s.warm_enabled and not Settings.from_env(environ={"DEMQ_WORKER_WARM": "off"}).warm_enabled
    assert not Settings.from_env(environ={"DEMQ_ENGINE_RUN": TARGET}).warm_enabled   # another engine: no warm-up
    for env, message in [({"DEMQ_CPU_PACKS": "mix"}, r"DEMQ_CPU_PACKS = 'mix' must be one of sequence, ensemble"),
                         ({"DEMQ_WORKER_WARM": "auto"}, r"DEMQ_WORKER_WARM = 'auto' must be one of on, off"),
                         ({"DEMQ_ENSEMBLE_COST_RATIO": "0.5"}, r"DEMQ_ENSEMBLE_COST_RATIO = 0.5 must be >= 1"),
                         ({"DEMQ_CANCEL_POLL_SECONDS": "0"}, r"DEMQ_CANCEL_POLL_SECONDS = 0.0 must be positive"),
                         ({"DEMQ_CANCEL_KILL_SECONDS": "-1"}, r"DEMQ_CANCEL_KILL_SECONDS = -1.0 must be >= 0")]:
        with pytest.raises(ValueError, match=message):
            Settings.from_env(environ=env)


def test_lanes_run_several_cpu_claims_at_once_each_with_its_share_of_the_cores(tmp_path, caplog, monkeypatch):
    """DEMQ_WORKER_LANES: a CPU worker runs several claims at once (its lanes, each registered so that the fair share
    divides the queue among them), each job reported done as its own run ends, every job done once; the lanes'
    simulation processes get cores / lanes Numba threads; stopping the worker ends every lane."""
    monkeypatch.setattr(os, "cpu_count", lambda: 6)
    settings = make_settings(tmp_path, engine_run_ensemble=ENSEMBLE_TARGET, lanes="3", standby="off")
    store = open_store(settings.database_url)
    worker = Worker(store, settings)
    jobs = _enqueue(store, *({"t_end": 0.6, "seed": s} for s in range(9)))
    with caplog.at_level(logging.INFO, logger="demq.worker"):
        worker.run_forever(exit_when_idle=True)
    got = [store.get(j.id) for j in jobs]
    assert [g.state for g in got] == [DONE] * 9 and all(g.attempts == 1 for g in got)
    assert "3 lanes (claims at once), 2 Numba threads each" in caplog.text
    assert len(worker._lanes) == 2
    assert {g.device for g in got} == {"test double, NUMBA_NUM_THREADS=2"}   # each lane's processes: 6 cores / 3
    spans = sorted((g.started_at, g.finished_at) for g in got)
    at_once = max(sum(a <= t < b for a, b in spans) for t, _ in spans)
    assert at_once >= 2, spans                       # claims of different lanes overlapped in time
    assert store.live_workers(settings.lease_s) == []   # every lane left the worker table
    store.close()


def test_lanes_setting():
    from jobs.settings import Settings

    assert Settings.from_env(environ={}).lanes == "auto"
    assert Settings.from_env(environ={"DEMQ_WORKER_LANES": "4"}).lane_count(("cpu",)) == 4
    with pytest.raises(ValueError, match="DEMQ_WORKER_LANES = 'many' must be 'auto' or a whole number >= 1"):
        Settings.from_env(environ={"DEMQ_WORKER_LANES": "many"})
    auto = Settings.from_env(environ={})
    assert auto.lane_count(("cpu", "cuda")) == 1             # a GPU worker: its claims share the GPU
    cores = os.cpu_count() or 1
    assert auto.lane_count(("cpu",)) == (1 if cores <= 3 else cores)


def test_a_sigkilled_worker_with_lanes_leaves_every_job_done_exactly_once(tmp_path):
    """kill -9 of a `demq worker` whose two lanes each run a claim: every lease expires, the next worker resumes the
    jobs that ran from their checkpoints and runs the rest, and each of the four jobs ends done once."""
    import signal

    from tests.service.test_durability import _checkpointed_past_start, start_worker, stop

    settings = make_settings(tmp_path, lease_s=2.0, heartbeat_s=0.3)
    store = open_store(settings.database_url)
    jobs = _enqueue(store, *({"t_end": 1.5, "seed": s} for s in range(4)))

    def mid_run():
        rows = [store.get(j.id) for j in jobs]
        return [r for r, j in zip(rows, jobs)
                if 0 < (r.progress or 0) < 1 and _checkpointed_past_start(settings.checkpoint_dir(j.id))]

    first = start_worker(settings, TARGET, DEMQ_WORKER_LANES="2", DEMQ_WORKER_STANDBY="off")
    try:
        _wait(lambda: len(mid_run()) >= 2, what="two jobs mid-run at once, one in each lane")
    finally:
        os.kill(first.pid, signal.SIGKILL)
        first.wait(10)
    claimed = [store.get(j.id).state == RUNNING for j in jobs]     # the lanes' fair shares: 2 and 1 of the 4
    assert sum(claimed) >= 2 and all(store.get(j.id).state in (RUNNING, QUEUED) for j in jobs)
    second = start_worker(settings, TARGET, DEMQ_WORKER_LANES="1")
    try:
        _wait(lambda: all(store.get(j.id).state in (DONE, FAILED, CANCELLED) for j in jobs), what="all four ended")
    finally:
        assert stop(second) == 0
    got = [store.get(j.id) for j in jobs]
    assert [g.state for g in got] == [DONE] * 4, [g.error for g in got]
    assert [g.attempts for g in got] == [2 if c else 1 for c in claimed]   # a killed claim counts its attempt
    assert sum((g.resumed_from_step or 0) > 0 for g in got) >= 2   # the two that ran resumed from checkpoints
    store.close()
