"""Backends own memory layout, loops and launches; the physics comes from engine.physics.

``make_backend(name, system, contact)`` (engine/backends/registry.py) returns a backend for 'cpu', 'cuda'
or 'auto' (CUDA when a GPU is present, else CPU); the shared types live in engine/backends/base.py.
"""

from engine.backends.base import ContactParams, SphereSystem, cuda_available
from engine.backends.registry import make_backend

__all__ = ["ContactParams", "SphereSystem", "make_backend", "cuda_available"]
