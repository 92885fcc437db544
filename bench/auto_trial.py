"""Does the auto list mode pay for its trial? (NVIDIA GPU required)

The scene of the issue: 1 000 000 spheres, 10 % of radius 1 and 90 % of radius 0.2 (number fractions), phi = 0.25,
float64, 3000 steps of one ``advance`` (list_mode "gpu", "cpu-sequential", "cpu-pipelined", "auto"; the same
start, kernels compiled before timing, median of ``--reps``). Prints each mode's particle-steps per second,
auto against the best mode, and auto's decisions (a skipped probe says how many steps and stages were left).

    python -m bench auto_trial --reps 3 --out DIR
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.list_modes import MODES, make_scene, run_mode, warm_up  # noqa: E402

SCENE = ("poly 1:5 dense, 3000 steps", 1_000_000, 0.25, [(1.0, 0.1), (0.2, 0.9)])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    warm_up()
    name, n, phi, species = SCENE
    system, c, _ = make_scene(n, phi, species)
    res = {"scene": name, "n": n, "phi": phi, "species": species, "steps": args.steps, "modes": {}}
    for mode in MODES:
        runs = [run_mode((system, c), mode, steps=args.steps) for _ in range(args.reps)]
        walls = [r["wall_s"] for r in runs]
        res["modes"][mode] = {"walls": walls, "cundall": n * args.steps / statistics.median(walls),
                              "decisions": (runs[-1].get("lists") or {}).get("decisions")}
        print(mode, f"{res['modes'][mode]['cundall']:.3g}", walls, flush=True)
    best = max(res["modes"][m]["cundall"] for m in MODES[:3])
    res["auto_over_best"] = res["modes"]["auto"]["cundall"] / best
    print(f"auto / best mode = {res['auto_over_best']:.3f}")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "auto_trial.json").write_text(json.dumps(res, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
