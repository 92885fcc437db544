"""Load test of the service: N jobs submitted by C concurrent clients while one worker drains them.

    python -m bench load_service [--jobs 1000] [--clients 20] [--database-url URL]

Starts `demq serve --no-worker` (uvicorn, loopback) and one `demq worker` as separate processes
on a fresh data directory. The worker runs every job in its own spawned simulation process as in
production, but with an instant engine (:func:`instant_run`, selected by DEMQ_ENGINE_RUN) that
writes an empty result file at once, so the figures measure the queue and the API, not physics.
Each client submits its share (POST /jobs) and reads each job back (GET /jobs/{id}); while the
worker drains, the clients keep polling GET /jobs/{id} on their jobs (4 requests/s each). At the end every job must
be accounted for exactly once (listed once, done, claimed once: attempts == 1).
Prints submit and GET latencies (p50/p99) and the drain throughput.
"""

from __future__ import annotations

import argparse
import os
import random
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import httpx

ROOT = Path(__file__).resolve().parents[1]
SPEC = {"n_particles": 64, "volume_fraction": 0.05, "box_length": 0.5, "t_end": 0.002,
        "thermalization": 0, "snapshots": 1}


def instant_run(spec, output, **_):
    """The instant engine: an empty result file, written atomically; no physics. Returns the fields
    of engine.driver.simulate.RunSummary the worker reads (without importing the engine's numerics)."""
    tmp = Path(f"{output}.part")
    tmp.write_bytes(b"")
    os.replace(tmp, output)
    return SimpleNamespace(output=Path(output), backend="instant", device="none", n_particles=spec.n_particles,
                           steps=0, loop_s=0.0, job_wall_s=0.0, cundall=0.0, resumed_from_step=None, extra={})


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _pct(values, q) -> float:
    return statistics.quantiles(values, n=100, method="inclusive")[q - 1] if len(values) > 1 else values[0]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=1000)
    ap.add_argument("--clients", type=int, default=20)
    ap.add_argument("--database-url", default=None, help="default: SQLite in a fresh data directory")
    args = ap.parse_args(argv)

    data = Path(tempfile.mkdtemp(prefix="demq-load-"))
    port = _free_port()
    env = {**os.environ, "PYTHONPATH": str(ROOT), "DEMQ_DATA_DIR": str(data), "DEMQ_POLL_SECONDS": "0.05",
           "DEMQ_ENGINE_RUN": "bench.load_service:instant_run", "DEMQ_MAX_BODY_BYTES": str(2**20)}
    if args.database_url:
        env["DEMQ_DATABASE_URL"] = args.database_url
        env["DEMQ_TABLE_PREFIX"] = f"load{os.getpid()}_"
    cli = [sys.executable, "-m", "service.cli"]
    server = subprocess.Popen([*cli, "serve", "--no-worker", "--port", str(port)], cwd=ROOT, env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    worker = subprocess.Popen([*cli, "worker"], cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
    url = f"http://127.0.0.1:{port}"
    try:
        for _ in range(200):
            try:
                if httpx.get(f"{url}/healthz").status_code == 200:
                    break
            except httpx.TransportError:
                time.sleep(0.1)
        submit_lat, get_lat, ids, errors = [], [], [], []
        lock = threading.Lock()
        drained = threading.Event()
        per_client = [args.jobs // args.clients + (i < args.jobs % args.clients) for i in range(args.clients)]

        def client(n: int) -> None:
            mine = []
            with httpx.Client(base_url=url, timeout=60) as c:
                for _ in range(n):
                    t = time.perf_counter()
                    r = c.post("/jobs", json={**SPEC, "seed": random.randrange(2**31)})
                    dt = time.perf_counter() - t
                    if r.status_code != 201:
                        errors.append(r.status_code)
                        continue
                    mine.append(r.json()["id"])
                    t = time.perf_counter()
                    r = c.get(f"/jobs/{mine[-1]}")
                    with lock:
                        submit_lat.append(dt)
                        get_lat.append(time.perf_counter() - t)
                        errors.extend([r.status_code] if r.status_code != 200 else [])
                with lock:
                    ids.extend(mine)
                while not drained.is_set():  # keep polling (4/s per client) while the worker drains
                    t = time.perf_counter()
                    r = c.get(f"/jobs/{random.choice(mine)}")
                    with lock:
                        get_lat.append(time.perf_counter() - t)
                    time.sleep(0.25)

        t0 = time.perf_counter()
        threads = [threading.Thread(target=client, args=(n,)) for n in per_client]
        for th in threads:
            th.start()
        while len(ids) < args.jobs - len(errors) and any(th.is_alive() for th in threads):
            time.sleep(0.05)
        t_submit = time.perf_counter() - t0
        while True:
            counts = httpx.get(f"{url}/healthz").json()["jobs"]
            if counts.get("queued", 0) + counts.get("running", 0) == 0:
                break
            time.sleep(0.5)
        drained.set()
        for th in threads:
            th.join()
        t_drain = time.perf_counter() - t0

        listed = []
        with httpx.Client(base_url=url, timeout=60) as c:
            while True:
                page = c.get("/jobs", params={"limit": 1000, "offset": len(listed)}).json()
                listed.extend(page["items"])
                if len(listed) >= page["total"]:
                    break
        listed_ids = [j["id"] for j in listed]
        ok = (not errors and len(ids) == args.jobs and sorted(listed_ids) == sorted(ids)
              and len(set(listed_ids)) == len(listed_ids)
              and all(j["state"] == "done" and j["attempts"] == 1 for j in listed))
        ms = lambda v: 1000 * v  # noqa: E731
        print(f"jobs={args.jobs} clients={args.clients} db={'postgresql' if args.database_url else 'sqlite'} "
              f"cpus={os.cpu_count()}")
        print(f"submitted in {t_submit:.1f} s ({args.jobs / t_submit:.0f} jobs/s); all done after {t_drain:.1f} s "
              f"({args.jobs / t_drain:.1f} jobs/s through one worker, one spawned process per job)")
        print(f"POST /jobs      p50 {ms(_pct(submit_lat, 50)):.1f} ms  p99 {ms(_pct(submit_lat, 99)):.1f} ms "
              f"(n={len(submit_lat)})")
        print(f"GET /jobs/{{id}}  p50 {ms(_pct(get_lat, 50)):.1f} ms  p99 {ms(_pct(get_lat, 99)):.1f} ms "
              f"(n={len(get_lat)})")
        print(f"accounting: submitted {len(ids)}, listed {len(listed_ids)} ({len(set(listed_ids))} distinct), "
              f"done+claimed once {sum(j['state'] == 'done' and j['attempts'] == 1 for j in listed)}, "
              f"errors {len(errors)} -> {'OK' if ok else 'FAILED'}")
        return 0 if ok else 1
    finally:
        for p in (worker, server):
            p.terminate()
            p.wait(30)


if __name__ == "__main__":
    sys.exit(main())
