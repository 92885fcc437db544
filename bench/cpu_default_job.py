"""The default job's warm wall time on the CPU, source trees alternated, optionally beside busy loops.

The job is ``engine.run`` of the README's default spec (``SimulationSpec()``: 4096 rough spheres, phi = 0.008,
e_n = e_t = 0.8, t_end = 0.1 s, 127 324 steps) with backend 'cpu'. Every run is a fresh process whose ``engine`` is
imported from one of ``--trees`` (PYTHONPATH; e.g. an old tree made with ``git archive main engine | tar -x -C
/tmp/base`` against this checkout), after one warm-up run per tree that fills the Numba disk cache. The trees are
alternated within each repetition, so that a change of the machine's load hits both alike. ``--busy K`` starts K
busy loops (other processes, one core each) for the runs that name it: the load the CPU loop's thread choice is
about (engine/backends/ensemble.py ``ThreadChoice``).

Printed per run: the tree, the busy loops, ``run_s`` (the whole ``engine.run`` call, result file included) and
``loop_s`` (``RunSummary.loop_s``, the time loop); then per tree and load the median and the range.

    python -m bench cpu_default_job --trees /tmp/base . --reps 3 --busy 0 1
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

_CHILD = r"""
import json, sys, time
t0 = time.perf_counter()
import engine
from engine.setup.spec import SimulationSpec
t1 = time.perf_counter()
r = engine.run(SimulationSpec(backend="cpu"), sys.argv[1])
t2 = time.perf_counter()
print(json.dumps({"engine": engine.__file__, "import_s": t1 - t0, "run_s": t2 - t1, "loop_s": r.loop_s}))
"""


def run_once(tree: Path, threads: int | None) -> dict:
    """One default job in a fresh process importing ``engine`` from ``tree``."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    if threads:
        env["NUMBA_NUM_THREADS"] = str(threads)
    with tempfile.TemporaryDirectory() as tmp:      # the child's cwd: not a checkout, so PYTHONPATH decides
        p = subprocess.run([sys.executable, "-c", _CHILD, str(Path(tmp) / "job.h5")], cwd=tmp, env=env,
                           capture_output=True, text=True, timeout=1800)
    if p.returncode != 0:
        raise RuntimeError(f"the job under {tree} failed:\n{p.stderr[-3000:]}")
    out = json.loads(p.stdout.strip().splitlines()[-1])
    if not Path(out["engine"]).resolve().is_relative_to(tree.resolve()):
        raise RuntimeError(f"the child imported {out['engine']}, not the tree {tree}")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trees", nargs="+", default=["."], help="source trees holding engine/ (PYTHONPATH of a run)")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--busy", type=int, nargs="+", default=[0], help="busy loops beside the runs (one set each)")
    ap.add_argument("--threads", type=int, default=None, help="NUMBA_NUM_THREADS of the runs (default: Numba's)")
    args = ap.parse_args(argv)
    trees = [Path(t).resolve() for t in args.trees]
    for tree in trees:                                # warm-up: compile or load the kernels once per tree
        run_once(tree, args.threads)
    rows = []
    for busy in args.busy:
        hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(busy)]
        try:
            for rep in range(args.reps):
                for tree in trees:
                    r = run_once(tree, args.threads)
                    rows.append((str(tree), busy, r["run_s"], r["loop_s"]))
                    print(f"tree={tree} busy={busy} rep={rep} run_s={r['run_s']:.3f} loop_s={r['loop_s']:.3f}",
                          flush=True)
        finally:
            for h in hogs:
                h.kill()
                h.wait()
    for busy in args.busy:
        for tree in trees:
            run = [r[2] for r in rows if r[0] == str(tree) and r[1] == busy]
            loop = [r[3] for r in rows if r[0] == str(tree) and r[1] == busy]
            print(f"summary tree={tree} busy={busy} run_s median {statistics.median(run):.2f} "
                  f"({min(run):.2f}-{max(run):.2f}) loop_s median {statistics.median(loop):.2f} "
                  f"({min(loop):.2f}-{max(loop):.2f})", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
