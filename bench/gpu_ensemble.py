"""Aggregate Cundall number of K small scenes advanced together on the GPU.

K independent scenes of N = 4096 rough spheres (paper size; phi = 0.058, e_n = 0.9, e_t = 0.5, Coulomb
mu = 0.5, rotation and quaternions, own seed and e_n per scene) in one :class:`CudaEnsemble`.
Aggregate Cundall number = K x N x steps / wall seconds of ``advance`` (after compilation, placement and
the first list build), median of ``--reps`` runs, for the many-steps-per-launch loop and, for
comparison, one launch per phase.

    python -m bench gpu_ensemble --k 1 16 64 256 1024
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time

import numpy as np

from bench import out_dir

_made: dict = {}


def scenes(k, n, phi, precision):
    """The first k scenes (placed once per precision and reused for smaller k and both loops)."""
    key = (n, phi, precision)
    have = _made.get(key, ([], []))
    if len(have[0]) < k:
        more = _place(len(have[0]), k, n, phi, precision)
        have = (have[0] + more[0], have[1] + more[1])
        _made[key] = have
    return have[0][:k], have[1][:k]


def _place(k0, k, n, phi, precision):
    from engine.setup.params import derive
    from engine.setup.scene import initial_spheres
    from engine.driver.simulate import contact_params
    from engine.setup.spec import SimulationSpec

    systems, contacts = [], []
    for s in range(k0, k):
        spec = SimulationSpec(n_particles=n, volume_fraction=phi, e_n=(0.8, 0.9, 0.95, 0.98)[s % 4], e_t=0.5,
                              friction=0.5, precision=precision, seed=1000 + s, snapshots=1)
        p = derive(spec)
        systems.append(initial_spheres(spec, p))
        contacts.append(contact_params(spec, p, thermalization=False))
    return systems, contacts


def measure(k, n, phi, precision, multistep, reps, target_s):
    from numba import cuda

    from engine.backends.cuda import CudaEnsemble

    t0 = time.perf_counter()
    systems, contacts = scenes(k, n, phi, precision)
    free0 = cuda.current_context().get_memory_info()[0]
    ens = CudaEnsemble(systems, contacts)
    ens.multistep = multistep
    ens.warmup()
    cuda.synchronize()
    free1 = cuda.current_context().get_memory_info()[0]
    setup = time.perf_counter() - t0
    ens.advance(10)
    t = time.perf_counter()
    ens.advance(50)
    per = (time.perf_counter() - t) / 50
    steps = int(max(20, min(50000, target_s / per)))
    runs = []
    b0, l0 = ens.builds, ens.launches
    for _ in range(reps):
        t = time.perf_counter()
        failed = ens.advance(steps)
        runs.append(k * n * steps / (time.perf_counter() - t))
        assert not failed, failed
    obs = ens.observe()
    row = dict(k=k, n=n, phi=phi, precision=precision, loop="multistep" if multistep else "per-phase",
               steps=steps, reps=reps, cundall_aggregate=float(np.median(runs)), cundall_runs=runs,
               us_per_step=1e6 * k * n / float(np.median(runs)),
               builds_per_step=(ens.builds - b0) / (reps * steps),
               launches_per_step=(ens.launches - l0) / (reps * steps),
               coop_blocks=ens._coop_blocks, bytes_per_particle_meminfo=(free0 - free1) / (k * n),
               contacts_per_particle=sum(o["contacts"] for o in obs) / (k * n), setup_s=setup)
    del ens
    return row


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--k", type=int, nargs="*", default=[1, 16, 64, 256, 1024])
    ap.add_argument("--n", type=int, default=4096)
    ap.add_argument("--phi", type=float, default=0.058)
    ap.add_argument("--precision", nargs="*", default=["float64", "float32"])
    ap.add_argument("--loop", choices=["multistep", "per-phase", "both"], default="both")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--target-s", type=float, default=0.5)
    ap.add_argument("--out", default=None, help="folder for gpu_ensemble.json (default ./bench-out/gpu_ensemble/)")
    args = ap.parse_args()
    from numba import cuda

    import numba
    dev = cuda.get_current_device()
    name = dev.name.decode() if isinstance(dev.name, bytes) else dev.name
    info = dict(gpu=name, date=time.strftime("%Y-%m-%d"), numba=numba.__version__, numpy=np.__version__,
                python=platform.python_version())
    print(json.dumps(info), flush=True)
    loops = {"multistep": [True], "per-phase": [False], "both": [True, False]}[args.loop]
    rows = []
    for prec in args.precision:
        _made.clear()
        for k in args.k:
            for ms in loops:
                try:
                    r = measure(k, args.n, args.phi, prec, ms, args.reps, args.target_s)
                except Exception as e:  # report and go on
                    r = dict(k=k, n=args.n, precision=prec, loop="multistep" if ms else "per-phase",
                             error=repr(e)[:300])
                rows.append(r)
                print(json.dumps(r), flush=True)
    with open(out_dir(args.out, "gpu_ensemble") / "gpu_ensemble.json", "w") as fh:
        json.dump(dict(info=info, rows=rows), fh, indent=1)
    print(f"\n{info['gpu']}: K x {args.n} rough spheres, phi = {args.phi}")
    print("| precision | K | loop | aggregate Cundall | us/step | builds/step | B/particle |")
    for r in rows:
        if "error" in r:
            print(f"| {r['precision']} | {r['k']} | {r['loop']} | ERROR {r['error'][:100]} |")
            continue
        print(f"| {r['precision']} | {r['k']} | {r['loop']} | {r['cundall_aggregate']:.3g} | {r['us_per_step']:.1f} | "
              f"{r['builds_per_step']:.3f} | {r['bytes_per_particle_meminfo']:.0f} |")


if __name__ == "__main__":
    sys.exit(main())
