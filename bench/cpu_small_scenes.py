"""Small CPU scenes: the time loop with and without parallel regions, and the whole default small job.

For each ``--n`` the same scene (the default spec at that N, no snapshots, one record, the random start with no
thermalisation, ``--t-end`` s) is run through ``engine.run`` on one Numba thread in both CPU time loops
(engine/loops/cpu.py ``make_run_steps``: ``parallel=True`` regions, and the loop compiled without them; the
engine picks the second below ``SERIAL_LOOP_BELOW`` particles), alternated within each repetition. Printed: the
loop's nanoseconds per particle-step (``RunSummary.loop_s`` / steps / N), median and range of ``--reps``.

Then ``--jobs`` jobs of 64 spheres with the default spec otherwise (200 records, 5 snapshots) through ``engine.run``
in this warm process, as the engine picks: the median wall time of the whole call and of its time loop. This is the
job of bench/small_jobs.py without the service around it.

    NUMBA_NUM_THREADS=1 python -m bench cpu_small_scenes [--n 64 256 1024 4096] [--reps 3] [--jobs 25]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path


def _loops(sizes, reps: int, t_end: float, folder: Path) -> None:
    import engine.loops.cpu as cpu
    from engine.driver.simulate import run
    from engine.setup.spec import SimulationSpec

    chosen = cpu.SERIAL_LOOP_BELOW
    try:
        for n in sizes:
            spec = SimulationSpec(n_particles=n, backend="cpu", snapshots=0, t_end=t_end, thermalization=0,
                                  output_interval=t_end)
            per: dict = {"regions": [], "no regions": []}
            for rep in range(reps + 1):          # the first round compiles or loads both loops: not counted
                for name, below in (("regions", 0), ("no regions", 1 << 62)):
                    cpu.SERIAL_LOOP_BELOW = below
                    s = run(spec.model_copy(update={"seed": rep + 1}), folder / f"loop-{n}-{rep}-{below}.h5")
                    if rep:
                        per[name].append(s.loop_s / s.steps / n * 1e9)
            text = "; ".join(f"{name} {statistics.median(v):.1f} ns ({min(v):.1f}-{max(v):.1f})"
                             for name, v in per.items())
            print(f"N = {n:6d}, {s.steps} steps: {text} per particle-step", flush=True)
    finally:
        cpu.SERIAL_LOOP_BELOW = chosen


def _small_jobs(jobs: int, folder: Path) -> None:
    from engine.driver.simulate import run
    from engine.setup.spec import SimulationSpec

    spec = SimulationSpec(n_particles=64, backend="cpu")
    run(spec, folder / "job-warm.h5")
    wall, loop = [], []
    for k in range(jobs):
        t0 = time.perf_counter()
        s = run(spec.model_copy(update={"seed": k + 1}), folder / f"job-{k}.h5")
        wall.append(time.perf_counter() - t0)
        loop.append(s.loop_s)
    print(f"{jobs} default jobs of 64 spheres ({s.steps} steps each): engine.run median "
          f"{statistics.median(wall) * 1e3:.1f} ms ({min(wall) * 1e3:.1f}-{max(wall) * 1e3:.1f}), of which the time "
          f"loop {statistics.median(loop) * 1e3:.1f} ms", flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, nargs="+", default=[64, 256, 1024, 4096])
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--t-end", type=float, default=0.02, help="simulated seconds of each loop scene")
    ap.add_argument("--jobs", type=int, default=25, help="64-sphere default jobs (0: none)")
    args = ap.parse_args(argv)
    import numba

    print(f"Numba threads: {numba.get_num_threads()}")
    with tempfile.TemporaryDirectory(prefix="demq-cpu-small-") as tmp:
        if args.n:
            _loops(args.n, args.reps, args.t_end, Path(tmp))
        if args.jobs:
            _small_jobs(args.jobs, Path(tmp))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
