"""The ``hertz`` shape (a test plug-in, tests/engine/test_add_shape.py): smooth elastic spheres with a Hertz
normal force instead of the sphere's linear spring and dashpot; its traits.

The pair law (hertz/law.py): F_n = k_n delta sqrt(delta / R_eff) along the line of centres, R_eff = r_i r_j /
(r_i + r_j), no dashpot and no tangential force, so the total energy (kinetic + (2/5) k_n delta^(5/2) /
sqrt(R_eff) per contact) is conserved. Plain Python, no engine imports (the spec and the scales read it).
"""

from __future__ import annotations

#: the spec's shape value
NAME = "hertz"
#: what the spec's shape field documents
SUMMARY = "smooth elastic spheres with a Hertz normal force (test plug-in)"
#: accepts elongation != 1
ELONGATED = False
#: accepts a size distribution (spec ``species``)
SPECIES = False
#: runs precision "mixed"
MIXED = False
#: a null ``start`` may be the sphere's random sequential addition (engine/setup/start_kind.py)
RANDOM_START = True
#: a null verlet_skin follows the sphere's volume-fraction rule
SKIN_BY_VOLUME_FRACTION = True
#: moment of inertia of a solid sphere in units of m a^2
Q_SPHERE = 0.4


def body(r_eq: float, elongation: float, mass: float) -> tuple:
    """(semi-axes (m), principal moments (kg m^2)) of a solid sphere of radius r_eq and this mass."""
    return (r_eq, r_eq, r_eq), (Q_SPHERE * mass * r_eq**2,) * 3


def spec_error(spec) -> str | None:
    """Why a Hertz sphere cannot run this (validated) spec, or None: its law has no dashpot and no tangential
    force, so only e_n = 1, e_t = -1 (smooth) and no friction."""
    if spec.e_n != 1.0:
        return f"e_n = {spec.e_n} but shape 'hertz' is elastic: set e_n to 1"
    if spec.e_t != -1.0:
        return f"e_t = {spec.e_t} but shape 'hertz' is smooth: set e_t to -1"
    if spec.friction is not None:
        return f"friction = {spec.friction} but shape 'hertz' has no tangential force: set friction to null"
    return None
