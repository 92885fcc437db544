"""Sphere orientations: accuracy against a t_c/1000 rerun, and what tracking them costs on the CPU.

    python -m bench orientation reference     # the rough lattice gas, 8 t_c at t_c/50 against a rerun at t_c/1000
    python -m bench orientation cost          # default spec: advance() with snapshots 2 (orientations) and 0

``reference``: the lattice gas of tests/engine/test_cuda_simulator.py (27 rough spheres, contacts
from the first steps), spins of 10, 100, 300 rad/s per component. The same start is run at dt = t_c/50 and at
t_c/1000 (CPU backend, one step per call: the mid-step spins are read back as w(t) - tau/I dt/2). Printed: the
largest |q - q_ref| of the engine's lazy exact turns and of the per-step Fincham update (Hidalgo et al. 2013) of the
same t_c/50 spins, q_ref = Fincham per step through the t_c/1000 run's spins, and the largest spin difference
between the two runs (the contact's own O(dt^2) error, which both schemes inherit). The test
tests/engine/test_lazy_orientation.py compares the schemes against the t_c/50 run's own spins instead (that
isolates the orientation integrator).

``cost``: the loop rate of the default spec (4096 spheres) on the CPU backend with and without orientations,
alternating three times (a diagnostic of the loop; bench/e2e.py gives the end-to-end figures).
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np


def _lattice_run(div: int, t_end: float, spin: float):
    from engine.backends.base import ContactParams
    from engine.physics.rotation import fincham_quat_step_space
    from engine.shapes.sphere.cpu_backend import CpuBackend
    from tests.engine.test_cuda_simulator import tiny_system

    k_n = 1.0e5
    t_c = np.pi * np.sqrt(0.5 / k_n)
    system = tiny_system(spin=spin, speed=1.0)
    be = CpuBackend(system, ContactParams(k_n=k_n, gamma_n_coef=2.0 * np.sqrt(k_n) * 0.2, k_t=k_n * 2 / 7 * 0.5,
                                          friction=0.3, dt=t_c / div, skin=0.02, precision="float64",
                                          orientation=True, overlap_limit=0.2))
    q = np.array(system.orientation, float)
    for _ in range(round(t_end / be.dt)):
        be.advance(1)
        wmid = be.omega - be.torque * be.inv_i[:, None] * (be.dt / 2)
        for i in range(be.n):
            q[i] = fincham_quat_step_space(*q[i], *wmid[i], be.dt, 0.5)
    return be.state(), q


def reference() -> None:
    t_c = np.pi * np.sqrt(0.5 / 1.0e5)
    print("| spin per component (rad/s) | lazy exact: max abs(q - q_ref) | per-step Fincham | max abs(w - w_ref) |")
    print("|---|---|---|---|")
    for spin in (10.0, 100.0, 300.0):
        ref, q_ref = _lattice_run(1000, 8 * t_c, spin)
        run, q_fincham = _lattice_run(50, 8 * t_c, spin)
        print(f"| {spin:g} | {np.abs(run['orientation'] - q_ref).max():.3e} | {np.abs(q_fincham - q_ref).max():.3e} | "
              f"{np.abs(run['angular_velocity'] - ref['angular_velocity']).max():.3g} |", flush=True)


def cost() -> None:
    from engine.setup.params import derive
    from engine.setup.scene import initial_spheres
    from engine.shapes.sphere.cpu_backend import CpuBackend
    from engine.driver.simulate import contact_params
    from engine.setup.spec import SimulationSpec

    rates = {2: [], 0: []}
    for _ in range(3):
        for snaps in (2, 0):
            spec = SimulationSpec(snapshots=snaps)
            p = derive(spec)
            be = CpuBackend(initial_spheres(spec, p), contact_params(spec, p, thermalization=False))
            be.warmup()
            be.advance(500)
            t = time.perf_counter()
            be.advance(3000)
            rates[snaps].append(spec.n_particles * 3000 / (time.perf_counter() - t))
    for snaps, r in rates.items():
        print(f"snapshots {snaps}: {np.median(r):.3g} particle-steps/s (runs {', '.join(f'{x:.3g}' for x in r)})")
    print(f"orientations cost: x{np.median(rates[0]) / np.median(rates[2]):.2f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=["reference", "cost"])
    args = ap.parse_args(argv)
    sys.path.insert(0, ".")
    reference() if args.what == "reference" else cost()
    return 0


if __name__ == "__main__":
    sys.exit(main())
