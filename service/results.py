"""Reading a job's HDF5 result: the energy time series, and the cooling-curve plot against theory."""

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


def cooling_plot_png(path: Path, title: str) -> bytes:
    """T/T0 and R/T0 against tau (paper 001 scaled time), log-log, with Luding's ODE for spheres.

    T0 is the translational temperature at the first record (start of the cooling run); the theory
    starts from the measured R(0)/T(0) and uses the effective tangential restitution (engine.params).
    """
    from matplotlib.figure import Figure

    from engine.params import derive
    from engine.spec import SimulationSpec
    from engine.theory import luding_ode, tau_factor

    series = read_energy(path)
    spec = SimulationSpec.model_validate(read_spec(path))
    t = np.asarray(series["time"])
    temp = np.asarray(series["temperature_translational"])
    rot = np.asarray(series["temperature_rotational"])
    t0 = temp[0] if temp.size and temp[0] > 0 else math.nan
    p = derive(spec)
    tau = tau_factor(p.radius, p.number_density, p.mass, spec.volume_fraction, t0) * t if t0 == t0 else t
    fig = Figure(figsize=(6.4, 4.4), dpi=100)
    ax = fig.add_subplot()
    ax.plot(tau, temp / t0, "o", ms=3, label="T/T$_0$ (simulation)")
    ax.plot(tau, rot / t0, "s", ms=3, label="R/T$_0$ (simulation)")
    if spec.shape == "sphere" and t0 == t0 and tau.size > 1:
        theory_t, theory_r = luding_ode(spec.e_n, p.e_t_effective, tau, t0=1.0, r0=rot[0] / t0)
        ax.plot(tau, theory_t, "-", color="C0", label="T/T$_0$ (Luding ODE)")
        ax.plot(tau, theory_r, "-", color="C1", label="R/T$_0$ (Luding ODE)")
    positive = tau > 0
    if positive.sum() > 1 and np.all(temp[positive] > 0):
        ax.set_xscale("log")
        ax.set_yscale("log")
    ax.set_xlabel(r"scaled time $\tau$" if t0 == t0 else "time t / s")
    ax.set_ylabel("temperature / T$_0$")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()
