"""Consistency of the per-collision measurement with the integrated deviations (this report's series.npz).

Luding's ODE with its two right-hand sides scaled by the measured (collision rate / Enskog) x lambda_T and
x lambda_R (dsmc.md, "Energy change per collision"; taken as functions of tau through the DEM's T(tau)) must
reproduce the DEM's T and R deviations if lambda and the rate are measured right, since per unit tau
dT/dtau = rate x lambda x closure at the measured state. Run from the repository root:

    python bench/reports/hcs-long/h100-32seeds/closure_check.py
"""

import json
from pathlib import Path

import numpy as np

from engine.theory import luding_ode

D = Path(__file__).resolve().parent
z = np.load(D / "series.npz")
s = json.loads((D / "summary.json").read_text())
print("| case | tau | DEM T dev % | ODE x rate x lambda: T dev % | DEM R dev % | ODE x rate x lambda: R dev % |")
print("|---|---|---|---|---|---|")
for key in s:
    tau, T, R = z[f"{key}/tau"], z[f"{key}/T"], z[f"{key}/R"]
    f_t, f_r = z[f"{key}/coll"] * z[f"{key}/loss_T"], z[f"{key}/coll"] * z[f"{key}/loss_R"]
    ok = np.isfinite(f_t) & np.isfinite(f_r) & (tau > 0.5)
    order = np.argsort(T)

    def rates(t):
        ta = float(np.interp(t, T[order], tau[order]))
        return float(np.interp(ta, tau[ok], f_t[ok])), float(np.interp(ta, tau[ok], f_r[ok]))

    c = s[key]
    t_ode, r_ode = luding_ode(c["e_n"], c["e_t_effective"], tau, 1.0, c["R0"])
    t_m, r_m = luding_ode(c["e_n"], c["e_t_effective"], tau, 1.0, c["R0"], rates=rates)
    for t in (5, 10, 20, 50, 99.5):
        i = int(np.argmin(np.abs(tau - t)))
        print(f"| {key} | {tau[i]:.1f} | {100 * (T[i] / t_ode[i] - 1):+.2f} | {100 * (t_m[i] / t_ode[i] - 1):+.2f} | "
              f"{100 * (R[i] / r_ode[i] - 1):+.2f} | {100 * (r_m[i] / r_ode[i] - 1):+.2f} |")
