"""The Boltzmann reference of the long-time HCS (docs/physics.md §7.3): what of the DEM's deviation from Luding's
ODE is the velocity distribution, and what is not.

Luding's ODE (Hidalgo et al. 2013, Eqs. 1-2; engine/analysis/theory.py) is the Maxwellian (mean-field) closure of the
Boltzmann equation for rough spheres with constant restitution (e_n, beta). In the HCS the one-particle distribution
f(v, omega) is not Maxwellian: the Sonine cumulants a20, a02, a11 and the correlation of v and omega
(Brilliantov, Pöschel, Kranz & Zippelius, PRL 98, 128001 (2007); Kranz et al., EPJ ST 179, 91 (2009))
change the cooling rates of T and R by O(1 %) (Santos, Kremer & Garzó, Prog. Theor. Phys. Suppl. 184, 31
(2010)). A DSMC of the same Boltzmann equation has all of these and nothing else (no finite density, no
spatial correlations, no soft contacts), so

    DEM / ODE - 1  =  (DSMC / ODE - 1)  [the distribution]  +  residual  [everything beyond Boltzmann + constant beta].

The DSMC is engine.validation.sonine._dsmc (m = 1, hard spheres, q = 2/5, beta = e_t,eff of the DEM's
tangential spring, engine.setup.params.e_t_effective), started Maxwellian at the DEM's measured R(0)/T(0), with the
time axis in the tau of Hidalgo et al. (2013): the pair rate is calibrated so that the Maxwellian collision frequency
per particle is (3/4) (T/T0)^(1/2) per unit tau, as for the DEM's G (tests/validation/test_hcs_dsmc.py checks
s = (3/4) tau in an elastic gas).

The soft-contact part (:func:`soft_contact_correction`) runs the DEM contact itself on binary collisions:
what the finite contact adds beyond a constant-restitution collision.

``demq validate hcs-long`` runs it on its own report; ``python -m engine.validation.hcs_long dsmc REPORT_DIR``
adds dsmc.md, dsmc.json and dsmc.png to an existing report (it reads that report's series.npz and summary.json,
so it runs anywhere, in minutes, after the GPU run). This module does not import hcs_long: the caller passes
the scene's spec.
"""

from __future__ import annotations

import json
import math
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numba
import numpy as np

from engine.analysis.theory import collisions_per_particle, luding_coefficients, luding_ode, luding_per_collision
from engine.setup.params import Q_SPHERE
from engine.validation.sonine import _dsmc, collision_normal, constant_restitution_impulse

#: tau values of the comparison table
TABLE_TAU = (1, 2, 5, 10, 20, 30, 40, 50, 60, 70, 80, 90, 99.5)


def collisions_to(e_n: float, beta: float, tau_end: float, r0: float = 1.0) -> float:
    """Collisions per particle s by tau_end in the ODE's Maxwellian closure (s = (3/4) int sqrt(T/T0) dtau),
    with 5 % to spare so the DSMC reaches tau_end."""
    tau = np.linspace(0.0, tau_end, 2001)
    t, _ = luding_ode(e_n, beta, tau, 1.0, r0)
    return 1.05 * float(collisions_per_particle(t, tau)[-1]) + 1.0


def cooling(e_n: float, beta: float, r0: float, tau, *, n: int = 100_000, repeats: int = 8, seed: int = 7,
            samples_per_collision: float = 10.0) -> dict:
    """T(tau)/T0 and R(tau)/T0 of the Boltzmann HCS of constant (e_n, beta) rough spheres (DSMC, Maxwellian
    start with R/T = r0): mean and standard error over ``repeats`` independent runs of n particles, linearly
    interpolated onto ``tau`` (samples every 1/samples_per_collision collisions per particle)."""
    tau = np.asarray(tau, dtype=float)
    s_end = collisions_to(e_n, beta, float(tau.max()), r0)

    coeffs = luding_coefficients(e_n, beta, Q_SPHERE)

    def one(r):
        out = _dsmc(n, e_n, beta, Q_SPHERE, s_end, samples_per_collision, seed + 1000 * r, r0)
        t_axis = out[:, 6]
        t_run, r_run = out[:, 7] * 2.0 * out[:, 1] / (3.0 * n), out[:, 7] * 2.0 * out[:, 3] / (3.0 * n)
        return (np.interp(tau, t_axis, t_run), np.interp(tau, t_axis, r_run), float(t_axis[-1]),
                collision_change_windows(t_axis, t_run, r_run, out[:, 0], coeffs, tau))

    _dsmc(100, 0.5, 0.5, Q_SPHERE, 1.0, 1.0, 0, 1.0)  # compile once, before the threads
    with ThreadPoolExecutor(max(1, min(repeats, numba.config.NUMBA_NUM_THREADS))) as pool:
        runs = list(pool.map(one, range(repeats)))
    if min(r[2] for r in runs) < tau.max():
        raise RuntimeError(f"DSMC reached tau = {min(r[2] for r in runs):.1f} < {tau.max():.1f}")
    t_all = np.array([r[0] for r in runs])
    r_all = np.array([r[1] for r in runs])
    se = math.sqrt(repeats) if repeats > 1 else math.nan
    loss_t, loss_t_err = ratio_of_sums([r[3][0] for r in runs], [r[3][1] for r in runs])
    loss_r, loss_r_err = ratio_of_sums([r[3][2] for r in runs], [r[3][3] for r in runs])
    return {"tau": tau, "T": t_all.mean(0), "T_err": t_all.std(0, ddof=1) / se, "R": r_all.mean(0),
            "R_err": r_all.std(0, ddof=1) / se, "n": n, "repeats": repeats,
            "loss_T": loss_t, "loss_T_err": loss_t_err, "loss_R": loss_r, "loss_R_err": loss_r_err}


def compare(report: Path, spec_for, *, n: int = 100_000, repeats: int = 8, samples: int = 4000,
            unstable: bool = False) -> dict:
    """For every linearly stable case (L < L_c) of an hcs-long report folder: DEM and DSMC deviations from the
    ODE (T and R) on the report's tau grid, the soft-contact part (:func:`soft_contact_correction`, ``samples``
    DEM binary collisions per temperature level, with ``spec_for(case_key, e_n)``: the case's spec, as run) and
    the residual DEM - DSMC - soft. Unstable boxes are left out (their late deviation is the shear mode's)
    unless ``unstable``: then they are compared too, and the table marks the rows after the measured shear
    onset (``tau_shear_measured``), where the homogeneous Boltzmann reference no longer applies."""
    summary = json.loads((report / "summary.json").read_text())
    series = np.load(report / "series.npz")
    out = {}
    for key, c in summary.items():
        if c.get("L_over_Lc", 0.0) >= 1.0 and not unstable:
            continue
        tau = series[f"{key}/tau"]
        beta = c["e_t_effective"]
        # 20 samples per collision and particle: >= 3 in the +-10 % tau windows of the per-collision changes
        # from tau = 1 on
        d = cooling(c["e_n"], beta, c["R0"], tau, n=n, repeats=repeats, samples_per_collision=20.0)
        t_ode, r_ode = luding_ode(c["e_n"], beta, tau, 1.0, c["R0"])
        out[key] = {
            "e_n": c["e_n"], "beta": beta, "R0": c["R0"], "seeds": c["seeds"], "tau": tau,
            "dem_T": series[f"{key}/T"] / t_ode - 1.0, "dem_T_err": series[f"{key}/T_err"] / t_ode,
            "dem_R": series[f"{key}/R"] / r_ode - 1.0, "dem_R_err": series[f"{key}/R_err"] / r_ode,
            "dsmc_T": d["T"] / t_ode - 1.0, "dsmc_T_err": d["T_err"] / t_ode,
            "dsmc_R": d["R"] / r_ode - 1.0, "dsmc_R_err": d["R_err"] / r_ode, "n": n, "repeats": repeats,
            "L_over_Lc": c.get("L_over_Lc"), "tau_shear_measured": c.get("tau_shear_measured")}
        spec = spec_for(key, c["e_n"])
        if abs(spec.e_t - c["e_t"]) > 1e-12:
            raise ValueError(f"{key}: the scene's e_t {spec.e_t} is not the report's {c['e_t']}")
        soft = soft_contact_correction(spec, beta, c["R0"], tau, samples=samples)
        out[key].update(soft_T=soft["T"], soft_R=soft["R"], soft_points=soft["points"], soft_fit=soft["fit"],
                        samples=samples, velocity_rms=spec.velocity_rms, soft_eps_T=soft["eps_T"],
                        soft_eps_R=soft["eps_R"])
        if f"{key}/loss_T" in series.files:
            # the energy change per collision (the collision counter): DEM and DSMC against the Maxwellian closure
            for q in ("T", "R"):
                out[key].update({f"dem_loss_{q}": series[f"{key}/loss_{q}"],
                                 f"dem_loss_{q}_err": series[f"{key}/loss_{q}_err"],
                                 f"dsmc_loss_{q}": d[f"loss_{q}"], f"dsmc_loss_{q}_err": d[f"loss_{q}_err"]})
            out[key].update(coll=series[f"{key}/coll"], coll_err=series[f"{key}/coll_err"])
        if f"{key}/dev_rate" in series.files:
            # the measured collision rate (hcs_long.collision_rate_ratio): used where it is precise
            se = rate_window_se(tau, series[f"{key}/coll_err"])
            out[key].update(rate_T=series[f"{key}/dev_rate"], rate_R=series[f"{key}/dev_R_rate"], rate_se=se,
                            rate_used=bool(se <= RATE_SE_MAX))
    return out


#: the collision-rate part enters the decomposition when the ratio's SE over tau +- 10 % windows is below this
#: (a rate error delta shifts the ODE's T by ~2 delta at late times)
RATE_SE_MAX = 0.015


def window_mean(tau, y, err, t):
    """Mean of y over the records with |tau - t| <= WINDOW t and its SE (the records' SEs taken as independent:
    each holds its own contacts, t_c far below the record interval); None when no record falls there."""
    sel = np.abs(tau - t) <= WINDOW * t
    if not sel.any():
        return None
    return float(np.mean(y[sel])), float(np.sqrt(np.sum(err[sel] ** 2)) / sel.sum())


#: half width of the tau windows of the table rows (:func:`window_mean`) and of the per-collision energy changes
#: (:func:`collision_change_windows`), relative to tau
WINDOW = 0.1


def collision_change_windows(tau, t, r, s, coeffs, grid, width: float = WINDOW):
    """What the collisions in a window changed, against what Luding's ODE says those collisions change.

    One run's series on its own records: tau, t = T/T0, r = R/T0 and s = collisions per particle so far (each
    collision counts for both partners: s = 2 C / N). For each grid point g, over the records in
    [g (1 - width), g (1 + width)]: the measured changes dT and dR, and the Maxwellian closure's changes for the
    collisions that happened there at the measured state, sum of (4/3) (-a T + b R) ds and (4/3) (b T - c R) ds
    over the record intervals (T and R at the interval's midpoint). Per collision and particle these are Luding's
    right-hand sides over Enskog's rate (engine.analysis.theory.luding_per_collision, ``coeffs`` = (a, b, c) of
    engine.analysis.theory.luding_coefficients), so the ratio measured / closure is the
    energy change per collision relative to uncorrelated Maxwellian pairs, whatever the rate. Returns
    (dT, dT_closure, dR, dR_closure), arrays like grid; NaN where a window holds fewer than two records.
    """
    tau, t, r, s = (np.asarray(x, dtype=float) for x in (tau, t, r, s))
    per_t, per_r = luding_per_collision(0.5 * (t[1:] + t[:-1]), 0.5 * (r[1:] + r[:-1]), coeffs)
    ds = np.diff(s)
    cum_t = np.concatenate([[0.0], np.cumsum(per_t * ds)])
    cum_r = np.concatenate([[0.0], np.cumsum(per_r * ds)])
    grid = np.asarray(grid, dtype=float)
    j0 = np.searchsorted(tau, grid * (1.0 - width), side="left")
    j1 = np.searchsorted(tau, grid * (1.0 + width), side="right") - 1
    ok = j1 > j0
    j0, j1 = np.where(ok, j0, 0), np.where(ok, j1, 0)
    nan = np.where(ok, 1.0, np.nan)
    return ((t[j1] - t[j0]) * nan, (cum_t[j1] - cum_t[j0]) * nan,
            (r[j1] - r[j0]) * nan, (cum_r[j1] - cum_r[j0]) * nan)


def ratio_of_sums(num, den) -> tuple[np.ndarray, np.ndarray]:
    """sum_i num_i / sum_i den_i over runs (axis 0) and its jackknife standard error (leave one run out): a ratio
    of means, robust where a single run's denominator is small. num, den: (runs, points)."""
    num, den = np.asarray(num, dtype=float), np.asarray(den, dtype=float)
    n = num.shape[0]
    with np.errstate(divide="ignore", invalid="ignore"):   # a closure change of 0 (smooth spheres' R): NaN
        ratio = np.where(den.sum(0) != 0.0, num.sum(0) / den.sum(0), np.nan)
        if n < 2:
            return ratio, np.full_like(ratio, np.nan)
        loo = (num.sum(0) - num) / (den.sum(0) - den)
        se = np.sqrt((n - 1) / n * np.sum((loo - loo.mean(0)) ** 2, axis=0))
    return ratio, np.where(np.isfinite(ratio), se, np.nan)


def rate_window_se(tau, coll_err) -> float:
    """Median over the table's tau windows of the SE of the window-mean collision-rate ratio (:func:`window_mean`)."""
    out = [w[1] for t in TABLE_TAU if (w := window_mean(tau, coll_err, coll_err, t)) is not None]
    return float(np.median(out)) if out else math.inf


def _row(c: dict, i: int) -> str:
    onset = c.get("tau_shear_measured")
    late = onset is not None and (c.get("L_over_Lc") or 0.0) >= 1.0 and c["tau"][i] >= onset
    cells = [f"{c['tau'][i]:.1f}" + (" (shear grown)" if late else "")]
    for q in ("T", "R"):
        res = c[f"dem_{q}"][i] - c[f"dsmc_{q}"][i] - c[f"soft_{q}"][i]
        err = math.hypot(c[f"dem_{q}_err"][i], c[f"dsmc_{q}_err"][i])
        cells += [f"{100 * c[f'dem_{q}'][i]:+.2f} ± {100 * c[f'dem_{q}_err'][i]:.2f}",
                  f"{100 * c[f'dsmc_{q}'][i]:+.2f} ± {100 * c[f'dsmc_{q}_err'][i]:.2f}",
                  f"{100 * c[f'soft_{q}'][i]:+.2f}", f"{100 * res:+.2f} ± {100 * err:.2f}"]
        if c.get("rate_used"):
            cells += [f"{100 * c[f'rate_{q}'][i]:+.2f}", f"{100 * (res - c[f'rate_{q}'][i]):+.2f} ± {100 * err:.2f}"]
    return "| " + " | ".join(cells) + " |"


def write(report: Path, res: dict, command: str) -> None:
    """dsmc.md (tables), dsmc.json (series), dsmc.png into the report folder."""
    lines = ["# Why the DEM leaves Luding's ODE: the velocity distribution and the soft contact", "",
             f"Command: `{command}`", "",
             "Deviations in % from Luding's ODE with e_t,eff (both from the DEM's measured R(0)/T(0)):", "",
             "- **DEM**: this report's ensemble (seed mean ± SE, series.npz);",
             "- **DSMC**: the Boltzmann equation for constant-restitution rough spheres (e_n, beta = e_t,eff, "
             "q = 2/5), which has the non-Maxwellian one-particle distribution (Sonine cumulants, v-omega "
             "correlation) and nothing else (engine/validation/hcs_dsmc.py; ± SE over its runs);",
             "- **soft**: the DEM contact itself. Two spheres of the scene are run through one whole contact on "
             "the CPU backend from Maxwellian pre-collision states (collision-rate weighted), and the mean "
             "translational and rotational energy changes are compared with the constant-restitution rule at "
             "the same states: eps = <dE>_DEM / <dE>_rule - 1 (table below). The ODE with its two rates scaled "
             "by (1 + eps(T)) gives this column. The contact lasts t_c at any speed, so the normal turns by "
             "~|g| t_c/(2a) during it and grazing collisions lose more than the rule says; eps grows with "
             "the speed (v_rms = 10 m/s here) and fades as the gas cools;",
             "- **rest** = DEM - DSMC - soft (± the DEM and DSMC errors combined): what neither explains;",
             "- **rate** (where the collision rate is measured precisely, SE <= "
             f"{100 * RATE_SE_MAX:.1f} % per tau window): Luding's ODE run at the DEM's measured collision rate "
             "(engine/validation/hcs_long.py collision_rate_ratio: the collision counter, or in older files the "
             "contacts open at each record) minus the ODE, and **rest - rate**. The measured rate includes the "
             "distribution's own effect on the rate (~a2/16, a few 0.1 % at most), which the DSMC column holds too.",
             ""]
    for key, c in res.items():
        lines += [f"## {key} (DEM: {c['seeds']} seeds, v_rms = {c['velocity_rms']} m/s; DSMC: N = {c['n']}, "
                  f"{c['repeats']} runs; soft: {c['samples']} collisions per level)", ""]
        if (c.get("L_over_Lc") or 0.0) >= 1.0:
            lines += [f"Linearly unstable box (L/L_c = {c['L_over_Lc']:.2f}): shear-mode energy x > 2 measured from "
                      f"tau = {c['tau_shear_measured']:.1f}; the rows from there on compare an inhomogeneous gas "
                      "with the homogeneous Boltzmann reference.", ""]
        if c.get("rate_used"):
            lines += ["| tau | DEM T % | DSMC T % | soft T % | rest T % | rate T % | rest - rate T % | DEM R % | "
                      "DSMC R % | soft R % | rest R % | rate R % | rest - rate R % |",
                      "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        else:
            if "rate_se" in c:
                lines += [f"Collision rate not used here: its SE per tau window is {100 * c['rate_se']:.1f} % "
                          f"(> {100 * RATE_SE_MAX:.1f} %).", ""]
            lines += [
                  "| tau | DEM T % | DSMC T % | soft T % | rest T % | DEM R % | DSMC R % | soft R % | rest R % |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for t in TABLE_TAU:
            lines.append(_row(c, int(np.argmin(np.abs(c["tau"] - t)))))
        lines += ["", "Soft-contact excess of the energy changes per collision (± SE, paired samples):", "",
                  "| T/T0 | T_rot/T | eps_tr % | eps_rot % |", "|---|---|---|---|"]
        for p in c["soft_points"]:
            lines.append(f"| {p['t_over_t0']:.3f} | {p['r_over_t']:.3f} | {100 * p['eps_tr']:+.2f} ± "
                         f"{100 * p['eps_tr_err']:.2f} | {100 * p['eps_rot']:+.2f} ± {100 * p['eps_rot_err']:.2f} |")
        f = c["soft_fit"]
        lines += ["", f"Check of the linear-in-speed picture, eps = c (T/T0)^(1/2): c_tr = {f['tr']['c']:.4f} ± "
                  f"{f['tr']['c_err']:.4f} (chi^2 {f['tr']['chi2']:.1f} / {f['tr']['dof']}), c_rot = "
                  f"{f['rot']['c']:.4f} ± {f['rot']['c_err']:.4f} (chi^2 {f['rot']['chi2']:.1f} / {f['rot']['dof']}); "
                  "the ODE uses the measured points (linear in (T/T0)^(1/2) between them), not this fit.", ""]
    lines += _loss_tables(res)
    lines += ["![dsmc](dsmc.png)", ""]
    (report / "dsmc.md").write_text("\n".join(lines))
    (report / "dsmc.json").write_text(json.dumps(
        {k: {a: (b.tolist() if isinstance(b, np.ndarray) else b) for a, b in c.items()} for k, c in res.items()},
        indent=1))
    from engine.optional import require_matplotlib

    require_matplotlib("a validation report's figures")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(res), 2, figsize=(12, 4 * len(res)), squeeze=False)
    for row, (key, c) in zip(axes, res.items()):
        for ax, q in zip(row, ("T", "R")):
            for who, col in (("dem", "C0"), ("dsmc", "C1")):
                y, e = 100 * c[f"{who}_{q}"], 100 * c[f"{who}_{q}_err"]
                ax.plot(c["tau"], y, color=col, label=f"{who.upper()} / ODE - 1")
                ax.fill_between(c["tau"], y - e, y + e, color=col, alpha=0.25, lw=0)
            ax.plot(c["tau"], 100 * c[f"soft_{q}"], color="C2", ls="--", label="soft contact (binary collisions)")
            ax.plot(c["tau"], 100 * (c[f"dsmc_{q}"] + c[f"soft_{q}"]), color="C3", label="DSMC + soft")
            if c.get("rate_used"):
                ax.plot(c["tau"], 100 * (c[f"dsmc_{q}"] + c[f"soft_{q}"] + c[f"rate_{q}"]), color="C4",
                        label="DSMC + soft + measured collision rate")
            ax.axhline(0, color="k", lw=0.8)
            ax.set_xlabel("tau")
            ax.set_ylabel(f"{q}: deviation from the ODE (%)")
            ax.set_title(key)
            ax.legend()
    fig.tight_layout()
    fig.savefig(report / "dsmc.png", dpi=110)
    plt.close(fig)


def loss_rest(c: dict, q: str, i: int) -> tuple[float, float]:
    """Per collision, what the distribution (DSMC) and the soft contact leave of the DEM's energy change:
    lambda_DEM / (lambda_DSMC (1 + eps)) - 1 at grid point i, with its SE (DEM and DSMC errors combined)."""
    dem, dsmc = c[f"dem_loss_{q}"][i], c[f"dsmc_loss_{q}"][i]
    rest = dem / (dsmc * (1.0 + c[f"soft_eps_{q}"][i])) - 1.0
    err = (1.0 + rest) * math.hypot(c[f"dem_loss_{q}_err"][i] / dem, c[f"dsmc_loss_{q}_err"][i] / dsmc)
    return float(rest), float(err)


def _loss_tables(res: dict) -> list:
    """dsmc.md's section on the energy change per collision (cases whose files had the collision counter)."""
    cases = {k: c for k, c in res.items() if "dem_loss_T" in c}
    if not cases:
        return []
    lines = ["## Energy change per collision", "",
             "The collision counter gives the collisions per particle s between records, so the energy change per "
             "collision is measured directly, apart from how often the gas collides. In tau windows of ± "
             f"{100 * WINDOW:.0f} % (collision_change_windows): lambda = the measured change of T/T0 (or R/T0) "
             "over what Luding's Maxwellian closure gives for the same collisions at the measured (T, R), "
             "(4/3) (-a T + b R) ds (and (4/3) (b T - c R) ds). lambda = 1: each collision changes the energy as "
             "an uncorrelated Maxwellian pair would. Ratio of the seed sums, jackknife SE over seeds (DEM) or over "
             "runs (DSMC, which counts its collisions the same way). The soft contact's factor is 1 + eps at "
             "the ODE's T (the table above). rest = lambda_DEM / (lambda_DSMC (1 + eps)) - 1: the part of the "
             "change per collision that neither the distribution nor the soft contact explains; below 0 for T: "
             "colliding pairs lose less translational energy than uncorrelated pairs of the same distribution "
             "(velocity correlations lower their normal relative speed). The rate over Enskog's and lambda "
             "multiply to the cooling rate over the ODE's.", "",
             "| case | tau | rate / Enskog | lambda_T DEM | lambda_T DSMC | 1 + eps_tr | rest T % | lambda_R DEM | "
             "lambda_R DSMC | 1 + eps_rot | rest R % |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for key, c in cases.items():
        onset = c.get("tau_shear_measured")
        for t in TABLE_TAU:
            if t > c["tau"][-1] + 0.5:
                break
            i = int(np.argmin(np.abs(c["tau"] - t)))
            if not np.isfinite(c["dem_loss_T"][i]) or not np.isfinite(c["dsmc_loss_T"][i]):
                continue
            late = onset is not None and (c.get("L_over_Lc") or 0.0) >= 1.0 and c["tau"][i] >= onset
            w = window_mean(c["tau"], c["coll"], c["coll_err"], t)
            cells = [key, f"{c['tau'][i]:.1f}" + (" (shear grown)" if late else ""),
                     f"{w[0]:.4f} ± {w[1]:.4f}" if w else "–"]
            for q in ("T", "R"):
                rest, err = loss_rest(c, q, i)
                cells += [f"{c[f'dem_loss_{q}'][i]:.4f} ± {c[f'dem_loss_{q}_err'][i]:.4f}",
                          f"{c[f'dsmc_loss_{q}'][i]:.4f} ± {c[f'dsmc_loss_{q}_err'][i]:.4f}",
                          f"{1.0 + c[f'soft_eps_{q}'][i]:.4f}", f"{100 * rest:+.2f} ± {100 * err:.2f}"]
            lines.append("| " + " | ".join(cells) + " |")
    return lines + [""]


# ---- the soft-contact part: DEM binary collisions against the constant-restitution rule ------------------

def _hard_rule(v1, v2, w1, w2, n, a, q, e_n, beta):
    """Post-collision (v1, v2, w1, w2) of two equal rough spheres (radius a, I = q m a^2) under the
    constant-restitution rule of the DSMC and Luding's ODE (engine.validation.sonine.
    constant_restitution_impulse); n the unit normal from 1 to 2."""
    s = w1 + w2
    j = np.array(constant_restitution_impulse(*(v1 - v2), *s, *n, a, e_n, beta, q))
    dw = np.cross(n, j) / (q * a)
    return v1 + j, v2 - j, w1 + dw, w2 + dw


def soft_contact_loss(spec, t_over_t0: float, r_over_t: float, samples: int, seed: int = 1) -> dict:
    """Collision-averaged energy changes of the DEM contact (the CPU backend: two spheres of ``spec`` through
    one whole contact) against the constant-restitution rule at the same pre-collision states (e_n, beta =
    e_t,eff), for a Maxwellian gas at T = t_over_t0 T0 (T0 = m v_rms^2 / 3) and T_rot = r_over_t T. Pairs
    are drawn as in the DSMC: relative velocity from the Maxwellian, the normal with density (g_hat.n)_+,
    weighted by |g| (the collision rate). Returns eps_tr = <dE_tr>_DEM / <dE_tr>_rule - 1 and eps_rot (same for
    the rotational energy), each with its standard error (paired samples)."""
    from engine.backends.base import ContactParams, SphereSystem
    from engine.shapes.sphere.cpu_backend import CpuBackend
    from engine.setup.params import derive, e_t_effective

    p = derive(spec)
    a, m = p.radius, p.mass
    inertia = Q_SPHERE * m * a * a
    beta = e_t_effective(spec.e_n, spec.e_t)
    kt = m * spec.velocity_rms ** 2 / 3.0 * t_over_t0
    sv, sw = math.sqrt(kt / m), math.sqrt(kt * r_over_t / inertia)
    rng = np.random.default_rng(seed)
    contact = ContactParams(k_n=p.k_n, gamma_n_coef=p.gamma_n_coef, k_t=p.k_t or None, friction=spec.friction,
                            dt=p.dt, skin=p.skin, overlap_limit=0.5)
    steps = int(3 * p.contact_time / p.dt) + 4
    mid = 0.5 * spec.box_length
    rows = np.zeros((samples, 5))
    for s in range(samples):
        v1, v2, w1, w2 = (rng.normal(0.0, x, 3) for x in (sv, sv, sw, sw))
        g = v1 - v2
        gabs = float(np.linalg.norm(g))
        # n from 1 to 2, drawn as in the DSMC (density (g_hat.n)_+)
        n = np.array(collision_normal(*(g / gabs), math.sqrt(rng.random()), 2.0 * math.pi * rng.random()))
        gap = 1.5 * g.dot(n) * p.dt  # the contact starts inside the second step
        pos = np.array([mid - (a + gap / 2) * n, mid + (a + gap / 2) * n])
        system = SphereSystem(spec.box_length, pos, np.array([v1, v2]), np.array([w1, w2]),
                              np.tile([1.0, 0.0, 0.0, 0.0], (2, 1)), np.full(2, a), np.full(2, m),
                              np.full(2, inertia))
        be = CpuBackend(system, contact)
        be.advance(steps)
        vel, om = be.vel, be.omega
        h = _hard_rule(v1, v2, w1, w2, n, a, Q_SPHERE, spec.e_n, beta)
        e_tr0 = 0.5 * m * (v1 @ v1 + v2 @ v2)
        e_rot0 = 0.5 * inertia * (w1 @ w1 + w2 @ w2)
        rows[s] = (gabs, 0.5 * m * (vel[0] @ vel[0] + vel[1] @ vel[1]) - e_tr0,
                   0.5 * inertia * (om[0] @ om[0] + om[1] @ om[1]) - e_rot0,
                   0.5 * m * (h[0] @ h[0] + h[1] @ h[1]) - e_tr0, 0.5 * inertia * (h[2] @ h[2] + h[3] @ h[3]) - e_rot0)
    w = rows[:, 0] / rows[:, 0].mean()
    out = {"t_over_t0": t_over_t0, "r_over_t": r_over_t, "samples": samples}
    for name, dem, rule in (("tr", 1, 3), ("rot", 2, 4)):
        den = float(np.mean(w * rows[:, rule]))
        diff = w * (rows[:, dem] - rows[:, rule])
        out[f"eps_{name}"] = float(np.mean(diff)) / den
        out[f"eps_{name}_err"] = float(np.std(diff, ddof=1) / math.sqrt(samples)) / abs(den)
    return out


def soft_contact_correction(spec, beta: float, r0: float, tau, *, samples: int = 2000,
                            levels=(1.0, 0.3, 0.1, 0.03)) -> dict:
    """The ODE's deviation caused by the DEM contact alone: eps_tr and eps_rot (:func:`soft_contact_loss`)
    measured at T/T0 in ``levels`` (T_rot/T from the ODE at that T) and interpolated linearly in (T/T0)^(1/2)
    through eps = 0 at T = 0 (the normal turns during a contact by an angle ~ |g| t_c / (2a), linear in the
    speed; the one-parameter fit eps = c (T/T0)^(1/2) and its chi^2 are reported as a check of that picture),
    and Luding's ODE integrated with its translational and rotational rates scaled by (1 + eps_tr) and
    (1 + eps_rot). Returns the deviations T/T_ODE - 1 and R/R_ODE - 1 on ``tau``, the points and the fit."""
    tau = np.asarray(tau, dtype=float)
    t_ode, r_ode = luding_ode(spec.e_n, beta, tau, 1.0, r0)
    pts = []
    for k, lev in enumerate(levels):
        i = int(np.argmin(np.abs(t_ode - lev)))
        pts.append(soft_contact_loss(spec, float(t_ode[i]), float(r_ode[i] / t_ode[i]), samples, seed=1 + k))
    fit = {}
    for name in ("tr", "rot"):
        x = np.sqrt([p["t_over_t0"] for p in pts])
        y = np.array([p[f"eps_{name}"] for p in pts])
        s = np.array([p[f"eps_{name}_err"] for p in pts])
        c = float(np.sum(x * y / s ** 2) / np.sum(x * x / s ** 2))
        fit[name] = {"c": c, "c_err": float(1.0 / math.sqrt(np.sum(x * x / s ** 2))),
                     "chi2": float(np.sum(((y - c * x) / s) ** 2)), "dof": len(pts) - 1}
    order = np.argsort([p["t_over_t0"] for p in pts])
    xs = np.concatenate([[0.0], np.sqrt([pts[i]["t_over_t0"] for i in order])])
    e_tr = np.concatenate([[0.0], [pts[i]["eps_tr"] for i in order]])
    e_rot = np.concatenate([[0.0], [pts[i]["eps_rot"] for i in order]])

    def eps(t):
        """(eps_tr, eps_rot) at T/T0 = t: linear in (T/T0)^(1/2) between the measured points."""
        root = np.sqrt(np.maximum(t, 0.0))
        return np.interp(root, xs, e_tr), np.interp(root, xs, e_rot)

    def rates(t):
        e_t, e_r = eps(t)
        return 1.0 + e_t, 1.0 + e_r

    t_soft, r_soft = luding_ode(spec.e_n, beta, tau, 1.0, r0, rates=rates)
    eps_t, eps_r = eps(t_ode)
    return {"points": pts, "fit": fit, "T": t_soft / t_ode - 1.0, "R": r_soft / r_ode - 1.0,
            "eps_T": eps_t, "eps_R": eps_r}

