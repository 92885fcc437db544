"""The sphere plug-in's run-time hooks: its host-side system, the start of a spec, the result file's particle
fields and its backend classes (looked up through engine.shapes.host by the backend factory, the ensembles and
the job driver)."""

from __future__ import annotations

from engine.backends.base import SphereSystem

#: the host-side state a backend is built from
SYSTEM = SphereSystem


def initial_system(spec, p) -> SphereSystem:
    """The start of a sphere spec (engine.scene.initial_spheres: placement, Maxwellian velocities and spins)."""
    from engine.scene import initial_spheres

    return initial_spheres(spec, p)


def writer_fields(system: SphereSystem, p) -> dict:
    """The per-particle fields of the result file (engine.h5md.H5MDWriter): radius and species index."""
    from engine.scene import species_index

    return {"radius": system.radius, "semi_axes": None, "species": species_index(system.radius, p)}


def cpu_backend():
    """The CPU host class (engine/shapes/sphere/cpu_backend.py)."""
    from engine.shapes.sphere.cpu_backend import CpuBackend

    return CpuBackend


def cuda_ensemble():
    """The packed CUDA ensemble: the base class engine.backends.cuda.CudaEnsemble is the sphere's host side."""
    from engine.backends.cuda import CudaEnsemble

    return CudaEnsemble


def cuda_backend():
    """One scene on the GPU (engine.backends.cuda.CudaBackend over :func:`cuda_ensemble`)."""
    from engine.backends.cuda import CudaBackend

    return CudaBackend
