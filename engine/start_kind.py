"""Which generator draws a spec's start, and where (engine/scene.py draws it; no numba here: engine/startup.py asks
before numba is imported)."""

from __future__ import annotations

import os

from engine.params import species_table

#: one-size starts of at least this many particles are drawn in parallel (engine/scene.py's docstring)
PARALLEL_START_MIN = 1 << 20
SEQUENTIAL_GENERATOR = "numpy-pcg64"
PARALLEL_GENERATOR = "splitmix64-counter"
#: environment switch: "0" = large starts are drawn on the host even for a GPU job (A/B timings)
DEVICE_START_ENV = "DEMQ_DEVICE_START"


def start_generator(spec) -> str:
    """Which generator draws a spec's start: the sequential NumPy one, or the parallel counter-based one
    for one-size starts of N >= PARALLEL_START_MIN (species starts are always sequential: RSA)."""
    if species_table(spec) is None and spec.n_particles >= PARALLEL_START_MIN:
        return PARALLEL_GENERATOR
    return SEQUENTIAL_GENERATOR


def device_start(spec) -> bool:
    """Whether a GPU job of ``spec`` draws its start on the device (engine/backends/cuda_start.py): a large
    one-size sphere start (the parallel generator), unless DEMQ_DEVICE_START=0."""
    return spec.shape == "sphere" and start_generator(spec) == PARALLEL_GENERATOR and \
        os.environ.get(DEVICE_START_ENV) != "0"
