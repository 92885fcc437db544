"""The driver's host time per scene and round of a packed batch, without a GPU.

engine.driver.simulate.drive runs K small scenes (64 spheres, no snapshots, default records) on a fake ensemble that
does nothing in its ``advance``. Printed: the host time between two advances (on a real ensemble the GPU is idle
then: the stops' records, progress and checkpoint checks), per scene and round.

    python -m bench driver_overhead [K]          (default K = 256)
"""

from __future__ import annotations

import os
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from engine.backends.protocol import Ensemble  # noqa: E402

_OBS = {"kinetic_energy_translational": 1.0, "kinetic_energy_rotational": 0.5, "contacts": 0,
        "elastic_energy": 0.0, "max_overlap": 0.0, "momentum": (0.0, 0.0, 0.0), "collisions": 0,
        "temperature_translational": 1.0}


class _Nothing(Ensemble):
    """A packed-style ensemble that advances nothing; its observe sums are constants."""

    name, device, builds = "cuda", "none", 0
    shares_observation = True
    marks: list = []

    def __init__(self, systems, contacts):
        self.n = self.n_scenes = len(systems)

    def warmup(self):
        pass

    def set_contact(self, k, contact):
        pass

    def advance(self, nsteps):
        _Nothing.marks.append(time.perf_counter())
        _Nothing.marks.append(time.perf_counter())
        return {}

    def deactivate(self, k):
        pass

    def observe(self):
        return [dict(_OBS) for _ in range(self.n)]

    def state(self, k, reuse=False):
        raise NotImplementedError("no snapshots in this benchmark")

    def contacts(self, k):
        raise NotImplementedError("no checkpoints in this benchmark")


def main() -> None:
    import engine.driver.simulate as sim
    from engine.driver.simulate import SceneRun, drive

    k = int(sys.argv[1]) if len(sys.argv) > 1 else 256
    out = tempfile.mkdtemp()
    spec = dict(n_particles=64, volume_fraction=0.058, box_length=2.0 * (64 / 4096) ** (1 / 3), snapshots=0,
                thermalization=0, t_end=0.002)
    sim.DEFER_MIN_SCENES = 10 ** 9   # the files in this process (their writing is not what is timed here)
    scenes = [SceneRun({**spec, "seed": s}, f"{out}/s{s}.h5", backend="cpu") for s in range(k)]
    drive(scenes, lambda systems, contacts: _Nothing(systems, contacts))
    m, rounds = _Nothing.marks, len(scenes[0].events)
    between = sum(m[i + 1] - m[i] for i in range(1, len(m) - 1, 2))
    print(f"K = {k}, {rounds} stops per scene: between advances {between:.3f} s = "
          f"{1e6 * between / rounds / k:.1f} us per scene and round")


if __name__ == "__main__":
    main()
