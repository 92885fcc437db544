"""The spheroid plug-in's run-time hooks: its host-side system, the start of a spec, the result file's
particle fields and its backend classes (looked up through engine.shapes.host by the backend factory, the
ensembles and the job driver)."""

from __future__ import annotations

import numpy as np

from engine.loops.system import EllipsoidSystem

#: the host-side state a backend is built from
SYSTEM = EllipsoidSystem


def initial_system(spec, p, on_device: bool = False) -> EllipsoidSystem:
    """The start of an ellipsoid spec (engine.setup.scene.initial_ellipsoids: placed without overlap, random
    orientations, Maxwellian velocities, spins about the two perpendicular axes, and the axial one when rough);
    ``on_device``: a GPU job's large start is left to its backend to draw (``system.draw``)."""
    from engine.setup.scene import initial_ellipsoids

    return initial_ellipsoids(spec, p, on_device)


def standin_system(p, n_edge: int) -> EllipsoidSystem:
    """n_edge^3 resting spheroids of the spec's size and one orientation on a simple cubic lattice of spacing
    2.5 a (bounding spheres apart): the small scene of the GPU start-up (engine/driver/startup.py), NumPy only."""
    from engine.shapes.sphere.host import _lattice

    n = n_edge ** 3
    return EllipsoidSystem(**_lattice(n_edge, 2.5 * p.semi_axes[0]),
                           semi_axes=np.tile(np.asarray(p.semi_axes, float), (n, 1)), mass=np.full(n, p.mass),
                           inertia=np.tile(np.asarray(p.inertia, float), (n, 1)))


def writer_fields(system: EllipsoidSystem, p) -> dict:
    """The per-particle fields of the result file (engine.output.h5md.H5MDWriter): the semi-axes (a, b, c)."""
    return {"radius": None, "semi_axes": system.semi_axes, "species": None}


def cpu_backend():
    """The CPU host class (engine/shapes/spheroid/cpu_backend.py)."""
    from engine.shapes.spheroid.cpu_backend import CpuEllipsoidBackend

    return CpuEllipsoidBackend


def cuda_ensemble():
    """The packed CUDA ensemble (engine/shapes/spheroid/cuda_backend.py)."""
    from engine.shapes.spheroid.cuda_backend import CudaEllipsoidEnsemble

    return CudaEllipsoidEnsemble


def cuda_backend():
    """One scene on the GPU (engine/shapes/spheroid/cuda_backend.py)."""
    from engine.shapes.spheroid.cuda_backend import CudaEllipsoidBackend

    return CudaEllipsoidBackend


def load_device_start(pos_dtype, dtype, placements=("lattice", "random")) -> None:
    """Load the kernels of a spheroid start drawn on the GPU (engine/shapes/spheroid/cuda_backend.py
    draw_ellipsoid_start; its positions are in the state precision ``dtype``): the GPU start-up thread's
    (engine/driver/startup.py), before a job whose start is drawn there."""
    from engine.shapes.spheroid.cuda_backend import load_device_start as load

    load(dtype, placements)
