"""The sphere plug-in's run-time hooks: its host-side system, the start of a spec, the result file's particle
fields and its backend classes (looked up through engine.shapes.host by the backend factory, the ensembles and
the job driver)."""

from __future__ import annotations

import numpy as np

from engine.loops.system import SphereSystem

#: the host-side state a backend is built from
SYSTEM = SphereSystem


def initial_system(spec, p, on_device: bool = False) -> SphereSystem:
    """The start of a sphere spec (engine.setup.scene.initial_spheres: placement, Maxwellian velocities and spins);
    ``on_device``: a GPU job's large start is left to its backend to draw (``system.draw``)."""
    from engine.setup.scene import initial_spheres

    return initial_spheres(spec, p, on_device)


def standin_system(p, n_edge: int) -> SphereSystem:
    """n_edge^3 resting spheres of the spec's size on a simple cubic lattice of spacing 2.5 radii (no contact):
    the small scene of the GPU start-up (engine/driver/startup.py), made with NumPy only."""
    return SphereSystem(**_lattice(n_edge, 2.5 * p.radius), radius=np.full(n_edge ** 3, p.radius),
                        mass=np.full(n_edge ** 3, p.mass), inertia=np.full(n_edge ** 3, p.inertia[0]))


def _lattice(n_edge: int, spacing: float) -> dict:
    """Box, positions (cell centres), zero velocities and spins, identity orientations of a cubic lattice."""
    g = (np.arange(n_edge) + 0.5) * spacing
    pos = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    n = pos.shape[0]
    quat = np.zeros((n, 4))
    quat[:, 0] = 1.0
    return dict(box_length=n_edge * spacing, position=pos, velocity=np.zeros((n, 3)),
                angular_velocity=np.zeros((n, 3)), orientation=quat)


def writer_fields(system: SphereSystem, p) -> dict:
    """The per-particle fields of the result file (engine.output.h5md.H5MDWriter): radius and species index."""
    from engine.setup.scene import species_index

    return {"radius": system.radius, "semi_axes": None, "species": species_index(system.radius, p)}


def cpu_backend():
    """The CPU host class (engine/shapes/sphere/cpu_backend.py)."""
    from engine.shapes.sphere.cpu_backend import CpuBackend

    return CpuBackend


def cuda_ensemble():
    """The packed CUDA ensemble (engine/shapes/sphere/cuda_backend.py)."""
    from engine.shapes.sphere.cuda_backend import CudaEnsemble

    return CudaEnsemble


def cuda_backend():
    """One scene on the GPU behind the Backend interface (engine/shapes/sphere/cuda_backend.py)."""
    from engine.shapes.sphere.cuda_backend import CudaBackend

    return CudaBackend


def load_device_start(pos_dtype, dtype, placements=("lattice", "random")) -> None:
    """Load the kernels of a start drawn on the GPU (engine/loops/cuda_start.py) for these position and state
    precisions and placements: the GPU start-up thread's (engine/driver/startup.py), before a job whose start is
    drawn there."""
    from engine.loops.cuda_start import load

    load(pos_dtype, dtype, placements)
