"""Cundall number (particle-steps per second) of the CPU backend against N, phi and thread count.

    python -m bench cpu_scaling --n 4096 32768 262144 --phi 0.058 0.008 --threads 1 2

What is timed (docs/design.md): the full rough-sphere step of engine/loops/cpu.py — velocity Verlet, periodic
wrap, Fincham quaternion update, tangential springs with history and contact-event corrections, torques,
Verlet lists rebuilt by the L_v/2 rule with spring carry-over, stability guards — plus the observables
reduction at the default output cadence (t_end/200 of a run as long as the timed one). Not timed: JIT
compilation (warmed up first), placement, the first list build. The gas is the spec's scene (the parameters of
Hidalgo et al. 2013; box scaled with N at fixed phi) after a short elastic warm-up so that collisions are under way.
Each figure is the median of --reps timed runs of about --seconds wall seconds each.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time

import numba

from bench import out_dir
from engine.shapes.sphere.cpu_backend import CpuBackend
from engine.setup.params import derive
from engine.setup.scene import initial_spheres
from engine.driver.simulate import contact_params
from engine.setup.spec import SimulationSpec


def scene(n: int, phi: float, precision: str):
    # keep the Hidalgo et al. (2013) particle size (a = 1.55 cm): L grows with N at fixed phi
    a = 0.015508762272485004
    box = (n * 4.0 / 3.0 * 3.141592653589793 * a**3 / phi) ** (1 / 3)
    spec = SimulationSpec(n_particles=n, volume_fraction=phi, box_length=box, precision=precision, backend="cpu",
                          snapshots=1)
    p = derive(spec)
    return spec, p, initial_spheres(spec, p)


def measure(n, phi, threads, precision, seconds, reps):
    numba.set_num_threads(threads)
    spec, p, system = scene(n, phi, precision)
    be = CpuBackend(system, contact_params(spec, p, thermalization=False))
    be.warmup()
    be.advance(50)
    # calibrate the number of steps for ~`seconds` of wall time
    t0 = time.perf_counter()
    be.advance(20)
    per_step = (time.perf_counter() - t0) / 20
    steps = max(50, int(seconds / per_step))
    every = max(1, steps // 200)
    rates = []
    builds0 = be.builds
    for _ in range(reps):
        t0 = time.perf_counter()
        done = 0
        while done < steps:
            k = min(every, steps - done)
            be.advance(k)
            be.observe()
            done += k
        rates.append(n * steps / (time.perf_counter() - t0))
    obs = be.observe()
    return {"n": n, "phi": phi, "threads": threads, "precision": precision, "steps": steps,
            "cundall_median": statistics.median(rates), "cundall_runs": rates,
            "builds_per_step": (be.builds - builds0) / (steps * reps), "contacts_per_particle": obs["contacts"] / n,
            "radius": p.radius, "box_length": spec.box_length}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, nargs="+", default=[4096, 32768, 262144])
    ap.add_argument("--phi", type=float, nargs="+", default=[0.058, 0.008])
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--precision", nargs="+", default=["float64"])
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--out", default=None, help="folder for cpu_scaling.json (default ./bench-out/cpu_scaling/)")
    a = ap.parse_args()
    cpu = "unknown"
    try:
        cpu = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    rows = []
    print(f"# {cpu}, {numba.config.NUMBA_NUM_THREADS} hardware threads, numba {numba.__version__}, {platform.python_version()}")
    print("| precision | phi | N | threads | Cundall (median) | runs | rebuilds/step | contacts/particle |")
    print("|---|---|---|---|---|---|---|---|")
    for prec in a.precision:
        for phi in a.phi:
            for n in a.n:
                for t in a.threads:
                    r = measure(n, phi, t, prec, a.seconds, a.reps)
                    rows.append(r)
                    print(f"| {prec} | {phi} | {n} | {t} | {r['cundall_median']:.3g} | "
                          f"{', '.join(f'{x:.3g}' for x in r['cundall_runs'])} | {r['builds_per_step']:.3f} | "
                          f"{r['contacts_per_particle']:.2e} |", flush=True)
    with open(out_dir(a.out, "cpu_scaling") / "cpu_scaling.json", "w") as fh:
        json.dump({"cpu": cpu, "numba": numba.__version__, "rows": rows}, fh, indent=1)


if __name__ == "__main__":
    main()
