"""Cancel latency of a running job: seconds from the cancel request to the job row's ``cancelled``.

A real worker (jobs/worker.py, default engine, SQLite queue in a temporary data directory) runs a CPU job of
``--n`` spheres (default 20 000; the default spec otherwise); once its time loop runs (its result file is open and
``--settle`` more seconds have passed), the job is cancelled through the store, as the API does, and the row is
read every 5 ms until it says ``cancelled``. Each repetition also checks that no result, partial result or
checkpoint is left. The engine's own cancel checks come at its stops (every ``output_every`` steps: about 1400
steps of 20 000 spheres, seconds on a CPU), so the latency measures the worker's path: its cancel poll
(DEMQ_CANCEL_POLL_SECONDS), the stop flag, the kill after DEMQ_CANCEL_KILL_SECONDS, the clean-up and the row write.

    python3 -m bench.cancel_latency [--n 20000] [--reps 3] [--settle 1.0]

Prints one line per repetition and the worst one. Run it with the CPU to itself: the kernels load from the disk
cache (a cold cache compiles first, before the measured part).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import threading
import time
from pathlib import Path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=20000, help="spheres of the job (default 20000)")
    parser.add_argument("--reps", type=int, default=3, help="cancelled jobs (default 3)")
    parser.add_argument("--settle", type=float, default=1.0, help="seconds of time loop before the cancel")
    args = parser.parse_args(argv)

    from jobs.schema import CANCELLED, RUNNING
    from jobs.settings import Settings
    from jobs.specs import parse_spec
    from jobs.store import NewJob
    from jobs.stores import open_store
    from jobs.worker import Worker

    latencies = []
    with tempfile.TemporaryDirectory(prefix="demq-cancel-") as tmp:
        settings = Settings.from_env(environ={}, data_dir=Path(tmp), warm="off", standby="off", poll_s=0.05)
        store = open_store(settings.database_url)
        worker = Worker(store, settings)
        thread = threading.Thread(target=worker.run_forever, daemon=True)
        thread.start()
        try:
            for rep in range(args.reps):
                spec = parse_spec({"n_particles": args.n, "backend": "cpu", "seed": rep})
                (job,) = store.submit([NewJob(spec.to_json())])
                part = settings.result_path(job.id).parent / f"{job.id}.h5.part"
                while not (part.exists() and store.get(job.id).state == RUNNING):
                    time.sleep(0.01)
                time.sleep(args.settle)
                t0 = time.perf_counter()
                store.request_cancel(job.id)
                while store.get(job.id).state != CANCELLED:
                    time.sleep(0.005)
                latency = time.perf_counter() - t0
                time.sleep(0.5)   # the worker's clean-up after the row write
                left = [p.name for p in (part, settings.result_path(job.id), settings.checkpoint_dir(job.id))
                        if p.exists()]
                latencies.append(latency)
                print(json.dumps({"rep": rep, "n_particles": args.n, "cancel_to_cancelled_s": round(latency, 3),
                                  "files_left": left}), flush=True)
        finally:
            worker.stop()
            thread.join(60)
            store.close()
    print(f"worst cancel latency over {len(latencies)} jobs of {args.n} spheres: {max(latencies):.3f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
