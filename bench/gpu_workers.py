"""One queue, one worker per GPU: a sweep drained by one worker, then by one worker on each GPU of the host.

    python -m bench gpu_workers [--devices 0 1] [--jobs 64] [--n 2097152] [--steps 5000] [--precision float64]
                                [--idle-s 10] [--out DIR]

The scaling-out path of docs/scaling-out.md ("One host, several GPUs"), run as an operator runs it: for each worker
count (one worker on the first device of ``--devices``, then one worker on each), a fresh data directory with its
SQLite queue, `demq serve --no-worker` and the workers, each a `demq worker` process with CUDA_VISIBLE_DEVICES set to
its device, its own worker id (``dev<k>``) and its own log. Once every worker has logged its start and ``--idle-s``
seconds have passed (a running cluster: the workers' standby processes are up), the sweep (``--jobs`` specs of
``--n`` spheres at phi = 0.058, ``--steps`` steps, no thermalisation, no snapshots, seeds 0, 1, ...) is submitted as
one batch (POST /batches) and timed from the submission until the last job has ended (its finished_at, the
server's clock). Before the timed runs a priming job of the same spec fills the kernel cache, so that every timed run
starts from the warm disk cache a restarted worker finds.

Checked (exit 1 when not): every job done at its first attempt, each reported done by exactly one worker's log, and,
with several workers, every worker did some of them. Where nvidia-smi answers, each GPU's utilisation is sampled every
0.5 s during a sweep and its mean printed. An empty ``--devices`` entry ("") starts a worker that sees no GPU (the
harness on a CPU machine: tests/bench/test_gpu_workers.py).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx

from bench.small_jobs import _free_port, _t

ROOT = Path(__file__).resolve().parents[1]
DONE = re.compile(r"job (\w+): done\b")


def sweep_base(n: int, steps: int, precision: str) -> dict:
    """The spec keys every job of the sweep shares: n spheres at phi = 0.058 (box scaled from the default 4096-sphere
    scene), exactly ``steps`` time steps (t_end = steps x dt), no thermalisation, no snapshots."""
    from bench.e2e import to_spec

    spec = to_spec(dict(n_particles=n, volume_fraction=0.058, box_length=2.0 * (n / 4096) ** (1.0 / 3.0),
                        precision=precision, snapshots=0, thermalization=0, seed=0, _steps=steps))
    base = spec.model_dump(mode="json")
    base.pop("seed")
    return base


class GpuSampler:
    """Each GPU's utilisation (%), sampled by nvidia-smi every ``period`` s on a thread until :meth:`stop`; empty
    where nvidia-smi does not answer."""

    def __init__(self, period: float = 0.5):
        self.samples: dict[int, list[float]] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(period,), daemon=True)
        self._thread.start()

    def _run(self, period: float) -> None:
        while not self._stop.is_set():
            try:
                out = subprocess.run(["nvidia-smi", "--query-gpu=index,utilization.gpu", "--format=csv,noheader,"
                                      "nounits"], capture_output=True, text=True, timeout=10).stdout
            except (OSError, subprocess.SubprocessError):
                return
            for line in out.splitlines():
                parts = [p.strip() for p in line.split(",")]
                if len(parts) == 2 and parts[0].isdigit():
                    self.samples.setdefault(int(parts[0]), []).append(float(parts[1]))
            self._stop.wait(period)

    def stop(self) -> dict[int, float]:
        """{GPU index: mean utilisation %} over the samples taken."""
        self._stop.set()
        self._thread.join(15)
        return {k: sum(v) / len(v) for k, v in sorted(self.samples.items()) if v}


class Queue:
    """`demq serve --no-worker` and one `demq worker` per entry of ``devices`` on a fresh data directory (SQLite)."""

    def __init__(self, out: Path, label: str, devices: list[str]):
        self.data = Path(tempfile.mkdtemp(prefix=f"demq-gpus-{label}-"))
        port = _free_port()
        self.url = f"http://127.0.0.1:{port}"
        path = os.pathsep.join([str(ROOT)] + ([os.environ["PYTHONPATH"]] if os.environ.get("PYTHONPATH") else []))
        self.env = {**os.environ, "PYTHONPATH": path, "DEMQ_DATA_DIR": str(self.data),
                    "DEMQ_MAX_PARTICLE_STEPS": "1e15"}
        cli = [sys.executable, "-m", "service.cli"]
        self.procs, self.logs, self.files = [], [], []

        def start(args, log: Path, env: dict) -> None:
            f = open(log, "w")    # a file, not a pipe nobody reads: a full pipe would stall the process
            self.files.append(f)
            self.procs.append(subprocess.Popen([*cli, *args], cwd=ROOT, env=env, stdout=f, stderr=subprocess.STDOUT))

        start(["serve", "--no-worker", "--host", "127.0.0.1", "--port", str(port)], out / f"{label}-serve.log",
              self.env)
        self.workers = []
        for k, dev in enumerate(devices):
            wid = f"dev{k}"
            log = out / f"{label}-worker-{wid}.log"
            start(["worker", "--worker-id", wid], log, {**self.env, "CUDA_VISIBLE_DEVICES": dev})
            self.workers.append((wid, dev, log))

    def wait_ready(self, ceiling_s: float = 600.0) -> None:
        """Until the API answers and every worker has logged its start."""
        deadline = time.monotonic() + ceiling_s
        while time.monotonic() < deadline:
            started = all(f"worker {wid} started" in log.read_text() for wid, _, log in self.workers)
            if started:
                try:
                    if httpx.get(f"{self.url}/healthz").status_code == 200:
                        return
                except httpx.TransportError:
                    pass
            for p in self.procs:
                if p.poll() is not None:
                    raise RuntimeError(f"a service process exited ({p.args}, code {p.returncode})")
            time.sleep(0.2)
        raise RuntimeError("the service or its workers did not start")

    def run_batch(self, base: dict, seeds: list, ceiling_s: float = 3600.0) -> list[dict]:
        """Submit the sweep as one batch; the job rows once every job has ended."""
        with httpx.Client(base_url=self.url, timeout=60.0) as c:
            r = c.post("/batches", json={"base": base, "sweep": {"seed": seeds}})
            r.raise_for_status()
            bid = r.json()["batch_id"]
            deadline = time.monotonic() + ceiling_s
            while time.monotonic() < deadline:
                rows = []
                while True:
                    page = c.get("/jobs", params={"batch_id": bid, "limit": 1000, "offset": len(rows)}).json()
                    rows.extend(page["items"])
                    if not page["items"] or len(rows) >= page["total"]:
                        break
                if len(rows) == len(seeds) and all(j["state"] in ("done", "failed", "cancelled") for j in rows):
                    return rows
                time.sleep(0.25)
        raise RuntimeError("the batch did not end before the ceiling")

    def done_by(self) -> dict[str, list[str]]:
        """{worker id: the job ids its log reports done}."""
        return {wid: DONE.findall(log.read_text()) for wid, _, log in self.workers}

    def close(self) -> None:
        for p in reversed(self.procs):     # the workers first (SIGTERM: graceful), then the API
            p.terminate()
        for p in self.procs:
            try:
                p.wait(60)
            except subprocess.TimeoutExpired:
                p.kill()
        for f in self.files:
            f.close()


def sweep(out: Path, label: str, devices: list[str], base: dict, jobs: int, idle_s: float) -> dict:
    """One timed sweep through a fresh queue with one worker per entry of ``devices``."""
    q = Queue(out, label, devices)
    try:
        q.wait_ready()
        time.sleep(idle_s)
        sampler = GpuSampler()
        rows = q.run_batch(base, list(range(jobs)))
        util = sampler.stop()
        by = q.done_by()
    finally:
        q.close()
    first = min(_t(j["created_at"]) for j in rows)
    last = max(_t(j["finished_at"]) for j in rows if j["finished_at"])
    ids = [j["id"] for j in rows]
    reported = [i for v in by.values() for i in v]
    problems = []
    if any(j["state"] != "done" or j["attempts"] != 1 for j in rows):
        problems.append("not every job done at its first attempt: " + json.dumps(
            sorted({(j["state"], j["attempts"]) for j in rows})))
    if sorted(reported) != sorted(ids):
        problems.append(f"the workers' logs report {len(reported)} jobs done ({len(set(reported))} distinct) "
                        f"for {len(ids)} jobs")
    if len(devices) > 1 and any(not v for v in by.values()):
        problems.append("a worker did no job: " + ", ".join(f"{w} {len(v)}" for w, v in by.items()))
    return {"label": label, "workers": len(devices), "devices": devices, "jobs": len(rows),
            "sweep_s": last - first, "jobs_per_worker": {w: len(v) for w, v in by.items()},
            "gpu_util_mean": util, "loop_s_sum": sum(j.get("loop_s") or 0.0 for j in rows),
            "job_wall_s_sum": sum(j.get("job_wall_s") or 0.0 for j in rows),
            "backends": sorted({j.get("backend") or "" for j in rows}), "problems": problems}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--devices", nargs="+", default=["0", "1"],
                    help="CUDA_VISIBLE_DEVICES of each worker ('' sees no GPU); the first alone is the reference")
    ap.add_argument("--jobs", type=int, default=64)
    ap.add_argument("--n", type=int, default=2_097_152, help="spheres per job")
    ap.add_argument("--steps", type=int, default=5000)
    ap.add_argument("--precision", default="float64", choices=("float64", "float32", "mixed"))
    ap.add_argument("--idle-s", type=float, default=10.0,
                    help="seconds the started workers idle before the submission (their standby processes start)")
    ap.add_argument("--no-prime", action="store_true", help="skip the priming job (kernel cache as found)")
    ap.add_argument("--out", type=Path, default=Path("bench-out") / "gpu_workers")
    args = ap.parse_args(argv)
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    base = sweep_base(args.n, args.steps, args.precision)
    print(f"sweep: {args.jobs} jobs of {args.n} spheres x {args.steps} steps, {args.precision}, phi = 0.058, "
          f"no snapshots; devices {args.devices}", flush=True)
    if not args.no_prime:
        t0 = time.perf_counter()
        sweep(out, "prime", args.devices[:1], base, 1, 0.0)
        print(f"priming job (kernel cache filled): {time.perf_counter() - t0:.1f} s", flush=True)
    runs = []
    for label, devices in (("one", args.devices[:1]), ("all", args.devices)):
        r = sweep(out, label, devices, base, args.jobs, args.idle_s)
        runs.append(r)
        print(f"{r['workers']} worker(s) on {devices}: {r['jobs']} jobs in {r['sweep_s']:.1f} s "
              f"(submission to the last finished_at); jobs per worker {r['jobs_per_worker']}; "
              f"GPU utilisation mean {r['gpu_util_mean']}; backends {r['backends']}; "
              f"sum of job_wall_s {r['job_wall_s_sum']:.1f} s, of loop_s {r['loop_s_sum']:.1f} s", flush=True)
        for p in r["problems"]:
            print(f"  PROBLEM: {p}", flush=True)
    speedup = runs[0]["sweep_s"] / runs[1]["sweep_s"] if runs[1]["sweep_s"] > 0 else 0.0
    print(f"speed-up with {len(args.devices)} workers: {speedup:.2f}", flush=True)
    (out / "gpu_workers.json").write_text(json.dumps({"runs": runs, "speedup": speedup, "base": base}, indent=1))
    return 0 if not any(r["problems"] for r in runs) else 1


if __name__ == "__main__":
    sys.exit(main())
