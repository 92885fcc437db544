"""Reading results: a job's energy time series and cooling-curve plot, a batch's mean-curve plot, against theory.

The plots need the ``plots`` extra (matplotlib); without it they raise engine.optional.MissingExtra."""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

import h5py
import numpy as np

#: Observables of the energy series, in column order (HDF5 ``/observables/<name>``).
SERIES = ("kinetic_energy_translational", "kinetic_energy_rotational",
          "temperature_translational", "temperature_rotational")


def read_energy(path: Path) -> dict:
    """``{"step": [...], "time": [...], <SERIES>: [...]}`` from ``/observables`` (step/time of the first)."""
    with h5py.File(path, "r") as f:
        obs = f["observables"]
        first = obs[SERIES[0]]
        out = {"step": first["step"][()].tolist(), "time": first["time"][()].tolist()}
        for name in SERIES:
            out[name] = obs[name]["value"][()].astype(float).tolist()
    return out


def energy_csv(series: dict) -> str:
    """The series as CSV with a header row."""
    columns = ["step", "time", *SERIES]
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(columns)
    writer.writerows(zip(*(series[c] for c in columns)))
    return buf.getvalue()


def read_spec(path: Path) -> dict:
    """The spec stored in the result (``/parameters@spec``)."""
    with h5py.File(path, "r") as f:
        return json.loads(f["parameters"].attrs["spec"])


def theory_curves(spec: dict, t, t0: float, r0_over_t0: float) -> dict:
    """Scaled time and the mean-field cooling curves for a spec from T(0) = t0 (J) and R(0)/T(0).

    Spheres: tau of Hidalgo et al. (2013) and Luding's ODE with the effective tangential restitution
    (engine.setup.params) -> {"x", "xlabel", "T", "R", "name"}. Ellipsoids: Haff's law with Gamma_0(xi) of Rubio-Largo
    et al. (2015) Eq. 28 (engine/validation/hcs_ellipsoids.py) and D_f = 5 -> x = t/t0, R is None. Rough ellipsoids: no
    theory (T and R None, x = t).
    """
    from engine.setup.params import derive
    from engine.setup.spec import SimulationSpec
    from engine.analysis.theory import DOF_SMOOTH_SPHEROID, haff, haff_rate, luding_ode, tau_factor

    spec = SimulationSpec.model_validate(spec)
    p = derive(spec)
    t = np.asarray(t, dtype=float)
    if spec.shape == "sphere":
        x = tau_factor(p.radius, p.number_density, p.mass, spec.volume_fraction, t0) * t
        theory_t, theory_r = luding_ode(spec.e_n, p.e_t_effective, x, t0=1.0, r0=r0_over_t0) if x.size > 1 \
            else (np.ones_like(x), np.full_like(x, r0_over_t0))
        return {"x": x, "xlabel": r"scaled time $\tau$", "T": theory_t, "R": theory_r, "name": "Luding ODE"}
    if not spec.smooth:
        # rough spheroids: no mean-field cooling theory is known (docs/physics.md §2.5)
        return {"x": t, "xlabel": "time t / s", "T": None, "R": None, "name": "no theory for rough spheroids"}
    from engine.validation.hcs_ellipsoids import gamma0

    g0 = gamma0(spec.elongation, spec.e_n, p.radius, p.number_density, p.mass, spec.volume_fraction, t0)["gamma0"]
    rate = haff_rate(spec.e_n, g0, DOF_SMOOTH_SPHEROID)
    return {"x": rate * t, "xlabel": r"Haff time $t/t_0$", "T": haff(t, rate), "R": None, "name": "Haff"}


def batch_plot_png(path: Path, title: str) -> bytes:
    """Mean T/T0 and R/T0 over the seeds of each group of a batch file, with +-1 standard-error bands,
    against Luding's ODE (spheres) or Haff's law (ellipsoids); T0 is the group's mean T(0)."""
    from engine.analysis.ensemble_stats import read_batch_result
    from engine.optional import require

    Figure = require("matplotlib.figure", "plots", "the batch plot").Figure

    data = read_batch_result(path)
    fig = Figure(figsize=(7.2, 5.0), dpi=100)
    ax = fig.add_subplot()
    xlabels, loglog = set(), True
    for i, g in enumerate(data["groups"]):
        colour = f"C{i % 10}"
        t = np.asarray(g["time"])
        tt, tr = g["temperature_translational"], g["temperature_rotational"]
        t0 = float(tt["mean"][0]) if len(t) and tt["mean"][0] > 0 else math.nan
        if not t0 == t0:
            continue
        th = theory_curves(g["spec"], t, t0, float(tr["mean"][0]) / t0)
        x = th["x"]
        xlabels.add(th["xlabel"])
        label = f"{g['label']} ({g['n_seeds']} seeds)"
        for q, style, what, theory in ((tt, "o", "T", th["T"]), (tr, "s", "R", th["R"])):
            mean = np.asarray(q["mean"]) / t0
            err = np.nan_to_num(np.asarray(q["standard_error"]) / t0)
            ax.plot(x, mean, style, ms=2.5, color=colour, label=f"{what}/T$_0$: {label}")
            ax.fill_between(x, mean - err, mean + err, color=colour, alpha=0.25, lw=0)
            if theory is not None:
                ax.plot(x, theory, "-" if what == "T" else "--", lw=1, color=colour,
                        label=f"{what}/T$_0$: {th['name']}" if i == 0 else None)
            loglog &= bool(np.all(mean[x > 0] > 0))
        positive = x > 0
        loglog &= positive.sum() > 1
    if loglog and data["groups"]:
        ax.set_xscale("log")
        ax.set_yscale("log")
    ax.set_xlabel(xlabels.pop() if len(xlabels) == 1 else "scaled time")
    ax.set_ylabel("temperature / T$_0$ (mean over seeds, band: $\\pm$1 standard error)")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=6, ncol=2)
    ax.grid(True, which="both", alpha=0.3)
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def cooling_plot_png(path: Path, title: str) -> bytes:
    """T/T0 and R/T0 against tau (the scaled time of Hidalgo et al. 2013), log-log, with Luding's ODE for spheres
    (Haff's law against t/t0 for ellipsoids; :func:`theory_curves`).

    T0 is the translational temperature at the first record (start of the cooling run); the theory
    starts from the measured R(0)/T(0) and uses the effective tangential restitution (engine.setup.params).
    """
    from engine.optional import require

    Figure = require("matplotlib.figure", "plots", "the cooling plot").Figure
    series = read_energy(path)
    t = np.asarray(series["time"])
    temp = np.asarray(series["temperature_translational"])
    rot = np.asarray(series["temperature_rotational"])
    t0 = temp[0] if temp.size and temp[0] > 0 else math.nan
    th = theory_curves(read_spec(path), t, t0, rot[0] / t0) if t0 == t0 else None
    tau = th["x"] if th is not None else t
    fig = Figure(figsize=(6.4, 4.4), dpi=100)
    ax = fig.add_subplot()
    ax.plot(tau, temp / t0, "o", ms=3, label="T/T$_0$ (simulation)")
    ax.plot(tau, rot / t0, "s", ms=3, label="R/T$_0$ (simulation)")
    if th is not None and th["T"] is not None and tau.size > 1:
        ax.plot(tau, th["T"], "-", color="C0", label=f"T/T$_0$ ({th['name']})")
        if th["R"] is not None:
            ax.plot(tau, th["R"], "-", color="C1", label=f"R/T$_0$ ({th['name']})")
    positive = tau > 0
    if positive.sum() > 1 and np.all(temp[positive] > 0):
        ax.set_xscale("log")
        ax.set_yscale("log")
    ax.set_xlabel(th["xlabel"] if th is not None else "time t / s")
    ax.set_ylabel("temperature / T$_0$")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()
