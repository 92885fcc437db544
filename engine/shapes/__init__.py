"""Particle shapes as plug-ins: the registry (one line per shape) and the lookups every other layer uses.

A shape is one package under engine/shapes/ (engine/shapes/README.md lists the steps to add one):

- ``<package>/__init__.py``: the shape's traits, plain Python that imports no other engine module, so that the
  spec and the scales can ask them (``NAME``, ``ELONGATED``, ``SPECIES``, ``SKIN_BY_VOLUME_FRACTION``, ``RANDOM_START``,
  ``body`` for the semi-axes and principal moments, ``spec_error`` for combinations the shape refuses);
- ``kernels.py``: njit functions of one particle or one list slot (``pre_step``, ``rotate``, ``pair``,
  ``observe``) that specialise the one CPU time loop (engine/loops/cpu.py);
- ``device.py``: ``make_cuda``, the factory of numba.cuda device functions that specialise the one CUDA time
  loop (engine/loops/cuda_loop.py);
- ``host.py``: the run-time hooks (the host-side system type, the start of a spec, the result file's particle
  fields, the contact models it runs, and its backend classes);
- its backend classes where the shared ones need the shape's own state (``cpu_backend.py``,
  ``cuda_backend.py``: subclasses of the shared machinery of engine/loops/, never an engine.backends module).

A package elsewhere on the path joins at run time through :func:`register` (the same as one more line in
``SHAPES``). Nothing outside engine/shapes/ names a shape package: engine/backends/registry.py,
engine/backends/ensemble.py, engine/driver/simulate.py, engine/setup/spec.py, engine/setup/scales.py and
engine/setup/start_kind.py reach a shape through these functions, at call time.
"""

from __future__ import annotations

import importlib
from pathlib import Path

#: spec shape name -> package (the one line a new shape adds)
SHAPES = {
    "sphere": "engine.shapes.sphere",
    "ellipsoid": "engine.shapes.spheroid",
}
#: the shapes of the source lines above (never removed by unregister)
_BUILT_IN = frozenset(SHAPES)


#: what a shape package must provide: module suffix -> names it defines (engine/shapes/README.md)
REQUIRED = {
    "": ("NAME", "SUMMARY", "ELONGATED", "SPECIES", "MIXED", "SKIN_BY_VOLUME_FRACTION", "RANDOM_START",
         "body", "spec_error"),
    ".kernels": ("NAME", "EXACT_DISPLACEMENT", "pre_step", "rotate", "settle", "pair", "observe"),
    ".device": ("FLAGS", "make_cuda"),
    ".host": ("SYSTEM", "initial_system", "writer_fields", "cpu_backend", "cuda_ensemble", "cuda_backend"),
}


def register(name: str, package: str) -> None:
    """Register the shape package ``package`` (an importable dotted name, anywhere on the path) under the spec
    name ``name``: the run-time equivalent of one line in :data:`SHAPES`. From then on the spec accepts
    ``shape = name`` and every layer reaches the package through the lookups below.

    A package outside engine/shapes/ has its sources added to the compiled code's disk-cache key
    (engine.numba_support.jitcache.include_sources), as the engine's own are.

    Raises ValueError when the name is taken, or when the package (or one of its parts) cannot be imported or
    lacks a required name (:data:`REQUIRED`); nothing is registered then.
    """
    if not isinstance(name, str) or not name:
        raise ValueError(f"shape name = {name!r}: expected a non-empty string")
    if name in SHAPES:
        raise ValueError(f"shape name = {name!r} is taken (by {SHAPES[name]}); registered: {sorted(SHAPES)}")
    for part, names in REQUIRED.items():
        try:
            module = importlib.import_module(package + part)
        except ImportError as e:
            raise ValueError(f"shape {name!r}: package {package + part!r} cannot be imported: {e}") from None
        missing = [n for n in names if not hasattr(module, n)]
        if missing:
            raise ValueError(f"shape {name!r}: {package + part} lacks {', '.join(missing)} "
                             f"(engine/shapes/README.md lists the parts of a shape package)")
    for part in ("", ".kernels"):
        if importlib.import_module(package + part).NAME != name:
            raise ValueError(f"shape {name!r}: {package + part}.NAME is "
                             f"{importlib.import_module(package + part).NAME!r}, expected {name!r}")
    root = _outside_root(package)
    if root is not None:
        # a package outside engine/shapes/ joins the cache key
        from engine.numba_support.jitcache import include_sources

        include_sources(root)
    SHAPES[name] = package


def unregister(name: str) -> None:
    """Remove a shape added by :func:`register` (tests do, after a plug-in's run); the shapes of :data:`SHAPES`'s
    source lines cannot be removed."""
    if name in _BUILT_IN:
        raise ValueError(f"shape name = {name!r} is built in; only a registered shape can be removed")
    if name not in SHAPES:
        raise ValueError(f"shape name = {name!r} is not registered; registered: {sorted(SHAPES)}")
    root = _outside_root(SHAPES.pop(name))
    if root is not None:
        from engine.numba_support.jitcache import exclude_sources

        exclude_sources(root)


def _outside_root(package: str):
    """The folder of ``package`` if it lies outside engine/shapes/ (not hashed by engine.numba_support.jitcache),
    else None."""
    root = Path(importlib.import_module(package).__file__).resolve().parent
    return None if Path(__file__).resolve().parent in root.parents else root


def _part(name: str, part: str):
    try:
        package = SHAPES[name]
    except (KeyError, TypeError):
        raise ValueError(f"shape = {name!r}: unknown; expected one of {sorted(SHAPES)}") from None
    return importlib.import_module(package + part)


def traits(name: str):
    """The traits of shape ``name`` (its package: ``NAME``, ``ELONGATED``, ``SPECIES``, ``body``, ...)."""
    return _part(name, "")


def kernels(name: str):
    """The njit plug-in of shape ``name`` for the CPU time loop (``pre_step``, ``rotate``, ``pair``, ``observe``)."""
    return _part(name, ".kernels")


def device(name: str):
    """The CUDA parts of shape ``name`` (``make_cuda``, ``FLAGS``) for the CUDA time loop."""
    return _part(name, ".device")


def host(name: str):
    """The run-time hooks of shape ``name`` (``SYSTEM``, ``initial_system``, ``writer_fields``, backends)."""
    return _part(name, ".host")


def shape_of(system) -> str:
    """The shape name of a host-side system (its class attribute ``shape``)."""
    return type(system).shape
