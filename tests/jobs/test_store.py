"""The store contract, run against SQLite and the real PostgreSQL."""

from __future__ import annotations

import json
import threading
import time

import pytest

from jobs.schema import CANCELLED, DONE, FAILED, QUEUED, RUNNING
from jobs.store import LeaseLost, NewJob
from jobs.stores import open_store


def _submit(store, n=1, priority=0, batch_id=None):
    return store.submit([NewJob(json.dumps({"seed": i}), priority) for i in range(n)], batch_id=batch_id)


def test_submit_get_list_counts(store):
    a = _submit(store, 3, batch_id="b1")
    b = _submit(store, 2)
    assert [j.state for j in a + b] == [QUEUED] * 5
    assert store.get(a[0].id).spec == {"seed": 0}
    assert store.get("nope") is None
    items, total = store.list(batch_id="b1")
    assert total == 3 and [j.id for j in items] == [j.id for j in a]
    page, total = store.list(limit=2, offset=2)
    assert total == 5 and [j.id for j in page] == [a[2].id, b[0].id]
    store.claim("w", 10)
    assert store.counts() == {QUEUED: 4, RUNNING: 1}
    assert store.list(state=RUNNING)[1] == 1


def test_claim_order_priority_then_fifo_and_specific(store):
    low = _submit(store, 2)
    high = _submit(store, 1, priority=5)
    picked = store.claim("w", 10, job_id=low[1].id)
    assert picked.id == low[1].id and picked.state == RUNNING and picked.attempts == 1
    assert store.claim("w", 10).id == high[0].id
    assert store.claim("w", 10).id == low[0].id
    assert store.claim("w", 10) is None
    assert store.claim("w", 10, job_id=low[0].id) is None  # already running


def test_heartbeat_progress_cancel_and_lease_owner(store):
    (job,) = _submit(store)
    store.claim("w1", 10)
    assert store.heartbeat(job.id, "w1", 10, {"progress": 0.25, "eta_s": 3.0}) is False
    got = store.get(job.id)
    assert got.progress == 0.25 and got.eta_s == 3.0 and got.lease_expires_at > time.time() + 5
    with pytest.raises(LeaseLost):
        store.heartbeat(job.id, "w2", 10)
    assert store.request_cancel(job.id).state == RUNNING
    assert store.heartbeat(job.id, "w1", 10) is True
    assert store.finish(job.id, "w2", CANCELLED) is False
    assert store.finish(job.id, "w1", CANCELLED) is True
    assert store.get(job.id).state == CANCELLED and store.get(job.id).lease_owner is None


def test_cancel_queued_is_immediate(store):
    (job,) = _submit(store)
    assert store.request_cancel(job.id).state == CANCELLED
    assert store.claim("w", 10) is None
    assert store.request_cancel("nope") is None


def test_release_returns_job_without_counting_the_attempt(store):
    a, b = _submit(store, 2)
    store.claim("w", 10)
    assert store.release(a.id, "w") is True
    got = store.get(a.id)
    assert got.state == QUEUED and got.attempts == 0 and got.lease_owner is None
    store.claim("w", 10)  # a again (FIFO)
    store.request_cancel(a.id)
    store.release(a.id, "w")
    assert store.get(a.id).state == CANCELLED  # a cancel that arrived while running is honoured


def test_finish_done_records_result(store):
    (job,) = _submit(store)
    store.claim("w", 10)
    assert store.finish(job.id, "w", DONE, result_path="/r.h5", loop_s=2.0, job_wall_s=2.5, cundall=1e6, error=None,
                        progress=1.0)
    got = store.get(job.id)
    assert (got.state, got.result_path, got.cundall, got.progress) == (DONE, "/r.h5", 1e6, 1.0)
    assert (got.loop_s, got.job_wall_s) == (2.0, 2.5)
    assert got.finished_at >= got.started_at >= got.created_at
    with pytest.raises(ValueError):
        store.finish(job.id, "w", RUNNING)


def test_finish_many_ends_a_packs_jobs_in_one_call_and_only_those_leased_to_the_owner(store):
    jobs = _submit(store, 4)
    mine = store.claim_ids("w1", 10, [j.id for j in jobs[:3]])
    store.claim("w2", 10, job_id=jobs[3].id)
    ends = [(j.id, DONE, {"result_path": f"/r/{j.id}.h5", "progress": 1.0, "loop_s": 0.5}) for j in mine]
    ends.append((jobs[3].id, DONE, {"result_path": "/r/other.h5"}))       # not w1's: left as it is
    ends[1] = (mine[1].id, FAILED, {"error": "InstabilityError: overlap"})
    assert store.finish_many("w1", ends) == {mine[0].id: True, mine[1].id: True, mine[2].id: True,
                                             jobs[3].id: False}
    got = [store.get(j.id) for j in jobs]
    assert [g.state for g in got] == [DONE, FAILED, DONE, RUNNING]
    assert got[0].result_path == f"/r/{mine[0].id}.h5" and got[0].loop_s == 0.5 and got[0].lease_owner is None
    assert got[1].error == "InstabilityError: overlap" and got[3].lease_owner == "w2"
    assert store.finish_many("w1", ends[:1]) == {mine[0].id: False}      # already ended
    with pytest.raises(ValueError):
        store.finish_many("w1", [(jobs[3].id, QUEUED, {})])


def test_reaper_requeues_then_fails_with_reason(store):
    (job,) = store.submit([NewJob("{}")], max_attempts=2)
    store.claim("w1", 0.01)
    assert store.reap_expired(now=time.time() - 60) == ([], [])  # lease not expired yet at that time
    assert store.reap_expired(now=time.time() + 1) == ([job.id], [])
    got = store.get(job.id)
    assert got.state == QUEUED and got.lease_owner is None and "attempt 1 of 2" in got.error
    store.claim("w2", 0.01)
    assert store.reap_expired(now=time.time() + 1) == ([], [job.id])
    got = store.get(job.id)
    assert got.state == FAILED and got.attempts == 2 and "lost" in got.error and "every attempt" in got.error


def test_reaper_honours_cancel_of_lost_job(store):
    (job,) = _submit(store)
    store.claim("w", 0.01)
    store.request_cancel(job.id)
    store.reap_expired(now=time.time() + 1)
    assert store.get(job.id).state == CANCELLED


def test_two_claimers_take_each_of_50_jobs_exactly_once(store, store_url):
    """Two workers (separate connections) race for 50 jobs: each job is claimed once, none lost."""
    url, prefix = store_url
    jobs = _submit(store, 50)
    claims: dict[str, list[str]] = {"a": [], "b": []}
    second = open_store(url, prefix)
    start = threading.Barrier(2)

    def drain(name, st):
        start.wait()
        while (job := st.claim(name, 30)) is not None:
            claims[name].append(job.id)
            st.finish(job.id, name, DONE, error=None)

    threads = [threading.Thread(target=drain, args=(n, s)) for n, s in (("a", store), ("b", second))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    second.close()
    claimed = claims["a"] + claims["b"]
    assert sorted(claimed) == sorted(j.id for j in jobs)  # every job once, no duplicates
    assert len(set(claimed)) == 50
    assert store.counts() == {DONE: 50}
    assert all(store.get(j.id).attempts == 1 for j in jobs)


def test_worker_registry_register_seen_unregister(store):
    before = time.time()
    store.register_worker("w-cpu", "host-a", 101, ["cpu"])
    store.register_worker("w-gpu", "host-b", 202, ("cpu", "cuda"), device_memory=150_000_000_000)
    live = store.live_workers(max_age_s=60)
    assert [(w.worker_id, w.host, w.pid, w.backends, w.device_memory) for w in live] == [
        ("w-cpu", "host-a", 101, ("cpu",), None), ("w-gpu", "host-b", 202, ("cpu", "cuda"), 150_000_000_000)]
    assert all(before <= w.started_at <= w.seen_at <= time.time() for w in live)

    first_seen = live[0].seen_at
    time.sleep(0.01)  # the clock must move for seen_at to change
    store.worker_seen("w-cpu")
    (cpu,) = [w for w in store.live_workers(60) if w.worker_id == "w-cpu"]
    assert cpu.seen_at > first_seen and cpu.started_at == live[0].started_at

    store.unregister_worker("w-cpu")
    assert [w.worker_id for w in store.live_workers(60)] == ["w-gpu"]
    store.worker_seen("nobody")      # unknown ids are no-ops, not errors
    store.unregister_worker("nobody")


def test_worker_registry_reregister_replaces_row(store):
    store.register_worker("w", "host-a", 1, ["cpu"])
    store.register_worker("w", "host-b", 2, ["cpu", "cuda"])
    (w,) = store.live_workers(60)
    assert (w.host, w.pid, w.backends) == ("host-b", 2, ("cpu", "cuda"))


def test_worker_registry_old_seen_at_is_not_live(store):
    store.register_worker("w", "h", 1, ["cpu"])
    time.sleep(0.05)
    assert store.live_workers(max_age_s=0.01) == []  # last seen longer ago than 0.01 s
    store.worker_seen("w")
    assert [w.worker_id for w in store.live_workers(max_age_s=30)] == ["w"]


def test_a_table_of_an_older_demq_gets_the_new_columns(store_url):
    """A job table created before the loop_s / job_wall_s columns existed (it had wall_s): opening the store adds
    them, and its old rows read and finish as usual."""
    from sqlalchemy import text

    url, prefix = store_url
    old = open_store(url, prefix)          # today's table, then made into the older one
    with old.engine.begin() as conn:
        for name in ("loop_s", "job_wall_s"):
            conn.execute(text(f"ALTER TABLE {prefix}jobs DROP COLUMN {name}"))
        conn.execute(text(f"ALTER TABLE {prefix}jobs ADD COLUMN wall_s FLOAT"))
    old.close()
    store = open_store(url, prefix)
    try:
        (job,) = _submit(store)
        store.claim("w", 10)
        assert store.finish(job.id, "w", DONE, loop_s=1.0, job_wall_s=1.5, cundall=1.0, error=None)
        got = store.get(job.id)
        assert (got.state, got.loop_s, got.job_wall_s) == (DONE, 1.0, 1.5)
    finally:
        store.drop_tables()
        store.close()
