"""Homogeneous cooling of rough prolate spheroids: the sphere limit, and T_tr/T_rot against xi and e_t.

Two parts, run as ensembles (`demq validate hcs-rough-spheroids`; on the GPU all spheroid runs are one CUDA
ensemble):

- **Limit xi -> 1.** A rough-spheroid gas at xi = 1.0001 and the rough-sphere gas of the same spec and seeds
  (e_n = e_t = 0.8; the Hidalgo et al. (2013) scene, or the reduced CI scene of engine.validation.hcs_spheres) against
  Luding's ODE with e_t,eff (engine.analysis.theory.luding_ode, as engine/validation/hcs_spheres.py), and against each
  other. Pass: the spheroid mean within 3 % of the ODE (the sphere check's bound) and within 3 SE + 0.5 % of the
  sphere mean at every record (the seed scatter, plus the O(xi - 1) and contact-time differences).
- **The map.** T_tr/T_rot late in the HCS (mean over the records with at least half the final number of
  collisions per particle; T_rot over the three rotational dof) for xi in {1.5, 2, 3} and e_t in {-0.5, 0, 0.5,
  0.9} at e_n = 0.9, N = 4096, phi = 0.058 (the Rubio-Largo et al. (2015) scene
  of engine/validation/hcs_ellipsoids.py, 20 initial collision times), with the seed scatter. For reference,
  the rough-sphere value of Luding's theory at e_t,eff (the asymptotic R/T of engine.analysis.theory.r_infinity). No
  kinetic theory of rough spheroids was found (searched: homogeneous cooling of rough inelastic ellipsoids / spheroids,
  translational-rotational temperature ratio; the theories found are for rough spheres: Huthmann & Zippelius 1997,
  Luding et al. 1998, Santos, Kremer & dos Santos 2011), so the map is reported with its scatter and the sphere value
  beside it.

Outputs: REPORT.md, summary.json, rough_spheroids.png.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np

from engine.analysis.theory import r_infinity
from engine.setup.params import derive, e_t_effective
from engine.setup.spec import SimulationSpec
from engine.validation import hcs_ellipsoids, hcs_spheres

XIS = (1.5, 2.0, 3.0)
E_TS = (-0.5, 0.0, 0.5, 0.9)
E_N = 0.9
LIMIT_XI = 1.0001
LIMIT_E = 0.8
#: late window: records with at least this fraction of the final collisions per particle
LATE_FRACTION = 0.5


def limit_spec(shape: str, seed: int, backend: str, quick: bool) -> SimulationSpec:
    """The rough-sphere HCS scene of engine.validation.hcs_spheres (e_n = e_t = 0.8), as spheres or as
    spheroids of elongation 1.0001."""
    base = (hcs_spheres.quick_spec if quick else hcs_spheres.full_spec)(LIMIT_E, seed, backend)
    if shape == "sphere":
        return base
    return base.model_copy(update={"shape": "ellipsoid", "elongation": LIMIT_XI})


def map_spec(xi: float, e_t: float, seed: int, backend: str, quick: bool) -> SimulationSpec:
    """The Rubio-Largo et al. (2015) HCS scene (engine.validation.hcs_ellipsoids._spec) with rough contacts: N = 4096,
    phi = 0.058, v_rms = 3.5 m/s, 20 initial collision times (the late window then spans ~5 collisions per
    particle, after T_tr/T_rot has settled; CI: N = 256, 9)."""
    if quick:
        base = hcs_ellipsoids.quick_spec(xi, E_N, seed, backend)
    else:
        base = hcs_ellipsoids._spec(xi, E_N, seed, backend, 4096, 20.0, 3.5, 3.0)
    return base.model_copy(update={"e_t": e_t})


def _ensemble(specs: list, paths: list, backend: str) -> None:
    from engine.driver.ensemble import run_ensemble

    t0 = time.time()
    for spec, path, s in zip(specs, paths, run_ensemble(specs, paths, backend=backend)):
        if isinstance(s, BaseException):
            raise s
    print(f"{len(specs)} runs ({specs[0].shape}) as one ensemble in {time.time() - t0:.1f} s", flush=True)


def late_ratio(run: dict) -> float:
    """Mean T_tr/T_rot over the late window of one run (engine.validation.hcs_ellipsoids.measure_run)."""
    late = run["coll"] >= LATE_FRACTION * run["coll"][-1]
    return float(np.mean(run["ratio"][late]))


def sphere_ratio(e_n: float, e_t: float) -> float:
    """T_tr/T_rot of rough spheres in the HCS, Luding's mean-field theory at e_t,eff (1/r_infinity)."""
    return 1.0 / r_infinity(e_n, e_t_effective(e_n, e_t))


def _mean_se(values) -> tuple[float, float]:
    v = np.asarray(values, float)
    return float(v.mean()), float(v.std(ddof=1) / math.sqrt(len(v))) if len(v) > 1 else 0.0


def analyse_limit(spheres: list, spheroids: list) -> dict:
    """Both gases against the ODE (hcs_spheres.compare) and the spheroid mean against the sphere mean."""
    cs = hcs_spheres.compare(spheres, LIMIT_E, LIMIT_E)
    ce = hcs_spheres.compare(spheroids, LIMIT_E, LIMIT_E)
    n = min(len(cs["T"]), len(ce["T"]))
    se = np.sqrt(cs["T_err"][:n] ** 2 + ce["T_err"][:n] ** 2)
    se_r = np.sqrt(cs["R_err"][:n] ** 2 + ce["R_err"][:n] ** 2)
    d_t = np.abs(ce["T"][:n] - cs["T"][:n])
    d_r = np.abs(ce["R"][:n] - cs["R"][:n])
    ok_pair = bool(np.all(d_t <= 3 * se + 0.005 * cs["T"][:n]) and np.all(d_r <= 3 * se_r + 0.005 * cs["R"][:n]))
    return {"spheres": cs, "spheroids": ce, "max_diff_T": float(np.max(d_t / cs["T"][:n])),
            "max_diff_R": float(np.max(d_r / cs["R"][:n])), "pair_within_scatter": ok_pair,
            "spheroid_max_dev": max(ce["max_dev_T"], ce["max_dev_R"]),
            "sphere_max_dev": max(cs["max_dev_T"], cs["max_dev_R"])}


def plot(limit: dict, cells: dict, path: Path) -> None:
    from engine.optional import require_matplotlib

    require_matplotlib("a validation report's figures")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
    for key, style in (("spheres", "-"), ("spheroids", "--")):
        c = limit[key]
        ax1.plot(c["tau"], c["T"], style, color="C0", label=f"T/T0 {key}")
        ax1.plot(c["tau"], c["R"], style, color="C1", label=f"R/T0 {key}")
    c = limit["spheres"]
    ax1.plot(c["tau"], c["T_theory"], ":", color="k", label="Luding's ODE (e_t,eff)")
    ax1.plot(c["tau"], c["R_theory"], ":", color="k")
    ax1.set_xlabel("tau")
    ax1.set_yscale("log")
    ax1.set_title(f"xi = {LIMIT_XI} spheroids vs spheres, e_n = e_t = {LIMIT_E}")
    ax1.legend(fontsize=7)
    for k, xi in enumerate(XIS):
        pts = [(e_t, cells[(xi, e_t)]["ratio"], cells[(xi, e_t)]["ratio_se"]) for e_t in E_TS if (xi, e_t) in cells]
        if pts:
            x, y, e = zip(*pts)
            ax2.errorbar(np.asarray(x) + 0.01 * (k - 1), y, yerr=e, fmt="o-", ms=4, capsize=3, label=f"xi = {xi}")
    grid = np.linspace(min(E_TS), max(E_TS), 60)
    ax2.plot(grid, [sphere_ratio(E_N, e) for e in grid], "k:", label="rough spheres (Luding, e_t,eff)")
    ax2.set_xlabel("e_t")
    ax2.set_ylabel("T_tr / T_rot (late HCS)")
    ax2.set_title(f"rough spheroids, e_n = {E_N}")
    ax2.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(out_dir="reports/hcs-rough-spheroids", seeds: int = 8, quick: bool = False, backend: str = "auto",
         limit_seeds: int | None = None, xis=XIS, e_ts=E_TS, command: str = "") -> int:
    """Run the limit (spheres and xi = 1.0001 spheroids) and the map (xis x e_ts x seeds) and write the report;
    0 when the limit checks pass."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    limit_seeds = limit_seeds or (4 if quick else seeds)
    t0 = time.time()
    sp_paths = [out / f"limit_sphere_seed{s}.h5" for s in range(limit_seeds)]
    _ensemble([limit_spec("sphere", s, backend, quick) for s in range(limit_seeds)], sp_paths, backend)
    cells_list = [(xi, e_t, s) for xi in xis for e_t in e_ts for s in range(seeds)]
    el_specs = [limit_spec("ellipsoid", s, backend, quick) for s in range(limit_seeds)] + \
               [map_spec(xi, e_t, s, backend, quick) for xi, e_t, s in cells_list]
    el_paths = [out / f"limit_spheroid_seed{s}.h5" for s in range(limit_seeds)] + \
               [out / f"xi{xi}_et{e_t}_seed{s}.h5" for xi, e_t, s in cells_list]
    _ensemble(el_specs, el_paths, backend)
    wall = time.time() - t0
    limit = analyse_limit([hcs_spheres.measure_run(p) for p in sp_paths],
                          [hcs_spheres.measure_run(p) for p in el_paths[:limit_seeds]])
    cells = {}
    runs_by_cell: dict = {}
    for (xi, e_t, s), p in zip(cells_list, el_paths[limit_seeds:]):
        runs_by_cell.setdefault((xi, e_t), []).append(hcs_ellipsoids.measure_run(p))
    for key, runs in runs_by_cell.items():
        m, se = _mean_se([late_ratio(r) for r in runs])
        cells[key] = {"ratio": m, "ratio_se": se, "seeds": len(runs),
                      "collisions": float(np.mean([r["coll"][-1] for r in runs])),
                      "max_overlap_b": max(r["max_overlap_b"] for r in runs),
                      "sphere_theory": sphere_ratio(E_N, key[1])}
    probe = hcs_spheres.measure_run(sp_paths[0])
    plot(limit, cells, out / "rough_spheroids.png")
    ok = limit["spheroid_max_dev"] <= 0.03 and limit["pair_within_scatter"]
    spec0 = map_spec(xis[0], e_ts[0], 0, backend, quick)
    p0 = derive(spec0)
    lines = ["# Rough spheroids in the homogeneous cooling state", "",
             f"Command: `{command or 'demq validate hcs-rough-spheroids'}`", "",
             f"Backend {probe['backend']} ({probe['device']}); wall time {wall:.0f} s for "
             f"{len(sp_paths) + len(el_paths)} runs.", "",
             f"## Limit xi -> 1 (xi = {LIMIT_XI}, e_n = e_t = {LIMIT_E}, {limit_seeds} seeds, "
             f"{'reduced CI scene' if quick else 'Hidalgo et al. (2013) scene'})", "",
             "| gas | max dev T/T0 from the ODE | max dev R/T0 | tau range |", "|---|---|---|---|"]
    for key in ("spheres", "spheroids"):
        c = limit[key]
        lines.append(f"| {key} | {100 * c['max_dev_T']:.2f} % | {100 * c['max_dev_R']:.2f} % | "
                     f"0 - {c['tau_end']:.2f} |")
    lines += ["", "Spheroids vs spheres, largest relative difference of the means: "
              f"T {100 * limit['max_diff_T']:.2f} %, "
              f"R {100 * limit['max_diff_R']:.2f} %; within 3 SE + 0.5 % at every record: "
              f"**{'yes' if limit['pair_within_scatter'] else 'NO'}**. Pass (spheroids within 3 % of the ODE and of "
              f"the spheres within the scatter): **{'yes' if ok else 'NO'}**.", "",
              f"## T_tr/T_rot of rough spheroids (e_n = {E_N}, N = {spec0.n_particles}, phi = "
              f"{spec0.volume_fraction}, {seeds} seeds per cell, late window: >= {LATE_FRACTION:g} of the final "
              f"collisions per particle)", "",
              "| xi | e_t | T_tr/T_rot (± SE over seeds) | rough spheres (Luding, e_t,eff) | collisions per particle | "
              "largest overlap / b |", "|---|---|---|---|---|---|"]
    for (xi, e_t), c in sorted(cells.items()):
        lines.append(f"| {xi} | {e_t} | {c['ratio']:.4f} ± {c['ratio_se']:.4f} | {c['sphere_theory']:.4f} | "
                     f"{c['collisions']:.1f} | {c['max_overlap_b']:.4f} |")
    lines += ["", "![rough spheroids](rough_spheroids.png)", "",
              "T_rot counts the three rotational dof (rough contacts exchange energy with the spin about the "
              "symmetry axis too). e_t sets k_t through Eq. 4 of Hidalgo et al. (2013) with the pair's tangential "
              "mass at the contact point (docs/physics.md §2.5); for a spheroid it is the tangential restitution of "
              "the equivalent isotropic contact, exact only in the sphere limit. No kinetic theory of rough spheroids "
              "was found (module docstring); the sphere column is Luding's mean-field value for rough spheres "
              f"with the same e_n and e_t,eff. Time step dt = {p0.dt:.3g} s (t_c/50).",
              "", "References: S. Luding, M. Huthmann, S. McNamara, A. Zippelius, PRE 58, 3416 (1998); M. Huthmann, "
              "A. Zippelius, PRE 56, R6275 (1997); A. Santos, G. M. Kremer, M. dos Santos, Phys. Fluids 23, 030604 "
              "(2011); S. M. Rubio-Largo, P. G. Lind, D. Maza, R. C. Hidalgo, Comput. Part. Mech. (2015) (smooth "
              "spheroids)."]
    (out / "REPORT.md").write_text("\n".join(lines) + "\n")
    summary = {"limit": {k: limit[k] for k in ("max_diff_T", "max_diff_R", "pair_within_scatter", "spheroid_max_dev",
                                                "sphere_max_dev")},
               "cells": {f"{xi}/{e_t}": c for (xi, e_t), c in cells.items()}, "pass": ok, "wall_s": wall}
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print("\n".join(lines[:12 + len(cells)]))
    return 0 if ok else 1
