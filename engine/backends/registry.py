"""The backend factory: which concrete backend class runs a system ('cpu', 'cuda' or 'auto').

The backend classes are the shape's (engine.shapes.host(shape): ``cpu_backend``, ``cuda_backend``); this module
names no shape (the ensembles' counterpart is engine/backends/ensemble.py). The backend classes build on the shared
machinery of engine/loops/ and never import this module. A job's driver builds ensembles (make_ensemble), not single
backends; this factory serves SerialEnsemble and code that drives one backend by hand.
"""

from __future__ import annotations

import os

from engine.backends.base import ContactParams, cuda_available
from engine.errors import BackendUnavailable
from engine.shapes import host, shape_of


def make_backend(name: str, system, contact: ContactParams):
    """Backend instance for 'cpu', 'cuda' or 'auto' ('auto': CUDA when a GPU is present) of a host-side system
    of any registered shape (engine/shapes/: :class:`SphereSystem`, :class:`EllipsoidSystem`, ...)."""
    if name == "auto":
        name = "cuda" if cuda_available() else "cpu"
    if name == "cpu":
        return host(shape_of(system)).cpu_backend()(system, contact)
    if name == "cuda":
        sim = os.environ.get("NUMBA_ENABLE_CUDASIM") == "1"
        if not sim and not cuda_available():
            raise BackendUnavailable(
                "backend = 'cuda' but no CUDA GPU is available here; use backend 'cpu' or 'auto'")
        return host(shape_of(system)).cuda_backend()(system, contact)
    raise BackendUnavailable(f"unknown backend {name!r}; expected 'auto', 'cpu' or 'cuda'")
