"""Seeds, system size and flow diagnostics for the open xi = 2.5, e_n = 0.9 cooling cell.

A 13-cell matrix (bench/hcs_ellipsoids_cuda.py, one seed per cell) gave a late T_tr/T_rot of
1.0493 +- 0.0068 at xi = 2.5, e_n = 0.9, +4.0 % from the e_eff(D) DSMC value 1.0093. This script runs, as ONE
CUDA ensemble (engine.driver.ensemble.run_ensemble), the Rubio-Largo et al. (2015) scene of engine/validation/hcs_ellipsoids.py
(phi = 0.058, v_rms = 3.5 m/s, 3 elastic sphere-rate collisions of thermalisation, Gamma_0 t_end = 40; box edge
2 m (N/4096)^(1/3)) for:

- xi = 2.5, e_n = 0.9 with 8 seeds at N = 4096 and 2 seeds at N = 16384 (statistics vs a finite-N effect);
  seed 0 has last session's spec, but the ensemble advances all scenes in lockstep to the next stop of any
  scene, so its stops (and with them the rounding of the split half kicks) differ from last session's 13-cell
  ensemble: it is a new realisation, not a rerun;
- the cells not run last session: (xi, e_n) = (1.15, 0.98) and (3.0, 0.98), one seed each;
- optional extras (dropped first when the projected time exceeds the budget): (2.5, 0.95) and (3.0, 0.9) with
  4 seeds each, to see whether the excess over DSMC scales with the dissipation and the elongation.

All runs write 11 snapshots (positions, velocities): the analysis measures the kinetic energy of the
coarse-grained flow field (cells of ~64 particles) in excess of its thermal-noise value (3/2 T per cell) and
the density fluctuation var(n_c)/<n_c> (1 for an ideal gas) -- a shear or clustering instability of the cooling
state would put translational energy into collective flow and raise the measured T_tr/T_rot.

Two steps (separate processes, so a run that overruns its budget still leaves an analysis of what finished):

    python -m bench ellipsoid_cooling_seeds simulate --work /tmp/ellc --out $OUT/r --budget-s 330
    python -m bench ellipsoid_cooling_seeds analyse  --work /tmp/ellc --out $OUT/r --dsmc /tmp/ellc/dsmc.json

The .h5 files stay in --work (not under --out). Late T_tr/T_rot per run: mean over the records with at least
half of the run's collisions per particle (engine.validation.hcs_ellipsoids.LATE_FRACTION, as the matrix);
standard error across seeds = std(ddof = 1)/sqrt(seeds).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from engine.validation import hcs_ellipsoids as H  # noqa: E402

MAIN = ["2.5:0.9:4096:8", "2.5:0.9:16384:2", "1.15:0.98:4096:1", "3.0:0.98:4096:1"]
EXTRA = ["2.5:0.95:4096:4", "3.0:0.9:4096:4"]
#: the 13-cell matrix (bench/hcs_ellipsoids_cuda.py, NVIDIA H200): late T_tr/T_rot of xi = 2.5, e = 0.9, seed 0
LAST_SESSION = {"ratio_late": 1.0492988, "ratio_err": 0.0068, "dsmc_dem": 1.0093, "theory": 1.0044}
SNAPSHOTS = 11


def parse_groups(items):
    out = []
    for it in items:
        xi, e, n, k = it.split(":")
        out.append((float(xi), float(e), int(n), int(k)))
    return out


def scenes(groups, collisions, backend):
    """(label, spec, file name) of every run: the Rubio-Largo et al. (2015) spec of hcs_ellipsoids (full_spec for
    N = 4096) with SNAPSHOTS snapshots."""
    out = []
    for xi, e, n, k in groups:
        for seed in range(k):
            spec = H._spec(xi, e, seed, backend, n, collisions, 3.5, 3.0).model_copy(update={"snapshots": SNAPSHOTS})
            out.append((f"{xi}:{e}:{n}:{seed}", spec, f"xi{xi}_e{e}_n{n}_seed{seed}.h5"))
    return out


def steps_of(spec):
    from engine.setup.params import derive

    p = derive(spec)
    return p.n_steps + p.n_thermalization_steps, p.n_steps // p.output_every + 1


def probe(specs, steps):
    """Seconds per step of an ensemble of random gases with the scenes' N and xi (cooling contact)."""
    from bench.gpu_ellipsoid_scaling import ellipsoid_gas
    from engine.shapes.spheroid.cuda_backend import CudaEllipsoidEnsemble

    made = [ellipsoid_gas(s.n_particles, 0.058, "float64", seed=900 + k, xi=s.elongation, e_n=s.e_n)
            for k, s in enumerate(specs)]
    t0 = time.perf_counter()
    ens = CudaEllipsoidEnsemble([m[0] for m in made], [m[1] for m in made])
    ens.warmup()
    ens.advance(200)
    setup = time.perf_counter() - t0
    t = time.perf_counter()
    failed = ens.advance(steps)
    per = (time.perf_counter() - t) / steps
    assert not failed, failed
    return per, setup


def projected(specs, per_all):
    """Wall seconds of the ensemble: phases between scene ends, each at the probe's time per step scaled by the
    active share of the particles (at least 30 %: latency-bound small ensembles), x 1.25, + 2 ms per stop."""
    if not specs:
        return 0.0
    info = [(steps_of(s), s.n_particles) for s in specs]
    p_all = sum(n for _, n in info)
    ends = sorted({st for (st, _), _ in info})
    total, prev = 0.0, 0
    for end in ends:
        active = sum(n for (st, _), n in info if st >= end)
        total += (end - prev) * per_all * max(active / p_all, 0.3)
        prev = end
    stops = sum(r for (_, r), _ in info) + SNAPSHOTS * len(specs)
    return 1.25 * total + 2e-3 * stops


def simulate(args) -> int:
    work, out = Path(args.work), Path(args.out)
    work.mkdir(parents=True, exist_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    main_g, extra_g = parse_groups(args.runs), parse_groups(args.extra)
    chosen = main_g + extra_g
    plan = dict(requested=args.runs + args.extra, backend=args.backend, collisions=args.collisions)
    if args.backend == "cuda" and args.probe_steps > 0:
        per, setup = probe([s for _, s, _ in scenes(chosen, args.collisions, args.backend)], args.probe_steps)
        plan.update(probe_s_per_step=per, probe_setup_s=setup)
        left = args.budget_s - (time.perf_counter() - t0)
        while True:
            est = projected([s for _, s, _ in scenes(chosen, args.collisions, args.backend)], per)
            if est <= left or len(chosen) <= len(main_g):
                break
            chosen = chosen[:-1]               # drop extras, last first
        plan.update(budget_left_s=left, estimated_s=est)
    runs = scenes(chosen, args.collisions, args.backend)
    plan["chosen"] = [f"{xi}:{e}:{n}:{k}" for xi, e, n, k in chosen]
    plan["dropped"] = [f"{xi}:{e}:{n}:{k}" for xi, e, n, k in main_g + extra_g if (xi, e, n, k) not in chosen]
    plan["scenes"] = {lab: dict(steps=steps_of(s)[0], n=s.n_particles, snapshots=s.snapshots) for lab, s, _ in runs}
    print(json.dumps(plan), flush=True)
    (out / "plan.json").write_text(json.dumps(plan, indent=1))
    from engine.driver.ensemble import run_ensemble

    t = time.perf_counter()
    res = run_ensemble([s for _, s, _ in runs], [work / f for _, _, f in runs], backend=args.backend)
    plan["wall_s"] = time.perf_counter() - t
    plan["failed"] = {lab: f"{type(r).__name__}: {r}" for (lab, _, _), r in zip(runs, res)
                      if isinstance(r, BaseException)}
    plan["cundall"] = {lab: getattr(r, "cundall", None) for (lab, _, _), r in zip(runs, res)
                       if not isinstance(r, BaseException)}
    (out / "plan.json").write_text(json.dumps(plan, indent=1))
    print(f"ensemble of {len(runs)} runs: {plan['wall_s']:.0f} s (estimated {plan.get('estimated_s', 0):.0f} s); "
          f"failed: {plan['failed'] or 'none'}", flush=True)
    return 0


# ---- analysis -----------------------------------------------------------------------------------------

def flow_diagnostics(path, n_per_cell=64):
    """Per snapshot frame: time, excess flow-energy fraction and density fluctuation (see module doc)."""
    import h5py

    from engine.output.h5md import read_parameters

    box = float(read_parameters(path)["spec"]["box_length"])
    with h5py.File(path, "r") as f:
        if "position" not in f["particles/all"]:
            return None
        g = f["particles/all"]
        pos = g["position/value"][()]
        vel = g["velocity/value"][()]
        times = g["position/time"][()]
    n = pos.shape[1]
    nc = max(2, int(round((n / n_per_cell) ** (1 / 3))))
    rows = []
    for k in range(pos.shape[0]):
        c = np.minimum((np.mod(pos[k], box) * (nc / box)).astype(np.int64), nc - 1)
        cid = (c[:, 0] * nc + c[:, 1]) * nc + c[:, 2]
        cnt = np.bincount(cid, minlength=nc ** 3).astype(float)
        v = vel[k] - vel[k].mean(0)
        mom = np.stack([np.bincount(cid, weights=v[:, d], minlength=nc ** 3) for d in range(3)], 1)
        occ = cnt > 0
        e_tr = 0.5 * float(np.sum(v * v))                       # per unit mass (equal masses)
        e_flow = 0.5 * float(np.sum(np.sum(mom[occ] ** 2, 1) / cnt[occ]))
        t_kin = 2.0 * e_tr / (3.0 * n)                           # T/m
        noise = 1.5 * t_kin * int(occ.sum())
        rows.append(dict(t=float(times[k]), flow_excess=(e_flow - noise) / e_tr, flow_noise=noise / e_tr,
                         density_fluct=float(cnt.var() / cnt.mean()), cells=nc ** 3))
    return rows


def _se(v):
    v = np.asarray(v, float)
    return float(np.std(v, ddof=1) / math.sqrt(len(v))) if len(v) > 1 else None


def analyse(args) -> int:
    work, out = Path(args.work), Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    plan = json.loads((out / "plan.json").read_text()) if (out / "plan.json").exists() else {}
    groups = parse_groups(plan.get("chosen", args.runs + args.extra))
    dsmc = {}
    if args.dsmc and Path(args.dsmc).exists():
        dsmc = json.loads(Path(args.dsmc).read_text()).get("results", {})
    cells, missing = {}, []
    for xi, e, n, k in groups:
        runs = []
        for seed in range(k):
            path = work / f"xi{xi}_e{e}_n{n}_seed{seed}.h5"
            try:
                r = H.measure_run(path)
            except Exception as exc:  # noqa: BLE001  (absent or unreadable: reported)
                missing.append(f"{xi}:{e}:{n}:{seed} ({type(exc).__name__})")
                continue
            late = r["coll"] >= H.LATE_FRACTION * r["coll"][-1]
            r["late"] = float(np.mean(r["ratio"][late]))
            r["flow"] = flow_diagnostics(path)
            r["path"] = path.name
            runs.append(r)
        if runs:
            c = H.analyse(runs, xi, e)
            c["runs"] = runs
            c["n"] = n
            cells[(xi, e, n)] = c
    summary = {"plan": plan, "missing": missing, "cells": {}}
    lines = ["# xi = 2.5, e_n = 0.9 cooling: seeds, system size, flow", "",
             f"Backend {next(iter(cells.values()))['device'] if cells else '?'}; scene of "
             "engine/validation/hcs_ellipsoids.py (phi = 0.058, v_rms = 3.5 m/s, 3 elastic collisions of "
             "thermalisation, Gamma_0 t_end = 40), all runs as one ensemble "
             f"({plan.get('wall_s', float('nan')):.0f} s wall). Late window: records with >= "
             f"{H.LATE_FRACTION:.0%} of the run's collisions per particle. SE = standard error across seeds "
             "(std ddof=1 / sqrt(seeds)).", "",
             "Flow excess = (kinetic energy of the cell-mean velocities - 3/2 T per occupied cell) / E_tr over the "
             "late snapshots (cells of ~64 particles; 0 without collective flow); var(n_c)/<n_c> of the cell "
             "counts (an ideal gas: 1; hard cores at phi = 0.058: about (1-phi)^4/(1+2phi)^2 = 0.63 for spheres; "
             "clustering: larger).", "",
             "## Late T_tr/T_rot per cell", "",
             "| xi | e_n | N | seeds | late T_tr/T_rot, per seed | mean ± SE(seeds) | DSMC e_eff(D) (here, ± SE) | "
             "dev | DSMC nominal e (here) | dev | Maxwell theory (notes) | flow excess / E_tr (late) | "
             "var(n_c)/<n_c> (late) |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for (xi, e, n), c in sorted(cells.items()):
        vals = [r["late"] for r in c["runs"]]
        mean, se = float(np.mean(vals)), _se(vals)
        d_dem = dsmc.get(f"{xi}/{e}/dem")
        d_nom = dsmc.get(f"{xi}/{e}/nominal")
        ref_dem = d_dem["mean"] if d_dem else (LAST_SESSION["dsmc_dem"] if (xi, e) == (2.5, 0.9) else None)
        theory = H.THEORY_NOTES.get((xi, e))
        flows = [fr for r in c["runs"] if r["flow"] for fr in r["flow"] if fr["t"] >= 0.5 * r["t"][-1]]
        fx = [fr["flow_excess"] for fr in flows]
        dfl = [fr["density_fluct"] for fr in flows]

        def dev(ref):
            if ref is None:
                return "–", None
            d = mean / ref - 1
            return f"{100 * d:+.2f} %", d

        sdem, ddem = dev(ref_dem)
        snom, dnom = dev(d_nom["mean"] if d_nom else None)
        z = None
        if ref_dem is not None and se is not None:
            se_ref = d_dem["se"] if d_dem and d_dem.get("se") else 0.0
            z = (mean - ref_dem) / math.hypot(se, se_ref)
        def fmt_ref(d):
            if not d:
                return "–"
            return f"{d['mean']:.4f}" + (f" ± {d['se']:.4f}" if d.get("se") else "") + f" ({len(d['values'])} seeds)"

        lines.append(
            f"| {xi} | {e} | {n} | {len(vals)} | {', '.join(f'{v:.4f}' for v in vals)} | {mean:.4f}"
            f"{f' ± {se:.4f}' if se is not None else ''} | "
            f"{fmt_ref(d_dem) if d_dem else (f'{ref_dem} (last session, 1 seed)' if ref_dem else '–')} | "
            f"{sdem}{f' ({z:+.1f} SE)' if z is not None else ''} | {fmt_ref(d_nom)} | {snom} | "
            f"{theory if theory is not None else '–'} | "
            f"{'–' if not fx else f'{np.mean(fx):+.4f} ± {_se(fx) or 0:.4f}'} | "
            f"{'–' if not dfl else f'{np.mean(dfl):.3f}'} |")
        summary["cells"][f"{xi}/{e}/{n}"] = dict(
            per_seed=vals, seeds=[r["seed"] for r in c["runs"]], mean=mean, se=se, ratio_err_engine=c["ratio_err"],
            dsmc_dem=d_dem, dsmc_nominal=d_nom, dsmc_dem_ref=ref_dem, dev_dem=ddem, dev_nominal=dnom, z_dem=z,
            theory_notes=theory, flow_excess_late=fx, density_fluct_late=dfl, coll_end=c["coll_end"],
            late_from_coll=c["late_from_coll"], max_overlap_b=c["max_overlap_b"],
            haff=c["haff"], gamma_fit_eff_over_gamma0=c["gamma_fit_eff"] / c["gamma0"])
    # the N dependence of (2.5, 0.9), the relaxation profile
    c4, c16 = cells.get((2.5, 0.9, 4096)), cells.get((2.5, 0.9, 16384))
    lines += ["", "## Checks", "",
              f"- Last session (13-cell ensemble, seed 0, N = 4096): {LAST_SESSION['ratio_late']:.4f} ± "
              f"{LAST_SESSION['ratio_err']:.4f} (block SE of one run); e_eff(D) DSMC then "
              f"{LAST_SESSION['dsmc_dem']} (one DSMC run); Maxwell theory {LAST_SESSION['theory']}."]
    if c4 and c16:
        v4 = [r["late"] for r in c4["runs"]]
        v16 = [r["late"] for r in c16["runs"]]
        d = float(np.mean(v16) - np.mean(v4))
        s = math.hypot(_se(v4) or 0.0, _se(v16) or 0.0)
        lines.append(f"- N dependence at xi = 2.5, e = 0.9: <N=16384> - <N=4096> = {d:+.4f} ± {s:.4f} "
                     f"({len(v16)} vs {len(v4)} seeds).")
        summary["n_dependence"] = dict(diff=d, se=s)
    if c4:
        # relaxation profile: mean over seeds in windows of collisions per particle
        edges = [0, 2, 5, 10, 15, 20, 25, 30]
        prof = []
        for lo, hi in zip(edges[:-1], edges[1:]):
            per = [float(np.mean(r["ratio"][(r["coll"] >= lo) & (r["coll"] < hi)])) for r in c4["runs"]
                   if np.any((r["coll"] >= lo) & (r["coll"] < hi))]
            if per:
                prof.append((lo, hi, float(np.mean(per)), _se(per)))
        lines.append("- xi = 2.5, e = 0.9, N = 4096, T_tr/T_rot by collisions per particle (mean ± SE over seeds): "
                     + "; ".join(f"[{lo}, {hi}): {m:.4f}" + (f" ± {s:.4f}" if s else "") for lo, hi, m, s in prof)
                     + ". An excess that is there from the first few collisions on is a property of the "
                       "collision process, not a late instability.")
        summary["profile_2.5_0.9_4096"] = prof
    if missing:
        lines += ["", "Not run / unreadable: " + "; ".join(missing)]
    lines += ["", "![runs](cooling_seeds.png)", ""]
    (out / "REPORT.md").write_text("\n".join(lines) + "\n")
    (out / "summary.json").write_text(json.dumps(summary, indent=1, default=float))
    series = {f"{xi}/{e}/{n}/{r['seed']}": dict(coll=r["coll"].tolist(), ratio=r["ratio"].tolist(), T=r["T"].tolist(),
                                                   flow=r["flow"])
              for (xi, e, n), c in cells.items() for r in c["runs"]}
    (out / "series.json").write_text(json.dumps(series))
    _plot(cells, dsmc, out / "cooling_seeds.png")
    print("\n".join(lines))
    return 0


def _plot(cells, dsmc, path):
    from engine.optional import require_matplotlib

    require_matplotlib("the cooling-seeds figure")
    import matplotlib.pyplot as plt

    fig, (a1, a2, a3) = plt.subplots(1, 3, figsize=(17, 4.8))
    for (xi, e, n), c in sorted(cells.items()):
        if (xi, e) != (2.5, 0.9):
            continue
        col = "C0" if n == 4096 else "C3"
        for r in c["runs"]:
            a1.plot(r["coll"], r["ratio"], "-", lw=0.4, color=col, alpha=0.5)
        m = np.mean([r["ratio"] for r in c["runs"]], axis=0)
        a1.plot(c["runs"][0]["coll"], m, "-", lw=1.8, color=col, label=f"N = {n}, mean of {len(c['runs'])}")
    d = dsmc.get("2.5/0.9/dem")
    a1.axhline(d["mean"] if d else LAST_SESSION["dsmc_dem"], color="k", lw=1, label="DSMC e_eff(D)")
    a1.axhline(LAST_SESSION["theory"], color="grey", lw=1, ls="--", label="Maxwell theory (nominal e)")
    a1.set_xlabel("collisions per particle")
    a1.set_ylabel("T_tr / T_rot")
    a1.set_title("xi = 2.5, e_n = 0.9")
    a1.legend(fontsize=7)
    labels = []
    for k, ((xi, e, n), c) in enumerate(sorted(cells.items())):
        vals = [r["late"] for r in c["runs"]]
        a2.plot([k] * len(vals), vals, "o", ms=3, color="C0")
        a2.errorbar([k + 0.15], [np.mean(vals)], yerr=[_se(vals) or 0], fmt="s", color="C1")
        for model, mk in (("dem", "x"), ("nominal", "+")):
            dd = dsmc.get(f"{xi}/{e}/{model}")
            if dd:
                a2.plot([k + 0.3], [dd["mean"]], mk, color="k", ms=8)
        labels.append(f"{xi}/{e}\nN={n}")
    a2.set_xticks(range(len(labels)))
    a2.set_xticklabels(labels, fontsize=7)
    a2.set_ylabel("late T_tr / T_rot")
    a2.set_title("per seed (o), mean ± SE (s), DSMC e_eff (x), nominal (+)")
    for (xi, e, n), c in sorted(cells.items()):
        pts = [(fr["t"] / r["t"][-1], fr["flow_excess"]) for r in c["runs"] if r["flow"] for fr in r["flow"]]
        if pts:
            pts = np.array(pts)
            a3.plot(pts[:, 0], pts[:, 1], ".", ms=4, label=f"{xi}/{e}/N={n}")
    a3.axhline(0, color="grey", lw=0.5)
    a3.set_xlabel("t / t_end")
    a3.set_ylabel("(E_flow - 3/2 T n_cells) / E_tr")
    a3.set_title("collective flow energy (excess over noise)")
    a3.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("step", choices=["simulate", "analyse"])
    ap.add_argument("--work", required=True, help="folder for the .h5 files (not the report folder)")
    ap.add_argument("--out", required=True, help="report folder (REPORT.md, PNG, JSON)")
    ap.add_argument("--runs", nargs="*", default=MAIN, help="xi:e:N:seeds")
    ap.add_argument("--extra", nargs="*", default=EXTRA, help="xi:e:N:seeds, dropped first to fit --budget-s")
    ap.add_argument("--backend", default="cuda")
    ap.add_argument("--collisions", type=float, default=40.0,
                    help="Gamma_0 t_end (40: as in the runs of Rubio-Largo et al. 2015)")
    ap.add_argument("--budget-s", type=float, default=330.0)
    ap.add_argument("--probe-steps", type=int, default=2000)
    ap.add_argument("--dsmc", default=None, help="JSON of bench/ellipsoid_dsmc_refs.py")
    args = ap.parse_args(argv)
    return simulate(args) if args.step == "simulate" else analyse(args)


if __name__ == "__main__":
    sys.exit(main())
