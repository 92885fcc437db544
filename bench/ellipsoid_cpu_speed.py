"""CPU speed of the ellipsoid backend on the Rubio-Largo et al. (2015) gas: Cundall number of
``CpuEllipsoidBackend.advance`` after compilation, placement and the first list build, median of --reps runs,
and a fingerprint of the final state (so that two code versions can be checked for identical trajectories).

Scene: bench/gpu_ellipsoid_scaling.py's random gas (xi = 2, phi = 0.058, e_n = 0.9, engine contact constants,
v_rms = 3.5 m/s, placement without overlaps), float64 by default.

    NUMBA_NUM_THREADS=1 python -m bench ellipsoid_cpu_speed --n 32768 --steps 200 --reps 3
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

import numba
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench import out_dir  # noqa: E402
from bench.gpu_ellipsoid_scaling import ellipsoid_gas  # noqa: E402


def fingerprint(be) -> str:
    h = hashlib.sha256()
    for a in (be.pos, be.vel, be.angm, be.quat):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=32768)
    ap.add_argument("--xi", type=float, default=2.0)
    ap.add_argument("--phi", type=float, default=0.058)
    ap.add_argument("--precision", default="float64")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--no-screen", action="store_true", help="disable the exact screens (PW_SCREEN < 0)")
    ap.add_argument("--pw-tol", type=float, default=None, help="Perram-Wertheim tolerance (default: PW_TOL)")
    ap.add_argument("--out", default=None,
                    help="folder for ellipsoid_cpu_speed.json (default ./bench-out/ellipsoid_cpu_speed/)")
    args = ap.parse_args(argv)
    from engine.shapes.spheroid import cpu_backend as cpu_ellipsoid
    from engine.shapes.spheroid.cpu_backend import CpuEllipsoidBackend

    if args.no_screen:
        cpu_ellipsoid.PW_SCREEN[args.precision] = -1.0
    if args.pw_tol is not None:
        cpu_ellipsoid.PW_TOL[args.precision] = args.pw_tol

    system, c = ellipsoid_gas(args.n, args.phi, args.precision, xi=args.xi)
    be = CpuEllipsoidBackend(system, c)
    be.warmup()
    be.advance(5)
    runs = []
    for _ in range(args.reps):
        t = time.perf_counter()
        be.advance(args.steps)
        runs.append(args.n * args.steps / (time.perf_counter() - t))
    obs = be.observe()
    row = dict(n=args.n, xi=args.xi, phi=args.phi, precision=args.precision, steps=args.steps, reps=args.reps,
               threads=numba.get_num_threads(), cundall_median=float(np.median(runs)), cundall_runs=runs,
               steps_done=be.steps_done, builds=be.builds, contacts=obs["contacts"],
               fingerprint=fingerprint(be), pw_tol=float(be.tol),
               screen_margin=float(getattr(be, "margin", float("nan"))))
    print(json.dumps(row))
    (out_dir(args.out, "ellipsoid_cpu_speed") / "ellipsoid_cpu_speed.json").write_text(json.dumps(row, indent=1))
    return row


if __name__ == "__main__":
    main()
