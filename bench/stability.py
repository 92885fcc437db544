"""The CPU stress matrix: every kind of bad or extreme scene, each in its own process.

Every cell either runs and passes its checks (``ok``), stops with the engine's own error
(``stopped: <InstabilityError message>``), is refused before it runs (``refused: <validation message>``),
or is a ``BUG`` (NaN in the result, a hang, a crash, an unexpected exception, a run that finishes but
fails its checks: silent garbage). Each cell runs in its own child process under a timeout, so a hang
or a segfault is reported instead of stopping the bench.

Checks of a finished run (``ok``):
- every observable and the final snapshot are finite;
- dissipative runs: the total energy E = E_tr + E_rot + E_el never rises above the lowest earlier record
  by more than ENERGY_TOL (the integration error is O((dt/t_c)^2) ~ 1e-3 at dt = t_c/10);
- elastic runs (e_n = 1, smooth): |E_end/E_0 - 1| < ENERGY_TOL (same O((dt/t_c)^2) reason);
- the largest recorded overlap is below overlap_limit (the run-time guard's bound);
- total momentum conserved: |P_end - P_0| / (sum m |v|)_0 below MOMENTUM_TOL[precision] (pair forces
  are antisymmetric bit for bit, so only the rounding of the velocity updates is left).

Reproduce: ``python -m bench stability [--out DIR]``; it writes
REPORT.md and results.json into DIR (default ./bench-out/stability/).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

ENERGY_TOL = 1e-2
MOMENTUM_TOL = {"float64": 1e-9, "float32": 1e-4}   # float32: eps 6e-8 per update, random walk over 1e4 steps
CELL_TIMEOUT_S = 60.0       # a running cell that reports no progress for this long is a hang
COMPILE_TIMEOUT_S = 900.0   # total limit per cell: Numba compiles a new specialisation in a fresh cache
MAX_STEPS = 30000

# ---- the matrix -------------------------------------------------------------------------------------

#: small periodic gas: N = 256 spheres (a full 4^3 fcc start lattice), phi = 0.1, L = 0.2 m, k_n = 1e8
BASE = dict(n_particles=256, volume_fraction=0.1, box_length=0.2, snapshots=2, thermalization=0.5,
            backend="cpu", seed=3)


def gas(overlap=0.01, collisions=2.0, max_steps=MAX_STEPS, **kw) -> dict:
    """Spec fields of a small gas whose typical head-on overlap is `overlap` radii (sqrt(2) v_rms/omega_0);
    t_end covers `collisions` collisions per particle, at most max_steps steps (thermalisation too)."""
    from engine.setup.params import derive
    from engine.setup.spec import SimulationSpec

    fields = dict(BASE)
    fields.update(kw)
    probe = SimulationSpec.model_construct(**{**SimulationSpec.model_construct().__dict__, **fields,
                                              "velocity_rms": 1.0, "dt": None})
    p = derive(probe)
    v = overlap * p.radius_min * p.omega0 / math.sqrt(2.0)
    probe = SimulationSpec.model_construct(**{**probe.__dict__, "velocity_rms": v})
    p = derive(probe)
    dt = fields.get("dt") or p.dt
    t_end = min(collisions / p.collision_rate0, max_steps * dt)
    therm = min(fields["thermalization"], 0.5 * max_steps * dt * p.collision_rate0)
    fields.update(velocity_rms=float(f"{v:.6g}"), t_end=float(f"{t_end:.6g}"), thermalization=float(f"{therm:.4g}"))
    return fields


def _tc(**kw) -> float:
    from engine.setup.params import derive
    from engine.setup.spec import SimulationSpec

    fields = {**SimulationSpec.model_construct().__dict__, **BASE, **kw, "dt": None}
    return derive(SimulationSpec.model_construct(**fields)).contact_time


def cells() -> list[dict]:
    tc = _tc()
    out = []

    def spec(name, fields, what):
        out.append({"name": name, "kind": "spec", "spec": fields, "what": what})

    # time step, from safe to 5x too large (the spec refuses dt > t_c/10)
    for frac in (50, 20, 10):
        spec(f"dt=tc/{frac}", gas(dt=float(f"{tc / frac:.6g}")), f"dt = t_c/{frac}")
    spec("dt=2x too large", gas(dt=float(f"{tc / 5:.6g}")), "dt = t_c/5 = 2x the spec limit t_c/10")
    spec("dt=5x too large", gas(dt=float(f"{tc / 2:.6g}")), "dt = t_c/2 = 5x the spec limit t_c/10")
    # restitution
    for e in (0.05, 0.3, 0.8):
        spec(f"e_n={e}", gas(e_n=e), f"e_n = {e}, e_t = 0.8")
    spec("e_n=1 smooth", gas(e_n=1.0, e_t=-1.0), "e_n = 1, e_t = -1 (elastic, smooth)")
    spec("e_n=1 e_t=0.8", gas(e_n=1.0), "e_n = 1, e_t = 0.8")
    spec("e_n=0.05 mu=0.3", gas(e_n=0.05, friction=0.3), "e_n = 0.05, Coulomb mu = 0.3")
    # impact speed: typical overlaps 1 %, 5 %, 20 % of the radius
    spec("overlap 1%", gas(overlap=0.01), "typical overlap 1 %, limit 0.05")
    spec("overlap 5% default limit", gas(overlap=0.05), "typical overlap 5 %, limit 0.05 (refusal expected)")
    spec("overlap 5% limit 0.2", gas(overlap=0.05, overlap_limit=0.2), "typical overlap 5 %, limit 0.2")
    spec("overlap 20% limit 0.5", gas(overlap=0.2, overlap_limit=0.5), "typical overlap 20 %, limit 0.5")
    spec("overlap 20% limit 0.2", gas(overlap=0.2, overlap_limit=0.2),
         "typical overlap 20 %, limit 0.2 (tails exceed it)")
    # dense starts
    spec("phi=0.3", gas(volume_fraction=0.3), "phi = 0.3")
    spec("phi=0.5", gas(volume_fraction=0.5, collisions=1.0), "phi = 0.5 (fcc start lattice, near its limit)")
    spec("phi=0.6 N=256", gas(volume_fraction=0.6, collisions=1.0),
         "phi = 0.6 (fcc start lattice of 256 sites holds up to 0.74)")
    # tiny systems
    spec("N=2", gas(n_particles=2, volume_fraction=0.008, box_length=2.0, collisions=0.5),
         "N = 2, phi = 0.008, L = 2 m")
    spec("N=3", gas(n_particles=3, volume_fraction=0.008, box_length=2.0, collisions=0.5),
         "N = 3, phi = 0.008, L = 2 m")
    spec("N=2 phi=0.3", gas(n_particles=2, volume_fraction=0.3, box_length=0.2),
         "N = 2, phi = 0.3: box smaller than 3 neighbour cutoffs")
    spec("N=3 phi=0.05", gas(n_particles=3, volume_fraction=0.05, box_length=0.2),
         "N = 3, phi = 0.05: tiny box")
    # float32
    spec("float32 base", gas(precision="float32"), "float32, e_n = 0.8")
    spec("float32 e_n=0.05", gas(precision="float32", e_n=0.05), "float32, e_n = 0.05")
    spec("float32 phi=0.5", gas(precision="float32", volume_fraction=0.5, collisions=1.0), "float32, phi = 0.5")
    spec("float32 dt=tc/10", gas(precision="float32", dt=float(f"{tc / 10:.6g}")), "float32, dt = t_c/10")
    spec("float32 e_n=1 smooth", gas(precision="float32", e_n=1.0, e_t=-1.0), "float32, elastic smooth")
    # ellipsoids (frictionless CPU backend), elongation 5
    ell = dict(shape="ellipsoid", elongation=5.0, e_t=-1.0, n_particles=64, volume_fraction=0.01,
               box_length=0.2, collisions=1.0, max_steps=6000)
    spec("ellipsoid xi=5", gas(**ell), "prolate spheroids xi = 5, frictionless, N = 64")
    spec("ellipsoid xi=5 float32", gas(**{**ell, "precision": "float32"}), "as above, float32")
    spec("ellipsoid rough", gas(**{**ell, "e_t": 0.8}), "xi = 5 with e_t = 0.8 (not supported)")
    # overlapping initial positions, through the backend API (the spec's placement never overlaps)
    for ov, lim in ((0.1, 0.05), (0.1, 0.5), (0.4, 0.5), (1.0, 0.5), (2.0, 0.5)):
        what = "coincident centres" if ov == 2.0 else f"start overlap {ov:g} radii"
        out.append({"name": f"pair start overlap {ov:g} limit {lim:g}", "kind": "pair", "overlap": ov,
                    "limit": lim, "what": f"2 spheres, {what}, overlap_limit {lim:g}, e_n = 1 smooth"})
    out.append({"name": "triple start overlap 0.3", "kind": "pair", "overlap": 0.3, "limit": 0.5, "n": 3,
                "what": "3 spheres in a row, neighbours overlapping 0.3 radii, limit 0.5"})
    out.append({"name": "pair coincident float32", "kind": "pair", "overlap": 2.0, "limit": 0.5,
                "precision": "float32", "what": "2 spheres, coincident centres, float32"})
    return out


# ---- child: run one cell ----------------------------------------------------------------------------

def _check_file(path, spec) -> list[str]:
    import h5py
    import numpy as np

    problems = []
    with h5py.File(path, "r") as f:
        obs = f["observables"]
        for name in obs:
            v = obs[name]["value"][()]
            if not np.all(np.isfinite(v)):
                problems.append(f"non-finite {name}")
        e = (obs["kinetic_energy_translational"]["value"][()] + obs["kinetic_energy_rotational"]["value"][()]
             + obs["elastic_energy"]["value"][()])
        ovl = float(np.max(obs["max_overlap"]["value"][()]))
        part = f["particles/all"]
        vel = part["velocity"]["value"][()].astype(np.float64)
        mass = part["mass"][()]
        if not np.all(np.isfinite(part["position"]["value"][()])) or not np.all(np.isfinite(vel)):
            problems.append("non-finite snapshot")
    dissipative = spec.e_n < 1.0 or (not spec.smooth and spec.e_t < 1.0) or spec.friction is not None
    if dissipative:
        rise = max((e[i] / np.min(e[:i]) - 1.0 for i in range(1, len(e))), default=0.0)
        if rise > ENERGY_TOL:
            problems.append(f"energy rose by {rise:.3g} in a dissipative run")
    elif spec.smooth:
        drift = abs(e[-1] / e[0] - 1.0)
        if drift > ENERGY_TOL:
            problems.append(f"energy drift {drift:.3g} in an elastic run")
    if ovl > spec.overlap_limit:
        problems.append(f"recorded overlap {ovl:.3g} above the limit {spec.overlap_limit}")
    p0 = (mass[:, None] * vel[0]).sum(0)
    p1 = (mass[:, None] * vel[-1]).sum(0)
    scale = float((mass * np.linalg.norm(vel[0], axis=1)).sum())
    dp = float(np.linalg.norm(p1 - p0)) / scale
    if dp > MOMENTUM_TOL[spec.precision]:
        problems.append(f"momentum changed by {dp:.3g} of sum m|v|")
    return problems, {"max_overlap": ovl, "energy_end/energy_0": float(e[-1] / e[0]), "momentum_rel": dp,
                      "records": int(len(e))}


def _run_spec(cell: dict) -> dict:
    from pydantic import ValidationError

    from engine.errors import InstabilityError, SpecError
    from engine.driver.simulate import run
    from engine.setup.spec import SimulationSpec

    try:
        spec = SimulationSpec.model_validate(cell["spec"])
    except ValidationError as exc:
        msgs = "; ".join(f"{'.'.join(map(str, er['loc'])) or 'spec'}: {er['msg']}" for er in exc.errors())
        return {"outcome": "refused", "message": msgs}
    beat = os.environ.get("DEMQ_STABILITY_HEARTBEAT")

    def progress(_):
        if beat:
            Path(beat).touch()

    with tempfile.TemporaryDirectory() as tmp:
        try:
            s = run(spec, Path(tmp) / "out.h5", backend="cpu", progress=progress)
        except SpecError as exc:
            return {"outcome": "refused", "message": str(exc)}
        except InstabilityError as exc:
            return {"outcome": "stopped", "message": str(exc)}
        problems, info = _check_file(s.output, spec)
        info["steps"] = s.steps
    if problems:
        return {"outcome": "BUG", "message": "silent garbage: " + "; ".join(problems), "info": info}
    return {"outcome": "ok", "message": "", "info": info}


def _run_pair(cell: dict) -> dict:
    """Two (or three) smooth elastic spheres of radius 1 cm placed overlapping, run through CpuBackend."""
    import numpy as np

    from engine.backends.base import ContactParams, SphereSystem
    from engine.shapes.sphere.cpu_backend import CpuBackend
    from engine.errors import InstabilityError
    from engine.setup.params import Q_SPHERE

    a, m, k = 0.01, 1e-2, 1e5
    n = cell.get("n", 2)
    d = (2.0 - cell["overlap"]) * a
    pos = np.array([[0.5 + (i - (n - 1) / 2) * d, 0.5, 0.5] for i in range(n)])
    vel = np.zeros((n, 3))
    tc = math.pi * math.sqrt(0.5 * m / k)
    params = ContactParams(k_n=k, gamma_n_coef=0.0, k_t=None, friction=None, dt=tc / 50, skin=0.4 * a,
                           precision=cell.get("precision", "float64"), overlap_limit=cell["limit"])
    system = SphereSystem(1.0, pos, vel, np.zeros((n, 3)), np.tile([1.0, 0, 0, 0], (n, 1)), np.full(n, a),
                          np.full(n, m), np.full(n, Q_SPHERE * m * a * a))
    try:
        be = CpuBackend(system, params)
        o = be.observe()
        e0 = o["kinetic_energy_translational"] + o["elastic_energy"]
        be.advance(int(5 * tc / (tc / 50)))
    except InstabilityError as exc:
        return {"outcome": "stopped", "message": str(exc)}
    o = be.observe()
    e1 = o["kinetic_energy_translational"] + o["elastic_energy"]
    vals = np.concatenate([be.pos.ravel(), be.vel.ravel()])
    problems = []
    if not np.all(np.isfinite(vals)) or not math.isfinite(e1):
        problems.append("non-finite state")
    elif abs(e1 / e0 - 1.0) > ENERGY_TOL:
        problems.append(f"elastic energy not conserved: E_end/E_0 = {e1 / e0:.4g}")
    p = float(np.linalg.norm((be.mass[:, None] * be.vel).sum(0)))
    scale = float((be.mass * np.linalg.norm(be.vel, axis=1)).sum())
    if scale > 0 and p / scale > MOMENTUM_TOL[params.precision]:
        problems.append(f"momentum {p / scale:.3g} of sum m|v|")
    info = {"energy_end/energy_0": float(e1 / e0), "momentum_rel": p / scale if scale else 0.0}
    if problems:
        return {"outcome": "BUG", "message": "silent garbage: " + "; ".join(problems), "info": info}
    return {"outcome": "ok", "message": "", "info": info}


def run_cell_inprocess(cell: dict) -> dict:
    import traceback

    try:
        return _run_spec(cell) if cell["kind"] == "spec" else _run_pair(cell)
    except Exception as exc:  # anything else is a bug of the engine
        tb = traceback.format_exc().strip().splitlines()
        return {"outcome": "BUG", "message": f"unexpected {type(exc).__name__}: {exc} ({tb[-3].strip()})"}


def _child() -> None:
    cell = json.loads(sys.stdin.read())
    res = run_cell_inprocess(cell)
    sys.stdout.write("\n@@RESULT@@" + json.dumps(res) + "\n")


# ---- parent ----------------------------------------------------------------------------------------

def run_cell(cell: dict, timeout: float = CELL_TIMEOUT_S) -> dict:
    """Run one cell in a child process; a hang, a crash or a missing result is a BUG."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        beat = Path(tmp) / "heartbeat"
        env["DEMQ_STABILITY_HEARTBEAT"] = str(beat)
        (Path(tmp) / "cell.json").write_text(json.dumps(cell))
        with open(Path(tmp) / "out", "w+") as out, open(Path(tmp) / "err", "w+") as err, \
                open(Path(tmp) / "cell.json") as inp:
            proc = subprocess.Popen([sys.executable, "-c", "import bench.stability as s; s._child()"],
                                    stdin=inp, stdout=out, stderr=err, env=env, cwd=str(ROOT))
            hang = None
            while proc.poll() is None:
                time.sleep(0.2)
                now = time.time()
                # the run reports progress every output interval once compiled: silence after that is a hang
                if beat.exists() and now - beat.stat().st_mtime > timeout:
                    hang = f"hang: no progress for {timeout:g} s"
                elif time.perf_counter() - t0 > COMPILE_TIMEOUT_S:
                    hang = f"hang: no result within {COMPILE_TIMEOUT_S:g} s"
                if hang:
                    proc.kill()
                    proc.wait()
                    break
            out.seek(0)
            err.seek(0)
            cp = subprocess.CompletedProcess(proc.args, proc.returncode, out.read(), err.read())
    if hang:
        res = {"outcome": "BUG", "message": hang}
    else:
        marker = "@@RESULT@@"
        if marker in cp.stdout:
            res = json.loads(cp.stdout.rsplit(marker, 1)[1].strip().splitlines()[0])
        elif cp.returncode < 0:
            res = {"outcome": "BUG", "message": f"crash: killed by signal {-cp.returncode}"}
        else:
            tail = (cp.stderr.strip().splitlines() or ["(no output)"])[-1]
            res = {"outcome": "BUG", "message": f"crash: exit status {cp.returncode}: {tail}"}
    res["wall_s"] = time.perf_counter() - t0
    return res


def _params_text(cell: dict) -> str:
    if cell["kind"] != "spec":
        return cell["what"]
    s = cell["spec"]
    keys = ("n_particles", "volume_fraction", "e_n", "e_t", "friction", "velocity_rms", "dt", "t_end",
            "precision", "overlap_limit", "elongation")
    return ", ".join(f"{k}={s[k]}" for k in keys if k in s and k not in ("snapshots",))


def write_report(results: list[dict], out_dir: Path, total_s: float) -> Path:
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "results.json").write_text(json.dumps(results, indent=1, sort_keys=True))
    counts = {}
    for r in results:
        counts[r["outcome"]] = counts.get(r["outcome"], 0) + 1
    lines = [
        "# Stability stress matrix (CPU backend)",
        "",
        "Reproduce: `python -m bench stability` (or `python -m bench stability`). Each cell runs "
        f"in a child process; no progress for {CELL_TIMEOUT_S:g} s after the first report, or no result in "
        f"{COMPILE_TIMEOUT_S:g} s (Numba compilation included), is a hang. Outcomes: `ok` (ran and passed the checks "
        "in bench/stability.py's docstring), `stopped` (the engine's InstabilityError), `refused` (the "
        "spec's validation or SpecError), `BUG` (NaN, hang, crash, unexpected exception or failed checks).",
        "",
        f"Totals: {', '.join(f'{k} {v}' for k, v in sorted(counts.items()))}; wall {total_s:.0f} s.",
        "",
        "| cell | what | parameters | outcome | message / checks | wall s |",
        "|---|---|---|---|---|---|",
    ]
    for r in results:
        msg = r.get("message", "")
        if r["outcome"] == "ok" and "info" in r:
            msg = ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in r["info"].items())
        msg = msg.replace("|", "/").replace("\n", " ")
        lines.append(f"| {r['name']} | {r['what']} | {_params_text(r['cell']).replace('|', '/')} | "
                     f"{r['outcome']} | {msg} | {r['wall_s']:.1f} |")
    path = out_dir / "REPORT.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def main(out_dir=None, only: str | None = None, timeout: float = CELL_TIMEOUT_S) -> int:
    """Run the matrix, write REPORT.md; exit status 1 when any cell is a BUG."""
    from bench import out_dir as bench_out

    out_dir = bench_out(out_dir, "stability")
    results = []
    t0 = time.perf_counter()
    for cell in cells():
        if only and only not in cell["name"]:
            continue
        res = run_cell(cell, timeout)
        res.update(name=cell["name"], what=cell["what"], cell=cell)
        results.append(res)
        print(f"{cell['name']:<34s} {res['outcome']:<8s} {res['wall_s']:6.1f}s  {res.get('message', '')[:150]}",
              flush=True)
    path = write_report(results, out_dir, time.perf_counter() - t0)
    print(f"wrote {path}")
    return 1 if any(r["outcome"] == "BUG" for r in results) else 0


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", "--out", dest="out_dir", metavar="DIR", default=None,
                    help="report folder (default ./bench-out/stability/)")
    ap.add_argument("--only", default=None, help="run only cells whose name contains this")
    ap.add_argument("--timeout", type=float, default=CELL_TIMEOUT_S)
    a = ap.parse_args()
    sys.exit(main(a.out_dir, a.only, a.timeout))
