"""The driver's host time per scene and round of a packed batch, without a GPU.

engine.simulate.drive runs K small scenes (64 spheres, no snapshots, default records) on a fake ensemble that
does nothing but run the driver's deferred record work in its ``advance`` (as the CUDA ensemble does in its waits
for the GPU). Printed: the host time between two advances (on a real ensemble the GPU is idle then), per scene
and round, and the time of the deferred units (inside the advances, overlapped on a real ensemble).

    python -m bench driver_overhead [K]          (default K = 256)
"""

from __future__ import annotations

import os
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


class _Nothing:
    """An ensemble that advances nothing; its observe sums are constants."""

    name, device, builds = "cuda", "none", 0
    idle = None
    inside = 0.0
    marks: list = []

    def __init__(self, systems, contacts):
        self.n = len(systems)

    def warmup(self):
        pass

    def set_contacts(self, contacts):
        pass

    def set_contact(self, i, contact):
        pass

    def advance(self, m):
        t = time.perf_counter()
        _Nothing.marks.append(t)
        if self.idle is not None:
            while self.idle():
                pass
        _Nothing.inside += time.perf_counter() - t
        _Nothing.marks.append(time.perf_counter())
        return {}

    def deactivate(self, i):
        pass

    def deactivate_many(self, ks):
        pass

    def observe_later(self):
        r = {"kinetic_energy_translational": 1.0, "kinetic_energy_rotational": 0.5, "contacts": 0,
             "elastic_energy": 0.0, "max_overlap": 0.0, "momentum": (0.0, 0.0, 0.0), "collisions": 0,
             "temperature_translational": 1.0}
        return lambda s: dict(r)

    def observe(self):
        f = self.observe_later()
        return [f(i) for i in range(self.n)]


def main() -> None:
    import engine.simulate as sim
    from engine.simulate import SceneRun, drive

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
          f"{1e6 * between / rounds / k:.1f} us per scene and round; deferred units {_Nothing.inside:.3f} s")


if __name__ == "__main__":
    main()
