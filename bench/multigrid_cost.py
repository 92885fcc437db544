"""Cost of a CPU Verlet-list build against the size ratio: one linked-cell grid vs multigrid cells.

    python -m bench multigrid_cost [--n 100000] [--phi 0.2] [--ratios 1 2 5 10] [--reps 5]
                                   [--out DIR]

Scenes: two sphere species of radius ratio R_L/R_s (ratio 1: one size), number fractions chosen so both
species hold the same solid volume (N_L R_L^3 = N_s R_s^3), N spheres at volume fraction phi in a unit
periodic box, placed without overlap by the engine's random sequential addition (engine/setup/scene.py);
skin L_v = 0.4 R_s (the CPU default, in units of the smallest radius).

What is timed, per build (median and fastest of --reps builds after a JIT warm-up; single-grid and
multigrid builds alternate, so a shared machine's load hits both alike), at 1 Numba thread and at all
threads:
- single grid: engine/loops/cpu.py ``bin_particles`` + ``build_list`` (cells of edge >= 2 R_max + L_v,
  nc <= (2N)^(1/3) + 1 per edge: today's CPU build, with the spring carry-over from the previous list);
- multigrid: engine/neighbours/multigrid.py ``bin_levels`` + ``build_levels_carry`` (Skorych & Dosta 2022,
  Algorithm 1 with the search rule of engine/neighbours/multigrid.py; what the CPU backend runs when the radii span
  more than one level, with the same carry-over).
Both start from the list of the same positions as the "previous" list, so the carry-over does the full
work of matching every pair. Candidates = distance tests per particle (the particles in the cells
searched); neighbours = list entries per particle (|r_ij| < R_i + R_j + L_v).
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import platform
import statistics
import time

import numba
import numpy as np

from bench import out_dir
from engine.backends.base import cell_grid
from engine.loops.cpu import bin_particles, build_list
from engine.loops.cpu_shared import SLOT
from engine.neighbours.cells import cell_coords, neighbour_cell, neighbour_cell_count
from engine.neighbours.multigrid import (bin_levels, build_levels_carry, count_candidates, grid_levels, level_arrays,
                                         main_level)
from engine.setup.scene import place_species


@numba.njit(parallel=True, cache=True)
def single_candidates(pos, nc, inv_cell, cell_start, out):
    """Distance tests per particle of engine/loops/cpu.py build_list (27 cells, fewer if nc < 3)."""
    for i in numba.prange(pos.shape[0]):
        cx, cy, cz = cell_coords(pos[i, 0], pos[i, 1], pos[i, 2], inv_cell, nc)
        cnt = 0
        for k in range(neighbour_cell_count(nc)):
            cc = neighbour_cell(cx, cy, cz, k, nc)
            cnt += cell_start[cc + 1] - cell_start[cc]
        out[i] = cnt - 1


def scene(n: int, phi: float, ratio: float, seed: int = 0):
    """(positions, radii, species, skin) of the two-species scene in a unit box."""
    if ratio == 1:
        counts, ratios = [n], [1.0]
    else:
        rho = 1.0 / ratio
        n_large = max(1, int(round(n * rho**3 / (1.0 + rho**3))))
        counts, ratios = [n_large, n - n_large], [1.0, rho]
    unit = sum(c * r**3 for c, r in zip(counts, ratios))
    r_max = (3.0 * phi / (4.0 * math.pi * unit)) ** (1.0 / 3.0)
    radii = [r * r_max for r in ratios]
    pos, species = place_species(counts, radii, 1.0, np.random.default_rng(seed))
    radius = np.asarray(radii)[species]
    return pos, radius, species, 0.4 * min(radii), counts, radii


def _alternating_times(fns, reps):
    """Wall seconds of reps calls of each function, called in turn (a, b, a, b, ...) so that both see the
    same load on a shared machine; one warm-up call each first (compilation, first touch)."""
    for fn in fns:
        fn()
    times = [[] for _ in fns]
    for _ in range(reps):
        for k, fn in enumerate(fns):
            t0 = time.perf_counter()
            fn()
            times[k].append(time.perf_counter() - t0)
    return times


def measure(n, phi, ratio, reps, thread_counts):
    pos, radius, species, skin, counts, radii = scene(n, phi, ratio)
    box, half, inv_box = 1.0, 0.5, 1.0
    # -- single grid: today's cpu.py build ---------------------------------------------------------
    nc = cell_grid(box, n, float(radius.max()), skin)
    inv_cell = nc / box
    cell_start = np.zeros(nc**3 + 1, np.int64)
    cursor = np.zeros(nc**3, np.int64)
    cell_list = np.zeros(n, np.int64)
    cell_of = np.zeros(n, np.int64)
    # -- multigrid -------------------------------------------------------------------------------
    levels = grid_levels(box, n, float(radius.min()), float(radius.max()), skin)
    level = main_level(radius, levels)
    mg = level_arrays(box, level, levels)

    def lists(stride):
        return (np.zeros((n, stride), np.int32), np.zeros(n, np.int32), np.zeros((n, stride, SLOT)),
                np.zeros((n, 3)))

    def single_build(old, new):
        bin_particles(pos, nc, inv_cell, cell_start, cell_list, cell_of, cursor)
        build_list(pos, radius, skin, box, inv_box, half, nc, cell_start, cell_list, cell_of,
                   old[0], old[1], old[2], new[0], new[1], new[2], new[3])

    def multi_build(old, new):
        bin_levels(pos, level, *mg)
        build_levels_carry(pos, radius, level, skin, box, inv_box, half, *mg, old[0], old[1], old[2],
                           new[0], new[1], new[2], new[3])

    # stride: the largest count, found by a first build into a one-slot list
    probe, empty = lists(1), lists(1)
    multi_build(empty, probe)
    stride = int(probe[1].max())
    out = {"ratio": ratio, "n": n, "phi": phi, "counts": counts, "radii_m": radii, "skin_m": skin,
           "single_nc": nc, "levels_nc": levels.nc.tolist(), "n_levels": levels.n_levels, "stride": stride}
    old_s, new_s, old_m, new_m = lists(stride), lists(stride), lists(stride), lists(stride)
    single_build(lists(stride), old_s)
    multi_build(lists(stride), old_m)
    assert np.array_equal(old_s[1], old_m[1]), "single grid and multigrid lists differ"
    for i in range(0, n, max(1, n // 500)):      # same neighbour sets (orders differ)
        assert set(old_s[0][i, :old_s[1][i]].tolist()) == set(old_m[0][i, :old_m[1][i]].tolist())
    cand_s = np.zeros(n, np.int64)
    cand_m = np.zeros(n, np.int64)
    single_candidates(pos, nc, inv_cell, cell_start, cand_s)   # cell_start is binned by single_build
    count_candidates(pos, level, mg[0], mg[1], mg[2], mg[3], mg[4], mg[5], cand_m)
    small = species == (len(counts) - 1)
    out["neighbours_per_particle"] = float(old_s[1].mean())
    out["candidates_single"] = float(cand_s.mean())
    out["candidates_multi"] = float(cand_m.mean())
    out["candidates_single_small"] = float(cand_s[small].mean())
    out["candidates_multi_small"] = float(cand_m[small].mean())
    out["candidates_single_large"] = float(cand_s[~small].mean()) if (~small).any() else out["candidates_single"]
    out["candidates_multi_large"] = float(cand_m[~small].mean()) if (~small).any() else out["candidates_multi"]
    out["times"] = {}
    for th in thread_counts:
        numba.set_num_threads(th)
        runs_s, runs_m = _alternating_times([lambda: single_build(old_s, new_s),
                                             lambda: multi_build(old_m, new_m)], reps)
        out["times"][str(th)] = {"single_s": statistics.median(runs_s), "multi_s": statistics.median(runs_m),
                                 "single_min_s": min(runs_s), "multi_min_s": min(runs_m),
                                 "single_runs": runs_s, "multi_runs": runs_m}
    return out


def markdown(rows, thread_counts) -> str:
    """The table of docs/performance.md: per size ratio, levels, list entries, candidates and build times."""
    head = ["R_L/R_s", "N_L + N_s", "levels: nc per edge (single grid)", "list entries / particle",
            "candidates / particle: single grid", "multigrid", "small spheres: single", "multi"]
    for t in thread_counts:
        head += [f"build, {t} thread{'s' if t > 1 else ''}: single grid", "multigrid", "ratio"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [f"{r['ratio']:g}", " + ".join(str(c) for c in r["counts"]),
                 f"{', '.join(str(c) for c in r['levels_nc'])} ({r['single_nc']})",
                 f"{r['neighbours_per_particle']:.2f}", f"{r['candidates_single']:.1f}",
                 f"{r['candidates_multi']:.1f}", f"{r['candidates_single_small']:.1f}",
                 f"{r['candidates_multi_small']:.1f}"]
        for t in thread_counts:
            tt = r["times"][str(t)]
            cells += [f"{1e3 * tt['single_s']:.0f} ({1e3 * tt['single_min_s']:.0f}) ms",
                      f"{1e3 * tt['multi_s']:.0f} ({1e3 * tt['multi_min_s']:.0f}) ms",
                      f"{tt['single_s'] / tt['multi_s']:.2f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return f"{line.split(':', 1)[1].strip()}, {numba.config.NUMBA_NUM_THREADS} threads"
    except OSError:
        pass
    return platform.processor() or platform.machine()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--phi", type=float, default=0.2)
    ap.add_argument("--ratios", type=float, nargs="+", default=[1, 2, 5, 10])
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--threads", type=int, nargs="+", default=None,
                    help="Numba thread counts (default: 1 and all)")
    ap.add_argument("--out", default=None, help="folder for multigrid_cost.json (default ./bench-out/multigrid_cost/)")
    ap.add_argument("--table-only", action="store_true", help="print the table of an existing --out file")
    args = ap.parse_args(argv)
    out_path = out_dir(args.out, "multigrid_cost") / "multigrid_cost.json"
    if args.table_only:
        with open(out_path) as fh:
            data = json.load(fh)
        print(markdown(data["rows"], data["meta"]["threads"]))
        return
    threads = args.threads or sorted({1, numba.config.NUMBA_NUM_THREADS})
    rows = []
    for ratio in args.ratios:
        numba.set_num_threads(max(threads))
        rows.append(measure(args.n, args.phi, ratio, args.reps, threads))
        print(json.dumps({k: v for k, v in rows[-1].items() if k != "times"}), flush=True)
    meta = {"date": datetime.date.today().isoformat(), "machine": _cpu_model(),
            "python": platform.python_version(), "numba": numba.__version__, "numpy": np.__version__,
            "threads": threads, "args": vars(args)}
    with open(out_path, "w") as fh:
        json.dump({"meta": meta, "rows": rows}, fh, indent=1)
    print(markdown(rows, threads))


if __name__ == "__main__":
    main()
