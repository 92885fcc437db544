"""How many pairs each exact screen removes before the Perram-Wertheim solve (speed).

Takes a snapshot of the Rubio-Largo et al. (2015) gas (bench/gpu_ellipsoid_scaling.py's random gas, xi = 2, phi = 0.058
by default) after --steps steps of the CPU backend, and classifies every list pair (i < j) whose bounding spheres
(radius a) overlap -- the pairs the force kernel sends to the contact function -- with the engine's own
functions (engine/physics/ellipsoid.py):

- plane: the plane normal to the centre line separates them (``plane_separated``, first screen);
- pw@1/2: not plane-separated, but F(1/2) > 1 + margin, i.e. the first Perram-Wertheim iterate proves them
  disjoint (second screen, first iterate);
- pw@k>1: a later Newton iterate has F > 1 + margin;
- full, disjoint: no screen fires, the full maximisation runs and finds W_0 >= 1;
- full, overlapping: in contact (W_0 < 1), always the full maximisation.

Only pairs not in contact at the previous step are screened in the engine; the snapshot counts all pairs
(the in-contact ones are a few per mille of them).

    NUMBA_NUM_THREADS=1 python -m bench ellipsoid_screen_stats --n 32768 --steps 300
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numba
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench import out_dir  # noqa: E402
from bench.gpu_ellipsoid_scaling import ellipsoid_gas  # noqa: E402
from engine.physics.contact import min_image  # noqa: E402
from engine.physics.ellipsoid import (ellipsoid_contact, plane_separated, pw_contact,  # noqa: E402
                                      shape_matrix_inverse, sym_adj)


@numba.njit
def classify(pos, quat, axes, bound, nbr, nn, box, tol, margin, out):
    """out[k] counts: 0 plane, 1 pw@1/2, 2 pw@k>1, 3 full disjoint, 4 full overlapping, 5 bounding pairs."""
    half = 0.5
    inv_box = 1.0 / box
    for i in range(pos.shape[0]):
        for kk in range(nn[i]):
            j = nbr[i, kk]
            if j <= i:
                continue
            rx = min_image(pos[j, 0] - pos[i, 0], box, inv_box, half)
            ry = min_image(pos[j, 1] - pos[i, 1], box, inv_box, half)
            rz = min_image(pos[j, 2] - pos[i, 2], box, inv_box, half)
            rc = bound[i] + bound[j]
            if rx * rx + ry * ry + rz * rz >= rc * rc:
                continue
            out[5] += 1
            ia = shape_matrix_inverse(quat[i, 0], quat[i, 1], quat[i, 2], quat[i, 3], axes[i, 0], axes[i, 1],
                                      axes[i, 2], half)
            ib = shape_matrix_inverse(quat[j, 0], quat[j, 1], quat[j, 2], quat[j, 3], axes[j, 0], axes[j, 1],
                                      axes[j, 2], half)
            g = ellipsoid_contact(rx, ry, rz, quat[i, 0], quat[i, 1], quat[i, 2], quat[i, 3], axes[i, 0],
                                  axes[i, 1], axes[i, 2], quat[j, 0], quat[j, 1], quat[j, 2], quat[j, 3], axes[j, 0],
                                  axes[j, 1], axes[j, 2], tol, half)
            if g[2] > 0:
                out[4] += 1
                continue
            if plane_separated(ia[0], ia[1], ia[2], ia[3], ia[4], ia[5], ib[0], ib[1], ib[2], ib[3], ib[4], ib[5],
                               rx, ry, rz, margin, half):
                out[0] += 1
                continue
            # F at the first iterate lambda = 1/2: (1/4) r^T ((M_A^-1 + M_B^-1)/2)^-1 r
            c = (0.5 * (ia[0] + ib[0]), 0.5 * (ia[1] + ib[1]), 0.5 * (ia[2] + ib[2]), 0.5 * (ia[3] + ib[3]),
                 0.5 * (ia[4] + ib[4]), 0.5 * (ia[5] + ib[5]))
            j6 = sym_adj(c[0], c[1], c[2], c[3], c[4], c[5])
            det = c[0] * j6[0] + c[1] * j6[1] + c[2] * j6[2]
            xx = (j6[0] * rx + j6[1] * ry + j6[2] * rz) / det
            xy = (j6[1] * rx + j6[3] * ry + j6[4] * rz) / det
            xz = (j6[2] * rx + j6[4] * ry + j6[5] * rz) / det
            f_half = 0.25 * (rx * xx + ry * xy + rz * xz)
            stopped = pw_contact(ia[0], ia[1], ia[2], ia[3], ia[4], ia[5], ib[0], ib[1], ib[2], ib[3], ib[4], ib[5],
                                 rx, ry, rz, tol, 1.0 + margin, half)[5]
            if f_half > 1.0 + margin:
                out[1] += 1
            elif stopped:
                out[2] += 1
            else:
                out[3] += 1


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=32768)
    ap.add_argument("--xi", type=float, default=2.0)
    ap.add_argument("--phi", type=float, default=0.058)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--out", default=None,
                    help="folder for ellipsoid_screen_stats.json (default ./bench-out/ellipsoid_screen_stats/)")
    args = ap.parse_args(argv)
    from engine.shapes.spheroid.cpu_backend import PW_SCREEN, PW_TOL, CpuEllipsoidBackend

    system, c = ellipsoid_gas(args.n, args.phi, "float64", xi=args.xi)
    be = CpuEllipsoidBackend(system, c)
    be.advance(args.steps)
    out = np.zeros(6, np.int64)
    classify(be.pos, be.quat, be.axes, be.bound, be.nbr, be.nn, float(be.box), PW_TOL["float64"],
             PW_SCREEN["float64"], out)
    names = ["plane", "pw_first_iterate", "pw_later_iterate", "full_disjoint", "full_overlapping"]
    tot = int(out[5])
    row = dict(n=args.n, xi=args.xi, phi=args.phi, steps=args.steps, margin=PW_SCREEN["float64"],
               bounding_pairs=tot, bounding_pairs_per_particle=tot / args.n,
               counts={k: int(v) for k, v in zip(names, out[:5])},
               fractions={k: float(v) / max(tot, 1) for k, v in zip(names, out[:5])},
               list_pairs=int(be.nn.sum()) // 2, contacts=be.observe()["contacts"])
    print(json.dumps(row, indent=1))
    (out_dir(args.out, "ellipsoid_screen_stats") / "ellipsoid_screen_stats.json").write_text(json.dumps(row, indent=1))
    return row


if __name__ == "__main__":
    main()
