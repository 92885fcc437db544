"""The ``hertz`` shape's CPU host class: the sphere's state and specialisation (engine/shapes/sphere/
cpu_backend.py) running this package's kernels."""

from __future__ import annotations

from engine.shapes.sphere.cpu_backend import CpuBackend
from tests.engine.shapes_demo.hertz import kernels


class CpuHertzBackend(CpuBackend):
    """Smooth elastic Hertz spheres on the CPU: the shared loop specialised by hertz/kernels.py."""

    shape = kernels

    def observe(self) -> dict:
        """The sphere's observables with the Hertz elastic energy (hertz/kernels.py ``elastic_energy``)."""
        out = super().observe()
        out["elastic_energy"] = float(kernels.elastic_energy(self.pos, self.radius, self.nbr, self.nn, self.box_c,
                                                             self.inv_box, self.half, float(self.k_n)))
        return out
