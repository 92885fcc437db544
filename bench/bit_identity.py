"""Trajectory fingerprints: SHA-1 of a result file's trajectory and observables for a fixed set of specs.

For refactors that must not change a bit: run this in two checkouts and compare the printed
digests (the whole file's, and its trajectory and observables apart). Only the public path (``engine.run``) and
the result file (H5MD contract) are used, so it runs on any commit that has them. Cases: spheres smooth, rough,
Coulomb, two species; ellipsoids (xi = 2) frictionless, rough and rough with Coulomb friction.

    python -m bench bit_identity --backend cpu
    NUMBA_ENABLE_CUDASIM=1 python -m bench bit_identity --backend cuda      # the CUDA simulator (slow: tiny N)
    python -m bench bit_identity --backend cuda --launch-cache off         # a GPU: the same digests as with it on
"""

from __future__ import annotations

import argparse
import hashlib
import json
import tempfile
from pathlib import Path

import h5py
import numpy as np

#: 64 particles, soft contacts (k_n = 1e5 N/m: dt = t_c/50 = 62 us), ~300 thermalisation + ~800 cooling steps
TINY = dict(n_particles=64, volume_fraction=0.05, box_length=0.5, t_end=0.05, thermalization=0.2, snapshots=2,
            velocity_rms=0.5, stiffness=1.0e5, seed=3)
CASES = {
    "spheres-smooth": dict(e_t=-1.0),
    "spheres-rough": dict(e_t=0.8),
    "spheres-coulomb": dict(e_t=0.8, friction=0.2),
    "spheres-species": dict(e_t=0.8, species=[{"radius_ratio": 1.0, "number_fraction": 0.5},
                                               {"radius_ratio": 0.6, "number_fraction": 0.5}]),
    "ellipsoids-smooth": dict(shape="ellipsoid", elongation=2.0, e_t=-1.0),
    "ellipsoids-rough": dict(shape="ellipsoid", elongation=2.0, e_t=0.8),
    "ellipsoids-coulomb": dict(shape="ellipsoid", elongation=2.0, e_t=0.8, friction=0.2),
}
DATASETS = ("particles/all/position/value", "particles/all/velocity/value", "particles/all/angular_velocity/value",
            "particles/all/orientation/value", "observables/kinetic_energy_translational/value",
            "observables/kinetic_energy_rotational/value", "observables/contacts/value")


def fingerprint(path: Path, names=DATASETS) -> str:
    h = hashlib.sha1()
    with h5py.File(path) as f:
        for name in names:
            h.update(name.encode())
            h.update(np.ascontiguousarray(f[name][()]).tobytes())
    return h.hexdigest()[:16]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--cases", nargs="*", default=list(CASES))
    ap.add_argument("--launch-cache", choices=["on", "off"], default="on",
                    help="off: every GPU launch through numba-cuda's dispatcher (engine/loops/cuda_launch.py); the "
                         "digests must not change")
    args = ap.parse_args(argv)
    from engine import run

    if args.launch_cache == "off":
        import engine.loops.cuda_launch as launch

        launch.ENABLED = False

    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.cases:
            spec = dict(TINY, backend=args.backend, **CASES[name])
            path = Path(tmp) / f"{name}.h5"
            run(spec, path)
            out[name] = fingerprint(path)
            # the two halves apart: the trajectory (particles/) and the observable series (observables/),
            # whose sums a change of the device reduction order alone may change in the last bits
            parts = [fingerprint(path, [d for d in DATASETS if d.startswith(g)])
                     for g in ("particles/", "observables/")]
            print(f"{name:20s} {out[name]}  trajectory {parts[0]}  observables {parts[1]}", flush=True)
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
