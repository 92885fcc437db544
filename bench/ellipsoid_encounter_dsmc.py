"""The ellipsoid excess (issue 18, part 3): DSMC with the whole DEM encounter as the collision rule.

Runs engine.validation.encounter_dsmc.run_dsmc for every (xi, rule, seed) in parallel processes (one Numba
thread each) and writes runs.json (rewritten after every finished run), summary.md (the table: late T_tr/T_rot,
mean ± standard error over seeds, per rule, with the DEM and the earlier DSMC numbers) and
encounter_dsmc.png. Rules (same sampling, same seeds): 'impulse' = one instantaneous impulse with e_eff(D) per
sampled contact (dsmc_ratio(dem=True)); 'soft' = the DEM pair integrated through the whole encounter with the
engine's njit functions, first contacts only; 'hard' = hard bodies, impulses with e_eff(D) at every contact of
the encounter (the stiff limit of 'soft'); 'first' = first contacts only, one impulse, repeats not resolved
(a diagnostic).

Full version (16 cores, ~5 min: one round of 12 'soft' runs of 6e5 encounters, ~200-300 s each on one core of
the 2-core dev VM, the 12 'impulse' runs alongside; bench/reports/ellipsoid-encounter-dsmc/REPORT.md):

    NUMBA_NUM_THREADS=1 OMP_NUM_THREADS=1 PYTHONPATH=. python bench/ellipsoid_encounter_dsmc.py --procs 16 \\
        --rules impulse soft --xi 1.5 2 2.5 --seeds 4 --n 20000 --coll 60 \\
        --out bench/reports/ellipsoid-encounter-dsmc/full

Only re-analyse what exists: add --analyse-only.
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

#: DEM late T_tr/T_rot at e = 0.9 (mean ± SE; N, seeds): bench/reports/hcs-ellipsoids-cuda (xi 1.5, 2: one
#: seed, block SE) and bench/reports/ellipsoid-cooling-seeds-cuda (xi 2.5: SE over seeds)
DEM = {1.5: [(0.9148, 0.0050, "N=4096, 1 seed")], 2.0: [(0.9901, 0.0048, "N=4096, 1 seed")],
       2.5: [(1.0233, 0.0036, "N=4096, 8 seeds"), (1.0333, 0.0014, "N=16384, 2 seeds")]}
#: earlier DSMC references at e = 0.9: PHYSICS-NOTES §3.2 (nominal e; xi 1.5, 2) and
#: bench/reports/ellipsoid-cooling-seeds-cuda/dsmc.json (e_eff(D), xi 2.5, 4 seeds)
DSMC_OLD = {1.5: (0.909, None, "nominal e, notes"), 2.0: (0.984, None, "nominal e, notes"),
            2.5: (1.0093, 0.0007, "e_eff(D), 4 seeds")}
RULE_ORDER = ("impulse", "first", "hard", "soft")


def _one(task):
    xi, e_n, rule, seed, n, coll, tf, kn = task
    from engine.validation.encounter_dsmc import run_dsmc

    r = run_dsmc(xi, e_n, rule, n=n, coll_per_particle=coll, seed=seed, temp_fraction=tf, kn_factor=kn)
    r.pop("constants", None)
    r["profile"] = _thin(r["profile"])
    return task, r


def _thin(profile, keep: int = 150):
    """At most ~keep rows of the (collisions per particle, T_tr/T_rot) profile (one row per sweep)."""
    step = max(1, len(profile) // keep)
    return profile[::step]


def _key(xi, e, rule):
    return f"{xi}/{e}/{rule}"


def summarise(runs: dict) -> dict:
    import numpy as np

    cells = {}
    for r in runs.values():
        cells.setdefault(_key(r["xi"], r["e_n"], r["rule"]), []).append(r)
    out = {}
    for k, rs in cells.items():
        vals = np.array([r["ratio"] for r in rs])
        se = float(np.std(vals, ddof=1) / math.sqrt(len(vals))) if len(vals) > 1 else None
        out[k] = {"xi": rs[0]["xi"], "e_n": rs[0]["e_n"], "rule": rs[0]["rule"], "seeds": len(rs),
                  "values": vals.tolist(), "mean": float(vals.mean()), "se": se,
                  "rejected_share": float(np.mean([r["rejected_share"] for r in rs])),
                  "later_contact_share": float(np.mean([r["later_contact_share"] for r in rs])),
                  "multi_contact_share": float(np.mean([r.get("multi_contact_share", float("nan")) for r in rs])),
                  "loss": float(np.mean([r["loss_per_collision_over_T"] for r in rs])),
                  "capped": int(sum(r["capped"] for r in rs)), "encounters": int(sum(r["encounters"] for r in rs)),
                  "max_overlap_over_b": float(max(r["max_overlap_over_b"] for r in rs)),
                  "softness": rs[0]["softness_delta_over_b"], "n": rs[0]["n"],
                  "coll": rs[0]["coll_per_particle"], "wall_s": float(sum(r["wall_s"] for r in rs))}
    return out


def table(summ: dict) -> str:
    f = lambda m, s: "–" if m is None else (f"{m:.4f}" if s is None else f"{m:.4f} ± {s:.4f}")  # noqa: E731
    lines = ["| xi | e | rule | seeds | late T_tr/T_rot, per seed | mean ± SE | vs impulse | rejected (not first) | "
             "encounters with >= 2 contacts | later contacts | loss/coll / T_tr | capped | max overlap/b |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for k in sorted(summ, key=lambda k: (summ[k]["xi"], summ[k]["e_n"], RULE_ORDER.index(summ[k]["rule"]))):
        c = summ[k]
        imp = summ.get(_key(c["xi"], c["e_n"], "impulse"))
        dv = "–"
        if imp is not None and c["rule"] != "impulse":
            d = c["mean"] / imp["mean"] - 1
            se = None
            if c["se"] is not None and imp["se"] is not None:
                se = math.hypot(c["se"] / imp["mean"], imp["se"] * c["mean"] / imp["mean"] ** 2)
            dv = f"{100 * d:+.2f} %" + ("" if se is None else f" ± {100 * se:.2f}")
        lines.append(f"| {c['xi']} | {c['e_n']} | {c['rule']} | {c['seeds']} | "
                     f"{', '.join(f'{v:.4f}' for v in c['values'])} | {f(c['mean'], c['se'])} | {dv} | "
                     f"{100 * c['rejected_share']:.1f} % | {100 * c['multi_contact_share']:.1f} % | "
                     f"{100 * c['later_contact_share']:.1f} % | "
                     f"{c['loss']:.4f} | {c['capped']} / {c['encounters']} | {c['max_overlap_over_b']:.4f} |")
    lines += ["", "| xi | DEM (e = 0.9) | earlier DSMC |", "|---|---|---|"]
    for xi in sorted({summ[k]["xi"] for k in summ}):
        dem = "; ".join(f"{m:.4f} ± {s:.4f} ({t})" for m, s, t in DEM.get(xi, []))
        o = DSMC_OLD.get(xi)
        lines.append(f"| {xi} | {dem or '–'} | {'–' if o is None else f(o[0], o[1]) + ' (' + o[2] + ')'} |")
    return "\n".join(lines)


def plot(runs: dict, summ: dict, path: Path) -> None:
    """Late ratio per xi (the 'first' diagnostic only in the table: it sits ~15 % lower), the same relative
    to the impulse DSMC (with the DEM), and the relaxation at the largest xi."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, (ax1, ax2, ax3) = plt.subplots(1, 3, figsize=(17, 4.8))
    marks = {"impulse": ("s", "C0"), "hard": ("^", "C2"), "soft": ("o", "C3")}
    off = {"impulse": -0.045, "hard": 0.015, "soft": 0.045}
    for rule, (mk, col) in marks.items():
        pts = sorted((c["xi"], c["mean"], c["se"] or 0.0) for c in summ.values() if c["rule"] == rule)
        if not pts:
            continue
        x = np.array([p[0] for p in pts])
        ax1.errorbar(x + off[rule], [p[1] for p in pts], yerr=[p[2] for p in pts], fmt=mk, color=col,
                     label=f"DSMC {rule}", capsize=3)
        if rule != "impulse":
            rel = []
            for xi, m, se in pts:
                imp = summ.get(_key(xi, 0.9, "impulse")) or next(
                    (c for c in summ.values() if c["xi"] == xi and c["rule"] == "impulse"), None)
                if imp is not None:
                    rel.append((xi, 100 * (m / imp["mean"] - 1), 100 * math.hypot(se, imp["se"] or 0) / imp["mean"]))
            if rel:
                ax2.errorbar([r[0] + off[rule] for r in rel], [r[1] for r in rel], yerr=[r[2] for r in rel],
                             fmt=mk, color=col, capsize=3, label=f"{rule} - impulse")
    for xi, rows in DEM.items():
        imp = next((c for c in summ.values() if c["xi"] == xi and c["rule"] == "impulse"), None)
        for i, (m, s, t) in enumerate(rows):
            lab = "DEM (cooling runs)" if (xi, i) == (1.5, 0) else None
            ax1.errorbar([xi + 0.07 + 0.03 * i], [m], yerr=[s], fmt="*", color="k" if i == 0 else "grey", ms=9,
                         capsize=3, label=lab)
            if imp is not None:
                ax2.errorbar([xi + 0.07 + 0.03 * i], [100 * (m / imp["mean"] - 1)],
                             yerr=[100 * math.hypot(s, imp["se"] or 0) / imp["mean"]], fmt="*",
                             color="k" if i == 0 else "grey", ms=9, capsize=3,
                             label=("DEM - impulse (N=4096; grey: 16384)" if (xi, i) == (1.5, 0) else None))
    ax1.set_xlabel("xi = a/b")
    ax1.set_ylabel("late T_tr / T_rot (e = 0.9)")
    ax1.legend(fontsize=8)
    ax1.set_title("mean ± SE over seeds")
    ax2.axhline(0, color="grey", lw=0.6)
    ax2.set_xlabel("xi = a/b")
    ax2.set_ylabel("excess over the impulse DSMC (%)")
    if ax2.get_legend_handles_labels()[0]:
        ax2.legend(fontsize=8)
    ax2.set_title("relative to the one-impulse DSMC (same sampling)")
    xs = sorted({r["xi"] for r in runs.values()})
    xi_p = xs[-1] if xs else None
    for rule, (mk, col) in marks.items():
        prof = [np.array(r["profile"]) for r in runs.values() if r["xi"] == xi_p and r["rule"] == rule]
        if prof:
            grid = np.linspace(0, min(p[-1, 0] for p in prof), 200)
            y = np.mean([np.interp(grid, p[:, 0], p[:, 1]) for p in prof], axis=0)
            ax3.plot(grid, y, "-", color=col, lw=1, label=f"{rule} ({len(prof)} seeds)")
    ax3.set_xlabel("collisions (encounters) per particle")
    ax3.set_ylabel("T_tr / T_rot")
    ax3.set_title(f"xi = {xi_p}: relaxation (seed mean)")
    if ax3.get_legend_handles_labels()[0]:
        ax3.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write(out: Path, runs: dict, meta: dict) -> dict:
    for r in runs.values():
        r["profile"] = _thin(r["profile"])
    summ = summarise(runs)
    (out / "runs.json").write_text(json.dumps({"meta": meta, "runs": runs}, indent=1))
    (out / "summary.json").write_text(json.dumps(summ, indent=1))
    (out / "summary.md").write_text(table(summ) + "\n")
    if runs:
        plot(runs, summ, out / "encounter_dsmc.png")
    return summ


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
    ap.add_argument("--out", default="bench/reports/ellipsoid-encounter-dsmc/run")
    ap.add_argument("--analyse-only", action="store_true")
    args = ap.parse_args(argv)
    from engine.validation.encounter_dsmc import LATE_TEMPERATURE_FRACTION

    tf = LATE_TEMPERATURE_FRACTION if args.temp_fraction is None else args.temp_fraction
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    runs = {}
    if (out / "runs.json").exists():
        runs = json.loads((out / "runs.json").read_text())["runs"]
    meta = {"argv": sys.argv if argv is None else argv, "procs": args.procs}
    if not args.analyse_only:
        # slow cells first (encounters at large xi), so the pool drains evenly
        tasks = [(xi, args.e_n, rule, s, args.n, args.coll, tf, args.kn_factor) for xi in sorted(args.xi, reverse=True)
                 for rule in ("soft", "hard", "first", "impulse") if rule in args.rules
                 for s in range(1, args.seeds + 1)]
        tasks = [t for t in tasks if "/".join(str(x) for x in t[:6]) not in runs]
        t0 = time.time()
        with ProcessPoolExecutor(max(1, args.procs), mp_context=multiprocessing.get_context("spawn")) as pool:
            futs = [pool.submit(_one, t) for t in tasks]
            for fu in as_completed(futs):
                task, r = fu.result()
                runs["/".join(str(x) for x in task[:6])] = r
                print(f"xi={task[0]} e={task[1]} {task[2]} seed {task[3]}: T_tr/T_rot {r['ratio']:.4f}, rejected "
                      f"{100 * r['rejected_share']:.1f} %, later contacts {100 * r['later_contact_share']:.1f} %, "
                      f"{r['wall_s']:.0f} s ({time.time() - t0:.0f} s total)", flush=True)
                meta["total_wall_s"] = time.time() - t0
                write(out, runs, meta)
    write(out, runs, meta)
    print((out / "summary.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
