"""Numba plumbing: the compiled kernels' disk cache keyed by the engine's sources, numba's first import without
``coverage``, and the numba-cuda internals the launches use. The map: engine/README.md."""
