"""How often do two spheroids touch more than once in one encounter? (the xi = 2.5 cooling excess)

The DSMC reference of the late T_tr/T_rot (engine/validation/hcs_ellipsoids.py: dsmc_ratio) draws every collision
from uncorrelated pre-collision states (molecular chaos) and applies one instantaneous impulse. Two elongated
bodies can instead touch several times in one encounter (a contact ends, the pair rotates, another part of them
touches): those contacts are correlated, which the DSMC cannot represent, and their share grows with the
elongation. This script counts them in the DEM itself (CPU backend, the Rubio-Largo et al. (2015) gas of
bench/gpu_ellipsoid_scaling.py: phi = 0.058, engine contact constants, e_n = 0.9): an encounter is a maximal
interval in which the bounding spheres (radius a) of a pair overlap; a contact starts when the pair's overlap
becomes positive. Reported per xi: encounters with at least one contact, the share with two or more, and the
share of all contacts that are second or later contacts of their encounter.

    NUMBA_NUM_THREADS=1 python -m bench ellipsoid_recollisions --xi 1.5 2 2.5 3 --n 1024 --steps 40000
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench import out_dir  # noqa: E402
from bench.gpu_ellipsoid_scaling import ellipsoid_gas  # noqa: E402


def count(xi, n, steps, e_n, seed=1):
    from engine.shapes.spheroid.cpu_backend import CpuEllipsoidBackend

    system, c = ellipsoid_gas(n, 0.058, "float64", seed=seed, xi=xi, e_n=e_n)
    be = CpuEllipsoidBackend(system, c)
    be.advance(1)
    box = be.box
    enc = np.zeros(n * n, np.int32)        # contacts so far in the pair's current encounter (i < j)
    in_contact = np.zeros(n * n, np.bool_)
    prev_open = np.zeros(0, np.int64)      # pairs whose bounding spheres overlapped at the previous step
    hist = {}
    t0 = time.time()
    for _ in range(steps):
        be.advance(1)
        i = np.repeat(np.arange(n), be.nn)
        kk = np.concatenate([np.arange(m) for m in be.nn]) if len(i) else np.zeros(0, np.int64)
        j = be.nbr[i, kk].astype(np.int64)
        keep = i < j
        i, j, kk = i[keep], j[keep], kk[keep]
        r = be.pos[j] - be.pos[i]
        r -= box * np.round(r / box)
        rc = be.bound[i] + be.bound[j]
        bo = np.sum(r * r, 1) < rc * rc
        lin = i * n + j
        ic = be.hist[i, kk, 3] > 0
        start = ic & ~in_contact[lin]
        enc[lin[start]] += 1
        in_contact[lin] = ic
        open_now = lin[bo | ic]
        ended = np.setdiff1d(prev_open, open_now, assume_unique=False)
        for k in enc[ended][enc[ended] > 0]:
            hist[int(k)] = hist.get(int(k), 0) + 1
        enc[ended] = 0
        in_contact[ended] = False
        prev_open = np.unique(open_now)
    wall = time.time() - t0
    encounters = sum(hist.values())
    contacts = sum(k * v for k, v in hist.items())
    multi = sum(v for k, v in hist.items() if k >= 2)
    return dict(xi=xi, n=n, steps=steps, e_n=e_n, encounters_with_contact=encounters, contacts=contacts,
                share_multi=multi / max(encounters, 1), share_later_contacts=(contacts - encounters) / max(contacts, 1),
                histogram={str(k): v for k, v in sorted(hist.items())}, wall_s=wall,
                contacts_now=be.observe()["contacts"])


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--xi", type=float, nargs="+", default=[1.5, 2.0, 2.5, 3.0])
    ap.add_argument("--n", type=int, default=1024)
    ap.add_argument("--steps", type=int, default=40000)
    ap.add_argument("--e-n", type=float, default=0.9)
    ap.add_argument("--out", default=None,
                    help="folder for ellipsoid_recollisions.json (default ./bench-out/ellipsoid_recollisions/)")
    args = ap.parse_args(argv)
    rows = []
    for xi in args.xi:
        r = count(xi, args.n, args.steps, args.e_n)
        rows.append(r)
        print(json.dumps(r), flush=True)
    (out_dir(args.out, "ellipsoid_recollisions") / "ellipsoid_recollisions.json").write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
