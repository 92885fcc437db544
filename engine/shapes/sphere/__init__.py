"""The sphere plug-in (Hidalgo et al. 2013: rough spheres with tangential springs, Coulomb friction, species): traits.

What the spec and the scales ask of a shape, in plain Python (no engine imports: engine/setup/spec.py and
engine/setup/scales.py import this). The time-loop parts are kernels.py (CPU) and device.py (CUDA), the run-time
hooks host.py; engine/shapes/__init__.py describes the plug-in interface.
"""

from __future__ import annotations

#: what the spec's shape field documents
SUMMARY = "rough spheres, Hidalgo et al. (2013)"
NAME = "sphere"
#: accepts elongation != 1
ELONGATED = False
#: accepts a size distribution (spec ``species``)
SPECIES = True
#: runs precision "mixed": positions in float64, the rest in float32 (engine/setup/precision.py)
MIXED = True
#: a null ``start`` may place it by random sequential addition (engine/setup/start_kind.py: cheap for small, dilute,
#: one-size scenes of spheres)
RANDOM_START = True
#: a null verlet_skin follows the volume-fraction rule of engine.setup.params.default_verlet_skin (else its CPU value)
SKIN_BY_VOLUME_FRACTION = True
#: moment of inertia of a solid sphere in units of m a^2
Q_SPHERE = 0.4


def body(r_eq: float, elongation: float, mass: float) -> tuple:
    """(semi-axes (m), principal moments (kg m^2)) of a solid sphere of radius r_eq and this mass."""
    return (r_eq, r_eq, r_eq), (Q_SPHERE * mass * r_eq**2,) * 3


def spec_error(spec) -> str | None:
    """Why a sphere cannot run this (validated) spec, or None: every contact model is available."""
    return None
