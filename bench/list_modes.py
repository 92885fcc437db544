"""Skorych & Dosta (2022) on the GPU machine: their three Verlet-list modes and the multigrid cost.

``python -m bench list_modes --out DIR`` (NVIDIA GPU required):

1. Modes: for each scene (dilute and dense, N from 1e5 to 1e7, mono- and polydisperse) the same start is
   run for the same number of steps with the list built on the GPU, on the CPU sequentially (Skorych & Dosta
   2022, Fig. 1A) and on the CPU pipelined (Fig. 1B), and with ``list_mode = "auto"``. Reported per scene:
   wall time of each mode, particle-steps per second, the sequential mode's tau_CPU, tau_GPU, tau_exch
   per stage, q (Eq. 5), G_max (Eq. 9), the measured gain G = t_seq / t_par - 1 (Eq. 7) and whether
   auto was within 5 % of the best mode. Also a G against G_max plot (Skorych & Dosta 2022, Fig. 5).
2. Multigrid cost: GPU list-build time and time per step at size ratios 1, 2, 5, 10 with the multigrid
   levels and with one grid of cell >= 2 R_max + L_v (engine.loops.cuda_rebuild.MULTIGRID = False), same start.

Writes DIR/list_modes.json, DIR/list_modes.md and DIR/g_vs_gmax.png. ``--quick`` runs small scenes.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

MODES = ("gpu", "cpu-sequential", "cpu-pipelined", "auto")

# (name, N, phi, species or None, box edge per particle^(1/3) in m)
SCENES = [
    ("mono dilute", 100_000, 0.058, None),
    ("mono dense", 1_000_000, 0.45, None),
    ("poly 1:5 dilute", 1_000_000, 0.058, [(1.0, 0.05), (0.2, 0.95)]),
    ("poly 1:10 dense", 1_000_000, 0.25, [(1.0, 0.01), (0.1, 0.99)]),
    ("mono dilute", 10_000_000, 0.058, None),
    ("poly 1:3", 10_000_000, 0.2, [(1.0, 0.2), (1.0 / 3.0, 0.8)]),
]
QUICK = [
    ("mono dilute", 50_000, 0.058, None),
    ("poly 1:5 dilute", 50_000, 0.058, [(1.0, 0.05), (0.2, 0.95)]),
]


def make_scene(n: int, phi: float, species, precision: str = "float64", seed: int = 1):
    """(system, contact params, derived) of a cooling gas at the spec defaults, box scaled with N."""
    from engine.setup.params import derive
    from engine.setup.scene import initial_spheres
    from engine.driver.simulate import contact_params
    from engine.setup.spec import SimulationSpec

    kw = dict(n_particles=n, volume_fraction=phi, box_length=2.0 * (n / 4096) ** (1.0 / 3.0), e_n=0.8,
              e_t=0.8, precision=precision, seed=seed, backend="cuda")
    if species:
        kw["species"] = [{"radius_ratio": r, "number_fraction": f} for r, f in species]
    spec = SimulationSpec(**kw)
    p = derive(spec)
    return initial_spheres(spec, p), contact_params(spec, p, thermalization=False), p


def warm_up() -> None:
    """Compile every kernel and the CPU builder (all modes, mono and poly) before anything is timed."""
    for sp in (None, [(1.0, 0.05), (0.2, 0.95)]):
        system, c, _ = make_scene(20_000, 0.2, sp)
        for mode in MODES:
            run_mode((system, c), mode, steps=300)


def run_mode(scene, mode, steps=None, target_builds=10, min_seconds=2.0, max_steps=20000):
    """Advance a copy of the start; returns timings. steps None: run until target_builds rebuilds and
    min_seconds of wall time (the GPU-list run; the other modes then run the same steps)."""
    from engine.backends.cuda import CudaBackend

    system, c = scene
    n = system.n
    be = CudaBackend(copy.deepcopy(system), c.with_(list_mode=mode))
    be.advance(1)  # compile and prime outside the timing
    cuda_sync(be)
    b0 = be.builds
    t0 = time.perf_counter()
    if steps is None:
        done = 0
        chunk = 25
        while (be.builds - b0 < target_builds or time.perf_counter() - t0 < min_seconds) and done < max_steps:
            be.advance(chunk)
            done += chunk
            chunk = min(2 * chunk, 400)
        steps = done
    else:
        be.advance(steps)
    cuda_sync(be)
    wall = time.perf_counter() - t0
    lists = be.e.lists
    out = {"mode": mode, "steps": steps, "wall_s": wall, "cundall": n * steps / wall, "builds": be.builds - b0,
           "max_nb": be.e.max_nb, "multigrid_levels": be.e.levels[0].n_levels if be.e.multigrid else 1}
    if lists is not None:
        out["lists"] = lists.summary()
        lists.close()
    del be
    return out


def cuda_sync(be) -> None:
    be.e.stream.synchronize()


def modes_table(scenes) -> list:
    rows = []
    for name, n, phi, species in scenes:
        t_scene = time.perf_counter()
        res = {"scene": name, "n": n, "phi": phi, "species": species}
        t0 = time.perf_counter()
        system, c, _ = make_scene(n, phi, species)
        res["placement_s"] = time.perf_counter() - t0
        gpu = run_mode((system, c), "gpu")
        steps = gpu["steps"]
        res["gpu"] = gpu
        for mode in MODES[1:]:
            res[mode] = run_mode((system, c), mode, steps=steps)
        seq = res["cpu-sequential"]["lists"]["cpu-sequential"]
        q = seq["tau_cpu"] / seq["tau_gpu"]
        res["q"] = q
        res["g_max"] = q if q <= 0.5 else (1.0 - q) / (2.0 * q)
        res["g"] = res["cpu-sequential"]["wall_s"] / res["cpu-pipelined"]["wall_s"] - 1.0
        best = min(res[m]["wall_s"] for m in MODES[:3])
        res["auto_over_best"] = res["auto"]["wall_s"] / best - 1.0
        res["scene_wall_s"] = time.perf_counter() - t_scene
        rows.append(res)
        print(json.dumps({k: v for k, v in res.items() if k not in MODES}), flush=True)
    return rows


def multigrid_cost(n=1_000_000, phi=0.2, ratios=(1, 2, 5, 10), reps=5) -> list:
    """GPU build time and step time, multigrid vs one grid, two species of equal solid volume."""
    from engine.backends.cuda import CudaBackend
    from engine.loops import cuda_rebuild

    rows = []
    for ratio in ratios:
        sp = None if ratio == 1 else [(1.0, 1.0 / (1.0 + ratio ** 3)), (1.0 / ratio, ratio ** 3 / (1.0 + ratio ** 3))]
        row = {"ratio": ratio, "n": n, "phi": phi}
        for label, multigrid in (("multigrid", True), ("single grid", False)):
            cuda_rebuild.MULTIGRID = multigrid
            system, c, _ = make_scene(n, phi, sp)
            be = CudaBackend(system, c)
            e = be.e
            be.advance(1)
            cuda_sync(be)
            t0 = time.perf_counter()
            for _ in range(reps):
                e._gpu_rebuild()
            cuda_sync(be)
            t_build = (time.perf_counter() - t0) / reps
            t0 = time.perf_counter()
            be.advance(100)
            cuda_sync(be)
            t_step = (time.perf_counter() - t0) / 100
            row[label] = {"build_ms": 1e3 * t_build, "step_ms": 1e3 * t_step, "max_nb": e.max_nb,
                          "levels": e.levels[0].n_levels if e.multigrid else 1}
            del be, e
        cuda_rebuild.MULTIGRID = True
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def report(out: Path, rows: list, cost: list, device: str) -> None:
    lines = [f"# Skorych & Dosta (2022) list modes and multigrid cost — {device}", "",
             "Command: `python -m bench list_modes --out DIR`. Each mode runs the same start for the same "
             "steps (the GPU-list run's count to reach 10 rebuilds); wall time excludes compilation and the "
             "first build. q = tau_CPU/tau_GPU of the sequential mode (Eq. 5), G_max by Eq. 9, "
             "G = t_seq/t_par - 1 measured (Eq. 7).", "",
             "| scene | N | phi | levels | steps | GPU list s | CPU seq s | CPU pipelined s | auto s (final mode) "
             "| tau_CPU ms | tau_GPU ms | tau_exch ms | q | G_max | G | auto vs best |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        seq = r["cpu-sequential"]["lists"]["cpu-sequential"]
        lines.append(
            f"| {r['scene']} | {r['n']:.0e} | {r['phi']} | {r['gpu']['multigrid_levels']} | {r['gpu']['steps']} "
            f"| {r['gpu']['wall_s']:.2f} | {r['cpu-sequential']['wall_s']:.2f} | {r['cpu-pipelined']['wall_s']:.2f} "
            f"| {r['auto']['wall_s']:.2f} ({r['auto'].get('lists', {}).get('final_mode', 'gpu')}) "
            f"| {1e3 * seq['tau_cpu']:.1f} | {1e3 * seq['tau_gpu']:.1f} | {1e3 * seq['tau_exch']:.1f} "
            f"| {r['q']:.2f} | {r['g_max']:+.3f} | {r['g']:+.3f} | {100 * r['auto_over_best']:+.1f} % |")
    lines += ["", "## Multigrid against one grid (GPU build)", "",
              "| size ratio | N | phi | levels | multigrid build ms | one grid build ms | multigrid step ms "
              "| one grid step ms | list stride |", "|---|---|---|---|---|---|---|---|---|"]
    for r in cost:
        m, s = r["multigrid"], r["single grid"]
        lines.append(f"| {r['ratio']} | {r['n']:.0e} | {r['phi']} | {m['levels']} | {m['build_ms']:.2f} "
                     f"| {s['build_ms']:.2f} | {m['step_ms']:.3f} | {s['step_ms']:.3f} | {m['max_nb']} |")
    (out / "list_modes.md").write_text("\n".join(lines) + "\n")
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(5, 4))
        qs = np.linspace(0.01, 3, 300)
        ax.plot(qs, [q if q <= 0.5 else (1 - q) / (2 * q) for q in qs], "k-", lw=1, label="G_max (Eq. 9)")
        for r in rows:
            ax.plot(r["q"], r["g"], "o", label=f"{r['scene']} N={r['n']:.0e}")
        ax.axhline(0, color="grey", lw=0.5)
        ax.set_xscale("log")
        ax.set_xlabel("q = tau_CPU / tau_GPU (sequential mode)")
        ax.set_ylabel("gain G of the pipelined mode")
        ax.set_title(f"analogue of Skorych & Dosta (2022) Fig. 5, {device}", fontsize=8)
        ax.legend(fontsize=6)
        fig.tight_layout()
        fig.savefig(out / "g_vs_gmax.png", dpi=120)
    except ImportError:
        pass


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--no-cost", action="store_true")
    ap.add_argument("--scenes", type=int, nargs="*", help="indices into SCENES (default: all)")
    a = ap.parse_args(argv)
    from numba import cuda

    a.out.mkdir(parents=True, exist_ok=True)
    warm_up()
    dev = cuda.get_current_device().name
    device = dev.decode() if isinstance(dev, bytes) else str(dev)
    scenes = QUICK if a.quick else SCENES
    if a.scenes is not None:
        scenes = [scenes[i] for i in a.scenes]
    rows = modes_table(scenes)
    cost = [] if a.no_cost else multigrid_cost(n=100_000 if a.quick else 1_000_000)
    (a.out / "list_modes.json").write_text(json.dumps({"device": device, "date": time.strftime("%Y-%m-%d"),
                                                        "modes": rows, "multigrid_cost": cost}, indent=1))
    report(a.out, rows, cost, device)
    print((a.out / "list_modes.md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
