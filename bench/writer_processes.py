"""A packed batch's last round of files (a diagnostic): 256 small result files (4096 spheres, 201
records of the 11 observables, no frames) written through the writer processes of engine/output/h5md_pool.py, and one
written in this process.

    python -m bench writer_processes
"""

from __future__ import annotations

import os
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

OBSERVABLES = ("kinetic_energy_translational", "kinetic_energy_rotational", "temperature_translational",
               "temperature_rotational", "contacts", "elastic_energy", "max_overlap", "sonine_a2_translational",
               "sonine_a2_rotational", "sonine_a11", "collisions")


def main() -> None:
    from engine.output import h5md, h5md_pool
    from engine.setup.params import derive
    from engine.setup.spec import SimulationSpec

    spec = SimulationSpec(n_particles=4096)
    n = spec.n_particles
    kwargs = dict(n=n, box_length=2.0, spec_json=spec.to_json(), derived=derive(spec).as_dict(),
                  radius=np.full(n, 0.01), semi_axes=None, mass=np.full(n, 1.0), species=None, creator_version="x",
                  author="demq", dtype=np.float64)
    rows = [(k, k * 1e-3, {name: (k if name in ("contacts", "collisions") else 0.5 * k) for name in OBSERVABLES})
            for k in range(201)]
    run_info = {"backend": "cuda", "device": "x", "wall_time": 1.0, "cundall_number": 1.0, "steps_total": 1,
                "neighbour_builds": 1, "resumed_from_step": -1, "timings": {"loop": 1.0}}
    out = tempfile.mkdtemp()
    for rep in range(3):
        t = time.perf_counter()
        h5md.write_whole_file(f"{out}/one{rep}.h5", kwargs, [rows], [], run_info)
        print(f"one file in this process: {1e3 * (time.perf_counter() - t):.1f} ms")
    h5md_pool.prewarm(h5md_pool.MAX_PROCESSES, ready=h5md.writer_process_ready)
    time.sleep(3)   # the processes' start-up, as during a batch's loop
    for rep in range(2):
        t = time.perf_counter()
        futs = [h5md_pool.submit(h5md.write_whole_file, f"{out}/r{rep}_{k}.h5", kwargs, [rows], [], run_info)
                for k in range(256)]
        for f in futs:
            f.result()
        print(f"256 files, {h5md_pool.MAX_PROCESSES} writer processes: {time.perf_counter() - t:.3f} s")


if __name__ == "__main__":
    main()
