"""Cundall number of the CUDA backend against N, volume fraction and precision.

Full rough-sphere physics: tangential springs with history, Coulomb limit, rotation and quaternions,
neighbour rebuilds by the L_v/2 rule. Cundall number = N x steps / wall seconds of ``advance`` (after
compilation, placement and the first list build), median of ``--reps`` runs. Per-kernel fractions
come from CUDA events around the phases of a step (a separate, profiled run).

    python -m bench gpu_scaling  # the full table
    python -m bench gpu_scaling --largest                              # largest N in float32
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time

import numpy as np

from bench import out_dir


def scene(n, phi, precision, seed=1, **contact):
    """A random start of ``n`` rough spheres (Hidalgo et al. 2013: e_n = 0.8, e_t = 0.5, friction 0.5, which
    ``contact`` overrides) and its contact constants."""
    from engine.setup.params import derive
    from engine.setup.scene import initial_spheres
    from engine.driver.simulate import contact_params
    from engine.setup.spec import SimulationSpec

    spec = SimulationSpec(n_particles=n, volume_fraction=phi, precision=precision, seed=seed, snapshots=1,
                          **{**dict(e_n=0.8, e_t=0.5, friction=0.5), **contact})
    p = derive(spec)
    c = contact_params(spec, p, thermalization=False)
    assert c.orientation and c.k_t is not None and c.friction is not None
    return initial_spheres(spec, p), c


def lattice_scene(n, phi, precision, seed=1, **contact):
    """A fast start for very large N: jittered simple-cubic lattice (no fcc placement); ``contact`` overrides the
    rough contact of Hidalgo et al. (2013) (e_n = 0.8, e_t = 0.5, friction 0.5)."""
    from engine.backends.base import SphereSystem
    from engine.setup.params import derive
    from engine.driver.simulate import contact_params
    from engine.setup.spec import SimulationSpec

    spec = SimulationSpec(n_particles=n, volume_fraction=phi, precision=precision, seed=seed, snapshots=1,
                          **{**dict(e_n=0.8, e_t=0.5, friction=0.5), **contact})
    p = derive(spec)
    c = contact_params(spec, p, thermalization=False)
    rng = np.random.default_rng(seed)
    m = math.ceil(n ** (1 / 3))
    a = spec.box_length / m
    idx = np.arange(n, dtype=np.int64)
    pos = np.empty((n, 3), np.float32)
    pos[:, 0] = (idx // (m * m)) * a
    pos[:, 1] = ((idx // m) % m) * a
    pos[:, 2] = (idx % m) * a
    pos += (0.5 * a + rng.uniform(-0.2, 0.2, size=(n, 3)).astype(np.float32) * (a - 2 * p.radius))
    vel = rng.standard_normal((n, 3), dtype=np.float32) * np.float32(spec.velocity_rms / math.sqrt(3))
    om = rng.standard_normal((n, 3), dtype=np.float32)
    q = np.zeros((n, 4), np.float32)
    q[:, 0] = 1
    one = np.ones(n, np.float32)
    return SphereSystem(box_length=spec.box_length, position=pos, velocity=vel, angular_velocity=om,
                        orientation=q, radius=one * p.radius, mass=one * p.mass,
                        inertia=one * p.inertia[0]), c


def dense_scene(n, phi, precision, seed=1):
    """Contact-rich stress scene (phi ~ 0.49 lattice, gaps 4 % of a radius), see tests/gpu."""
    sys.path.insert(0, ".")
    from tests.gpu.test_cuda_gpu import _dense

    return _dense(n_side=round(n ** (1 / 3)), precision=precision, seed=seed)


def measure(n, phi, precision, reps, target_s, make=scene, multistep=None, backend=None):
    """One row; ``backend``: the single-scene backend class (default CudaBackend; the ellipsoid bench
    passes CudaEllipsoidBackend with its own ``make``)."""
    from numba import cuda

    from engine.backends.cuda import CudaBackend

    t0 = time.perf_counter()
    system, c = make(n, phi, precision)
    free0 = cuda.current_context().get_memory_info()[0]
    be = (backend or CudaBackend)(system, c)
    del system
    if multistep is not None:
        be.e.multistep = multistep
    be.warmup()
    cuda.synchronize()
    free1 = cuda.current_context().get_memory_info()[0]
    setup = time.perf_counter() - t0
    be.advance(10 if make is not dense_scene else 60)  # dense: let the contacts form first
    t = time.perf_counter()
    be.advance(20)
    per = (time.perf_counter() - t) / 20
    steps = int(max(10, min(20000, target_s / per)))
    runs = []
    b0 = be.builds
    for _ in range(reps):
        t = time.perf_counter()
        be.advance(steps)
        runs.append(n * steps / (time.perf_counter() - t))
    builds_per_step = (be.builds - b0) / (reps * steps)
    # per-kernel fractions: profiled in the one-launch-per-phase loop (CUDA events between phases)
    loop = "multistep" if be.e.multistep else "per-phase"
    be.e.multistep = False
    be.profile = {}
    psteps = min(steps, 1000)
    be.advance(psteps)
    prof = be.profile
    tot = sum(prof.values())
    frac = {k: v / tot for k, v in prof.items()}
    obs = be.observe()
    row = dict(n=n, phi=phi, precision=precision, loop=loop, steps=steps, reps=reps,
               cundall_median=float(np.median(runs)), cundall_runs=runs, frac=frac, kernel_ms_per_step=tot / psteps,
               builds_per_step=builds_per_step, late_rebuilds=be.late_rebuilds, list_slots=be.list_slots,
               bytes_per_particle_arrays=be.device_bytes() / n, bytes_per_particle_meminfo=(free0 - free1) / n,
               contacts_per_particle=obs["contacts"] / n, setup_s=setup)
    del be
    return row


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, nargs="*", default=[4096, 32768, 262144, 2097152, 16777216])
    ap.add_argument("--phi", type=float, nargs="*", default=[0.008, 0.058, 0.3])
    ap.add_argument("--precision", nargs="*", default=["float32", "float64"])
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--target-s", type=float, default=0.4)
    ap.add_argument("--largest", action="store_true")
    ap.add_argument("--dense-n", type=int, nargs="*", default=[], help="contact-rich stress scenes")
    ap.add_argument("--largest-n", type=int, nargs="*", default=[])
    ap.add_argument("--largest-auto", action="store_true",
                    help="after the table, probe the largest float32 N that fits (from the measured B/particle)")
    ap.add_argument("--loop", choices=["auto", "multistep", "per-phase", "both"], default="auto",
                    help="time loop: many steps per launch, one launch per phase, the automatic choice, or both")
    ap.add_argument("--out", default=None, help="folder for gpu_scaling.json (default ./bench-out/gpu_scaling/)")
    args = ap.parse_args()
    from numba import cuda

    import numba
    dev = cuda.get_current_device()
    name = dev.name.decode() if isinstance(dev.name, bytes) else dev.name
    info = dict(gpu=name, date=time.strftime("%Y-%m-%d"), numba=numba.__version__, numpy=np.__version__,
                python=platform.python_version(), total_mem=cuda.current_context().get_memory_info()[1])
    print(json.dumps(info), flush=True)
    rows = []
    if not args.largest:
        for prec in args.precision:
            for phi in args.phi:
                for n in args.n:
                    loops = {"auto": [None], "multistep": [True], "per-phase": [False],
                             "both": [True, False]}[args.loop]
                    for ms in loops:
                        try:
                            r = measure(n, phi, prec, args.reps, args.target_s, multistep=ms)
                        except Exception as e:  # report and go on
                            r = dict(n=n, phi=phi, precision=prec, error=repr(e)[:300])
                        rows.append(r)
                        print(json.dumps(r), flush=True)
    for n in args.dense_n:
        for prec in args.precision:
            r = measure(n, 0.49, prec, args.reps, args.target_s, make=dense_scene)
            r["dense"] = True
            rows.append(r)
            print(json.dumps(r), flush=True)
    if args.largest_auto:
        ok = [r for r in rows if "error" not in r and r["precision"] == "float32" and r["phi"] == 0.058]
        if ok:
            r = max(ok, key=lambda r: r["n"])
            free = cuda.current_context().get_memory_info()[0]
            for f in (0.92, 0.8, 0.65):
                args.largest_n.append(int(f * free / r["bytes_per_particle_meminfo"]) // 1000000 * 1000000)
    done_largest = False
    for n in args.largest_n:
        if done_largest:
            break
        try:
            r = measure(n, 0.058, "float32", 1, 1.0, make=lattice_scene)
            r["largest_probe"] = True
            done_largest = True
        except Exception as e:
            r = dict(n=n, phi=0.058, precision="float32", error=repr(e)[:300], largest_probe=True)
        rows.append(r)
        print(json.dumps(r), flush=True)
    with open(out_dir(args.out, "gpu_scaling") / "gpu_scaling.json", "w") as fh:
        json.dump(dict(info=info, rows=rows), fh, indent=1)
    print("\n| precision | phi | N | loop | Cundall (median) | KD | rebuild | forces | B/particle | list slots |")
    for r in rows:
        if "error" in r:
            print(f"| {r['precision']} | {r['phi']} | {r['n']} | ERROR {r['error'][:80]} |")
            continue
        f = r["frac"]
        print(f"| {r['precision']} | {r['phi']} | {r['n']} | {r['loop']} | {r['cundall_median']:.3g} | "
              f"{f['kick_drift']:.2f} | "
              f"{f['rebuild']:.2f} | {f['forces']:.2f} | {r['bytes_per_particle_meminfo']:.0f} | {r['list_slots']} | "
              f"{r['contacts_per_particle']:.2g} |")


if __name__ == "__main__":
    sys.exit(main())
