"""Where a packed batch's wall time goes on the main thread, by the driver's phases (a diagnostic).

bench/e2e.py's batch-256x4096-20k through engine.run_ensemble, in this process, with timers around the driver's
methods on the main thread (advance, at_stop, the ensemble's observe, the files'
open and finish, the build). numba.cuda is imported before the timer starts (so the set-up excludes it). On the
GPU machine, after a run that filled the kernel cache:

    python -m bench batch_where
"""

from __future__ import annotations

import collections
import functools
import json
import os
import sys
import tempfile
import threading
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

SECONDS: dict = collections.defaultdict(float)
CALLS: collections.Counter = collections.Counter()


def _timed(owner, name: str, label: str) -> None:
    """Replace owner.name by a wrapper that adds its main-thread wall time to SECONDS[label]."""
    f = getattr(owner, name)

    @functools.wraps(f)
    def wrapper(*a, **k):
        if threading.current_thread() is not threading.main_thread():
            return f(*a, **k)
        t = time.perf_counter()
        try:
            return f(*a, **k)
        finally:
            SECONDS[label] += time.perf_counter() - t
            CALLS[label] += 1

    setattr(owner, name, wrapper)


def main() -> None:
    import engine.backends.cuda as cb
    import engine.driver.ensemble as ens_mod
    import engine.driver.simulate as sim
    from bench.e2e import case_specs, to_spec

    for owner, name, label in ((sim.SceneRun, "at_stop", "at_stop"),
                               (sim, "_build", "build"), (sim.SceneRun, "open", "open"),
                               (sim.SceneRun, "finish_begin", "finish_begin"),
                               (sim.SceneRun, "finish_end", "finish_end"), (cb.CudaEnsemble, "set_contacts", "set_contacts"),
                               (cb.CudaEnsemble, "advance", "advance"),
                               (cb.CudaEnsemble, "observe", "ensemble observe"),
                               (cb.CudaEnsemble, "deactivate_many", "deactivate_many"), (sim, "drive", "drive")):
        _timed(owner, name, label)
    ens_mod.drive = sim.drive
    specs = [to_spec(d) for d in case_specs("batch-256x4096-20k", False)["specs"]]
    out = tempfile.mkdtemp()
    t0 = time.perf_counter()
    res = ens_mod.run_ensemble(specs, [f"{out}/s{k}.h5" for k in range(len(specs))])
    wall = time.perf_counter() - t0
    loop = max(r.loop_s for r in res)
    print(json.dumps({"wall": round(wall, 3), "loop": round(loop, 3), "ratio": round(loop / wall, 3),
                      "setup": round(res[0].extra["ensemble_setup_s"], 3)}))
    for label, s in sorted(SECONDS.items(), key=lambda x: -x[1]):
        print(f"  {s:7.3f} s x{CALLS[label]:<6d} {label}")


if __name__ == "__main__":
    main()
