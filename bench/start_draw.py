"""How long a large start takes to draw (set-up): engine.setup.scene's initial_spheres / initial_ellipsoids in
fresh Python processes, the first call (the compiled draws' disk-cache loads and numba's thread pool included) and
two more in the same process. numba and numba.cuda are imported before the clock, as in a GPU job, where they are
imported before the start is drawn (engine/driver/startup.py).

    python -m bench start_draw [--n 2097152] [--shape sphere|ellipsoid] [--procs 3]

Prints one line per process: the first, second and third draw in seconds. A first process, marked ``prime``,
fills the disk cache (it compiles the draws when the cache is empty).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def child(n: int, shape: str) -> dict:
    import numba  # noqa: F401  (imported before the clock: see the module docstring)

    try:
        import numba.cuda  # noqa: F401
    except ImportError:
        pass
    sys.path.insert(0, ROOT)
    from engine.setup.params import derive
    from engine.setup.scene import initial_ellipsoids, initial_spheres
    from engine.setup.spec import SimulationSpec

    kw = dict(shape="ellipsoid", elongation=2.0) if shape == "ellipsoid" else {}
    spec = SimulationSpec(n_particles=n, volume_fraction=0.058, box_length=2.0 * (n / 4096) ** (1.0 / 3.0),
                          thermalization=0, **kw)
    p = derive(spec)
    draw = initial_ellipsoids if shape == "ellipsoid" else initial_spheres
    times = []
    for _ in range(3):
        t = time.perf_counter()
        draw(spec, p)
        times.append(round(time.perf_counter() - t, 4))
    return {"n": n, "shape": shape, "draws_s": times}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=2_097_152)
    ap.add_argument("--shape", choices=("sphere", "ellipsoid"), default="sphere")
    ap.add_argument("--procs", type=int, default=3)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        print(json.dumps(child(a.n, a.shape)))
        return
    for k in range(a.procs + 1):
        out = subprocess.run([sys.executable, "-m", "bench.start_draw", "--child", "--n", str(a.n), "--shape", a.shape],
                             cwd=ROOT, capture_output=True, text=True, check=True).stdout.strip().splitlines()[-1]
        print(("prime " if k == 0 else "") + out, flush=True)


if __name__ == "__main__":
    main()
