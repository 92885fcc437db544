"""Neighbour velocity correlations in the ellipsoid cooling gas (the many-body rest).

The DSMC with the whole DEM encounter as its collision rule leaves the DEM's late T_tr/T_rot +0.8-0.9 % above it,
at N = 4096 and 16 384 alike (bench/ellipsoid_cooling_seeds.py, 8 x 8 seeds on an H100). A two-body rule assumes
molecular chaos. This measures how far the DEM gas is from it, in the snapshot frames of
bench/ellipsoid_cooling_seeds.py's result files (engine/analysis/velocity_correlations.py): c_v = <v_i . v_j> / <|v|^2>
and the approaching pairs' normal relative speed, g_n_ratio = <(g . r_hat)^2> / (2 <|v|^2> / 3) - 1, for centre
distances below r_cut = f x 2a (a: the long semi-axis, the bounding radius; f = 1: bounding spheres touch).

Frame 0 is the gas after its elastic thermalisation: no correlations in equilibrium, so it is the baseline.
"Late" = the frames at or after half of the run. Seed mean ± SE (std / sqrt(seeds)) per N.

    python -m bench ellipsoid_velocity_correlations --work /tmp/ellc --out DIR
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from engine.analysis.velocity_correlations import file_correlations  # noqa: E402

FACTORS = (1.0, 1.5, 3.0)


def _mean_se(x):
    x = np.asarray(x, dtype=float)
    return float(x.mean()), float(x.std(ddof=1) / math.sqrt(len(x))) if len(x) > 1 else math.nan


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", required=True, help="folder of bench/ellipsoid_cooling_seeds.py's .h5 files")
    ap.add_argument("--out", required=True)
    ap.add_argument("--factors", type=float, nargs="*", default=list(FACTORS))
    args = ap.parse_args(argv)
    import h5py

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    runs: dict = {}
    for path in sorted(Path(args.work).glob("xi*_e*_n*_seed*.h5")):
        m = re.match(r"xi([\d.]+)_e([\d.]+)_n(\d+)_seed(\d+)\.h5", path.name)
        with h5py.File(path, "r") as f:
            a = float(np.max(f["particles/all/semi_axes"][()][:, 0]))
        per = {}
        for fac in args.factors:
            c = file_correlations(path, fac * 2.0 * a)
            late = c["time"] >= 0.5 * c["time"][-1]
            per[fac] = {"c_v0": float(c["c_v"][0]), "g_n0": float(c["g_n_ratio"][0]),
                        "c_v_late": float(np.nanmean(c["c_v"][late])),
                        "g_n_late": float(np.nanmean(c["g_n_ratio"][late])),
                        "c_v": c["c_v"].tolist(), "g_n_ratio": c["g_n_ratio"].tolist(), "time": c["time"].tolist(),
                        "pairs_late": float(np.mean(c["pairs"][late]))}
        runs.setdefault(f"xi = {m[1]}, e = {m[2]}, N = {m[3]}", []).append({"seed": int(m[4]), "factors": per})
        print(path.name, {f: round(v["c_v_late"], 4) for f, v in per.items()}, flush=True)
    lines = ["# Neighbour velocity correlations in the ellipsoid cooling gas", "",
             "Command: `python -m bench ellipsoid_velocity_correlations " + " ".join(sys.argv[1:]) + "`", "",
             __doc__.split("\n\n")[1].replace("\n", " "), "",
             "| case | seeds | r_cut / 2a | pairs per frame (late) | c_v frame 0 | c_v late | g_n_ratio frame 0 | "
             "g_n_ratio late |", "|---|---|---|---|---|---|---|---|"]
    summary = {}
    for case, rs in runs.items():
        for fac in args.factors:
            cells = {}
            for key in ("c_v0", "c_v_late", "g_n0", "g_n_late", "pairs_late"):
                cells[key] = _mean_se([r["factors"][fac][key] for r in rs])
            summary[f"{case}, f = {fac}"] = cells
            lines.append(f"| {case} | {len(rs)} | {fac} | {cells['pairs_late'][0]:.0f} | "
                         f"{cells['c_v0'][0]:+.4f} ± {cells['c_v0'][1]:.4f} | "
                         f"{cells['c_v_late'][0]:+.4f} ± {cells['c_v_late'][1]:.4f} | "
                         f"{cells['g_n0'][0]:+.4f} ± {cells['g_n0'][1]:.4f} | "
                         f"{cells['g_n_late'][0]:+.4f} ± {cells['g_n_late'][1]:.4f} |")
    (out / "README.md").write_text("\n".join(lines) + "\n")
    (out / "correlations.json").write_text(json.dumps({"summary": summary, "runs": runs}, indent=1))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
