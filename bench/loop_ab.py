"""Side-by-side loop variants: one JAX-MD comparison case through ``engine.run``, engine settings switched per run.

In one warm process (kernels compiled by a 20-step run of each variant first), each repetition runs every variant
once, in turn, on the same case of bench/vs_jaxmd.py (its scene, its spec: no thermalisation, no snapshots), and
prints one JSON line per run: the loop and end-to-end Cundall numbers. A variant is ``default`` or a ``+``-joined
list of bench/e2e.py ``--off`` switch names (e.g. ``launch_cache``, ``multistep``), or ``multistep_on`` (the
many-steps-per-launch loop forced for a large scene). For the cost of one piece of machinery inside the loop,
without the fresh-process noise of bench/e2e.py.

    python -m bench loop_ab --cases elastic-2M-f64 elastic-8M-f32 --variants launch_cache default multistep_on
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def apply(variant: str) -> None:
    """Put every switch back on, then turn off those the variant names (bench.e2e.SWITCHES)."""
    import importlib

    from bench.e2e import SWITCHES, switch_off
    import engine.loops.cuda_ensemble as ensemble

    for module, setting, _ in SWITCHES.values():
        mod = importlib.import_module(module)
        setattr(mod, setting, None if (module, setting) == ("engine.loops.cuda_ensemble", "MULTISTEP") else True)
    if variant == "multistep_on":
        ensemble.MULTISTEP = True
    elif variant != "default":
        switch_off(variant.split("+"))


def main(argv=None) -> int:
    from bench.vs_jaxmd import CASES, case_spec

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", choices=list(CASES), default=["elastic-2M-f64"])
    ap.add_argument("--variants", nargs="+", default=["launch_cache", "default"])
    ap.add_argument("--reps", type=int, default=1)
    ap.add_argument("--backend", choices=("cuda", "cpu"), default="cuda")
    ap.add_argument("--steps-scale", type=float, default=1.0)
    args = ap.parse_args(argv)
    from engine import run

    with tempfile.TemporaryDirectory(prefix="loop_ab_") as tmp:
        for case in args.cases:
            n, precision, steps, rough = CASES[case]
            steps = max(1, int(steps * args.steps_scale))
            for v in args.variants:
                apply(v)
                run(case_spec(n, precision, 20, rough, args.backend), Path(tmp) / "warm.h5", backend=args.backend)
            for rep in range(args.reps):
                for v in args.variants:
                    apply(v)
                    spec = case_spec(n, precision, steps, rough, args.backend)
                    t0 = time.perf_counter()
                    s = run(spec, Path(tmp) / "run.h5", backend=args.backend)
                    wall = time.perf_counter() - t0
                    print(json.dumps({"case": case, "variant": v, "rep": rep, "device": s.device, "steps": s.steps,
                                      "loop_s": round(s.loop_s, 4), "wall_s": round(wall, 3),
                                      "cundall_loop": float(f"{n * s.steps / s.loop_s:.3e}"),
                                      "cundall_end_to_end": float(f"{n * s.steps / wall:.3e}")}), flush=True)
    apply("default")
    return 0


if __name__ == "__main__":
    sys.exit(main())
