"""The issue-4 ellipsoid cooling matrix as ONE CUDA ensemble, within a wall-time budget (device machine).

Runs ``engine.validation.hcs_ellipsoids.main(..., backend='cuda', ensemble=True)`` (the runs of Rubio-Largo et al. 2015:
N = 4096, phi = 0.058, Gamma_0 t_end = 40; 312 000-651 000 steps a cell, xi = 1.15 longest) for the cells that fit
in ``--budget-s``. A killed ensemble leaves only unreadable .h5.part files, so the cells are chosen before
the run: a probe ensemble of all requested cells (random gas starts, bounding spheres overlapping as in the
thermalised gas) is timed for ``--probe-steps`` steps, and the projected wall time
    1.3 x (largest step count of the chosen cells) x (time per ensemble step, scaled by the chosen share
    of the scenes, at least 30 % of it) + 2 ms per output stop
must fit the budget; cells are dropped in reverse priority order (the DSMC cells of docs/physics.md
first, then xi = 3 and 1.15 at e = 0.9, 0.95, then e = 0.98) until it does. The plan and the measured
cost go to <out>/plan.json. The analysis runs on the device without the e_eff(D) DSMC (``dsmc=False``);
run it again where there is time with
    python -c "from engine.validation import hcs_ellipsoids as h; h.main('<out>', simulate=False)"
(add ``cells=...`` for a subset) to add the DSMC columns.

    python -m bench hcs_ellipsoids_cuda --out /tmp/hcs --budget-s 240 --cells 1.5:0.9 2.0:0.9
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from engine.validation import hcs_ellipsoids as H  # noqa: E402

PRIORITY = list(H.DSMC_CELLS) + [(3.0, 0.9), (3.0, 0.95), (1.15, 0.9), (1.15, 0.95),
                                 (1.5, 0.98), (2.0, 0.98), (2.5, 0.98), (3.0, 0.98), (1.15, 0.98)]


def parse_cells(items):
    cells = []
    for it in items:
        xi, e = it.split(":")
        cells.append((float(xi), float(e)))
    return cells


def steps_of(cell, seed=0):
    from engine.setup.params import derive

    p = derive(H.full_spec(cell[0], cell[1], seed, "cuda"))
    return p.n_steps + p.n_thermalization_steps, p.n_steps // p.output_every + 1


def probe(cells, steps):
    """Seconds per step of one ensemble of the cells (random gas starts, cooling contact)."""
    from bench.gpu_ellipsoid_scaling import ellipsoid_gas
    from engine.shapes.spheroid.cuda_backend import CudaEllipsoidEnsemble

    made = [ellipsoid_gas(4096, 0.058, "float64", seed=500 + k, xi=xi, e_n=e) for k, (xi, e) in enumerate(cells)]
    t0 = time.perf_counter()
    ens = CudaEllipsoidEnsemble([m[0] for m in made], [m[1] for m in made])
    ens.warmup()
    ens.advance(100)
    compile_s = time.perf_counter() - t0
    t = time.perf_counter()
    failed = ens.advance(steps)
    per = (time.perf_counter() - t) / steps
    assert not failed, failed
    obs = ens.observe()
    return per, compile_s, sum(o["contacts"] for o in obs) / (4096 * len(cells)), ens.multistep


def choose(cells, per_all, budget):
    info = {c: steps_of(c) for c in cells}
    chosen = sorted(cells, key=lambda c: PRIORITY.index(c) if c in PRIORITY else len(PRIORITY))

    def cost(sel):
        if not sel:
            return 0.0
        share = max(len(sel) / len(cells), 0.3)
        stops = sum(info[c][1] for c in sel)
        return 1.3 * max(info[c][0] for c in sel) * per_all * share + 2e-3 * stops

    while chosen and cost(chosen) > budget:
        chosen.pop()
    return chosen, cost(chosen), {f"{c[0]}:{c[1]}": info[c][0] for c in cells}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", required=True)
    ap.add_argument("--cells", nargs="*", default=[f"{x}:{e}" for x, e in H.CELLS])
    ap.add_argument("--budget-s", type=float, default=300.0, help="wall seconds for the simulations")
    ap.add_argument("--probe-steps", type=int, default=3000)
    args = ap.parse_args()
    t0 = time.perf_counter()
    cells = parse_cells(args.cells)
    per, compile_s, cpp, ms = probe(cells, args.probe_steps)
    left = args.budget_s - (time.perf_counter() - t0)
    chosen, est, steps = choose(cells, per, left)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    plan = dict(requested=[f"{x}:{e}" for x, e in cells], chosen=[f"{x}:{e}" for x, e in chosen],
                dropped=[f"{x}:{e}" for x, e in cells if (x, e) not in chosen], steps=steps,
                probe_s_per_step=per, probe_aggregate_cundall=4096 * len(cells) / per, probe_multistep=ms,
                probe_contacts_per_particle=cpp, compile_and_setup_s=compile_s, budget_left_s=left,
                estimated_s=est)
    print(json.dumps(plan), flush=True)
    (out / "plan.json").write_text(json.dumps(plan, indent=1))
    if not chosen:
        print("no cell fits the budget", flush=True)
        return 2
    t = time.perf_counter()
    rc = H.main(out_dir=str(out), seeds=1, backend="cuda", cells=chosen, ensemble=True, dsmc=False)
    plan["wall_s"] = time.perf_counter() - t
    (out / "plan.json").write_text(json.dumps(plan, indent=1))
    print(f"simulations + analysis: {plan['wall_s']:.0f} s (estimated {est:.0f} s)", flush=True)
    return rc


if __name__ == "__main__":
    sys.exit(main())
