"""The measured effect of each compile-time specialisation (docs/design.md).

The engine builds its time loop for the argument types it is given, so a scene that does not need a
piece of physics does not pay for it (engine/loops/cpu.py module doc):

- smooth vs rough spheres: ``k_t = None`` (e_t = -1 or mu = 0) drops the tangential spring, the torque
  and the spin update ("rotation off when it carries no energy");
- Coulomb limit off/on: ``friction = None`` drops the sliding cap;
- orientation integration off/on: ``ContactParams.orientation`` (the driver turns it on when
  ``snapshots > 0``) drops the quaternion update;
- snapshot output off/on: host copies and HDF5 frames only at snapshot steps (measured through the
  driver, with orientation on in both rows, so that only the output differs);
- float32 vs float64 (``precision``);
- ellipsoids: the bounding-sphere broad phase has **no switch** in engine/shapes/spheroid/cpu_backend.py (it is
  always on), so it cannot be measured on and off; this bench measures the ellipsoid float32/float64 rows
  and *estimates* what the broad phase saves (list pairs it rejects x the measured cost of one
  Perram-Wertheim evaluation), labelled as an estimate.

Method: each variant gets its own backend built from the same thermalised state, is compiled (not
timed), then advanced ``steps`` steps ``reps`` times; Cundall number = N x steps / wall s (median).
One switch differs from the baseline per row (two in 'maximal'; baseline: rough e_t = 0.8, no Coulomb
limit, orientation off, float64, no output). Scenes: the default spec, the scene of Hidalgo et al. (2013) (N = 4096,
phi = 0.008: ~1e-4 contacts per particle) and a contact-rich gas (phi = 0.3).

    PYTHONPATH=. NUMBA_NUM_THREADS=1 python -m bench specialisation [--quick] [--backend cuda] [--n N]
    python -m bench specialisation [--quick] [--backend cpu|cuda]
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from bench import out_dir as bench_out
from bench.accuracy import _json_default, gas_spec, machine, SIZES as ACC_SIZES

SIZES = {
    "full": dict(n=4096, steps=20000, reps=3, ell_n=256, ell_steps=1500, therm_steps=1500, ell_therm_collisions=2.0),
    "quick": dict(n=2048, steps=2000, reps=1, ell_n=128, ell_steps=600, therm_steps=600, ell_therm_collisions=1.0),
    "tiny": dict(n=512, steps=300, reps=1, ell_n=64, ell_steps=100, therm_steps=200, ell_therm_collisions=0.1),
}

#: (name, what, ContactParams changes, precision) relative to the baseline
VARIANTS = [
    ("baseline", "rough (e_t = 0.8), no Coulomb limit, orientation off, float64", {}, "float64"),
    ("smooth", "smooth spheres (e_t = -1): no spring, torque or spin update", {"k_t": None}, "float64"),
    ("coulomb", "Coulomb limit on (mu = 0.5)", {"friction": 0.5}, "float64"),
    ("orientation", "quaternion integration on", {"orientation": True}, "float64"),
    ("float32", "float32 state and arithmetic", {}, "float32"),
    ("maximal", "rough + Coulomb + orientation, float64 (nothing pruned)",
     {"friction": 0.5, "orientation": True}, "float64"),
]
#: what each row's speed-up means: (specialisation, row is the specialised one?)
SPEEDUP = {"smooth": ("smooth instead of rough", True),
           "coulomb": ("no Coulomb cap (friction = null)", False),
           "orientation": ("no quaternion update (snapshots = 0)", False),
           "float32": ("float32 instead of float64", True),
           "maximal": ("no Coulomb cap and no quaternion update together", False)}


def _scenes(cfg: dict, backend: str) -> dict:
    from engine.setup.spec import SimulationSpec

    # L_v = 0.4 a on both backends (the CPU default; CUDA's is 0.8 a): speed-ups are ratios at one skin
    dilute = SimulationSpec(n_particles=cfg["n"], box_length=2.0 * (cfg["n"] / 4096) ** (1 / 3), snapshots=0,
                            backend=backend, seed=1, verlet_skin=0.4)
    size = replace(ACC_SIZES["full"], gas_n=cfg["n"], phi=0.3)
    dense = gas_spec(size, dt_fraction=50, precision="float64", skin=0.4, e_n=0.8, e_t=0.8, collisions=1.0,
                     thermalization=0.0, backend=backend)
    return {"dilute (default spec, Hidalgo et al. 2013, phi = 0.008)": (dilute, False),
            "contact-rich (phi = 0.3)": (dense, True)}


def _state(spec, backend: str, therm_steps: int, thermalise: bool):
    """The spec's start, optionally advanced `therm_steps` with the elastic rough law (contacts formed)."""
    from engine.backends.registry import make_backend
    from engine.setup.params import derive
    from engine.setup.scene import initial_spheres
    from engine.driver.simulate import contact_params

    p = derive(spec)
    system = initial_spheres(spec, p)
    base = contact_params(spec, p, thermalization=False)
    if thermalise:
        be = make_backend(backend, system, contact_params(spec, p, thermalization=True).with_(orientation=False))
        be.advance(therm_steps)
        st = be.state()
        system = replace(system, position=np.asarray(st["position"], float),
                         velocity=np.asarray(st["velocity"], float),
                         angular_velocity=np.asarray(st["angular_velocity"], float))
    return system, base, p


def _time_variant(system, contact, backend: str, steps: int, reps: int) -> tuple[float, list, dict, str]:
    from engine.backends.registry import make_backend

    runs, obs, device = [], None, None
    for _ in range(max(1, reps)):
        be = make_backend(backend, system, contact)
        be.warmup()
        t0 = time.perf_counter()
        be.advance(steps)
        obs = be.observe()          # synchronises a GPU backend; one reduction on the CPU
        wall = time.perf_counter() - t0
        runs.append(system.n * steps / wall)
        device = be.device
    return float(statistics.median(runs)), runs, obs, device


def build_spheres(cfg: dict, backend: str, log) -> list:
    rows = []
    for scene, (spec, thermalise) in _scenes(cfg, backend).items():
        system, base, p = _state(spec, backend, cfg["therm_steps"], thermalise)
        base = base.with_(orientation=False, friction=None)
        base_c = None
        for name, what, change, prec in VARIANTS:
            c = base.with_(precision=prec, **change)
            cund, runs, obs, device = _time_variant(system, c, backend, cfg["steps"], cfg["reps"])
            if name == "baseline":
                base_c = cund
            rows.append({"scene": scene, "variant": name, "what": what, "cundall": cund, "runs": runs,
                         "vs_baseline": cund / base_c, "contacts_per_particle": obs["contacts"] / system.n,
                         "n": system.n, "steps": cfg["steps"], "device": device})
            log(f"{scene} {name}: Cundall {cund:.3g} (x{cund / base_c:.2f}), contacts/particle "
                f"{obs['contacts'] / system.n:.3g}")
    return rows


def build_output(cfg: dict, backend: str, log) -> list:
    """Snapshot output through the driver: snapshots = 2 (first and last frame) vs one frame per record."""
    from engine.setup.params import derive
    from engine.driver.simulate import run
    from engine.setup.spec import SimulationSpec

    n = cfg["n"]
    base = SimulationSpec(n_particles=n, box_length=2.0 * (n / 4096) ** (1 / 3), backend=backend, seed=1,
                          thermalization=0.0, verlet_skin=0.4)
    p = derive(base)
    t_end = cfg["steps"] * p.dt
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        many = int(max(3, min(200, 1e9 / (n * 104))))     # a frame is 13 doubles per particle: <= ~1 GB
        for snaps, what in ((0, "snapshots = 0: no frames, orientation off (what the driver builds)"),
                            (2, "snapshots = 2: orientation on, 2 frames"),
                            (many, f"snapshots = {many}: orientation on, {many} frames in 200 records")):
            spec = base.model_copy(update={"t_end": t_end, "snapshots": snaps})
            runs = []
            for _ in range(max(1, cfg["reps"])):
                s = run(spec, Path(tmp) / "o.h5", backend=backend)
                runs.append(s.cundall)
            cund = float(statistics.median(runs))
            rows.append({"scene": "driver, default spec (Hidalgo et al. 2013)", "variant": f"snapshots={snaps}",
                         "what": what, "cundall": cund, "runs": runs, "n": n, "steps": s.steps, "device": s.device})
            log(f"output snapshots={snaps}: Cundall {cund:.3g}")
    ref = rows[1]["cundall"]
    for r in rows:
        r["vs_baseline"] = r["cundall"] / ref
    return rows


def build_ellipsoids(cfg: dict, log) -> dict:
    """Ellipsoid float64/float32 Cundall (CPU) and the estimated saving of the bounding-sphere broad phase."""
    from engine.backends.registry import make_backend
    from engine.setup.params import derive
    from engine.setup.scene import initial_ellipsoids
    from engine.driver.simulate import contact_params
    from tests.engine.test_ellipsoid_geometry import H, contact_batch

    size = replace(ACC_SIZES["full"], ell_n=cfg["ell_n"])
    spec = gas_spec(size, dt_fraction=50, precision="float64", skin=0.4, e_n=0.8, e_t=-1.0, collisions=1.0,
                    thermalization=0.0, backend="cpu", shape="ellipsoid")
    p = derive(spec)
    system = initial_ellipsoids(spec, p)
    c = contact_params(spec, p, thermalization=True).with_(orientation=True)
    be = make_backend("cpu", system, c)
    # thermalise until the lattice start has mixed (bounding spheres meet as in the gas: ~1 overlapping
    # bounding-sphere pair per particle at this phi_b = phi xi^2)
    therm = int(min(cfg["ell_therm_collisions"] / (p.collision_rate0 * p.dt), 40000))
    be.advance(therm)
    st = be.state()
    system = replace(system, position=np.asarray(st["position"], float), velocity=np.asarray(st["velocity"], float),
                     angular_velocity=np.asarray(st["angular_velocity"], float),
                     orientation=np.asarray(st["orientation"], float))
    rows = []
    for prec in ("float64", "float32"):
        cc = contact_params(spec, p, thermalization=False).with_(precision=prec)
        cund, runs, obs, device = _time_variant(system, cc, "cpu", cfg["ell_steps"], cfg["reps"])
        rows.append({"scene": f"ellipsoid gas (xi = {spec.elongation}, phi = {spec.volume_fraction}, N = {system.n}, "
                              f"{cfg['ell_therm_collisions']:g} collisions per particle of mixing)",
                     "variant": prec, "what": f"{prec}, frictionless ellipsoids", "cundall": cund, "runs": runs,
                     "n": system.n, "steps": cfg["ell_steps"], "device": device})
        log(f"ellipsoid {prec}: Cundall {cund:.3g}")
    rows[1]["vs_baseline"] = rows[1]["cundall"] / rows[0]["cundall"]
    rows[0]["vs_baseline"] = 1.0
    # broad-phase estimate from the float64 list of the thermalised state
    be = make_backend("cpu", system, contact_params(spec, p, thermalization=False))
    pos, q, axes = be.pos.astype(float), be.quat.astype(float), be.axes.astype(float)
    bound = axes.max(axis=1)
    box = spec.box_length
    pairs = [(i, int(j)) for i in range(system.n) for j in be.nbr[i, :be.nn[i]]]
    i_idx = np.array([a for a, _ in pairs], int)
    j_idx = np.array([b for _, b in pairs], int)
    r = pos[j_idx] - pos[i_idx]
    r -= box * np.round(r / box)
    far = np.linalg.norm(r, axis=1) >= bound[i_idx] + bound[j_idx]
    k = int(far.sum())
    est = {"list_entries_per_step": len(pairs), "rejected_per_step": k}
    if k:
        reps_tile = max(1, 20000 // k)
        arrs = [np.ascontiguousarray(np.tile(x, (reps_tile, 1))) for x in
                (r[far], q[i_idx[far]], axes[i_idx[far]], q[j_idx[far]], axes[j_idx[far]])]
        out = np.zeros((len(arrs[0]), 9))
        contact_batch(*arrs, 1e-15, H, out)
        t0 = time.perf_counter()
        contact_batch(*arrs, 1e-15, H, out)
        per_pair = (time.perf_counter() - t0) / len(arrs[0])
        step_s = system.n / rows[0]["cundall"]
        extra = k * per_pair
        est.update(pw_seconds_per_pair=per_pair, step_seconds=step_s, extra_seconds_per_step=extra,
                   estimated_speedup=(step_s + extra) / step_s)
        log(f"ellipsoid broad phase: rejects {k} of {len(pairs)} list entries per step; estimated speed-up "
            f"x{(step_s + extra) / step_s:.2f}")
    return {"rows": rows, "broad_phase_estimate": est}


def write_report(out: Path, res: dict, cmd: str) -> str:
    m = res["machine"]
    dev = m.get("device") or m["cpu"]
    L = ["# Compile-time specialisations: measured speed-ups", "",
         f"Command: `{cmd}` ({res['variant']} variant), {res['wall_s'] / 60:.1f} min wall.",
         f"Machine: backend **{m['backend']}** on **{dev}**; host CPU {m['cpu']} ({m['cores']} cores), "
         f"{m['numba_threads']} Numba thread(s), load average {m['load_average']:.2f} at the start; numba "
         f"{m['numba']}, numpy {m['numpy']}; {m['date']}.", "",
         "Cundall number = N x steps / wall s of `advance` (compilation excluded; one observables reduction "
         f"at the end), median of {res['reps']} run(s) from the same state. Each row changes one switch (maximal: two) "
         "against the baseline of its scene (rough e_t = 0.8, no Coulomb limit, orientation off, float64); "
         "x = Cundall / baseline Cundall. **speed-up** = what the specialisation buys: x for the rows that "
         "are the specialised build (smooth, float32), 1/x for the rows that switch the work on (coulomb, "
         "orientation, maximal). The min-max column shows the run-to-run scatter (up to +-20 % on the shared "
         "2-core development VM, where speed-ups within 0.8-1.2 are not significant).", ""]
    for scene in dict.fromkeys(r["scene"] for r in res["spheres"]):
        L += [f"### {scene}", "", "| variant | what | Cundall | runs (min-max) | x baseline | contacts/particle | "
              "specialisation | speed-up |", "|---|---|---|---|---|---|---|---|"]
        for r in res["spheres"]:
            if r["scene"] == scene:
                spec_name, pruned = SPEEDUP.get(r["variant"], ("-", True))
                x = r["vs_baseline"] if pruned else 1 / r["vs_baseline"]
                sp = "-" if r["variant"] == "baseline" else f"**x{x:.2f}**"
                L.append(f"| {r['variant']} | {r['what']} | {r['cundall']:.3g} | "
                         f"{min(r['runs']):.3g}-{max(r['runs']):.3g} | {r['vs_baseline']:.2f} | "
                         f"{r['contacts_per_particle']:.2g} | {spec_name} | {sp} |")
        L.append("")
    L += ["### Snapshot output (driver, default spec of Hidalgo et al. 2013)", "",
          "Whole `run()` of the default spec (N as above, no thermalisation, 200 observable records); "
          "x relative to snapshots = 2 (orientation on in both), so the last row is the cost of more frames "
          "alone and the snapshots = 0 row what orientation + 2 frames cost.", "",
          "| variant | what | Cundall | runs (min-max) | x |", "|---|---|---|---|---|"]
    for r in res["output"]:
        L.append(f"| {r['variant']} | {r['what']} | {r['cundall']:.3g} | {min(r['runs']):.3g}-{max(r['runs']):.3g} | "
                 f"{r['vs_baseline']:.2f} |")
    ell = res.get("ellipsoids")
    if ell:
        L += ["", "### Ellipsoids (CPU; the engine has no CUDA ellipsoid backend)", "",
              "| scene | variant | Cundall | x float64 |", "|---|---|---|---|"]
        for r in ell["rows"]:
            L.append(f"| {r['scene']} | {r['variant']} | {r['cundall']:.3g} | {r['vs_baseline']:.2f} |")
        e = ell["broad_phase_estimate"]
        L += ["", "**Broad phase on/off: no switch exists** in engine/shapes/spheroid/cpu_backend.py "
              "(the bounding-sphere test before the Perram-Wertheim solve is always on), so it cannot be measured "
              "off. Estimate, not "
              f"a measurement: the Verlet list holds {e['list_entries_per_step']} entries, of which the broad "
              f"phase rejects {e['rejected_per_step']} per step"]
        if "estimated_speedup" in e:
            L[-1] += (f"; one PW evaluation costs {e['pw_seconds_per_pair'] * 1e9:.0f} ns here, so without the "
                      f"broad phase a step would take {e['extra_seconds_per_step'] * 1e3:.3g} ms more than its "
                      f"measured {e['step_seconds'] * 1e3:.3g} ms: estimated speed-up of the broad phase "
                      f"**x{e['estimated_speedup']:.1f}**.")
        else:
            L[-1] += "."
    L += ["", "Raw rows: summary.json (same folder)."]
    text = "\n".join(L) + "\n"
    (out / "REPORT.md").write_text(text)
    return text


def main(out_dir=None, variant: str = "full", backend: str = "cpu", threads: int = 1, n: int | None = None,
         reps: int | None = None, ellipsoids: bool = True, cmd: str | None = None, log=print) -> int:
    import numba

    if threads:
        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    cfg = dict(SIZES[variant])
    if n:
        cfg["n"] = n
    if reps:
        cfg["reps"] = reps
    out = bench_out(out_dir, "specialisation")
    t0 = time.time()
    res = {"variant": variant, "reps": cfg["reps"], "config": cfg, "machine": machine(backend)}
    res["spheres"] = build_spheres(cfg, backend, log)
    res["output"] = build_output(cfg, backend, log)
    if ellipsoids:
        res["ellipsoids"] = build_ellipsoids(cfg, log)
    if backend != "cpu":
        res["machine"]["device"] = res["spheres"][0]["device"]
    res["wall_s"] = time.time() - t0
    flags = {"quick": " --quick", "tiny": " --tiny"}.get(variant, "")
    cmd = cmd or f"python -m bench specialisation{flags} --backend {backend}"
    res["command"] = cmd
    text = write_report(out, res, cmd)
    (out / "summary.json").write_text(json.dumps(res, indent=1, default=_json_default))
    log(text)
    return 0


def cli(argv=None) -> int:
    ap = argparse.ArgumentParser(description="measured speed-up of each compile-time specialisation")
    ap.add_argument("-o", "--out", dest="out_dir", metavar="DIR", default=None,
                    help="report folder (default ./bench-out/specialisation/)")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--tiny", action="store_true", help="smallest scenes (smoke test)")
    ap.add_argument("--backend", choices=["cpu", "cuda"], default="cpu")
    ap.add_argument("--threads", type=int, default=1, help="Numba threads (CPU; default 1)")
    ap.add_argument("--n", type=int, default=None, help="spheres per scene (default 4096)")
    ap.add_argument("--reps", type=int, default=None)
    ap.add_argument("--no-ellipsoids", action="store_true")
    ap.add_argument("--reanalyse", action="store_true", help="only rewrite REPORT.md from OUT/summary.json")
    a = ap.parse_args(argv)
    if a.reanalyse:
        out = bench_out(a.out_dir, "specialisation")
        res = json.loads((out / "summary.json").read_text())
        print(write_report(out, res, res["command"]))
        return 0
    variant = "tiny" if a.tiny else "quick" if a.quick else "full"
    return main(a.out_dir, variant, a.backend, a.threads, a.n, a.reps, not a.no_ellipsoids)


if __name__ == "__main__":
    raise SystemExit(cli())
