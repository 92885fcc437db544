"""Where a fresh process's 2M-sphere job spends its time outside the loop (issue 14): cProfile of engine.run.

Runs, each in a fresh Python process: two plain jobs (the first fills the kernel caches), two probes of the
one-off start-up (numba import, numba.cuda import and driver check, context creation, engine.scene import),
one job under cProfile (written to $OUT/profile.txt and $OUT/run.prof, cumulative and internal time) and a
last plain job (their JSON lines also go to $OUT/runs.jsonl). The job is bench/e2e.py's spheres-2M-f64 case
with PSTEPS steps (default 200). On the GPU machine:

    OUT=/tmp/prof python3 bench/e2e_profile.py

The 2026-11-25 H100 profile is in bench/reports/e2e-cuda/fresh-process-profile/profile.txt.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
OUT = os.environ.get("OUT", "/tmp")
STEPS = int(os.environ.get("PSTEPS", "200"))


def child(mode: str) -> None:
    """One job (or probe) in this process; prints one JSON line."""
    t0 = time.perf_counter()
    from bench.e2e import case_specs, to_spec
    import engine.simulate as simulate

    t1 = time.perf_counter()
    d = case_specs("spheres-2M-f64", False)["specs"][0]
    d["_steps"] = STEPS
    spec = to_spec(d)
    if mode == "probe":
        import numba  # noqa: F401  (its import time is what is measured)

        t2 = time.perf_counter()
        from numba import cuda

        cuda.is_available()
        t3 = time.perf_counter()
        cuda.current_context()
        t4 = time.perf_counter()
        import engine.scene  # noqa: F401

        t5 = time.perf_counter()
        print(json.dumps(dict(mode=mode, imports=t1 - t0, numba=t2 - t1, is_available=t3 - t2, context=t4 - t3,
                              scene_import=t5 - t4)))
        return
    prof = None
    if mode == "profile":
        import cProfile

        prof = cProfile.Profile()
        prof.enable()
    ta = time.perf_counter()
    summary = simulate.run(spec, f"/tmp/e2e_profile_{mode}.h5")
    tb = time.perf_counter()
    if prof is not None:
        import io
        import pstats

        prof.disable()
        prof.dump_stats(os.path.join(OUT, "run.prof"))
        text = io.StringIO()
        stats = pstats.Stats(prof, stream=text)
        stats.sort_stats("cumtime").print_stats(90)
        stats.sort_stats("tottime").print_stats(40)
        with open(os.path.join(OUT, "profile.txt"), "w") as f:
            f.write(text.getvalue())
    print(json.dumps(dict(mode=mode, imports=t1 - t0, wall=tb - ta, timings=summary.extra["timings"])))


def main() -> None:
    with open(os.path.join(OUT, "runs.jsonl"), "a") as log:
        for mode in ("plain", "probe", "probe", "plain", "profile", "plain"):
            t = time.perf_counter()
            p = subprocess.run([sys.executable, __file__, mode], capture_output=True, text=True)
            line = p.stdout.strip().splitlines()[-1] if p.stdout.strip() else ""
            print(mode, f"{time.perf_counter() - t:.2f} s", line, p.stderr[-1500:] if p.returncode else "", flush=True)
            log.write(line + "\n")


if __name__ == "__main__":
    if len(sys.argv) > 1:
        child(sys.argv[1])
    else:
        main()
