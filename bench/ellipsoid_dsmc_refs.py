"""DSMC references of the late-time T_tr/T_rot of smooth spheroids, with seed-to-seed standard errors.

Runs engine.validation.hcs_ellipsoids.dsmc_ratio (N = 2e4, 60 collisions per particle, mean over the second
half) for several seeds per (xi, e_n, restitution model) in
parallel processes (one numpy thread each), and writes mean, standard error across seeds (ddof = 1) and the
per-seed values to OUT/dsmc.json (rewritten after every finished run). 'dem' = the restitution the DEM
dashpot gives at each contact geometry, e_eff(D); 'nominal' = the constant e_n (docs/physics.md).

    OMP_NUM_THREADS=1 python -m bench ellipsoid_dsmc_refs --out DIR \\
        --jobs 2.5:0.9:dem:4 2.5:0.9:nominal:2 --procs 6
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench import out_dir  # noqa: E402


def _one(task):
    xi, e, model, seed, n, coll = task
    from engine.validation.hcs_ellipsoids import dsmc_ratio

    t = time.time()
    r = dsmc_ratio(xi, e, dem=(model == "dem"), n=n, coll_per_particle=coll, seed=seed)
    return task, r["ratio"], time.time() - t


def parse(items):
    out = []
    for it in items:
        xi, e, model, k = it.split(":")
        assert model in ("dem", "nominal"), it
        out.append((float(xi), float(e), model, int(k)))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default=None, help="folder for dsmc.json (default ./bench-out/ellipsoid_dsmc_refs/)")
    ap.add_argument("--jobs", nargs="+", required=True, help="xi:e:dem|nominal:seeds")
    ap.add_argument("--procs", type=int, default=max(1, (os.cpu_count() or 2) - 4))
    ap.add_argument("--n", type=int, default=20000)
    ap.add_argument("--coll", type=float, default=60.0)
    args = ap.parse_args(argv)
    out_path = out_dir(args.out, "ellipsoid_dsmc_refs") / "dsmc.json"
    tasks = [(xi, e, model, 1 + s, args.n, args.coll) for xi, e, model, k in parse(args.jobs) for s in range(k)]
    t0 = time.time()
    res: dict = {}

    def write():
        for r in res.values():
            v = r["values"]
            r["mean"] = sum(v) / len(v)
            r["se"] = (math.sqrt(sum((x - r["mean"]) ** 2 for x in v) / (len(v) - 1) / len(v)) if len(v) > 1
                       else None)
        out = {"total_wall_s": time.time() - t0, "procs": args.procs, "done": sum(len(r["values"]) for r in
                                                                                   res.values()),
               "tasks": len(tasks), "results": res}
        tmp = out_path.with_suffix(".tmp")
        tmp.write_text(json.dumps(out, indent=1))
        os.replace(tmp, out_path)        # rewritten after every run: a stopped job leaves what it finished

    with ProcessPoolExecutor(max_workers=args.procs) as pool:
        for fut in as_completed([pool.submit(_one, t) for t in tasks]):
            (xi, e, model, seed, n, coll), ratio, wall = fut.result()
            key = f"{xi}/{e}/{model}"
            res.setdefault(key, {"xi": xi, "e_n": e, "model": model, "n": n, "coll_per_particle": coll,
                                 "seeds": [], "values": [], "wall_s": []})
            res[key]["seeds"].append(seed)
            res[key]["values"].append(ratio)
            res[key]["wall_s"].append(wall)
            print(f"dsmc {key} seed {seed}: {ratio:.5f} ({wall:.0f} s)", flush=True)
            write()
    return 0


if __name__ == "__main__":
    sys.exit(main())
