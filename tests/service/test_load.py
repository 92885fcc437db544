"""Exactly-once under concurrency (small version of bench/load_service.py): 30 jobs from 6 concurrent
HTTP clients against uvicorn on loopback, drained by two workers on the same SQLite queue."""

from __future__ import annotations

import socket
import threading
import time

import httpx
import uvicorn

from jobs.stores import open_store
from jobs.worker import Worker
from service.app import create_app
from tests.jobs.conftest import TINY, make_settings
from tests.waiting import wait_for


def test_concurrent_clients_two_workers_every_job_once(tmp_path):
    settings = make_settings(tmp_path)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(create_app(settings), host="127.0.0.1", port=port, log_level="warning"))
    server_thread = threading.Thread(target=server.run, daemon=True)
    server_thread.start()
    workers = [Worker(open_store(settings.database_url), settings) for _ in range(2)]
    worker_threads = [threading.Thread(target=w.run_forever) for w in workers]
    for t in worker_threads:
        t.start()
    url = f"http://127.0.0.1:{port}"
    try:
        while not server.started:
            time.sleep(0.05)
        ids, statuses = [], []

        def client(k: int) -> None:
            with httpx.Client(base_url=url, timeout=30) as c:
                for i in range(5):
                    r = c.post("/jobs", json={**TINY, "seed": 100 * k + i})
                    statuses.append(r.status_code)
                    ids.append(r.json()["id"])
                    statuses.append(c.get(f"/jobs/{ids[-1]}").status_code)

        clients = [threading.Thread(target=client, args=(k,)) for k in range(6)]
        for t in clients:
            t.start()
        for t in clients:
            t.join(60)
        assert set(statuses) == {200, 201} and len(ids) == 30
        def done() -> int:
            return httpx.get(f"{url}/jobs", params={"state": "done"}).json()["total"]

        wait_for(lambda: done() >= 30, "30 jobs done", activity=done)
        listed = httpx.get(f"{url}/jobs", params={"limit": 1000}).json()
    finally:
        for w in workers:
            w.stop()
        for t in worker_threads:
            t.join(30)
        server.should_exit = True
        server_thread.join(30)   # not left running into the interpreter's exit
    assert listed["total"] == 30 and sorted(j["id"] for j in listed["items"]) == sorted(ids)
    bad = [(j["state"], j["attempts"], j.get("error")) for j in listed["items"]
           if not (j["state"] == "done" and j["attempts"] == 1)]
    assert not bad, bad
