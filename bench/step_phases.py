"""GPU time per step phase, kernel by kernel (kick_drift, forces and, for smooth spheres, the fused kernel).

A diagnostic of the one-launch-per-phase loop, less noisy than the phase shares of bench/gpu_scaling.py (CUDA
events around the phases of whole steps, host waits included): on the Hidalgo et al. (2013) rough scene (lattice start,
phi = 0.058, e_t = 0.5, Coulomb 0.5, orientations tracked), after ``--warm-s`` seconds of steps (lists and
contacts settle, the GPU's clocks ramp up: without it the first scene timed in a process ran up to 40 % slow), it
times ``--launches`` back-to-back launches of kick_drift alone, then of forces alone, with CUDA events (GPU time
per launch; for a specialisation that has it, the fused forces_kick_drift too), and the whole loop: N x steps /
wall of ``advance`` (the loop Cundall number; bench/e2e.py gives the end-to-end one), the fused step and the two
launches alternated (engine.loops.cuda_stepping.FUSED). ``--contact elastic`` runs elastic frictionless spheres
(bench/vs_jaxmd.py's contact) on the same start. One JSON line per (contact, precision, N).

The state the lone-phase launches change (positions moved without forces, springs advanced at fixed positions) is
put back before the loop is timed.

    python -m bench step_phases --n 2097152 16777216 --precision float64 float32 mixed
    python -m bench step_phases --n 2097152 8388608 --precision float64 float32 --contact elastic paper
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np


#: the device arrays that kick_drift or forces launched alone change (restored after timing them)
_TOUCHED = ("pos", "vel", "omega", "quat", "q_last", "f_cur", "f_nxt", "torque", "hist")


#: --contact: the module doc's rough scene (Hidalgo et al. 2013), or elastic frictionless spheres (bench/vs_jaxmd.py's)
CONTACTS = {"paper": {}, "elastic": dict(e_n=1.0, e_t=-1.0, friction=None)}


def measure(n: int, precision: str, launches: int, loop_steps: int, warm_s: float, contact: str = "paper") -> dict:
    from numba import cuda

    import engine.loops.cuda_stepping as stepping
    from bench.gpu_scaling import lattice_scene
    from engine.backends.cuda import CudaBackend

    system, c = lattice_scene(n, 0.058, precision, **CONTACTS[contact])
    be = CudaBackend(system, c)
    del system
    e = be.e
    e.multistep = False
    be.warmup()
    be.advance(50)
    t = time.perf_counter()
    while time.perf_counter() - t < warm_s:   # the GPU's clocks ramp up under load: time it at speed
        be.advance(50)
    cuda.synchronize()
    out = dict(n=n, precision=precision, contact=contact, gpu=e.device, launches=launches)
    # the phases timed alone move the particles without forces (kick_drift) and advance the contact springs at
    # fixed positions (forces): the state is put back afterwards, or the loop timed next would start from
    # overlaps that no real step makes
    kept = {name: getattr(e, name).copy_to_host(stream=e.stream) for name in _TOUCHED if hasattr(e, name)}
    cuda.synchronize()
    for name in ("kick_drift", "forces") + (("forces_kick_drift",) if "forces_kick_drift" in e.k else ()):
        ms = []
        for _ in range(3):
            a, b = cuda.event(timing=True), cuda.event(timing=True)
            a.record(e.stream)
            for j in range(launches):
                step = e.steps_done + j
                if name == "kick_drift":
                    e._kick_drift(0, step, exact=0)
                elif name == "forces":
                    e._forces(step)
                else:
                    e._forces_kick_drift(step, j & 1, 0)
            b.record(e.stream)
            b.synchronize()
            ms.append(cuda.event_elapsed_time(a, b) / launches)
        out[name + "_ms"] = float(np.median(ms))
    for name, a in kept.items():
        getattr(e, name).copy_to_device(a, stream=e.stream)
    cuda.synchronize()
    be.advance(10)
    walls = {True: [], False: []}
    for _ in range(5):
        for fused in (True, False):     # the fused step and the two-launch step, alternated
            stepping.FUSED = fused
            t = time.perf_counter()
            be.advance(loop_steps)
            walls[fused].append(time.perf_counter() - t)
    stepping.FUSED = True
    for fused, key in ((True, ""), (False, "_two_launch")):
        out["loop_cundall" + key] = n * loop_steps / float(np.median(walls[fused]))
        out["loop_ms_per_step" + key] = 1e3 * float(np.median(walls[fused])) / loop_steps
    out["kick_drift_share"] = out["kick_drift_ms"] / (out["kick_drift_ms"] + out["forces_ms"])
    out["contacts_per_particle"] = be.observe()["contacts"] / n
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, nargs="*", default=[2097152, 16777216])
    ap.add_argument("--precision", nargs="*", default=["float64", "float32", "mixed"])
    ap.add_argument("--launches", type=int, default=200)
    ap.add_argument("--loop-steps", type=int, default=300)
    ap.add_argument("--warm-s", type=float, default=3.0, help="seconds of steps before timing (clock ramp-up)")
    ap.add_argument("--label", default="")
    ap.add_argument("--contact", nargs="*", choices=list(CONTACTS), default=["paper"])
    args = ap.parse_args()
    for contact in args.contact:
        for prec in args.precision:
            for n in args.n:
                r = measure(n, prec, args.launches, args.loop_steps, args.warm_s, contact)
                r["label"] = args.label
                print(json.dumps(r), flush=True)
    return 0


if __name__ == "__main__":
    sys.path.insert(0, ".")
    sys.exit(main())
