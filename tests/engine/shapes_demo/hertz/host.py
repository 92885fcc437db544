"""The ``hertz`` shape's run-time hooks: its system type, the start of a spec (the sphere's), the result
file's fields (the sphere's) and its backend classes."""

from __future__ import annotations

import dataclasses
from typing import ClassVar

from engine.loops.system import SphereSystem
from engine.shapes.sphere import host as sphere


@dataclasses.dataclass
class HertzSystem(SphereSystem):
    """Host-side state of N Hertz spheres (the sphere's fields)."""

    shape: ClassVar[str] = "hertz"


SYSTEM = HertzSystem


def initial_system(spec, p, on_device: bool = False) -> HertzSystem:
    """The sphere's start of the spec, drawn on the host (``on_device`` is the sphere's large GPU start, which
    engine.setup.start_kind.device_start grants spheres only)."""
    s = sphere.initial_system(spec, p)
    return HertzSystem(**{f.name: getattr(s, f.name) for f in dataclasses.fields(s)})


writer_fields = sphere.writer_fields


def cpu_backend():
    from tests.engine.shapes_demo.hertz.cpu_backend import CpuHertzBackend

    return CpuHertzBackend


def cuda_ensemble():
    from tests.engine.shapes_demo.hertz.cuda_backend import CudaHertzEnsemble

    return CudaHertzEnsemble


def cuda_backend():
    from tests.engine.shapes_demo.hertz.cuda_backend import CudaHertzBackend

    return CudaHertzBackend
