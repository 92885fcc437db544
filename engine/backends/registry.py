"""The backend factory: which concrete backend class runs a system ('cpu', 'cuda' or 'auto').

The only module that names every single-system backend (the ensembles' counterpart is
engine/backends/ensemble.py); the backends themselves import only engine/backends/base.py and the
neutral helpers (status.py, host.py), never this module or each other's private names.
"""

from __future__ import annotations

import os

from engine.backends.base import ContactParams, EllipsoidSystem, SphereSystem, cuda_available
from engine.errors import BackendUnavailable


def make_backend(name: str, system: SphereSystem, contact: ContactParams):
    """Backend instance for 'cpu', 'cuda' or 'auto' ('auto': CUDA when a GPU is present), for spheres
    (:class:`SphereSystem`) and ellipsoids (:class:`EllipsoidSystem`)."""
    ellipsoid = isinstance(system, EllipsoidSystem)
    if name == "auto":
        name = "cuda" if cuda_available() else "cpu"
    if name == "cpu":
        if ellipsoid:
            from engine.backends.cpu_ellipsoid import CpuEllipsoidBackend

            return CpuEllipsoidBackend(system, contact)
        from engine.backends.cpu import CpuBackend

        return CpuBackend(system, contact)
    if name == "cuda":
        sim = os.environ.get("NUMBA_ENABLE_CUDASIM") == "1"
        if not sim and not cuda_available():
            raise BackendUnavailable(
                "backend = 'cuda' but no CUDA GPU is available here; use backend 'cpu' or 'auto'")
        if ellipsoid:
            from engine.backends.cuda_ellipsoid import CudaEllipsoidBackend

            return CudaEllipsoidBackend(system, contact)
        from engine.backends.cuda import CudaBackend

        return CudaBackend(system, contact)
    raise BackendUnavailable(f"unknown backend {name!r}; expected 'auto', 'cpu' or 'cuda'")
