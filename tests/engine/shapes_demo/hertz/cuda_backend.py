"""The ``hertz`` shape's CUDA host classes: the sphere's ensemble (engine/shapes/sphere/cuda_backend.py) under
this shape's name, so that the shared CUDA loop is specialised by hertz/device.py."""

from __future__ import annotations

from engine.shapes.sphere.cuda_backend import CudaBackend, CudaEnsemble


class CudaHertzEnsemble(CudaEnsemble):
    """K scenes of Hertz spheres on the GPU (the sphere's state and observables, hertz/device.py's law)."""

    shape = "hertz"


class CudaHertzBackend(CudaBackend):
    """One scene of Hertz spheres on the GPU, behind the Backend interface."""

    ensemble_class = CudaHertzEnsemble
