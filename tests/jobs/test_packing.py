"""The worker packs compatible queued jobs into one ensemble run and keeps every per-job guarantee.

Most cases use the fake ensemble engine (tests/jobs/fake_engine.py: run_ensemble) in a real spawned
simulation process; the last ones run the real engine on tiny CPU scenes. A claim of several jobs runs as one
ensemble on the GPU; on the CPU it runs as a sequence by default (tests/jobs/test_claims.py), so these cases,
which pin the ensemble mode on this CPU-only host, set DEMQ_CPU_PACKS=ensemble.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import threading
import time
from pathlib import Path

import h5py
import pytest

from jobs.packing import SOLO, Packer, is_solo
from jobs.runner import TEST_CRASH_ENV
from jobs.schema import CANCELLED, DONE, FAILED, QUEUED, RUNNING
from jobs.specs import parse_spec
from jobs.store import NewJob
from jobs.stores import open_store
from jobs.worker import Worker
from tests.jobs.conftest import TINY, make_settings
from tests.jobs.fake_engine import ENSEMBLE_TARGET, FAIL_SEED
from tests.waiting import wait_for

REAL, REAL_ENSEMBLE = "engine.driver.simulate:run", "engine.driver.ensemble:run_ensemble"


def _enqueue(store, *specs):
    return store.submit([NewJob(parse_spec({**TINY, **s}).to_json()) for s in specs])


def _wait(cond, what="condition", activity=None):
    wait_for(cond, what, activity=activity)


def _jobs_activity(store, jobs):
    """What changes while the jobs run: their states, phases, steps and attempts (a wait's hang detector)."""
    return lambda: [(got.state, got.phase, got.step, got.attempts) for got in (store.get(j.id) for j in jobs)]


@pytest.fixture
def packing(tmp_path):
    settings = make_settings(tmp_path, engine_run_ensemble=ENSEMBLE_TARGET, cpu_packs="ensemble")
    store = open_store(settings.database_url)
    yield store, Worker(store, settings), settings
    store.close()


class _Running:
    """run_forever in a thread; stopped and joined on exit."""

    def __init__(self, worker):
        self.worker = worker
        self.thread = threading.Thread(target=worker.run_forever)

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.worker.stop()
        self.thread.join(60)
        assert not self.thread.is_alive()


# ---- the store's pack operations, on SQLite and PostgreSQL ---------------------------------------------

def _raw(store, n, priority=0):
    return store.submit([NewJob(json.dumps({"seed": i}), priority) for i in range(n)])


def test_peek_and_claim_ids(store):
    low = _raw(store, 3)
    (high,) = _raw(store, 1, priority=5)
    assert [j.id for j in store.peek_queued(10)] == [high.id] + [j.id for j in low]  # claim order
    assert [j.id for j in store.peek_queued(2)] == [high.id, low[0].id]
    assert all(j.state == QUEUED for j in store.peek_queued(10))
    store.claim("other", 10, job_id=low[1].id)
    got = store.claim_ids("w", 10, [low[2].id, low[1].id, low[0].id, "nope"])
    assert [j.id for j in got] == [low[2].id, low[0].id]  # the one another worker holds is skipped
    assert all(j.state == RUNNING and j.lease_owner == "w" and j.attempts == 1 for j in got)
    assert store.claim_ids("w", 10, []) == [] and store.claim_ids("w2", 10, [low[0].id]) == []
    assert [j.id for j in store.peek_queued(10)] == [high.id]


def test_concurrent_pack_claims_never_share_a_job(store):
    jobs = _raw(store, 40)
    ids = [j.id for j in jobs]
    got: dict = {}

    def claimer(name, order):
        got[name] = [j.id for j in store.claim_ids(name, 10, order)]

    threads = [threading.Thread(target=claimer, args=(f"w{i}", ids[::1 if i % 2 else -1])) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    claimed = [i for v in got.values() for i in v]
    assert sorted(claimed) == sorted(ids)  # every job once, none twice


def test_heartbeat_many_lease_cancel_progress_and_release_note(store):
    a, b, c = _raw(store, 3)
    store.claim_ids("w", 10, [a.id, b.id, c.id])
    store.request_cancel(b.id)
    with store.engine.begin() as conn:
        conn.execute(store.table.update().where(store.table.c.id == c.id).values(lease_owner="thief"))
    answer = store.heartbeat_many([a.id, b.id, c.id], "w", 10, {a.id: {"progress": 0.5, "eta_s": 2.0}})
    assert answer == {a.id: False, b.id: True}  # c's lease is lost
    assert store.get(a.id).progress == 0.5 and store.get(b.id).progress == 0.0
    assert store.release(a.id, "w", error=SOLO + "its pack died")
    assert store.release(b.id, "w", error=SOLO + "its pack died")
    got_a, got_b = store.get(a.id), store.get(b.id)
    assert (got_a.state, got_a.attempts) == (QUEUED, 0) and is_solo(got_a)
    assert got_b.state == CANCELLED and got_b.error is None  # a cancelled job carries no requeue note


def test_settings_defaults_and_checks(tmp_path):
    from jobs.settings import Settings

    s = Settings.from_env(environ={})
    assert (s.ensemble_max_jobs, s.ensemble_max_particles) == (256, 4 * 2**20) and s.packing
    assert s.engine_run_ensemble == "engine.driver.ensemble:run_ensemble"
    assert not make_settings(tmp_path).packing  # a custom engine without an ensemble engine: no packing
    assert not Settings.from_env(environ={"DEMQ_ENSEMBLE_MAX_JOBS": "1"}).packing
    with pytest.raises(ValueError, match=r"DEMQ_ENSEMBLE_MAX_JOBS = 0 must be >= 1 \(1 disables packing\)"):
        Settings.from_env(environ={"DEMQ_ENSEMBLE_MAX_JOBS": "0"})
    with pytest.raises(ValueError, match=r"DEMQ_ENSEMBLE_MAX_PARTICLES = 1 must be >= 2"):
        Settings.from_env(environ={"DEMQ_ENSEMBLE_MAX_PARTICLES": "1"})


def test_pack_selection_rules(packing):
    store, _, _ = packing
    jobs = _enqueue(store, {}, {"seed": 1, "e_n": 0.5, "n_particles": 100}, {"precision": "float32"},
                    {"backend": "cuda"}, {"seed": 2, "volume_fraction": 0.02},
                    {"shape": "ellipsoid", "elongation": 1.5, "e_t": -1.0}, {"seed": 3}, {"seed": 4})
    first, rest = jobs[0], jobs[1:]
    packer = Packer(max_jobs=256, max_particles=10**6, resolve=lambda name, shape: "cuda" if name == "cuda" else "cpu",
                    cpu_mode="ensemble")
    picked = [j.id for j in packer.select(first, rest)]
    assert picked == [jobs[1].id, jobs[4].id, jobs[6].id, jobs[7].id]  # any N, e_n, phi, seed; same shape,
    #                                                                    precision, resolved backend
    assert [j.id for j in Packer(3, 10**6, packer._resolve, "ensemble").select(first, rest)] == [jobs[1].id,
                                                                                                 jobs[4].id]
    assert [j.id for j in packer.select(first, rest, max_jobs=3)] == [jobs[1].id, jobs[4].id]  # a fair share
    # particles: 64 + 100 > 150, so job 1 is skipped and job 4 taken (128); then 192 > 150
    assert [j.id for j in Packer(256, 150, packer._resolve, "ensemble").select(first, rest)] == [jobs[4].id]
    assert Packer(1, 10**6, packer._resolve, "ensemble").select(first, rest) == []
    solo = dataclasses.replace(jobs[6], error=SOLO + "its pack died")
    assert is_solo(solo) and Packer(256, 10**6, packer._resolve, "ensemble").select(solo, rest) == []
    assert solo.id not in [j.id for j in packer.select(first, [solo])]
    # an ensemble pack groups jobs within a factor 4 of the first one's particle-steps (N x steps): a small job does
    # not wait for a large one's scene, nor a large one hold a pack of small ones
    costly = dataclasses.replace(jobs[6], spec={**jobs[6].spec, "t_end": 5 * jobs[6].spec["t_end"]})
    cheap = dataclasses.replace(jobs[7], spec={**jobs[7].spec, "t_end": jobs[7].spec["t_end"] / 5})
    near = dataclasses.replace(jobs[7], id="near", spec={**jobs[7].spec, "t_end": 3 * jobs[7].spec["t_end"]})
    assert [j.id for j in packer.select(first, [costly, cheap, near])] == [near.id]
    # a job that asks for a CPU-built Verlet list (a list mode of Skorych & Dosta 2022: one scene) is never packed
    cpu_list = dataclasses.replace(jobs[6], spec={**jobs[6].spec, "list_mode": "cpu-pipelined"})
    assert packer.key(cpu_list) is None and cpu_list.id not in [j.id for j in packer.select(first, [cpu_list])]
    assert packer.key(dataclasses.replace(jobs[6], spec={**jobs[6].spec, "list_mode": "auto"})) is not None


def test_compatible_jobs_run_as_one_pack_each_with_its_own_result(packing, caplog):
    store, worker, settings = packing
    # costs (particle-steps) within a factor 4 of a's: b has half, c 5/8 of a's (a pack groups similar costs)
    a, b, c, other = _enqueue(store, {"t_end": 0.4}, {"seed": 1, "e_n": 0.6, "t_end": 0.2},
                              {"seed": 2, "n_particles": 80, "t_end": 0.2}, {"precision": "float32", "t_end": 0.4})
    seen: dict = {}
    worker.on_progress = lambda job, p: seen.setdefault(job.id, []).append(p["fraction"])
    claim = worker._next(None)
    assert [j.id for j in claim] == [a.id, b.id, c.id]
    assert all(store.get(j.id).state == RUNNING and store.get(j.id).lease_owner == worker.owner for j in claim)
    with caplog.at_level(logging.INFO, logger="demq.worker"):
        outcome = worker.execute_pack(claim)
    assert outcome == {a.id: DONE, b.id: DONE, c.id: DONE}
    assert "packing 3 jobs into one ensemble run" in caplog.text
    for job in (a, b, c):
        got = store.get(job.id)
        assert got.state == DONE and got.progress == 1.0 and got.error is None and got.backend == "fake"
        assert Path(got.result_path) == settings.result_path(job.id)
        with h5py.File(got.result_path) as f:
            assert f["observables/temperature_translational/value"].shape[0] > 1
        assert seen[job.id] == sorted(seen[job.id]) and seen[job.id][-1] == 1.0
        assert not settings.checkpoint_dir(job.id).exists()
    assert store.get(other.id).state == QUEUED  # float32: not in this pack
    assert [j.id for j in worker._next(None)] == [other.id]


def test_a_pack_is_supervised_with_one_cancel_read_per_poll(tmp_path):
    """The supervisor's work does not grow with the pack's jobs per poll: one read of the cancel requests for the
    whole pack every DEMQ_CANCEL_POLL_SECONDS (a query per job per poll had kept a 256-job pack waiting on its
    pipe for 40 s on a GPU host)."""
    settings = make_settings(tmp_path, engine_run_ensemble=ENSEMBLE_TARGET, cpu_packs="ensemble",
                             cancel_poll_s=0.05, heartbeat_s=2.0, lease_s=20.0)
    store = open_store(settings.database_url)
    worker = Worker(store, settings)
    jobs = _enqueue(store, *({"t_end": 1.0, "seed": s} for s in range(12)))
    reads = []
    cancel_requests = store.cancel_requests
    store.cancel_requests = lambda ids: reads.append(len(ids)) or cancel_requests(ids)
    claim = worker._next(None)
    assert len(claim) == 12
    t0 = time.monotonic()
    assert worker.execute_pack(claim) == {j.id: DONE for j in jobs}
    supervised = time.monotonic() - t0
    # each read asks for every job still running: the whole pack until its results come in, one by one, at the end
    # (a poll that lands among them reads the rest); a read per job would ask for one
    assert reads and reads[0] == 12 and reads == sorted(reads, reverse=True), reads
    # one read per poll over the pack's supervision (about a second of fake steps, longer on a loaded machine): a
    # read per job and poll would be 12 times as many
    assert len(reads) <= 2 + supervised / settings.cancel_poll_s, (len(reads), supervised)
    store.close()


def test_the_jobs_whose_ends_arrive_together_are_written_in_one_transaction(packing):
    from jobs.worker import _Slot

    store, worker, settings = packing
    _enqueue(store, {"seed": 1}, {"seed": 2}, {"seed": 3})
    claim = worker._next(None)
    slots = [_Slot(j, settings.result_path(j.id), settings.checkpoint_dir(j.id)) for j in claim]
    summary = {"loop_s": 0.5, "job_wall_s": 0.6, "cundall": 1e6, "backend": "fake", "device": "cpu",
               "resumed_from_step": None}
    for slot in slots:
        slot.final = ("done", summary)
    slots[2].final = ("error", "InstabilityError: overlap of particle 7")
    calls, finish_many = [], store.finish_many
    store.finish_many = lambda owner, ends: calls.append([e[0] for e in ends]) or finish_many(owner, ends)
    worker._conclude_all(slots)
    assert calls[0] == [claim[0].id, claim[1].id]      # the two done in one call (then the failed one alone)
    got = [store.get(j.id) for j in claim]
    assert [g.state for g in got] == [DONE, DONE, FAILED] and [x.outcome for x in slots] == [DONE, DONE, FAILED]
    assert got[0].loop_s == 0.5 and got[0].result_path == str(settings.result_path(claim[0].id))
    assert got[2].error == "InstabilityError: overlap of particle 7"


def test_cancel_one_job_the_rest_of_the_pack_finishes(packing):
    store, worker, settings = packing
    a, b, c = _enqueue(store, {"t_end": 3.0}, {"t_end": 3.0, "seed": 1}, {"t_end": 3.0, "seed": 2})
    with _Running(worker):
        _wait(lambda: store.get(b.id).progress > 0.1, what="the pack running")
        store.request_cancel(b.id)
        _wait(lambda: store.get(b.id).state == CANCELLED, what="b cancelled")
        assert store.get(a.id).state == RUNNING and store.get(c.id).state == RUNNING  # undisturbed
        _wait(lambda: store.get(a.id).state == DONE and store.get(c.id).state == DONE, what="a, c done")
    assert store.get(b.id).result_path is None and not settings.result_path(b.id).exists()
    assert not settings.checkpoint_dir(b.id).exists()
    assert all(store.get(j.id).attempts == 1 for j in (a, b, c))


def test_failing_job_fails_alone(packing):
    store, worker, _ = packing
    a, bad, c = _enqueue(store, {"t_end": 0.5}, {"t_end": 0.5, "seed": FAIL_SEED}, {"t_end": 0.5, "seed": 2})
    outcome = worker.execute_pack(worker._next(None))
    assert outcome == {a.id: DONE, bad.id: FAILED, c.id: DONE}
    assert store.get(bad.id).error.startswith("InstabilityError: overlap of particle 7")


def test_crash_of_a_pack_requeues_its_jobs_to_run_alone(packing, monkeypatch):
    """A signal kills the pack's process: no job can be blamed, so each runs alone next; then only the
    culprit fails."""
    store, worker, _ = packing
    monkeypatch.setenv(TEST_CRASH_ENV, "4242")
    a, crash, c = _enqueue(store, {"t_end": 0.5}, {"t_end": 0.5, "seed": 4242}, {"t_end": 0.5, "seed": 2})
    outcome = worker.execute_pack(worker._next(None))
    assert outcome == {a.id: "requeued", crash.id: "requeued", c.id: "requeued"}
    for job in (a, crash, c):
        got = store.get(job.id)
        assert (got.state, got.attempts) == (QUEUED, 0) and is_solo(got)
        assert "killed by signal SIGSEGV" in got.error
    for _ in range(3):
        (one,) = worker._next(None)  # solo jobs are never packed
        worker.execute_pack([one])
    assert store.get(crash.id).state == FAILED
    assert store.get(crash.id).error == "simulation process killed by signal SIGSEGV"
    assert store.get(a.id).state == DONE and store.get(c.id).state == DONE and store.get(a.id).error is None


def test_stop_releases_every_job_of_the_pack(packing):
    store, worker, settings = packing
    jobs = _enqueue(store, {"t_end": 30.0}, {"t_end": 30.0, "seed": 1})
    with _Running(worker):
        _wait(lambda: all(store.get(j.id).progress > 0 for j in jobs), what="the pack running")
    for j in jobs:
        got = store.get(j.id)
        assert (got.state, got.attempts, got.lease_owner) == (QUEUED, 0, None)
        assert (settings.checkpoint_dir(j.id) / "fake.ckpt").exists()  # kept for the next attempt


def test_lost_lease_of_one_job_stops_only_its_scene(packing):
    store, worker, _ = packing
    a, b = _enqueue(store, {"t_end": 2.0}, {"t_end": 2.0, "seed": 1})
    with _Running(worker):
        _wait(lambda: store.get(b.id).progress > 0.1, what="the pack running")
        with store.engine.begin() as conn:  # another worker took b over (its lease had expired)
            conn.execute(store.table.update().where(store.table.c.id == b.id).values(lease_owner="thief"))
        _wait(lambda: store.get(a.id).state == DONE, what="a done")
    got = store.get(b.id)
    assert (got.state, got.lease_owner) == (RUNNING, "thief") and got.progress < 1.0  # untouched by us


def test_two_packing_workers_run_every_job_once(tmp_path, caplog):
    settings = make_settings(tmp_path, engine_run_ensemble=ENSEMBLE_TARGET, ensemble_max_jobs=4, cpu_packs="ensemble")
    store = open_store(settings.database_url)
    jobs = _enqueue(store, *[{"t_end": 0.2, "seed": 100 + i} for i in range(24)])
    workers = [Worker(open_store(settings.database_url), settings) for _ in range(2)]
    with caplog.at_level(logging.INFO, logger="demq.worker"), _Running(workers[0]), _Running(workers[1]):
        _wait(lambda: store.counts().get(DONE, 0) == len(jobs), what="every job done")
    assert all(store.get(j.id).attempts == 1 for j in jobs)
    packs = [ln for ln in caplog.text.splitlines() if "into one ensemble run" in ln]
    assert packs and all("packing 4 jobs" in ln or "packing 3 jobs" in ln or "packing 2 jobs" in ln
                         for ln in packs)
    assert sorted(p.name for p in settings.results_dir.glob("*.h5")) == sorted(f"{j.id}.h5" for j in jobs)
    for w in workers:
        w.store.close()
    store.close()


def test_scene_deaf_to_cancel_ends_its_job_without_killing_the_pack(tmp_path):
    settings = make_settings(tmp_path, engine_run_ensemble="tests.jobs.test_packing:deaf_ensemble",
                             cancel_grace_s=0.5, cpu_packs="ensemble")
    store = open_store(settings.database_url)
    worker = Worker(store, settings)
    a, b = _enqueue(store, {"t_end": 4.0}, {"t_end": 4.0, "seed": 1})
    with _Running(worker):
        _wait(lambda: store.get(b.id).progress > 0.1, what="the pack running")
        store.request_cancel(b.id)
        _wait(lambda: store.get(b.id).state == CANCELLED, what="b cancelled after the grace")
        assert store.get(a.id).state == RUNNING
        _wait(lambda: store.get(a.id).state == DONE, what="a done")
    # b's scene ran to its end regardless: its late result and checkpoints are removed, b stays cancelled
    assert store.get(b.id).state == CANCELLED and store.get(b.id).result_path is None
    assert not settings.result_path(b.id).exists() and not settings.checkpoint_dir(b.id).exists()
    store.close()


def deaf_ensemble(specs, outputs, **kwargs):
    """The fake ensemble engine with cancel checks that never fire (a scene stuck in a kernel)."""
    from tests.jobs.fake_engine import run_ensemble

    return run_ensemble(specs, outputs, **{**kwargs, "should_cancel": None})


# ---- the real engine -------------------------------------------------------------------------------------

#: tests/engine/test_simulate.py's blow-up (overlap beyond the limit)
UNSTABLE = {"velocity_rms": 1.2, "stiffness": 1e6, "overlap_limit": 0.02, "thermalization": 0.5, "t_end": 0.1}


def test_real_engine_pack_done_cancelled_and_failed_jobs(tmp_path):
    # one pack of jobs of very different costs (the job to cancel runs longest): no cost bound
    settings = make_settings(tmp_path, engine_run=REAL, engine_run_ensemble=REAL_ENSEMBLE, cpu_packs="ensemble",
                             ensemble_cost_ratio=1e9)
    assert settings.packing
    store = open_store(settings.database_url)
    worker = Worker(store, settings)
    done, cancel, bad, done2 = _enqueue(store, {"t_end": 0.05, "e_n": 0.7},
                                        {"t_end": 2.0, "seed": 1, "n_particles": 48},
                                        {**UNSTABLE, "seed": 3},
                                        {"t_end": 0.03, "seed": 2, "volume_fraction": 0.03, "e_t": -1.0})
    with _Running(worker):
        _wait(lambda: store.get(cancel.id).progress > 0.05, what="the pack running",
              activity=_jobs_activity(store, (done, cancel, bad, done2)))
        store.request_cancel(cancel.id)
        _wait(lambda: all(store.get(j.id).state not in (QUEUED, RUNNING) for j in (done, cancel, bad, done2)),
              what="every job ended", activity=_jobs_activity(store, (done, cancel, bad, done2)))
    assert store.get(cancel.id).state == CANCELLED and not settings.result_path(cancel.id).exists()
    assert store.get(bad.id).state == FAILED
    assert store.get(bad.id).error.startswith("InstabilityError: overlap of")
    for job in (done, done2):
        got = store.get(job.id)
        assert got.state == DONE, got.error
        assert got.backend == "cpu" and got.cundall > 0
        with h5py.File(got.result_path) as f:
            assert f["parameters"].attrs["ensemble_size"] == 4  # one ensemble run of all four jobs
            assert f["observables/kinetic_energy_translational/value"].shape[0] > 1
    store.close()


def test_sigkilled_packing_worker_every_job_resumes_from_its_checkpoint(tmp_path):
    """`demq worker` packs two real-engine jobs and is SIGKILLed mid-run: both leases expire, the next
    worker packs them again and each scene resumes from its own checkpoint."""
    import os
    import signal

    from tests.service.test_durability import _checkpointed_past_start, start_worker, stop

    settings = make_settings(tmp_path, lease_s=2.0, heartbeat_s=0.3)
    store = open_store(settings.database_url)
    jobs = _enqueue(store, {"t_end": 1.0, "seed": 1}, {"t_end": 0.8, "seed": 2, "e_n": 0.6})
    env = {"DEMQ_ENGINE_RUN_ENSEMBLE": REAL_ENSEMBLE, "DEMQ_CPU_PACKS": "ensemble", "DEMQ_WORKER_WARM": "off"}
    first = start_worker(settings, REAL, **env)
    try:
        _wait(lambda: all(_checkpointed_past_start(settings.checkpoint_dir(j.id)) for j in jobs),
              what="checkpoints of both jobs", activity=_jobs_activity(store, jobs))
    finally:
        os.kill(first.pid, signal.SIGKILL)
        first.wait(10)
    assert all(store.get(j.id).state == RUNNING for j in jobs)
    # the killed worker's row ages out with its leases; until then the fair share would count it live and the next
    # worker would claim one job of the two (a race this test is not about)
    _wait(lambda: not store.live_workers(settings.lease_s), what="the killed worker's row to age out")
    second = start_worker(settings, REAL, **env)
    try:
        _wait(lambda: all(store.get(j.id).state in (DONE, FAILED) for j in jobs), what="both done",
              activity=_jobs_activity(store, jobs))
    finally:
        assert stop(second) == 0
    for j in jobs:
        got = store.get(j.id)
        assert got.state == DONE, got.error
        assert got.attempts == 2 and got.resumed_from_step > 0
        with h5py.File(got.result_path) as f:
            assert f["parameters"].attrs["ensemble_size"] == 2
            times = f["observables/kinetic_energy_translational/time"][()]
        assert len(times) > 1 and (times[1:] > times[:-1]).all()  # one series, no repeated records
    store.close()
