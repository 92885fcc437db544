"""Long-time homogeneous cooling of rough spheres: Luding's ODE to tau ~ 100, shear modes and S(k_min).

docs/physics.md §7.3. Scenes (rough spheres, e_n = e_t = e, e = 0.8 and 0.6, k_n = 1e8 N/m, rho = 2000 kg/m^3):

- ``hidalgo2013``: the Hidalgo et al. (2013) scene (N = 4096, L = 2 m, phi = 0.008), linearly STABLE against the shear
  mode (L/L_c = 0.23 at e = 0.8, 0.29 at e = 0.6; engine/analysis/shear_instability.py). Its T/T0 must follow
  the ODE (with e_t,eff) within 1 % for as long as the shear mode has not grown.
- ``unstable``: a denser, larger box (N = 32768, L = 4 m, phi = 0.1: L/L_c = 2.6 and 3.4) where the
  linear theory predicts growing shear modes, so their onset and the deviation from the ODE they cause
  can be shown.

Cost. tau = (4/3) omega_E(T0) t grows linearly in t, and dt = t_c/50 is fixed by the contact, so the
steps to tau are tau/(tau_factor dt) ~ 1/velocity_rms: for the Hidalgo et al. (2013) scene 1.86e5 steps per unit tau
at v_rms = 2.5 m/s (the hcs-spheres value), i.e. 1.9e7 steps and 8.0e10 particle-steps per seed to
tau = 100. At ~3e9 particle-steps/s (H200, CUDA ensemble) 2 x 32 seeds would take ~28 min, so the full
run uses v_rms = 10 m/s (4x fewer steps: 4.9e6 steps and 2.0e10 particle-steps per seed; the linear
spring-dashpot contact gives the same e_n and e_t,eff at any speed, the largest overlap grows ~ v to
~1.5 % of a and t_c omega_E to <= 8e-4) and 12 seeds per e (not 32): 4.8e11 particle-steps. The unstable
scene (v_rms = 5 m/s, 4 seeds per e): 4.0e5 steps, 1.3e10 particle-steps per seed, 1.1e11 in all. In all
5.9e11 particle-steps: ~200 s at 3e9/s, ~300 s at 2e9/s, which leaves room for start-up, snapshot I/O
(~3.8 GB of frames) and the analysis inside one 7-minute device command.

S(k_min) and the fcc start. The start lattice (engine/setup/scene.py) has almost no density fluctuation at
k_min, while the velocities are Maxwellian: the k_min sound mode starts with its kinetic half only, and
the ensemble mean of S(k_min) of a homogeneous gas then rises as S_eq sin^2(omega_s t) (omega_s the sound
frequency; period L/c ~ 5 collision times in the Hidalgo et al. (2013) box, ~60 in the unstable one) and settles
at or below S_eq as the sound damps. So S(k_min) BELOW the equilibrium value S_CS(phi) is the start's
memory, and S(k_min) ABOVE S_CS (at 2 SE) signals density growth (HCS density correlations, then
clustering; the linear heat mode is not modelled here). The transverse
modes do not couple to density in linear order and start at their noise level.

Observables: T/T0 and R/T0 from the records (T0 = T_tr at t = 0 after the elastic thermalisation;
tau = (2/3) G T0^(1/2) t), and from the snapshot frames (101 over the run) the six k_min shear-mode
energies in units of T (x = 1: thermal noise), the longitudinal ones and S(k_min) (engine/analysis/hydro_modes.py).
Ensemble means over seeds with standard errors (std/sqrt(seeds)); each run is interpolated onto the
tau grid of the seed-mean T0.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np

from engine.analysis.hydro_modes import file_mode_series, structure_factor_cs
from engine.analysis.shear_instability import (onset_tau, predicted_mode_energy, predicted_unstable_excess,
                                               shear_stability)
from engine.analysis.theory import luding_coefficients, luding_ode, tau_factor
from engine.output.h5md import read_series
from engine.setup.params import derive, e_t_effective
from engine.setup.spec import SimulationSpec
from engine.validation.hcs_spheres import measure_run

CASES = (0.8, 0.6)

#: scene -> (spec fields, tau_end, seeds by default, records, snapshots)
SCENES = {
    # 4000 records: files without the collision counter measure the rate from the contacts open at each record,
    # ~1 in this dilute box
    # every scene keeps the protocol its figures in docs/physics.md §7.3 were measured with: the lattice start
    # melted by elastic collisions
    "hidalgo2013": (dict(n_particles=4096, volume_fraction=0.008, box_length=2.0, velocity_rms=10.0,
                      start="lattice", thermalization=4.0), 100.0, 12, 4000, 101),
    "unstable": (dict(n_particles=32768, volume_fraction=0.1, box_length=4.0, velocity_rms=5.0,
                      start="lattice", thermalization=4.0), 100.0, 4, 400, 101),
    # CI: N = 1000, phi = 0.05, tau <= 4 (stable: L/L_c = 0.51 and 0.65); ~3e7 particle-steps per run
    "quick": (dict(n_particles=1000, volume_fraction=0.05, box_length=2.0, velocity_rms=7.0,
                   start="lattice", thermalization=1.0), 4.0, 4, 80, 9),
}

#: tau values of the report table (the nearest record)
TABLE_TAU = (1, 2, 5, 10, 20, 30, 40, 50, 60, 70, 80, 90, 100)

REFERENCES = [
    "S. Luding, M. Huthmann, S. McNamara, A. Zippelius, PRE 58, 3416 (1998) — the mean-field ODE "
    "(Hidalgo et al. 2013, Eqs. 1-2; engine/analysis/theory.py)",
    "I. Goldhirsch, G. Zanetti, PRL 70, 1619 (1993) — clustering/shear instability of the HCS",
    "J. J. Brey, M. J. Ruiz-Montero, D. Cubero, PRE 60, 3150 (1999) — origin of density clustering; "
    "the transverse shear mode drives the instability, critical size checked by DSMC",
    "V. Garzó, J. W. Dufty, PRE 59, 5895 (1999) — Enskog shear viscosity eta* and cooling rate zeta* of "
    "inelastic hard spheres (first Sonine, a2 neglected)",
    "V. Garzó, PRE 72, 021106 (2005) — linear stability of the Enskog HCS",
    "V. Garzó, A. Santos, G. M. Kremer, PRE 97, 052901 (2018) — instability of rough spheres (roughness "
    "shifts the threshold; here approximated by an effective normal restitution)",
    "T. P. C. van Noije, M. H. Ernst, R. Brito, J. A. G. Orza, PRL 79, 411 (1997) — fluctuating "
    "hydrodynamics: stationary enhancement 1/(1 - k_c^2/k^2) of stable transverse modes",
    "T. P. C. van Noije, M. H. Ernst, Granular Matter 1, 57 (1998); N. V. Brilliantov, T. Pöschel, Kinetic "
    "Theory of Granular Gases (OUP 2004) — a2 and its 3 a2/16 correction to the cooling rate (order of "
    "magnitude of the non-Gaussian shift)",
]


def scene_spec(scene: str, e: float, seed: int, backend: str = "auto", velocity_rms: float | None = None,
               tau_end: float | None = None) -> SimulationSpec:
    """The spec of one run: the scene's fields, e_n = e_t = e, t_end from tau_end (at the nominal T0)."""
    if scene not in SCENES:
        raise ValueError(f"scene = {scene!r}; choose one of {sorted(SCENES)}")
    fields, tau_default, _, records, snaps = SCENES[scene]
    fields = dict(fields)
    if velocity_rms is not None:
        fields["velocity_rms"] = velocity_rms
    tau_end = tau_default if tau_end is None else tau_end
    if not tau_end > 0:
        raise ValueError(f"tau_end = {tau_end} must be > 0")
    base = SimulationSpec(e_n=e, e_t=e, seed=seed, backend=backend, snapshots=snaps, **fields)
    p = derive(base)
    t_end = tau_end / tau_factor(p.radius, p.number_density, p.mass, base.volume_fraction, p.temperature0)
    return base.model_copy(update={"t_end": t_end, "output_interval": t_end / records})


def cost(specs) -> dict:
    """Steps and particle-steps (thermalisation + cooling) of a list of specs."""
    steps = [derive(s).n_steps + derive(s).n_thermalization_steps for s in specs]
    return {"runs": len(specs), "max_steps": max(steps),
            "particle_steps": float(sum(st * s.n_particles for st, s in zip(steps, specs)))}


# ---- analysis of result files -------------------------------------------------------------------------

def _read_run(path) -> dict:
    """engine.validation.hcs_spheres.measure_run of one result file, with its hydrodynamic-mode series, the
    number of contacts at each record and the contact duration (see :func:`collision_rate_ratio`)."""
    r = {**measure_run(path), "modes": file_mode_series(path)}
    r["contacts"] = np.asarray(read_series(path, "contacts")["value"], dtype=float)
    r["t_contact"] = contact_duration(derive(SimulationSpec(**r["spec"])))
    try:   # the collision counter (spheres; older files lack it)
        c = read_series(path, "collisions")
        r["collisions"] = (np.asarray(c["time"], dtype=float), np.asarray(c["value"], dtype=float))
    except KeyError:
        r["collisions"] = None
    return r


def contact_duration(p) -> float:
    """How long two spheres overlap in a collision (s): pi / omega with omega^2 = omega0^2 - (gamma_n / 2 m12)^2,
    the damped spring's half period (the contact ends when the overlap returns to 0, rule (a) of
    engine/physics/contact.py), the same for every impact speed and angle (the normal motion is linear). p: the
    engine.setup.params.Derived of a monodisperse spec (its m12 and gamma_n are those of the smallest pair)."""
    eta = p.gamma_n / (2.0 * p.m12)
    return math.pi / math.sqrt(p.omega0 ** 2 - eta ** 2)


def save_runs(path, cases: dict, meta: dict) -> None:
    """The runs of a report, reduced (:func:`_read_run` dicts: records, mode series, collision counts; a few MB
    instead of the GB of result files), as one npz: ``cases`` = {case key: [(seed, run dict), ...]}. Reports of
    several calls are then analysed together by ``merge`` (:func:`load_runs`)."""
    arrays = {"meta": np.array(json.dumps(meta, default=str))}
    for key, runs in cases.items():
        for seed, r in runs:
            base = f"{key}/{seed}/"
            scalars = {}
            for name, v in r.items():
                if name == "modes":
                    for m, mv in v.items():
                        if isinstance(mv, np.ndarray):
                            arrays[base + "modes/" + m] = mv
                        else:
                            scalars["modes/" + m] = mv
                elif name == "collisions":
                    if v is not None:
                        arrays[base + "collisions/time"], arrays[base + "collisions/value"] = v
                elif isinstance(v, np.ndarray):
                    arrays[base + name] = v
                else:
                    scalars[name] = v
            arrays[base + "scalars"] = np.array(json.dumps(scalars, default=float))
    np.savez_compressed(path, **arrays)


def load_runs(path) -> tuple[dict, dict]:
    """(cases, meta) of a :func:`save_runs` file: cases = {case key: {seed: run dict}}."""
    z = np.load(path)
    items: dict = {}          # (case key, seed) -> {name below the seed: value}
    for name in z.files:
        if name == "meta":
            continue
        key, seed, sub = name.split("/", 2)
        value = json.loads(str(z[name])) if sub == "scalars" else z[name]
        items.setdefault((key, int(seed)), {})[sub] = value
    cases: dict = {}
    for (key, seed), got in items.items():
        r = {"collisions": None}
        for sub, v in {**got.pop("scalars"), **got}.items():
            if sub.startswith("modes/"):
                r.setdefault("modes", {})[sub[6:]] = v
            elif not sub.startswith("collisions/"):
                r[sub] = v
        if "collisions/time" in got:
            r["collisions"] = (got["collisions/time"], got["collisions/value"])
        cases.setdefault(key, {})[seed] = r
    return cases, json.loads(str(z["meta"]))


def collisions_per_particle(run: dict) -> np.ndarray:
    """Collisions per particle since the scene started, s = 2 C / N, at the run's records (C: the ``collisions``
    series, contacts begun; each collision involves two particles)."""
    t, c = run["collisions"]
    return np.interp(run["time"], t, 2.0 * c / run["spec"]["n_particles"])


def collision_rate_ratio(run: dict) -> np.ndarray:
    """The DEM's collision rate over Enskog's at each record of one run.

    Where the file has the collision counter (series ``collisions``: every contact begun, engine/shapes/sphere),
    the rate is its time derivative: collisions per particle per second = 2 dC/dt / N (each collision involves
    two particles), taken between the records around each one. Otherwise, from the contacts C open at the
    record: a collision lasts t_contact whatever its speed, so the rate is 2 C / (N t_contact). Per unit tau
    both are divided by k = tau/t. Enskog's (with the Carnahan-Starling g(2a) of the tau of Hidalgo et al. (2013), as
    Luding's ODE assumes) is (3/4) (T/T0)^(1/2) per unit tau (engine.analysis.theory.collisions_per_particle). Ratio 1:
    the gas collides as often as the ODE assumes; below 1: velocity or position correlations (or a distribution other
    than Maxwell's, a ~ a2/16 effect) make collisions rarer.
    """
    n = run["spec"]["n_particles"]
    if run.get("collisions") is not None:
        rate = np.gradient(collisions_per_particle(run), run["time"]) / run["k"]
    else:
        rate = 2.0 * run["contacts"] / (n * run["t_contact"] * run["k"])
    return rate / (0.75 * np.sqrt(run["T"]))


def _mean_se(rows) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(rows, dtype=float)
    mean = a.mean(axis=0)
    se = a.std(axis=0, ddof=1) / math.sqrt(a.shape[0]) if a.shape[0] > 1 else np.zeros_like(mean)
    return mean, se


def analyse(paths) -> dict:
    """Seed-averaged time series of result files of one case (same spec up to the seed).

    Returns tau (records), T, T_err, R, R_err, T_ode, R_ode, dev (T/T_ode - 1), dev_err; on the frames:
    tau_f, x_shear(+_err), x_long(+_err), S(+_err), shear_fraction(+_err); the linear theory (stab,
    x_pred at k_min, dev_pred from the unstable modes) and the onsets (see :func:`onsets`); where the files
    have the collision counter, the energy change per collision (:func:`collision_loss`).
    """
    return analyse_runs([_read_run(p) for p in paths], [str(p) for p in paths])


def collision_loss(runs: list, tau, coeffs) -> dict:
    """The energy change per collision against the Maxwellian closure (engine.validation.hcs_dsmc.
    collision_change_windows), seed ratio of sums with jackknife SE, on the tau grid: loss_T, loss_T_err,
    loss_R, loss_R_err. Empty where a run lacks the collision counter."""
    from engine.validation.hcs_dsmc import collision_change_windows, ratio_of_sums

    if any(r.get("collisions") is None for r in runs):
        return {}
    rows = [collision_change_windows(r["k"] * r["time"], r["T"], r["R"], collisions_per_particle(r), coeffs, tau)
            for r in runs]
    out = {}
    for q, (num, den) in (("T", (0, 1)), ("R", (2, 3))):
        out[f"loss_{q}"], out[f"loss_{q}_err"] = ratio_of_sums([x[num] for x in rows], [x[den] for x in rows])
    return out


def analyse_runs(runs: list, paths: list) -> dict:
    """:func:`analyse` of runs already read (:func:`_read_run` dicts, e.g. from :func:`load_runs`); ``paths``
    name them in error messages."""
    if not runs:
        raise ValueError("analyse: no result files given")
    s0 = runs[0]["spec"]
    for p, r in zip(paths, runs):
        for key in ("e_n", "e_t", "n_particles", "volume_fraction", "box_length", "t_end"):
            if r["spec"][key] != s0[key]:
                raise ValueError(f"{p}: {key} = {r['spec'][key]} differs from {s0[key]} of {paths[0]}: "
                                 f"analyse one case (seeds of one spec) at a time")
    e_n, e_t, n = s0["e_n"], s0["e_t"], s0["n_particles"]
    k_mean = float(np.mean([r["k"] for r in runs]))
    tau = k_mean * runs[0]["time"]
    T, T_err = _mean_se([np.exp(np.interp(tau, r["k"] * r["time"], np.log(r["T"]))) for r in runs])
    R, R_err = _mean_se([np.exp(np.interp(tau, r["k"] * r["time"], np.log(r["R"]))) for r in runs])
    e_eff = e_t_effective(e_n, e_t) if e_t > -1 else -1.0
    r0 = float(R[0])
    T_ode, R_ode = luding_ode(e_n, e_eff, tau, 1.0, r0)
    tau_f = k_mean * runs[0]["modes"]["time"]
    coll, coll_err = _mean_se([np.interp(tau, r["k"] * r["time"], collision_rate_ratio(r)) for r in runs])
    out = {"e_n": e_n, "e_t": e_t, "e_t_effective": e_eff, "seeds": len(runs), "spec": s0, "R0": r0,
           "tau": tau, "T": T, "T_err": T_err, "R": R, "R_err": R_err, "T_ode": T_ode, "R_ode": R_ode,
           "dev": T / T_ode - 1.0, "dev_err": T_err / T_ode, "dev_R": R / R_ode - 1.0, "dev_R_err": R_err / R_ode,
           "tau_f": tau_f, "max_overlap": max(r["max_overlap"] for r in runs),
           "backend": runs[0]["backend"], "device": runs[0]["device"], "coll": coll, "coll_err": coll_err,
           "coll_source": "counter" if all(r["collisions"] is not None for r in runs) else "contacts"}
    # Luding's ODE run at the measured collision rate (both equations' rates scaled by the smoothed ratio, as a
    # function of T): what the DEM's rarer or more frequent collisions alone do to T
    w = max(1, len(tau) // 40)
    smooth = np.convolve(coll, np.ones(w) / w, mode="same")
    smooth[: w // 2 + 1] = smooth[w // 2 + 1]
    smooth[-(w // 2 + 1):] = smooth[-(w // 2 + 2)]
    order = np.argsort(T)
    t_sorted, f_sorted = T[order], smooth[order]

    def rates(t):
        f = float(np.interp(t, t_sorted, f_sorted))
        return f, f

    T_rate, R_rate = luding_ode(e_n, e_eff, tau, 1.0, r0, rates=rates)
    out["coll_smooth"] = smooth
    out.update(collision_loss(runs, tau, luding_coefficients(e_n, e_eff)))
    out["dev_rate"] = T_rate / T_ode - 1.0
    out["dev_R_rate"] = R_rate / R_ode - 1.0
    for key in ("x_shear", "x_long", "S", "shear_fraction"):
        out[key], out[key + "_err"] = _mean_se([np.interp(tau_f, r["k"] * r["modes"]["time"], r["modes"][key])
                                               for r in runs])
    stab = shear_stability(e_n, e_t, s0["volume_fraction"], n, s0["box_length"])
    out["stab"] = stab
    out["x_pred"], out["s_pred"] = predicted_mode_energy(e_n, e_eff, stab, tau_f, r0=r0)
    out["dev_pred"] = predicted_unstable_excess(e_n, e_eff, stab, n, tau, r0=r0)
    out["S_cs"] = structure_factor_cs(s0["volume_fraction"])
    out.update(onsets(out))
    return out


def onsets(c: dict) -> dict:
    """Where things happen (tau; inf = not within the run):

    - ``tau_within_1pct``: end of the initial stretch where |T/T_ode - 1| <= 1 % (the last record before the
      first one outside);
    - ``tau_dev_significant``: first tau where |dev| - 2 SE > 1 % (the deviation exceeds 1 % at 2 sigma);
    - ``tau_shear_measured``: first frame where x_shear - 2 SE > 2 (the shear modes hold twice the thermal
      noise at 2 sigma); ``tau_shear_predicted``: x_pred(k_min) = 2;
    - ``tau_dev_predicted``: the unstable shear modes hold 1 % of the translational energy (linear theory);
    - ``tau_S_above_eq``: first frame where S(k_min) - 2 SE exceeds the equilibrium S_CS (density growth).
    """
    dev, err, tau = np.abs(c["dev"]), c["dev_err"], c["tau"]
    out_idx = np.nonzero(dev > 0.01)[0]
    within = float(tau[-1]) if out_idx.size == 0 else (float(tau[out_idx[0] - 1]) if out_idx[0] > 0 else 0.0)
    sig = np.nonzero(dev - 2 * err > 0.01)[0]
    xs = np.nonzero(c["x_shear"] - 2 * c["x_shear_err"] > 2.0)[0]
    sc = np.nonzero(c["S"] - 2 * c["S_err"] > c["S_cs"])[0]
    return {"tau_S_above_eq": float(c["tau_f"][sc[0]]) if sc.size else math.inf,
            "tau_within_1pct": within, "tau_dev_significant": float(tau[sig[0]]) if sig.size else math.inf,
            "tau_shear_measured": float(c["tau_f"][xs[0]]) if xs.size else math.inf,
            "tau_shear_predicted": onset_tau(c["tau_f"], c["x_pred"], 2.0),
            "tau_dev_predicted": onset_tau(tau, c["dev_pred"], 0.01)}


def criterion(c: dict) -> bool:
    """The goal: within 1 % (at 2 SE) of the ODE for as long as the shear mode has not grown, i.e.
    no significant deviation before the measured shear onset."""
    return c["tau_dev_significant"] >= c["tau_shear_measured"]


# ---- report ---------------------------------------------------------------------------------------------

def _fmt_tau(t: float) -> str:
    return "never" if not math.isfinite(t) else f"{t:.1f}"


def _plots(results: dict, out: Path) -> None:
    from engine.optional import require_matplotlib

    require_matplotlib("a validation report's figures")
    import matplotlib.pyplot as plt

    keys = list(results)
    fig, axes = plt.subplots(1, len(keys), figsize=(5.2 * len(keys), 4.2), squeeze=False)
    for ax, key in zip(axes[0], keys):
        c = results[key]
        ax.fill_between(c["tau"], 100 * (c["dev"] - c["dev_err"]), 100 * (c["dev"] + c["dev_err"]), alpha=0.3)
        ax.plot(c["tau"], 100 * c["dev"], label="T/T_ODE - 1 (mean ± SE)")
        ax.plot(c["tau"], 100 * (c["R"] / c["R_ode"] - 1), lw=0.8, label="R/R_ODE - 1")
        if np.any(c["dev_pred"] > 0):
            ax.plot(c["tau"], 100 * c["dev_pred"], "k--", lw=1, label="unstable shear modes (linear theory)")
        for y in (-1, 1):
            ax.axhline(y, color="grey", lw=0.6, ls=":")
        if math.isfinite(c["tau_dev_predicted"]):
            ax.axvline(c["tau_dev_predicted"], color="r", lw=0.8, ls="--", label="predicted: shear modes 1 % of E_tr")
        if math.isfinite(c["tau_shear_measured"]):
            ax.axvline(c["tau_shear_measured"], color="m", lw=0.8, label="measured shear onset (x > 2)")
        ax.set_xlabel("tau")
        ax.set_ylabel("deviation from Luding's ODE (%)")
        ax.set_title(key, fontsize=9)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "deviation.png", dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(2, len(keys), figsize=(5.2 * len(keys), 7.0), squeeze=False)
    for j, key in enumerate(keys):
        c = results[key]
        ax = axes[0][j]
        ax.errorbar(c["tau_f"], c["x_shear"], yerr=c["x_shear_err"], fmt="o", ms=2.5, label="shear modes (k_min)")
        ax.errorbar(c["tau_f"], c["x_long"], yerr=c["x_long_err"], fmt="s", ms=2, alpha=0.6, label="longitudinal")
        ax.plot(c["tau_f"], c["x_pred"], "k-", lw=1, label="linear theory (Eq. 3)")
        ax.axhline(1.0, color="grey", lw=0.6, ls=":")
        if math.isfinite(c["tau_shear_predicted"]):
            ax.axvline(c["tau_shear_predicted"], color="r", lw=0.8, ls="--", label="predicted x = 2")
        ax.set_yscale("log")
        ax.set_ylabel("mode energy / T  (1 = thermal noise)")
        ax.set_title(key, fontsize=9)
        ax.legend(fontsize=7)
        ax = axes[1][j]
        ax.errorbar(c["tau_f"], c["S"], yerr=c["S_err"], fmt="o", ms=2.5, label="S(k_min), mean of x, y, z")
        ax.axhline(c["S_cs"], color="grey", lw=0.6, ls=":", label="equilibrium hard spheres (CS)")
        if math.isfinite(c["tau_S_above_eq"]):
            ax.axvline(c["tau_S_above_eq"], color="m", lw=0.8, label="measured S > S_CS (2 SE)")
        if math.isfinite(c["tau_dev_predicted"]):
            ax.axvline(c["tau_dev_predicted"], color="r", lw=0.8, ls="--", label="predicted shear onset (1 % E_tr)")
        ax.set_yscale("log")
        ax.set_xlabel("tau")
        ax.set_ylabel("S(k_min)")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "modes.png", dpi=110)
    plt.close(fig)


def sonine_shift(e: float, tau: float, loss: float) -> float:
    """Order of magnitude of the non-Gaussian correction to T/T_ODE at tau for smooth spheres of restitution
    e: van Noije & Ernst's a2 = 16(1-e)(1-2e^2)/(81 - 17e + 30e^2(1-e)) raises the cooling rate by
    eps = 3 a2/16 (Brilliantov & Pöschel), so T ~ (1 + c(1+eps) tau)^-2 with c = loss/2 (loss = A - B r_inf)
    gives T/T_ODE - 1 ~ -2 eps c tau/(1 + c tau). Rough spheres have other a2 values (docs/physics.md §7.4)."""
    a2 = 16.0 * (1 - e) * (1 - 2 * e * e) / (81 - 17 * e + 30 * e * e * (1 - e))
    eps = 3.0 * a2 / 16.0
    ct = 0.5 * loss * tau
    return -2.0 * eps * ct / (1.0 + ct)


def _verdict(c: dict) -> str:
    """One sentence per case for the report."""
    st = c["stab"]
    dev = f"|T/T_ODE - 1| <= 1 % up to tau = {c['tau_within_1pct']:.1f}"
    sig = ("; never beyond 1 % at 2 SE" if not math.isfinite(c["tau_dev_significant"])
           else f"; beyond 1 % at 2 SE from tau = {c['tau_dev_significant']:.1f}")
    if st.box_over_Lc < 1:
        shear = (f"box linearly stable (L/L_c = {st.box_over_Lc:.2f}): shear-mode energy {c['x_shear'][-1]:.2f} T at "
                 f"the end (linear theory {c['x_pred'][-1]:.2f}, stationary x* = {st.x_stationary:.2f})"
                 + ("; a deviation here is NOT caused by the shear mode" if math.isfinite(c["tau_dev_significant"])
                    else ""))
    else:
        shear = (f"box unstable (L/L_c = {st.box_over_Lc:.2f}, {st.unstable_pairs} unstable mode pairs): "
                 f"x > 2 measured "
                 f"from tau = {_fmt_tau(c['tau_shear_measured'])} (predicted {_fmt_tau(c['tau_shear_predicted'])}), "
                 f"x = {c['x_shear'][-1]:.1f} at the end (predicted {c['x_pred'][-1]:.1f}); unstable modes predicted "
                 f"to hold 1 % of E_tr from tau = {_fmt_tau(c['tau_dev_predicted'])}")
    dens = (f"; S(k_min) {c['S'][0]:.2f} -> {c['S'][-1]:.2f} (equilibrium {c['S_cs']:.2f}"
            + ("" if not math.isfinite(c["tau_S_above_eq"]) else
               f"; above it from tau = {c['tau_S_above_eq']:.1f}: density growth") + ")")
    return dev + sig + "; " + shear + dens + "; goal " + \
        ("met." if criterion(c) else "NOT met.")


def write_report(results: dict, out: Path, command: str, meta: dict) -> None:
    """README.md (command, references, theory, tables), deviation.png, modes.png, summary.json, series.npz."""
    _plots(results, out)
    lines = ["# Long-time homogeneous cooling: Luding's ODE, shear modes and S(k_min)", "",
             f"Command: `{command}`", "",
             f"Backend {meta.get('backend')} ({meta.get('device')}); wall time {meta.get('wall_s', 0):.0f} s for "
             f"{meta.get('runs')} runs, {meta.get('particle_steps', 0):.3g} particle-steps.", "",
             "## Linear theory (engine/analysis/shear_instability.py)", "",
             "Transverse mode k, scaled by the thermal speed: d u*/dt = (zeta/2 - nu k^2) u*, nu = eta/(n m); "
             "unstable for k < k_c, k_c^2 = zeta n m/(2 eta) = (zeta*/(2 eta*)) (256 pi/25) n^2 sigma^4 "
             "(Goldhirsch & Zanetti 1993; Brey, Ruiz-Montero & Cubero 1999; Garzó 2005). zeta from Luding's "
             "ODE in its asymptotic state, eta* of Garzó & Dufty (1999) at the effective restitution e_eff "
             "with (1 - e_eff^2)/4 = A - B r_inf (rough spheres mapped on smooth ones with the same cooling "
             "rate; an approximation, +-20 % on L_c). Mode energy per collision: dx/ds = 2 lambda x + 2 mu "
             "(fluctuating hydrodynamics with the elastic noise), x = 1 at t = 0.", "",
             "| case | e_eff | zeta* | eta* | L_c (m) | L/L_c | mean free path (m) | growth/collision at k_min | "
             "stable x* | unstable pairs |", "|---|---|---|---|---|---|---|---|---|---|"]
    for key, c in results.items():
        st = c["stab"]
        lines.append(f"| {key} | {st.e_eff:.4f} | {st.zeta_star:.4f} | {st.eta_star:.4f} | {st.L_c:.3f} | "
                     f"{st.box_over_Lc:.2f} | {st.mean_free_path:.4f} | {st.lambda_kmin:+.4f} | "
                     f"{st.x_stationary:.3f} | {st.unstable_pairs} |")
    lines += ["", "## Results", "",
              "| case | seeds | tau within 1 % | dev > 1 % (2 SE) from | shear x > 2 measured | predicted x = 2 | "
              "predicted 1 % of E_tr | S(k_min) > S_CS (2 SE) from | goal met | largest overlap / a |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for key, c in results.items():
        lines.append(f"| {key} | {c['seeds']} | 0 - {c['tau_within_1pct']:.1f} | "
                     f"{_fmt_tau(c['tau_dev_significant'])} | "
                     f"{_fmt_tau(c['tau_shear_measured'])} | {_fmt_tau(c['tau_shear_predicted'])} | "
                     f"{_fmt_tau(c['tau_dev_predicted'])} | {_fmt_tau(c['tau_S_above_eq'])} | "
                     f"{'yes' if criterion(c) else 'NO'} | "
                     f"{c['max_overlap']:.4f} |")
    lines += ["", "Goal: |T/T_ODE - 1| <= 1 % for as long as the shear mode has not grown; "
              "\"goal met\" = no deviation beyond 1 % at 2 SE before the measured shear onset.", "",
              "Onset scale: an unstable mode starts at the noise level (energy T, a fraction 2/(3N) of E_tr) and "
              "holds a fraction f of E_tr after s* = ln(3 N f / 2) / (2 lambda) collisions per particle; s grows "
              "only logarithmically in tau (s = (3/4) int sqrt(T/T0) dtau, ~28 and ~21 by tau = 100 for e = 0.8 "
              "and 0.6), so the onset in tau is late and sensitive to lambda.", ""]
    for key, c in results.items():
        lines.append(f"- **{key}**: " + _verdict(c))
    lines += ["", "Other sources of a deviation (present in a stable box too): the velocity distribution is not "
              "Maxwellian (the ODE assumes it); with the smooth-sphere a2 at e_eff the cooling rate changes by "
              "3 a2/16, i.e. T/T_ODE - 1 of about " + ", ".join(
                  f"{100 * sonine_shift(c['stab'].e_eff, float(c['tau'][-1]), (1 - c['stab'].e_eff ** 2) / 4):+.2f} % "
                  f"({key}, tau = {c['tau'][-1]:.0f})" for key, c in results.items())
              + "; and velocity correlations that build up in the HCS (van Noije & Ernst), which grow with the "
              "number of collisions and with phi.", ""]
    for key, c in results.items():
        lines += [f"### {key}", "",
                  "| tau | T/T0 (± SE) | ODE | deviation % (± SE) | R/T0 dev % | shear x (± SE) | theory x | "
                  "shear share of E_tr | S(k_min) (± SE) |", "|---|---|---|---|---|---|---|---|---|"]
        for tt in TABLE_TAU:
            if tt > c["tau"][-1] + 0.5:
                break
            i = int(np.argmin(np.abs(c["tau"] - tt)))
            j = int(np.argmin(np.abs(c["tau_f"] - tt)))
            lines.append(f"| {c['tau'][i]:.1f} | {c['T'][i]:.5f} ± {c['T_err'][i]:.5f} | {c['T_ode'][i]:.5f} | "
                         f"{100 * c['dev'][i]:+.2f} ± {100 * c['dev_err'][i]:.2f} | {100 * c['dev_R'][i]:+.2f} | "
                         f"{c['x_shear'][j]:.2f} ± {c['x_shear_err'][j]:.2f} | {c['x_pred'][j]:.2f} | "
                         f"{100 * c['shear_fraction'][j]:.3f} % | {c['S'][j]:.2f} ± {c['S_err'][j]:.2f} |")
        lines.append("")
    counted = all(c.get("coll_source") == "counter" for c in results.values())
    how = ("Counted: every contact begun (the result files' `collisions` series, engine/shapes/sphere), rate = "
           "2 dC/dt / N per particle between records" if counted else
           "Measured from the contacts open at each record (a collision lasts t_c = pi/omega whatever its speed: "
           "rate = 2 C / (N t_c) per particle)")
    lines += ["## Collision rate against Enskog's", "",
              how + " (collision_rate_ratio), over Enskog's (3/4) (T/T0)^(1/2) per "
              "unit tau that Luding's ODE assumes, seed mean ± SE, averaged over the records in tau ± 10 % (count "
              "noise). 'ODE at the measured rate': Luding's ODE with both rates scaled by the smoothed ratio "
              "(as a function of T); its deviation from the plain ODE is what the rarer (or more frequent) "
              "collisions alone do to T. Where the ratio's SE is more than a few % (files without the counter: "
              "few contacts open per record, the box of Hidalgo et al. (2013) has ~1), the smoothed ratio is count "
              "noise and so is the ODE run with it.", "",
              "| case | tau | rate / Enskog (± SE) | DEM T dev % (± SE) | ODE at the measured rate: T dev % | "
              "DEM R dev % | ODE at the measured rate: R dev % |", "|---|---|---|---|---|---|---|"]
    from engine.validation.hcs_dsmc import window_mean

    for key, c in results.items():
        for tt in TABLE_TAU:
            if tt > c["tau"][-1] + 0.5:
                break
            w = window_mean(c["tau"], c["coll"], c["coll_err"], tt)
            if w is None:
                continue
            ratio, ratio_se = w
            i = int(np.argmin(np.abs(c["tau"] - tt)))
            lines.append(f"| {key} | {c['tau'][i]:.1f} | {ratio:.4f} ± {ratio_se:.4f} | "
                         f"{100 * c['dev'][i]:+.2f} ± {100 * c['dev_err'][i]:.2f} | {100 * c['dev_rate'][i]:+.2f} | "
                         f"{100 * c['dev_R'][i]:+.2f} | {100 * c['dev_R_rate'][i]:+.2f} |")
    lines.append("")
    lines += ["![deviation](deviation.png)", "", "![modes](modes.png)", "",
              "Definitions: tau = (2/3) G T0^(1/2) t; T0 = T_tr at t = 0 of each seed; deviation = seed mean / "
              "ODE - 1 (ODE from the measured R(0)/T(0), e_t,eff of the contact model); x = mean over the six "
              "k_min shear modes of M |u_perp(k)|^2 / T (1 = thermal noise of a Maxwellian; "
              "engine/analysis/hydro_modes.py); "
              "S(k_min) mean over x, y, z (1 = ideal gas; S_CS = equilibrium hard spheres). The fcc start leaves "
              "S(k_min) below S_CS until the k_min sound mode has equilibrated (engine/validation/hcs_long.py "
              "docstring), so only S above S_CS signals density growth. SE = std over seeds / sqrt(seeds).", "",
              "## References", ""] + [f"- {r}" for r in REFERENCES] + [""]
    (out / "README.md").write_text("\n".join(lines) + "\n")
    summary = {}
    arrays = {}
    for key, c in results.items():
        st = c["stab"]
        summary[key] = {k: c[k] for k in ("e_n", "e_t", "e_t_effective", "seeds", "R0", "max_overlap",
                                          "tau_within_1pct", "tau_dev_significant", "tau_shear_measured",
                                          "tau_shear_predicted", "tau_dev_predicted", "tau_S_above_eq")}
        summary[key].update(goal_met=bool(criterion(c)), L_over_Lc=st.box_over_Lc, L_c=st.L_c, e_eff=st.e_eff,
                            max_abs_dev=float(np.max(np.abs(c["dev"]))),
                            x_shear_final=float(c["x_shear"][-1]), S_final=float(c["S"][-1]),
                            T_final=float(c["T"][-1]))
        for name in ("tau", "T", "T_err", "R", "R_err", "T_ode", "R_ode", "dev", "dev_err", "tau_f", "x_shear",
                     "x_shear_err", "x_long", "x_long_err", "S", "S_err", "shear_fraction", "x_pred", "dev_pred",
                     "coll", "coll_err", "coll_smooth", "dev_rate", "dev_R", "dev_R_rate", "loss_T", "loss_T_err",
                     "loss_R", "loss_R_err"):
            if name in c:
                arrays[f"{key}/{name}"] = np.asarray(c[name])
    summary = json.loads(json.dumps(summary, default=float).replace("Infinity", "null"))
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    np.savez_compressed(out / "series.npz", **arrays)


# ---- the validation ---------------------------------------------------------------------------------------

def main(out_dir="reports/hcs-long", seeds: int | None = None, quick: bool = False, backend: str = "auto",
         scenes=None, scratch=None, keep: bool = False, velocity_rms: float | None = None,
         tau_end: float | None = None, unstable_seeds: int | None = None, seed_offset: int = 0,
         dsmc: bool = True, command: str = "demq validate hcs-long") -> int:
    """Run every (scene, e, seed) as one ensemble, analyse, write the report to out_dir.

    scenes: default ('hidalgo2013', 'unstable'), quick: ('quick',). seeds: per e of the hidalgo2013 and quick
    scenes, unstable_seeds of the unstable scene (default: the scene's, SCENES).
    scratch: folder for the result files (default out_dir/runs); they are deleted after the analysis
    unless ``keep``; their reduced series stay in out_dir/runs.npz (:func:`save_runs`), so that runs with other
    seeds (``seed_offset``: seeds seed_offset, seed_offset + 1, ...) made in another call can be analysed
    with them (``merge``). Returns 0 when the goal (:func:`criterion`) holds for every case (quick: the CI checks, see
    :func:`quick_checks`), else 1.
    """
    from engine.driver.ensemble import run_ensemble

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    scenes = tuple(scenes or (("quick",) if quick else ("hidalgo2013", "unstable")))
    work = Path(scratch) if scratch else out / "runs"
    work.mkdir(parents=True, exist_ok=True)
    tasks = []
    for scene in scenes:
        n_seeds = (unstable_seeds if scene == "unstable" else seeds) or SCENES[scene][2]
        if n_seeds < 2:
            raise ValueError(f"seeds = {n_seeds} for scene {scene}: need >= 2 for a standard error")
        for e in CASES:
            for seed in range(seed_offset, seed_offset + n_seeds):
                tasks.append((scene, e, seed, scene_spec(scene, e, seed, backend, velocity_rms, tau_end),
                              work / f"{scene}_e{e}_seed{seed}.h5"))
    specs = [t[3] for t in tasks]
    c = cost(specs)
    print(f"hcs-long: {c['runs']} runs as one ensemble, up to {c['max_steps']:.3g} steps, "
          f"{c['particle_steps']:.3g} particle-steps (~{c['particle_steps'] / 3e9:.0f} s at 3e9/s)", flush=True)
    t0 = time.time()
    last = [t0]

    def progress(k: int, p) -> None:   # scene 0 has the most steps: a line every 30 s for the log
        now = time.time()
        if k == 0 and now - last[0] >= 30.0:
            last[0] = now
            print(f"hcs-long: {100 * p.fraction:.0f} % of the longest run after {now - t0:.0f} s, "
                  f"ETA {p.eta_s:.0f} s, Cundall {p.cundall:.3g} per scene", flush=True)

    results_run = run_ensemble(specs, [t[4] for t in tasks], backend=None if backend == "auto" else backend,
                               progress=progress)
    wall = time.time() - t0
    for (scene, e, seed, _, _), s in zip(tasks, results_run):
        if isinstance(s, BaseException):
            raise s
    print(f"hcs-long: ensemble done in {wall:.1f} s", flush=True)
    results, cases = {}, {}
    for scene in scenes:
        for e in CASES:
            sel = [t for t in tasks if t[0] == scene and t[1] == e]
            runs = [_read_run(t[4]) for t in sel]
            cases[f"{scene} e={e}"] = [(t[2], r) for t, r in zip(sel, runs)]
            results[f"{scene} e={e}"] = analyse_runs(runs, [str(t[4]) for t in sel])
    first = next(iter(results.values()))
    meta = {"backend": first["backend"], "device": first["device"], "wall_s": wall, "runs": c["runs"],
            "particle_steps": c["particle_steps"], "command": command}
    save_runs(out / "runs.npz", cases, meta)
    write_report(results, out, command, meta)
    if not keep:
        for t in tasks:
            for p in (t[4], t[4].with_suffix(".xmf")):
                if p.exists():
                    p.unlink()
    for key, r in results.items():
        print(f"{key}: within 1 % to tau {r['tau_within_1pct']:.1f}; dev > 1 % (2 SE) from "
              f"{_fmt_tau(r['tau_dev_significant'])}; shear x > 2 from {_fmt_tau(r['tau_shear_measured'])} "
              f"(predicted {_fmt_tau(r['tau_shear_predicted'])}); L/L_c = {r['stab'].box_over_Lc:.2f}; "
              f"goal {'met' if criterion(r) else 'NOT met'}", flush=True)
    if not quick and dsmc:
        from engine.validation import hcs_dsmc

        parts = hcs_dsmc.compare(out, _spec_for(velocity_rms))
        if parts:
            hcs_dsmc.write(out, parts, f"{command} (then engine/validation/hcs_dsmc.py on its report)")
            print(f"hcs-long: the deviation's parts (DSMC, soft contact) in {out / 'dsmc.md'}", flush=True)
    if quick:
        problems = quick_checks(results)
        for p in problems:
            print("quick check failed:", p)
        return 1 if problems else 0
    return 0 if all(criterion(r) for r in results.values()) else 1


def merge(reports, out_dir, command: str) -> dict:
    """Analyse together the runs of several reports (their runs.npz, :func:`save_runs`; e.g. the seeds of one
    scene split over two device calls with ``--seed-offset``) and write the report to out_dir. A seed that two
    reports both hold is an error (the same run twice would shrink the SE). Returns the results."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cases: dict = {}
    metas = []
    for rep in reports:
        got, meta = load_runs(Path(rep) / "runs.npz")
        metas.append(meta)
        for key, runs in got.items():
            have = cases.setdefault(key, {})
            for seed, r in runs.items():
                if seed in have:
                    raise ValueError(f"{rep}: {key} seed {seed} is already in another report")
                have[seed] = r
    results = {}
    for key, runs in cases.items():
        seeds = sorted(runs)
        results[key] = analyse_runs([runs[k] for k in seeds], [f"{key} seed {k}" for k in seeds])
    first = next(iter(results.values()))
    meta = {"backend": first["backend"], "device": first["device"],
            "wall_s": sum(float(m.get("wall_s", 0.0)) for m in metas),
            "runs": sum(int(m.get("runs", 0)) for m in metas),
            "particle_steps": sum(float(m.get("particle_steps", 0.0)) for m in metas)}
    write_report(results, out, command + "; merged from: " + "; ".join(
        f"{rep} (`{m.get('command', '?')}`)" for rep, m in zip(reports, metas)), meta)
    save_runs(out / "runs.npz", {k: sorted(v.items()) for k, v in cases.items()}, {**meta, "command": command})
    return results


#: quick scene: |T/T_ODE - 1| <= QUICK_DEV_SYSTEMATIC + QUICK_DEV_SIGMAS * SE at every record, and <= QUICK_DEV_MAX
QUICK_DEV_SYSTEMATIC, QUICK_DEV_SIGMAS, QUICK_DEV_MAX = 0.01, 3.0, 0.05
#: quick scene: the SE-weighted energy change per collision (collision_loss) within 1 +- this: the soft contact and
#: the distribution move it by ~1-2 % at this speed, the 4-seed window SEs are 5-50 % (their weighted mean ~3 %);
#: a factor 2 in the collision count or in the closure fails
QUICK_LOSS_TOL = 0.2


def quick_checks(results: dict) -> list:
    """CI checks of the reduced scene (N = 1000, phi = 0.05, L = 2 m, tau <= 4, 4 seeds per e).

    - ODE: |T/T_ODE - 1| <= 1 % + 3 SE at every record and <= 5 % everywhere. The seed scatter of T/T0 at
      N = 1000 is ~2-4 % per run by tau = 4 (measured: SE of the 4-seed mean 0.2 % at tau = 0.5, ~2 % at
      tau = 4), so the check is a 3-sigma test plus 1 % for the ODE's own (Enskog, Maxwellian) error; the
      5 % cap catches a cooling law without the translation-rotation exchange (smooth spheres' ODE lies
      +4.7 % / +7.8 % above the rough one at tau = 4 for e = 0.8 / 0.6); it cannot resolve nominal vs
      effective e_t (0.2 % / 0.9 %), which is the full run's job.
    - every mode observable finite; at tau = 0 (Maxwellian velocities independent of the positions) the
      shear and longitudinal mode energies are thermal noise, x within 1 +- 0.75: per frame the mean of
      6 (3) exponential variables scatters by 41 % (58 %), over 4 seeds SE 0.20 (0.29), so 0.75 is > 2.5 SE;
      a wrong normalisation (factor 2 or N) fails.
    - the energy change per collision (the collision counter against Luding's closure at the measured state),
      SE-weighted over tau >= 1: 1 within QUICK_LOSS_TOL.
    - the box is stable (L/L_c = 0.51, 0.65): x_shear < 4 at every frame (theory x* = 1.36, 1.74; the 4-seed
      SE is ~0.35, so 4 is > 6 SE above x*) and 0 < S(k_min) <= 2.5 S_CS (no clustering; the seed-mean S
      scatters with SE ~0.2 around <= 0.8 here, so the bound is > 4 SE away). S starts low (0.4): the fcc
      start suppresses the k_min density fluctuation (module docstring), so S(0) is not checked against
      the equilibrium value.
    """
    problems = []
    for key, c in results.items():
        dev, err = np.abs(c["dev"]), c["dev_err"]
        bad = np.nonzero(dev > QUICK_DEV_SYSTEMATIC + QUICK_DEV_SIGMAS * err)[0]
        if bad.size:
            i = int(bad[0])
            problems.append(f"{key}: |T/T_ODE - 1| = {100 * dev[i]:.2f} % at tau = {c['tau'][i]:.2f} exceeds "
                            f"1 % + 3 SE = {100 * (QUICK_DEV_SYSTEMATIC + QUICK_DEV_SIGMAS * err[i]):.2f} %")
        if not float(dev.max()) <= QUICK_DEV_MAX:
            problems.append(f"{key}: max |T/T_ODE - 1| = {100 * dev.max():.2f} % > {100 * QUICK_DEV_MAX:.0f} %")
        for name in ("x_shear", "x_long", "S", "shear_fraction"):
            if not np.all(np.isfinite(c[name])):
                problems.append(f"{key}: {name} has non-finite values")
        if not abs(c["x_shear"][0] - 1.0) <= 0.75:
            problems.append(f"{key}: shear-mode energy at tau = 0 is {c['x_shear'][0]:.2f} T, not thermal noise (1)")
        if not abs(c["x_long"][0] - 1.0) <= 0.75:
            problems.append(f"{key}: longitudinal mode energy at tau = 0 is {c['x_long'][0]:.2f} T, not 1")
        if not float(np.max(c["x_shear"])) < 4.0:
            problems.append(f"{key}: shear-mode energy reached {np.max(c['x_shear']):.2f} T in a stable box")
        if "loss_T" in c:
            lam, se = np.asarray(c["loss_T"]), np.asarray(c["loss_T_err"])
            sel = (np.asarray(c["tau"]) >= 1.0) & np.isfinite(lam) & np.isfinite(se) & (se > 0)
            mean = float(np.average(lam[sel], weights=se[sel] ** -2.0)) if sel.sum() > 5 else float("nan")
            if not abs(mean - 1.0) <= QUICK_LOSS_TOL:
                problems.append(f"{key}: energy change per collision over the Maxwellian closure's is {mean:.3f} "
                                f"(SE-weighted over tau >= 1), not 1 within {QUICK_LOSS_TOL}")
        if not (np.all(c["S"] > 0) and float(np.max(c["S"])) <= 2.5 * c["S_cs"]):
            problems.append(f"{key}: S(k_min) left (0, {2.5 * c['S_cs']:.2f}] in a stable box: "
                            f"max {np.max(c['S']):.2f}")
    return problems


def _spec_for(velocity_rms):
    """spec_for(case key, e_n) of engine.validation.hcs_dsmc.compare: the case's scene at the run's v_rms."""
    return lambda key, e_n: scene_spec(key.split()[0], e_n, 0, "cpu", velocity_rms=velocity_rms)


def _cli(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m engine.validation.hcs_long",
                                 description="Long-time HCS validation (run) or analysis of result files.")
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="run the scenes as one ensemble and write the report")
    r.add_argument("--out-dir", default="reports/hcs-long")
    r.add_argument("--seeds", type=int, default=None, help="seeds per e of hidalgo2013/quick (default 12/4)")
    r.add_argument("--unstable-seeds", type=int, default=None, help="seeds per e of the unstable scene (default 4)")
    r.add_argument("--scenes", nargs="+", choices=sorted(SCENES), default=None)
    r.add_argument("--quick", action="store_true")
    r.add_argument("--backend", choices=["auto", "cpu", "cuda"], default="auto")
    r.add_argument("--scratch", default=None, help="folder for the (large) result files")
    r.add_argument("--keep", action="store_true", help="keep the result files")
    r.add_argument("--velocity-rms", type=float, default=None, help="override the scenes' v_rms (m/s)")
    r.add_argument("--tau-end", type=float, default=None, help="override the scenes' tau_end")
    r.add_argument("--seed-offset", type=int, default=0, help="first seed (runs of other seeds made elsewhere "
                   "can then be merged with these: the merge command)")
    r.add_argument("--no-dsmc", action="store_true", help="leave out the DSMC and soft-contact parts (run the dsmc "
                   "command on the report later, e.g. after a merge)")
    g = sub.add_parser("merge", help="analyse the runs of several reports together (their runs.npz)")
    g.add_argument("out_dir")
    g.add_argument("reports", nargs="+")
    d = sub.add_parser("dsmc", help="add the deviation's parts (DSMC, soft contact; engine/validation/hcs_dsmc.py) "
                                    "to a report folder")
    d.add_argument("report", help="a report folder (series.npz, summary.json)")
    d.add_argument("--velocity-rms", type=float, default=None, help="the run's v_rms if it overrode the scene's")
    d.add_argument("--n", type=int, default=100_000, help="DSMC particles per run")
    d.add_argument("--repeats", type=int, default=8, help="independent DSMC runs per case")
    d.add_argument("--samples", type=int, default=4000, help="DEM binary collisions per temperature level")
    d.add_argument("--unstable", action="store_true",
                   help="compare the linearly unstable boxes too (rows after the measured shear onset marked)")
    a = sub.add_parser("analyse", help="seed-averaged series of result files of one case -> CSV")
    a.add_argument("files", nargs="+")
    a.add_argument("-o", "--output", default=None, help="CSV path (default: stdout)")
    args = ap.parse_args(argv)
    if args.cmd == "run":
        import sys

        return main(out_dir=args.out_dir, seeds=args.seeds, quick=args.quick, backend=args.backend,
                    scenes=args.scenes, scratch=args.scratch, keep=args.keep, velocity_rms=args.velocity_rms,
                    tau_end=args.tau_end, unstable_seeds=args.unstable_seeds, seed_offset=args.seed_offset,
                    dsmc=not args.no_dsmc, command="python -m engine.validation.hcs_long " + " ".join(sys.argv[1:]))
    if args.cmd == "merge":
        import sys

        results = merge(args.reports, args.out_dir, "python -m engine.validation.hcs_long " + " ".join(sys.argv[1:]))
        for key, r in results.items():
            print(f"{key}: {r['seeds']} seeds; within 1 % to tau {r['tau_within_1pct']:.1f}")
        return 0
    if args.cmd == "dsmc":
        import sys

        from engine.validation import hcs_dsmc

        report = Path(args.report)
        parts = hcs_dsmc.compare(report, _spec_for(args.velocity_rms), n=args.n, repeats=args.repeats,
                                 samples=args.samples, unstable=args.unstable)
        hcs_dsmc.write(report, parts, "python -m engine.validation.hcs_long " + " ".join(sys.argv[1:]))
        print((report / "dsmc.md").read_text())
        return 0
    c = analyse(args.files)
    lines = ["tau,T,T_err,T_ode,dev,dev_err,x_shear,x_shear_err,x_pred,S,S_err"]
    for j, tf in enumerate(c["tau_f"]):
        i = int(np.argmin(np.abs(c["tau"] - tf)))
        lines.append(f"{tf:.6g},{c['T'][i]:.6g},{c['T_err'][i]:.3g},{c['T_ode'][i]:.6g},{c['dev'][i]:.5g},"
                     f"{c['dev_err'][i]:.3g},{c['x_shear'][j]:.5g},{c['x_shear_err'][j]:.3g},{c['x_pred'][j]:.5g},"
                     f"{c['S'][j]:.5g},{c['S_err'][j]:.3g}")
    text = "\n".join(lines) + "\n"
    if args.output:
        Path(args.output).write_text(text)
    else:
        print(text, end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(_cli())
