"""The spheroid plug-in (Rubio-Largo et al. 2015: prolate ellipsoids; frictionless, or rough with the
tangential law of Hidalgo et al. (2013) at the contact point): traits.

What the spec and the scales ask of a shape, in plain Python (no engine imports: engine/setup/spec.py and
engine/setup/scales.py import this). The time-loop parts are kernels.py (CPU) and device.py (CUDA), the run-time
hooks host.py, the host classes cpu_backend.py and cuda_backend.py; engine/shapes/__init__.py describes the
plug-in interface.
"""

from __future__ import annotations

#: what the spec's shape field documents
SUMMARY = "prolate spheroid, Rubio-Largo et al. (2015); rough or frictionless contacts"
NAME = "ellipsoid"
#: accepts elongation != 1 (the aspect ratio xi = a/b of the prolate spheroid)
ELONGATED = True
#: accepts a size distribution (spec ``species``)
SPECIES = False
#: runs precision "mixed": the contact solver has no mixed-precision variant
MIXED = False
#: a null ``start`` places it by random sequential addition of the spheroids themselves where their bounding spheres'
#: volume fraction phi xi^2 allows (engine/setup/start_kind.py, engine/setup/cell_rsa.py), else on the lattice
RANDOM_START = True
#: a null verlet_skin is the CPU default (the skin rule over phi was measured for spheres only)
SKIN_BY_VOLUME_FRACTION = False


def body(r_eq: float, elongation: float, mass: float) -> tuple:
    """(semi-axes (a, b, b) (m), principal moments (kg m^2)) of a solid prolate spheroid with a/b = elongation
    and a b^2 = r_eq^3 (Table 1 of Rubio-Largo et al. 2015 keeps the volume of the sphere of radius r_eq)."""
    b = r_eq / elongation ** (1.0 / 3.0)
    a = elongation * b
    i_perp = mass * (a * a + b * b) / 5.0
    return (a, b, b), (2.0 * mass * b * b / 5.0, i_perp, i_perp)


def spec_error(spec) -> str | None:
    """Why a spheroid cannot run this (validated) spec, or None: frictionless (e_t = -1, Rubio-Largo et al. 2015) and
    rough contacts (any e_t, friction; the tangential law of Hidalgo et al. (2013) at the contact point) both run."""
    return None
