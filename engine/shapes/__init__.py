"""Particle shapes as plug-ins of the CPU and CUDA time loops: one module per shape (plus its ``_cuda`` sibling for
the GPU), one registry line each.

A shape module (engine/shapes/sphere.py documents the interface) provides ``NAME``, ``EXACT_DISPLACEMENT`` and
njit functions of one particle or one list slot: ``pre_step`` and ``rotate`` (the shape's part of the
kick-drift; the translation is shared) and ``pair`` (the pair evaluator: contact geometry and force law). engine/backends/cpu.py builds one compiled time
loop, one kick-drift and one force loop per shape from them (``make_run_steps``, ``make_step``,
``make_forces``); the list/cell machinery
(engine/cells.py, engine/multigrid.py) and the list-slot history store (engine/backends/cpu_shared.py) are shared by every shape.

On the GPU the same holds: a shape's sibling module ``<module>_cuda`` (engine/shapes/sphere_cuda.py documents the
interface) provides ``make_cuda``, a factory of numba.cuda device functions (its rotation step, pair evaluator and
observables on the device layout); engine/backends/cuda_loop.py builds the one CUDA time loop from them, and the
list kernels (engine/backends/cuda_kernels.py, cuda_lists.py) are shared. Shape modules import only
engine/physics/ (and numba); they never import a backend (the CUDA layout is handed to ``make_cuda``).
"""

from __future__ import annotations

import importlib

#: spec shape name -> module (the one line a new shape adds)
SHAPES = {
    "sphere": "engine.shapes.sphere",
    "ellipsoid": "engine.shapes.spheroid",
}


def shape_module(name: str):
    """The plug-in module of shape ``name`` (a key of SHAPES)."""
    try:
        return importlib.import_module(SHAPES[name])
    except KeyError:
        raise ValueError(f"shape = {name!r}: unknown; expected one of {sorted(SHAPES)}") from None


def shape_cuda_module(name: str):
    """The CUDA parts of shape ``name``: the ``_cuda`` sibling of its module (``make_cuda``, ``FLAGS``)."""
    try:
        return importlib.import_module(SHAPES[name] + "_cuda")
    except KeyError:
        raise ValueError(f"shape = {name!r}: unknown; expected one of {sorted(SHAPES)}") from None
