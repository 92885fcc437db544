"""Particle sizes, masses and the contact time scale of a spec's fields: what engine.setup.spec's own checks need.

Owns the first half of the derivation (engine.setup.params.derive does the rest from it): the radius from N, phi
and L, the semi-axes and principal moments (the shape's ``body``: engine/shapes/), the species table of a polydisperse
spec, the reduced mass and contact time of the shortest contact, the time step and the initial temperature (rules in the
docstring of engine/setup/params.py). It reads the spec's fields only (a SimulationSpec or anything with its fields) and
imports no other engine module but the shapes' traits, so engine/setup/spec.py can validate without importing
engine/setup/params.py.
SI units: m, kg, kg m^2, s, J.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

from engine.shapes import traits
from engine.shapes.sphere import Q_SPHERE  # noqa: F401  (I = q m a^2 of a solid sphere; re-exported by params)


def radius_from_volume_fraction(n: int, phi: float, box_length: float) -> float:
    """Radius in m of N equal spheres that fill a fraction phi of a cube of edge L."""
    return (3.0 * phi * box_length**3 / (4.0 * math.pi * n)) ** (1.0 / 3.0)


def species_counts(n: int, fractions) -> tuple:
    """Particles per species: round(N f_k), the remainder to the largest fraction (first of equals).

    Raises ValueError naming ``species[k].number_fraction`` when a species would hold no particle.
    """
    counts = [int(math.floor(n * f + 0.5)) for f in fractions]
    big = max(range(len(fractions)), key=lambda k: (fractions[k], -k))
    counts[big] += n - sum(counts)
    for k, c in enumerate(counts):
        if c < 1:
            raise ValueError(
                f"species[{k}].number_fraction = {fractions[k]:g} gives {c} of n_particles = {n} particles: "
                f"every species needs at least one particle; raise n_particles or the fraction")
    return tuple(counts)


@dataclass(frozen=True)
class SpeciesTable:
    """Per-species radius (m), count, mass (kg) and inertia (kg m^2), in the spec's species order."""

    radius: tuple
    count: tuple
    mass: tuple
    inertia: tuple


def species_table(spec):
    """The :class:`SpeciesTable` of a sphere spec with two or more species, else None.

    A one-entry species list is the monodisperse scene and goes the monodisperse way (bit-identical).
    """
    sp = getattr(spec, "species", None)
    if sp is None or len(sp) < 2 or not traits(spec.shape).SPECIES:
        return None
    ratios = [float(s.radius_ratio) for s in sp]
    counts = species_counts(spec.n_particles, [float(s.number_fraction) for s in sp])
    unit = sum(c * r**3 for c, r in zip(counts, ratios))
    r_max = (3.0 * spec.volume_fraction * spec.box_length**3 / (4.0 * math.pi * unit)) ** (1.0 / 3.0)
    radius = tuple(r * r_max for r in ratios)
    mass = tuple(spec.density * (4.0 / 3.0 * math.pi * r**3) for r in radius)
    inertia = tuple(Q_SPHERE * m * r**2 for m, r in zip(mass, radius))
    return SpeciesTable(radius=radius, count=counts, mass=mass, inertia=inertia)


@dataclass(frozen=True)
class Scales:
    """The size, mass and time scales of a spec (SI units); see :class:`engine.setup.params.Derived` for the meaning."""

    species: Optional[SpeciesTable]   # None: one size
    radius: float          # sphere radius, or volume-equivalent radius; species: of the largest species
    semi_axes: tuple       # (a, b, c)
    radius_max: float      # bounding-sphere radius (largest semi-axis)
    radius_min: float      # smallest semi-axis; species: the smallest radius
    mass: float            # kg
    inertia: tuple         # principal moments (I_1, I_2, I_3), kg m^2
    m12: float             # reduced mass of the shortest contact (equal pair; species: smallest pair), kg
    mass_mean: float       # number mean <m>, kg
    k_n: float             # N/m
    omega0: float          # sqrt(k_n/m12), 1/s
    contact_time: float    # t_c = pi/omega0, s
    dt: float              # the spec's dt or t_c/50, s
    temperature0: float    # <m> v_rms^2 / 3, J


def scales(spec) -> Scales:
    """The :class:`Scales` of a spec; raises ValueError naming ``species[k].number_fraction`` when a species
    would hold no particle (:func:`species_counts`)."""
    n, L, phi = spec.n_particles, spec.box_length, spec.volume_fraction
    sp = species_table(spec)          # None: one size
    # one size: the (volume-equivalent) radius; species: the radius of the largest species
    r_eq = radius_from_volume_fraction(n, phi, L) if sp is None else max(sp.radius)
    volume = 4.0 / 3.0 * math.pi * r_eq**3
    mass = spec.density * volume
    xi = spec.elongation
    semi, inertia = traits(spec.shape).body(r_eq, xi, mass)
    # reduced mass of an equal pair; species: of the smallest pair, which has the shortest contact
    m12 = 0.5 * mass if sp is None else 0.5 * min(sp.mass)
    mass_mean = mass if sp is None else sum(c * m for c, m in zip(sp.count, sp.mass)) / n
    k_n = spec.stiffness
    omega0 = math.sqrt(k_n / m12)
    t_c = math.pi / omega0
    dt = spec.dt if spec.dt is not None else t_c / 50.0
    t0 = mass_mean * spec.velocity_rms**2 / 3.0      # species: equipartition, T0 = <m> v_rms^2 / 3
    return Scales(species=sp, radius=r_eq, semi_axes=semi, radius_max=max(semi),
                  radius_min=min(semi) if sp is None else min(sp.radius), mass=mass, inertia=inertia, m12=m12,
                  mass_mean=mass_mean, k_n=k_n, omega0=omega0, contact_time=t_c, dt=dt, temperature0=t0)
