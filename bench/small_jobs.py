"""Small jobs come back fast: latency of real jobs through `demq serve` (the workstation default: SQLite, one
embedded worker) on this machine's CPU.

Up to three scenes, each on a fresh server and data directory:

1. ``--jobs`` jobs of 64 spheres (the default spec otherwise) submitted from ``--clients`` threads at once;
   printed: each job's time from its submission to done (median, 90th percentile) against the time from the
   first submission until the last job is done, and how long the submissions themselves took (while the worker
   keeps up with them, a job's latency is close to its own run; a backlog is worked off in submission order).
2. with ``--lone K``: K jobs of 64 spheres submitted one at a time, each 1.5 s after the previous one was done;
   printed: each one's time from its submission to done.
3. ten default jobs (4096 spheres) and one of 512 spheres, submitted together as one batch of specs, the small
   one last; printed: when the small one was done against the first of the ten.

``--lanes L ...`` runs only this instead: a CPU worker (it sees no GPU) with L lanes (DEMQ_WORKER_LANES,
jobs/worker.py), for each L, ``--lane-jobs`` jobs of 512 spheres as one batch; printed: the time from the batch's
submission until its last job is done, against the first L's, the jobs' distinct end times, and a lane's seconds
per job (that time x L / jobs) against the engine's own (the mean of the jobs' job_wall_s: the run from its spec to
its closed result file): their difference is what the queue costs a job, or what the lanes' jobs cost each other.
With ``--lane-sleep S`` the jobs run no physics: each sleeps S wall seconds in 200 records, with the engine's progress
report and cancel check at each, and writes an empty result (:func:`sleep_run`): what the queue costs a job at L
lanes, free of the jobs' contention for the cores (a lane's seconds per job against S).

Times are the server's own (the job rows' created_at and finished_at). Nothing is asserted here: the figures go
into docs/performance.md.

    python -m bench small_jobs [--jobs 100] [--clients 10] [--lone K] [--skip-large] [--out DIR]
    python -m bench small_jobs --lanes 1 8 [--lane-jobs 200] [--lane-sleep S]
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from datetime import datetime
from pathlib import Path
from typing import Optional

import httpx

ROOT = Path(__file__).resolve().parents[1]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Server:
    """`demq serve` with its embedded worker on a fresh data directory, on loopback, once the worker is warm."""

    def __init__(self, log: Path, env_extra: Optional[dict] = None, wait_for_warm_up: bool = True):
        self.data = Path(tempfile.mkdtemp(prefix="demq-small-"))
        self.port = _free_port()
        path = os.pathsep.join([str(ROOT)] + ([os.environ["PYTHONPATH"]] if os.environ.get("PYTHONPATH") else []))
        env = {**os.environ, "PYTHONPATH": path, "DEMQ_DATA_DIR": str(self.data), **(env_extra or {})}
        self.log = open(log, "w")
        self.proc = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--port", str(self.port)],
                                     cwd=ROOT, env=env, stdout=self.log, stderr=subprocess.STDOUT)
        self.url = f"http://127.0.0.1:{self.port}"
        # ready = the API answers and (unless not asked for) the embedded worker has logged the end of its warm-up
        # ("warm: N kernels in X s"); the ceiling only catches a hang (a first warm-up on an empty kernel cache
        # compiles for minutes)
        deadline = time.monotonic() + 1800
        while time.monotonic() < deadline:
            text = log.read_text()
            warmed = any(line in text for line in ("warm: ", "warm-up ended without", "cannot start the warm-up"))
            if warmed or not wait_for_warm_up:
                try:
                    if httpx.get(f"{self.url}/healthz").status_code == 200:
                        return
                except httpx.TransportError:
                    pass
            time.sleep(0.2)
        raise RuntimeError(f"the server was not ready within 1800 s (log: {log})")

    def wait_all_done(self, ids, ceiling_s: float = 3600.0) -> list[dict]:
        """The job rows once every job has ended (the server's counts of queued and running jobs polled every 0.2 s,
        two requests a round, so that the polling takes little of the machine the server runs on; the ceiling only
        catches a hang)."""
        deadline = time.monotonic() + ceiling_s
        with httpx.Client(base_url=self.url, timeout=60) as c:
            while time.monotonic() < deadline:
                left = sum(c.get("/jobs", params={"state": state, "limit": 1}).json()["total"]
                           for state in ("queued", "running"))
                if not left:
                    wanted, rows, offset = set(ids), {}, 0
                    while True:
                        page = c.get("/jobs", params={"limit": 1000, "offset": offset}).json()
                        rows.update((j["id"], j) for j in page["items"] if j["id"] in wanted)
                        offset += len(page["items"])
                        if not page["items"] or offset >= page["total"]:
                            break
                    return [rows[i] for i in ids]
                time.sleep(0.2)
        raise RuntimeError("jobs not ended before the ceiling")

    def close(self) -> None:
        self.proc.terminate()
        self.proc.wait(60)
        self.log.close()


def _t(stamp: str) -> float:
    return datetime.fromisoformat(stamp).timestamp()


def many_small(out: Path, n_jobs: int, clients: int) -> dict:
    server = Server(out / "many_small.log")
    try:
        ids, lock = [], threading.Lock()
        per_client = [n_jobs // clients + (i < n_jobs % clients) for i in range(clients)]

        def client(n: int, offset: int) -> None:
            with httpx.Client(base_url=server.url, timeout=60) as c:
                for k in range(n):
                    r = c.post("/jobs", json={"n_particles": 64, "seed": offset + k})
                    r.raise_for_status()
                    with lock:
                        ids.append(r.json()["id"])

        threads = [threading.Thread(target=client, args=(n, 1000 * i)) for i, n in enumerate(per_client)]
        for th in threads:
            th.start()
        for th in threads:
            th.join()
        jobs = server.wait_all_done(ids)
    finally:
        server.close()
    latency = sorted(_t(j["finished_at"]) - _t(j["created_at"]) for j in jobs)
    first = min(_t(j["created_at"]) for j in jobs)
    last = max(_t(j["finished_at"]) for j in jobs)
    submitted = max(_t(j["created_at"]) for j in jobs) - first
    return {"submit_window_s": submitted, "jobs": n_jobs, "clients": clients,
            "states": sorted({j["state"] for j in jobs}),
            "median_latency_s": statistics.median(latency), "p90_latency_s": latency[int(0.9 * (len(latency) - 1))],
            "first_submit_to_last_done_s": last - first,
            "median_over_last": statistics.median(latency) / (last - first)}


def lone_jobs(out: Path, count: int, pause_s: float = 1.5) -> dict:
    """``count`` jobs of 64 spheres submitted one at a time, each ``pause_s`` after the previous one was done (the
    pace of a person submitting by hand): each job's time from its submission to done."""
    server = Server(out / "lone_jobs.log")
    latency = []
    try:
        for k in range(count):
            r = httpx.post(f"{server.url}/jobs", json={"n_particles": 64, "seed": k}, timeout=60)
            r.raise_for_status()
            job = server.wait_all_done([r.json()["id"]])[0]
            latency.append(_t(job["finished_at"]) - _t(job["created_at"]))
            time.sleep(pause_s)
    finally:
        server.close()
    return {"jobs": count, "latency_s": latency, "median_latency_s": statistics.median(latency)}


def small_among_large(out: Path) -> dict:
    server = Server(out / "small_among_large.log")
    try:
        specs = [{"seed": k} for k in range(10)] + [{"n_particles": 512}]
        r = httpx.post(f"{server.url}/batches", json={"specs": specs}, timeout=60)
        r.raise_for_status()
        batch = r.json()
        ids = batch["job_ids"]
        jobs = server.wait_all_done(ids)
    finally:
        server.close()
    by_id = {j["id"]: j for j in jobs}
    small = by_id[ids[-1]]
    large_done = sorted(_t(by_id[i]["finished_at"]) for i in ids[:-1])
    t0 = min(_t(j["created_at"]) for j in jobs)
    return {"small_done_s": _t(small["finished_at"]) - t0, "first_large_done_s": large_done[0] - t0,
            "last_large_done_s": large_done[-1] - t0,
            "small_before_all_large": _t(small["finished_at"]) < large_done[0],
            "states": sorted({j["state"] for j in jobs})}


#: Wall seconds a job of :func:`sleep_run` takes (``--lane-sleep``; read in the simulation process).
SLEEP_ENV = "DEMQ_BENCH_SLEEP_S"
#: Progress reports of a job of :func:`sleep_run` (the engine's records of a default job).
SLEEP_RECORDS = 200


def sleep_run(spec, output, *, progress=None, should_cancel=None, **_):
    """The engine of ``--lane-sleep`` (engine.driver.simulate.run's signature, DEMQ_ENGINE_RUN): the job sleeps
    DEMQ_BENCH_SLEEP_S wall seconds in SLEEP_RECORDS records, with a progress report and a cancel check at each, and
    writes an empty result file atomically; no physics."""
    from engine.driver.simulate import Progress, RunSummary
    from engine.errors import Cancelled

    seconds = float(os.environ[SLEEP_ENV])
    t0 = time.monotonic()
    for k in range(SLEEP_RECORDS):
        if should_cancel is not None and should_cancel():
            raise Cancelled(f"cancelled at record {k}")
        time.sleep(seconds / SLEEP_RECORDS)
        if progress is not None:
            wall = time.monotonic() - t0
            progress(Progress(phase="cooling", fraction=(k + 1) / SLEEP_RECORDS, step=k + 1, time=0.0,
                              eta_s=wall / (k + 1) * (SLEEP_RECORDS - k - 1), cundall=0.0, loop_s=wall))
    partial = Path(f"{output}.part")
    partial.write_bytes(b"")
    os.replace(partial, output)
    wall = time.monotonic() - t0
    return RunSummary(output=Path(output), backend="sleep", device="none", n_particles=spec.n_particles,
                      steps=SLEEP_RECORDS, loop_s=wall, cundall=0.0, job_wall_s=wall)


def lanes(out: Path, lane_counts: list, n_jobs: int, n_particles: int = 512, sleep_s: Optional[float] = None) -> list:
    """A CPU worker's lanes (DEMQ_WORKER_LANES): for each count, a fresh server whose worker sees no GPU
    (CUDA_VISIBLE_DEVICES empty), one job to load the kernels, then ``n_jobs`` jobs of ``n_particles`` spheres (the
    default spec otherwise) as one batch; the time from the batch's submission to its last job done, and how many
    distinct end times the jobs have (each job reported done as its own run ends, not with its claim). With
    ``sleep_s``, the jobs run :func:`sleep_run` instead of the engine."""
    rows = []
    for count in lane_counts:
        env = {"DEMQ_WORKER_LANES": str(count), "CUDA_VISIBLE_DEVICES": "", "DEMQ_WORKER_WARM": "off"}
        if sleep_s is not None:
            env.update({"DEMQ_ENGINE_RUN": "bench.small_jobs:sleep_run", SLEEP_ENV: str(sleep_s),
                        "DEMQ_ENGINE_RUN_ENSEMBLE": "engine.driver.ensemble:run_ensemble"})
        server = Server(out / f"lanes_{count}.log", env_extra=env, wait_for_warm_up=False)
        try:
            first = httpx.post(f"{server.url}/jobs", json={"n_particles": n_particles, "seed": 10**6}, timeout=60)
            first.raise_for_status()
            server.wait_all_done([first.json()["id"]])
            r = httpx.post(f"{server.url}/batches", json={"base": {"n_particles": n_particles},
                                                        "sweep": {"seed": list(range(n_jobs))}}, timeout=60)
            r.raise_for_status()
            jobs = server.wait_all_done(r.json()["job_ids"])
        finally:
            server.close()
        t0 = min(_t(j["created_at"]) for j in jobs)
        ends = sorted(_t(j["finished_at"]) for j in jobs)
        walls = [j["job_wall_s"] for j in jobs if j["job_wall_s"] is not None]
        rows.append({"lanes": count, "jobs": n_jobs, "n_particles": n_particles, "sleep_s": sleep_s,
                     "span_s": ends[-1] - t0,
                     "lane_s_per_job": (ends[-1] - t0) * count / n_jobs,
                     "engine_s_per_job": statistics.mean(walls) if walls else None,
                     "distinct_end_times": len(set(ends)), "states": sorted({j["state"] for j in jobs})})
    base = rows[0]["span_s"]
    for row in rows:
        row["speed_up"] = base / row["span_s"]
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=100)
    ap.add_argument("--clients", type=int, default=10)
    ap.add_argument("--skip-large", action="store_true", help="only the many small jobs (and --lone)")
    ap.add_argument("--lone", type=int, default=0, help="then this many lone small jobs, one at a time")
    ap.add_argument("--lanes", type=int, nargs="+", default=None, metavar="L",
                    help="only this: a CPU worker with L lanes for each L (the first is the reference), "
                         "--lane-jobs jobs of 512 spheres each")
    ap.add_argument("--lane-jobs", type=int, default=200)
    ap.add_argument("--lane-sleep", type=float, default=None, metavar="S",
                    help="with --lanes: jobs that sleep S wall seconds each instead of running the engine (the "
                         "queue's own cost per job)")
    ap.add_argument("--out", type=Path, default=Path("bench-out/small_jobs"))
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.lanes:
        rows = lanes(args.out, args.lanes, args.lane_jobs, sleep_s=args.lane_sleep)
        kind = "spheres" if args.lane_sleep is None else f"spheres sleeping {args.lane_sleep:g} s (no engine)"
        for row in rows:
            engine = row["engine_s_per_job"]
            print(f"{row['lanes']} lane(s), {os.cpu_count()} cores: {row['jobs']} jobs of {row['n_particles']} "
                  f"{kind} done {row['span_s']:.2f} s after the batch's submission (x{row['speed_up']:.2f} of "
                  f"{rows[0]['lanes']} lane(s)); a lane's {row['lane_s_per_job']:.3f} s per job against the engine's "
                  f"{'-' if engine is None else f'{engine:.3f}'} s; {row['distinct_end_times']} distinct end times; "
                  f"states {row['states']}", flush=True)
        (args.out / "lanes.json").write_text(json.dumps(rows, indent=2))
        return 0
    report = {"cpus": os.cpu_count(), "many_small": many_small(args.out, args.jobs, args.clients)}
    m = report["many_small"]
    print(f"{args.jobs} jobs of 64 spheres from {args.clients} threads: median submit-to-done "
          f"{m['median_latency_s']:.2f} s, 90th percentile {m['p90_latency_s']:.2f} s; first submit to last done "
          f"{m['first_submit_to_last_done_s']:.2f} s (median / last = {m['median_over_last']:.2f}); the submissions "
          f"took {m['submit_window_s']:.2f} s; states {m['states']}")
    if args.lone:
        report["lone"] = lone = lone_jobs(args.out, args.lone)
        print(f"{args.lone} lone jobs of 64 spheres, one at a time: submit-to-done "
              f"{' '.join(f'{x:.2f}' for x in lone['latency_s'])} s (median {lone['median_latency_s']:.2f} s)")
    if not args.skip_large:
        report["small_among_large"] = s = small_among_large(args.out)
        print(f"ten default jobs and one of 512 spheres in one batch: the small one done after "
              f"{s['small_done_s']:.1f} s, the first default after {s['first_large_done_s']:.1f} s, the last after "
              f"{s['last_large_done_s']:.1f} s; states {s['states']}")
    (args.out / "small_jobs.json").write_text(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
