"""Where a fresh process's 2M-sphere job spends its time outside the loop: cProfile of engine.run.

Runs, each in a fresh Python process: two plain jobs (the first fills the kernel caches), two probes of the
one-off start-up stage by stage (numba import, numba.cuda import, driver check, context creation, the first
cached CPU kernel's load (numba's CPU target; engine/numba_support/jitcache.py's fast loads skip its registries and scipy.linalg,
which the probe reports as imported or not), the GPU start-up thread's stand-in scene: CUDA registries and kernel
cache loads),
one job under cProfile (written to OUT/profile.txt and OUT/run.prof, cumulative and internal time) and a
last plain job (their JSON lines also go to OUT/runs.jsonl). The job is bench/e2e.py's case PCASE (default
spheres-2M-f64; a batch case runs through run_ensemble) with PSTEPS steps (default 200). On the GPU machine:

    python -m bench e2e_profile [--out DIR]          (MODES="probe probe" for the probes alone)
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
#: the folder of profile.txt and run.prof, set by main() for the child processes
OUT = os.environ.get("OUT", "/tmp")
STEPS = int(os.environ.get("PSTEPS", "200"))
#: the bench/e2e.py case (a one-scene case through engine.run, or a batch case through engine.run_ensemble)
CASE = os.environ.get("PCASE", "spheres-2M-f64")


def child(mode: str) -> None:
    """One job (or probe) in this process; prints one JSON line."""
    t0 = time.perf_counter()
    from bench.e2e import case_specs, to_spec
    import engine.driver.simulate as simulate

    t1 = time.perf_counter()
    info = case_specs(CASE, False)
    d = info["specs"][0]
    d["_steps"] = STEPS
    spec = to_spec(d)
    batch = [to_spec(dict(x, _steps=STEPS)) for x in info["specs"]] if info["path"] == "ensemble" else None
    if mode == "probe":
        # the one-off start-up, stage by stage, in this order (each stage's imports included)
        import numba  # noqa: F401  (its import time is what is measured)

        t = [time.perf_counter()]
        from numba import cuda

        t.append(time.perf_counter())
        cuda.is_available()
        t.append(time.perf_counter())
        cuda.current_context()
        t.append(time.perf_counter())
        import engine.setup.scene as scene

        scene._stream_key(1, 1)    # the first cached njit call: numba's CPU target
        t.append(time.perf_counter())
        from engine.setup.params import derive
        from engine.shapes import host
        from engine.driver.simulate import contact_params
        from engine.driver.startup import STANDIN_EDGE, GpuStartup

        p = derive(spec)
        s = GpuStartup("sphere", host("sphere").standin_system(p, STANDIN_EDGE),
                       (contact_params(spec, p, thermalization=False),))
        s.wait()                   # the stand-in backend: CUDA registries and the kernels' cache loads
        t.append(time.perf_counter())
        d = [b - a for a, b in zip(t, t[1:])]
        print(json.dumps(dict(mode=mode, imports=t1 - t0, numba=t[0] - t1, numba_cuda_import=d[0],
                              is_available=d[1], context=d[2], cpu_first_load=d[3], kernels=d[4],
                              startup_error=s.error,
                              scipy_imported="scipy.linalg" in sys.modules)))
        return
    prof = None
    if mode == "profile":
        import cProfile

        prof = cProfile.Profile()
        prof.enable()
    ta = time.perf_counter()
    if batch is None:
        summary = simulate.run(spec, f"/tmp/e2e_profile_{mode}.h5")
    else:
        from engine.driver.ensemble import run_ensemble

        summary = run_ensemble(batch, [f"/tmp/e2e_profile_{mode}_{k}.h5" for k in range(len(batch))])[-1]
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
    import argparse

    from bench import out_dir

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=None, help="folder for profile.txt, run.prof, runs.jsonl "
                    "(default ./bench-out/e2e_profile/)")
    out = str(out_dir(ap.parse_args().out, "e2e_profile"))
    with open(os.path.join(out, "runs.jsonl"), "a") as log:
        for mode in os.environ.get("MODES", "plain probe probe plain profile plain").split():
            t = time.perf_counter()
            p = subprocess.run([sys.executable, __file__, mode], capture_output=True, text=True,
                               env={**os.environ, "OUT": out})
            line = p.stdout.strip().splitlines()[-1] if p.stdout.strip() else ""
            print(mode, f"{time.perf_counter() - t:.2f} s", line, p.stderr[-1500:] if p.returncode else "", flush=True)
            log.write(line + "\n")


if __name__ == "__main__":
    if len(sys.argv) > 1 and not sys.argv[1].startswith("-"):
        child(sys.argv[1])
    else:
        main()
