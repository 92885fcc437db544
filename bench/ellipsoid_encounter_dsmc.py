"""The ellipsoid excess: DSMC with the whole DEM encounter as the collision rule.

Runs engine.validation.encounter_dsmc.run_dsmc for every (xi, rule, seed) in parallel processes (one Numba
thread each) and writes runs.json (rewritten after every finished run), summary.md (the table: late T_tr/T_rot,
mean ± standard error over seeds, per rule, with the DEM and the earlier DSMC numbers) and
encounter_dsmc.png. Rules (same sampling, same seeds): 'impulse' = one instantaneous impulse with e_eff(D) per
sampled contact (dsmc_ratio(dem=True)); 'soft' = the DEM pair integrated through the whole encounter with the
engine's njit functions, first contacts only; 'hard' = hard bodies, impulses with e_eff(D) at every contact of
the encounter (the stiff limit of 'soft'); 'first' = first contacts only, one impulse, repeats not resolved
(a diagnostic).

Full version (16 cores, ~5 min: one round of 12 'soft' runs of 6e5 encounters, ~200-300 s each on one core of
the 2-core dev VM, the 12 'impulse' runs alongside):

    NUMBA_NUM_THREADS=1 OMP_NUM_THREADS=1 python -m bench ellipsoid_encounter_dsmc --procs 16 \\
        --rules impulse soft --xi 1.5 2 2.5 --seeds 4 --n 20000 --coll 60 \\
        --out DIR

Only re-analyse what exists: add --analyse-only.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench import out_dir  # noqa: E402
from engine.validation.encounter_report import RULE_ORDER, run_cells, write  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--xi", type=float, nargs="+", default=[1.5, 2.0, 2.5])
    ap.add_argument("--e-n", type=float, default=0.9)
    ap.add_argument("--rules", nargs="+", default=list(RULE_ORDER), choices=RULE_ORDER)
    ap.add_argument("--seeds", type=int, default=4, help="seeds 1..k for every (xi, rule)")
    ap.add_argument("--n", type=int, default=20000)
    ap.add_argument("--coll", type=float, default=60.0, help="collisions (encounters) per particle")
    ap.add_argument("--temp-fraction", type=float, default=None,
                    help="T_tr held at this fraction of the DEM scene's T0 (default: the DEM late window, 0.36)")
    ap.add_argument("--kn-factor", type=float, default=1.0,
                    help="k_n of the DEM scene times this (softness test; dt = t_c/50 follows)")
    ap.add_argument("--procs", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--out", default=None, help="report folder (default ./bench-out/ellipsoid_encounter_dsmc/)")
    ap.add_argument("--analyse-only", action="store_true")
    args = ap.parse_args(argv)
    from engine.validation.encounter_dsmc import LATE_TEMPERATURE_FRACTION

    tf = LATE_TEMPERATURE_FRACTION if args.temp_fraction is None else args.temp_fraction
    out = out_dir(args.out, "ellipsoid_encounter_dsmc")
    runs = {}
    if (out / "runs.json").exists():
        runs = json.loads((out / "runs.json").read_text())["runs"]
    meta = {"argv": sys.argv if argv is None else argv, "procs": args.procs}
    if not args.analyse_only:
        # slow cells first (encounters at large xi), so the pool drains evenly
        tasks = [(xi, args.e_n, rule, s, args.n, args.coll, tf, args.kn_factor) for xi in sorted(args.xi, reverse=True)
                 for rule in ("soft", "hard", "first", "impulse") if rule in args.rules
                 for s in range(1, args.seeds + 1)]
        t0 = time.time()

        def done(task, r):
            print(f"xi={task[0]} e={task[1]} {task[2]} seed {task[3]}: T_tr/T_rot {r['ratio']:.4f}, rejected "
                  f"{100 * r['rejected_share']:.1f} %, later contacts {100 * r['later_contact_share']:.1f} %, "
                  f"{r['wall_s']:.0f} s ({time.time() - t0:.0f} s total)", flush=True)
            meta["total_wall_s"] = time.time() - t0
            write(out, runs, meta)

        run_cells(tasks, args.procs, runs, done)
    write(out, runs, meta)
    print((out / "summary.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
