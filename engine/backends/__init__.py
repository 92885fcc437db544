"""Backends: the interfaces every backend and ensemble implements (protocol.py), the factories (registry.py:
``make_backend``; ensemble.py: ``make_ensemble``, SerialEnsemble) and the GPU probe (base.py). The memory layout,
loops and launches they run are the shared machinery of engine/loops/ specialised by the shape plug-ins of
engine/shapes/; the physics comes from engine.physics.

``make_backend(name, system, contact)`` returns a backend for 'cpu', 'cuda' or 'auto' (CUDA when a GPU is present,
else CPU); the shared types are named in engine/backends/base.py.
"""

from engine.backends.base import ContactParams, SphereSystem, cuda_available
from engine.backends.registry import make_backend

__all__ = ["ContactParams", "SphereSystem", "make_backend", "cuda_available"]
