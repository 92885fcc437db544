"""The random start against the lattice start: does a cooling run from each follow Luding's ODE as closely?

The Hidalgo et al. (2013) scene (4096 rough spheres, phi = 0.008, e_n = e_t = 0.8, velocity_rms 2 m/s) cools from two
starts, ``--seeds`` seeds each, all packed into one ensemble run:

- ``random``: the default start (random sequential addition, Maxwellian velocities and spins) with its
  default thermalisation (none at this density);
- ``lattice``: fcc sites with a random displacement, melted by one collision per particle of elastic dynamics.

For each start the seed means of T/T0 and R/T0 (T0 = the translational temperature at t = 0) are compared with
Luding's mean-field ODE (docs/physics.md §6.3) with the effective tangential restitution, on the scaled time
tau in [0, --tau]. Printed: the largest relative deviation of each start and its standard error there, and the
largest difference between the two starts in units of its standard error. JSON of every curve goes to --out.

    python -m bench.hcs_start --seeds 32 --tau 20 --backend cuda --out bench-out/hcs_start
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np

from engine.driver.ensemble import run_ensemble
from engine.setup.params import derive, e_t_effective
from engine.setup.spec import SimulationSpec
from engine.analysis.theory import luding_ode, tau_factor
from engine.validation.hcs_spheres import measure_run

STARTS = {"random": {"start": None, "thermalization": None},
          "lattice": {"start": "lattice", "thermalization": 1.0}}


def scene(start: str, seed: int, tau_end: float, backend: str, **overrides) -> SimulationSpec:
    """The Hidalgo et al. (2013) cooling scene from ``start`` ("random" or "lattice"), recorded 200 times up to
    tau_end."""
    base = SimulationSpec(e_n=0.8, e_t=0.8, seed=seed, backend=backend, snapshots=0, **STARTS[start],
                          **overrides)
    p = derive(base)
    t_end = tau_end / tau_factor(p.radius, p.number_density, p.mass, base.volume_fraction, p.temperature0)
    return base.model_copy(update={"t_end": t_end, "output_interval": t_end / 200})


def deviations(runs: list, e_n: float, e_t: float, tau_end: float) -> dict:
    """Seed mean of T/T0 and R/T0 against Luding's ODE (effective e_t, from the measured R(0)/T(0)): the
    relative deviation curves, their standard errors and their largest magnitudes on tau <= tau_end."""
    tau = runs[0]["tau"]
    out = {"tau": tau.tolist(), "seeds": len(runs)}
    T = np.array([r["T"] for r in runs])
    R = np.array([r["R"] for r in runs])
    t_theory, r_theory = luding_ode(e_n, e_t_effective(e_n, e_t), tau, 1.0, float(R[:, 0].mean()))
    window = tau <= tau_end + 1e-9
    for name, values, theory in (("T", T, t_theory), ("R", R, r_theory)):
        dev = values.mean(axis=0) / theory - 1.0
        sem = values.std(axis=0, ddof=1) / math.sqrt(len(runs)) / theory
        worst = int(np.argmax(np.abs(dev) * window))
        out[name] = {"deviation": dev.tolist(), "sem": sem.tolist(), "max_abs_deviation": float(abs(dev[worst])),
                     "sem_at_max": float(sem[worst]), "tau_at_max": float(tau[worst])}
    return out


def compare_starts(a: dict, b: dict, tau_end: float) -> dict:
    """Largest |mean_a - mean_b| / SE of the difference, per temperature, on tau <= tau_end (records align:
    both starts record at the same fractions of the same t_end)."""
    tau = np.asarray(a["tau"])
    window = tau <= tau_end + 1e-9
    out = {}
    for name in ("T", "R"):
        diff = np.asarray(a[name]["deviation"]) - np.asarray(b[name]["deviation"])
        se = np.hypot(np.asarray(a[name]["sem"]), np.asarray(b[name]["sem"]))
        z = np.where(se > 0, np.abs(diff) / np.where(se > 0, se, 1.0), 0.0)[window]
        out[name] = {"max_z": float(z.max()), "max_abs_difference": float(np.abs(diff)[window].max())}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=32)
    ap.add_argument("--tau", type=float, default=20.0, help="end of the compared window in scaled time")
    ap.add_argument("--backend", choices=["auto", "cpu", "cuda"], default="auto")
    ap.add_argument("--n-particles", type=int, default=4096)
    ap.add_argument("--out", type=Path, default=Path("bench-out/hcs_start"))
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)

    specs, outputs, labels = [], [], []
    for start in STARTS:
        for seed in range(args.seeds):
            specs.append(scene(start, seed, args.tau, args.backend, n_particles=args.n_particles))
            outputs.append(args.out / f"{start}-{seed}.h5")
            labels.append(start)
    t0 = time.perf_counter()
    results = run_ensemble(specs, outputs)
    wall = time.perf_counter() - t0
    failed = [(lab, r) for lab, r in zip(labels, results) if isinstance(r, BaseException)]
    if failed:
        raise SystemExit(f"{len(failed)} runs failed, first: {failed[0][0]}: {failed[0][1]!r}")

    report = {"seeds": args.seeds, "tau": args.tau, "n_particles": args.n_particles, "wall_s": wall,
              "backend": str(results[0].extra.get("backend", "")) if hasattr(results[0], "extra") else ""}
    for start in STARTS:
        runs = [measure_run(o) for o, lab in zip(outputs, labels) if lab == start]
        report[start] = deviations(runs, 0.8, 0.8, args.tau)
        report[start]["device"] = runs[0]["device"]
        report[start]["max_overlap"] = max(r["max_overlap"] for r in runs)
    report["difference"] = compare_starts(report["random"], report["lattice"], args.tau)
    (args.out / "hcs_start.json").write_text(json.dumps(report))

    print(f"scene of Hidalgo et al. (2013), {args.seeds} seeds per start, tau <= {args.tau:g}, "
          f"device {report['random']['device']}, {wall:.0f} s")
    print(f"{'start':8} {'max |T/T_ODE - 1|':>22} {'max |R/R_ODE - 1|':>22}")
    for start in STARTS:
        r = report[start]
        print(f"{start:8} " + " ".join(
            f"{100 * r[k]['max_abs_deviation']:9.3f} % ± {100 * r[k]['sem_at_max']:.3f} (tau {r[k]['tau_at_max']:4.1f})"
            for k in ("T", "R")))
    d = report["difference"]
    print(f"random - lattice: largest difference {100 * d['T']['max_abs_difference']:.3f} % in T "
          f"({d['T']['max_z']:.2f} SE), {100 * d['R']['max_abs_difference']:.3f} % in R ({d['R']['max_z']:.2f} SE)")
    for out in outputs:
        out.unlink(missing_ok=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
