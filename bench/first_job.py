"""A worker's first result: `demq serve` started, then a job submitted the moment the server answers.

Each round starts `demq serve` (SQLite, its embedded worker) on a fresh data directory and the kernel cache that
``--cache`` names, polls ``/healthz`` every 50 ms, and submits the job as soon as it answers, with ``backend`` set
explicitly (``cuda`` on a GPU host: the admission check must already know the host's backends), then waits for
it and downloads its result; then a second job (the next seed) on the same server, a warm job. Printed per round:
start to the first answer, the first answer to the first job's result downloaded, the warm job's submission to its
download, and the ratios the queue is held to: first / warm with a warm cache, (first - own compile) / warm with an
empty one, where "own compile" is what the same job run alone through engine.run in a fresh process takes longer
on an empty cache than on the one it filled (:func:`own_compile`).

``--cache empty`` uses a new, empty ``NUMBA_CACHE_DIR`` (a fresh host); ``warm`` the one an empty round has just
filled (a restarted worker); ``both`` (default) the two in that order. ``--job``: ``2M`` (bench/e2e.py's
``spheres-2M-f64``: 2 097 152 spheres, 5000 steps, float64) or ``default`` (the README's default job, as `demq
submit` sends it). The worker's warm-up of every other specialisation runs beside the jobs (jobs/warm.py) and is
not waited for. Nothing is asserted here: the figures go into docs/performance.md and docs/scaling-out.md.

    python -m bench first_job [--cache both|empty|warm] [--job 2M|default] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]


def _spec(job: str, backend: str) -> dict:
    if job == "default":
        return {"backend": backend}
    from bench.e2e import case_specs, to_spec

    spec = to_spec(case_specs("spheres-2M-f64", quick=False)["specs"][0]).model_dump(mode="json")
    return {**spec, "backend": backend}


def _submit_and_fetch(c: httpx.Client, spec: dict, out: Path) -> dict:
    """Submit ``spec``, wait (polling every 50 ms) until it ends, download its result; the times and the row."""
    t0 = time.monotonic()
    r = c.post("/jobs", json=spec)
    admitted = r.status_code
    if admitted != 201:
        return {"admitted": admitted, "detail": r.text[:500]}
    job_id = r.json()["id"]
    while (row := c.get(f"/jobs/{job_id}").json())["state"] not in ("done", "failed", "cancelled"):
        time.sleep(0.05)
    got = c.get(f"/jobs/{job_id}/result")
    out.write_bytes(got.content)
    seconds = time.monotonic() - t0
    compile_s = None
    if got.status_code == 200:
        import h5py

        with h5py.File(out) as f:
            compile_s = json.loads(f["parameters"].attrs["timings"]).get("compile")
    return {"admitted": admitted, "state": row["state"], "error": row.get("error"), "seconds": seconds,
            "loop_s": row.get("loop_s"), "job_wall_s": row.get("job_wall_s"), "device": row.get("device"),
            "compile_s": compile_s}


def own_compile(job: str) -> float:
    """Seconds the job's own kernels cost when the cache lacks them: the job through engine.run in a fresh process on
    an empty kernel cache, less the same in a fresh process on the cache it filled (bench/e2e.py's case; its wall
    seconds from the call to the closed file). On a GPU the kernels compile on the start-up thread beside the set-up
    (engine/driver/startup.py), so the job's own ``compile`` timing does not show them."""
    from bench.e2e import fresh_process

    case = "spheres-2M-f64" if job == "2M" else "quickstart"
    before = os.environ.get("NUMBA_CACHE_DIR")
    os.environ["NUMBA_CACHE_DIR"] = tempfile.mkdtemp(prefix="demq-own-compile-")
    try:
        cold, warm = (fresh_process(case, quick=False)["wall_s"] for _ in range(2))
    finally:
        if before is None:
            os.environ.pop("NUMBA_CACHE_DIR")
        else:
            os.environ["NUMBA_CACHE_DIR"] = before
    return cold - warm


def one_round(out: Path, cache: Path, job: str, backend: str) -> dict:
    """One fresh server on ``cache``: its first job sent at its first answer, then a warm job."""
    data = Path(tempfile.mkdtemp(prefix="demq-first-"))
    from bench.small_jobs import _free_port

    port = _free_port()
    path = os.pathsep.join([str(ROOT)] + ([os.environ["PYTHONPATH"]] if os.environ.get("PYTHONPATH") else []))
    env = {**os.environ, "PYTHONPATH": path, "DEMQ_DATA_DIR": str(data), "NUMBA_CACHE_DIR": str(cache),
           "DEMQ_MAX_PARTICLE_STEPS": "1e15"}
    url = f"http://127.0.0.1:{port}"
    log = open(out / f"server-{cache.name}-{int(time.time())}.log", "w")
    t_start = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--port", str(port)], cwd=ROOT, env=env,
                            stdout=log, stderr=subprocess.STDOUT)
    try:
        with httpx.Client(base_url=url, timeout=120) as c:
            while True:
                try:
                    if c.get("/healthz").status_code == 200:
                        break
                except httpx.TransportError:
                    pass
                if proc.poll() is not None:
                    raise RuntimeError(f"demq serve exited with {proc.returncode} (log: {log.name})")
                time.sleep(0.05)
            answer_s = time.monotonic() - t_start
            spec = _spec(job, backend)
            first = _submit_and_fetch(c, spec, out / "first.h5")
            second = _submit_and_fetch(c, {**spec, "seed": int(spec.get("seed", 0)) + 1}, out / "second.h5")
    finally:
        proc.terminate()
        proc.wait(60)
        log.close()
    return {"start_to_answer_s": answer_s, "first": first, "warm": second,
            "start_to_first_result_s": answer_s + first.get("seconds", float("nan"))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", choices=("both", "empty", "warm"), default="both",
                    help="the kernel cache the server starts on (default: an empty one, then the one it filled)")
    ap.add_argument("--job", choices=("2M", "default"), default="2M", help="the job (default: 2M spheres, f64)")
    ap.add_argument("--out", type=Path, default=Path("bench-out/first_job"), help="report folder")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    from engine.driver.startup import nvidia_driver

    backend = "cuda" if nvidia_driver() else "cpu"
    cache = Path(os.environ.get("NUMBA_CACHE_DIR") or Path.home() / ".cache" / "demq-numba")
    rounds = {"own_compile_s": own_compile(args.job) if args.cache != "warm" else None}
    if rounds["own_compile_s"] is not None:
        print(f"the job's own kernels: {rounds['own_compile_s']:.2f} s (engine.run in a fresh process on an empty "
              f"kernel cache, less the same on the cache it filled)", flush=True)
    for kind in (("empty", "warm") if args.cache == "both" else (args.cache,)):
        if kind == "empty":
            cache = Path(tempfile.mkdtemp(prefix="demq-kernel-cache-"))
        r = one_round(args.out, cache, args.job, backend)
        first, warm = r["first"], r["warm"]
        if first.get("admitted") != 201 or warm.get("admitted") != 201:
            print(f"{kind} cache: refused: first {first.get('admitted')} {first.get('detail', '')}; warm "
                  f"{warm.get('admitted')}", flush=True)
        else:
            own = rounds["own_compile_s"] if kind == "empty" else 0.0
            r["first_over_warm"] = first["seconds"] / warm["seconds"]
            r["first_less_own_compile_over_warm"] = (first["seconds"] - own) / warm["seconds"]
            print(f"{kind} cache ({args.job}, backend {backend}, {first['device']}): server answered "
                  f"{r['start_to_answer_s']:.2f} s after start; {backend} job admitted ({first['admitted']}); first "
                  f"job {first['seconds']:.2f} s from the first answer to its result downloaded ({first['state']}; "
                  f"loop {first['loop_s']:.2f} s); warm job {warm['seconds']:.2f} s ({warm['state']}); first / warm "
                  f"{r['first_over_warm']:.2f}, (first - own compile) / warm "
                  f"{r['first_less_own_compile_over_warm']:.2f}", flush=True)
        rounds[kind] = r
    (args.out / "first_job.json").write_text(json.dumps(rounds, indent=2, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
