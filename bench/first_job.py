"""A fresh GPU host's first job: `demq serve` on an empty kernel cache, then two 2M-sphere jobs.

The server (SQLite, its embedded worker) starts with a new, empty ``NUMBA_CACHE_DIR`` and data directory; its
worker compiles every kernel specialisation the host can run before its first claim and logs ``warm: N kernels
in X s`` (jobs/warm.py). Once it has (the worker is ready), bench/e2e.py's ``spheres-2M-f64`` job (2 097 152
spheres, 5000 steps, float64) is submitted over HTTP and waited for; then the same job with the next seed. Printed:
the warm-up's seconds, each job's time from submission to done (the server's own created_at and finished_at) and
the first's over the second's. Nothing is asserted here: the figures go into docs/performance.md.

    python -m bench first_job [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import tempfile
import time
from pathlib import Path

import httpx


def _job_seconds(job: dict) -> float:
    from bench.small_jobs import _t

    return _t(job["finished_at"]) - _t(job["created_at"])


def main(argv=None) -> int:
    from bench.e2e import case_specs, to_spec
    from bench.small_jobs import Server

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("bench-out/first_job"))
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    os.environ["NUMBA_CACHE_DIR"] = tempfile.mkdtemp(prefix="demq-empty-kernel-cache-")
    os.environ["DEMQ_MAX_PARTICLE_STEPS"] = "1e15"
    spec = to_spec(case_specs("spheres-2M-f64", quick=False)["specs"][0]).model_dump(mode="json")
    log = args.out / "server.log"
    t0 = time.monotonic()
    server = Server(log)                       # returns once the worker has logged its warm-up
    ready_s = time.monotonic() - t0
    warm = re.search(r"warm: .*", log.read_text())
    jobs = []
    try:
        with httpx.Client(base_url=server.url, timeout=60) as c:
            for k in range(2):
                r = c.post("/jobs", json={**spec, "seed": int(spec.get("seed", 0)) + k})
                r.raise_for_status()
                jobs.append(server.wait_all_done([r.json()["id"]])[0])
    finally:
        server.close()
    first, second = (_job_seconds(j) for j in jobs)
    report = {"server_start_to_ready_s": ready_s, "warm_line": warm.group(0) if warm else None,
              "states": [j["state"] for j in jobs], "first_job_s": first, "second_job_s": second,
              "first_over_second": first / second, "device": jobs[0].get("device")}
    print(f"server start to ready {ready_s:.1f} s ({report['warm_line']}); the first 2M-sphere job {first:.2f} s "
          f"from submission to done, the second {second:.2f} s: {first / second:.2f} x; states {report['states']}")
    (args.out / "first_job.json").write_text(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
