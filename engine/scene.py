"""Initial states: homogeneous non-overlapping placement and Maxwellian velocities (paper 001 protocol).

Placement: the sites of an fcc lattice with at least N sites fill the box; N of them are chosen at
random and each particle is displaced at random inside the free room around its site (at most half
the gap to its nearest neighbour), so no two particles overlap at any volume fraction the lattice can
hold (up to ~0.5 for awkward N, 0.74 at best) and the start is homogeneous. Dilute starts lose the
lattice memory within a few collisions of the thermalisation phase.
"""

from __future__ import annotations

import math

import numpy as np

from engine.backends.base import EllipsoidSystem, SphereSystem
from engine.errors import SpecError
from engine.params import Derived


def fcc_sites(n: int, box: float) -> tuple[np.ndarray, float]:
    """At least n fcc sites in a cube of edge box, and their nearest-neighbour distance."""
    m = max(1, math.ceil((n / 4.0) ** (1.0 / 3.0) - 1e-9))
    a = box / m
    base = np.array([[0, 0, 0], [0.5, 0.5, 0], [0.5, 0, 0.5], [0, 0.5, 0.5]]) * a
    g = np.arange(m) * a
    cells = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 1, 3)
    sites = (cells + base[None, :, :]).reshape(-1, 3) + 0.25 * a
    return sites, a / math.sqrt(2.0)


def place_spheres(n: int, box: float, radius: float, rng: np.random.Generator) -> np.ndarray:
    """N non-overlapping sphere centres in [0, box)^3 (see module docstring)."""
    sites, nn_dist = fcc_sites(n, box)
    gap = nn_dist - 2.0 * radius
    if gap <= 0:
        phi = n * 4.0 / 3.0 * math.pi * radius**3 / box**3
        raise SpecError(
            f"volume_fraction = {phi:.4g}: {n} spheres of radius {radius:.4g} m do not fit on the "
            f"{len(sites)}-site fcc start lattice of a {box:g} m box; lower volume_fraction "
            f"(or choose n_particles = 4 m^3 for a full lattice)")
    chosen = rng.choice(len(sites), size=n, replace=False)
    pos = sites[np.sort(chosen)]
    # random displacement in a ball of radius gap/2 keeps every pair at least 2a apart
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    r = 0.5 * gap * rng.random(n) ** (1.0 / 3.0) * (1.0 - 1e-9)
    pos = pos + u * r[:, None]
    return np.mod(pos, box)


def maxwellian(n: int, rms: float, rng: np.random.Generator) -> np.ndarray:
    """Gaussian velocities with zero mean and sqrt(<|v|^2>) = rms exactly."""
    v = rng.normal(size=(n, 3))
    if n > 1:
        v -= v.mean(axis=0)
    norm = math.sqrt(np.mean(np.sum(v * v, axis=1)))
    return v * (rms / norm) if norm > 0 else v


def random_quaternions(n: int, rng: np.random.Generator) -> np.ndarray:
    """Uniformly random unit quaternions (w, x, y, z)."""
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def initial_spheres(spec, p: Derived) -> SphereSystem:
    """The starting state of a sphere spec: placed, Maxwellian, spins at equal temperature."""
    rng = np.random.default_rng(spec.seed)
    n = spec.n_particles
    pos = place_spheres(n, spec.box_length, p.radius, rng)
    vel = maxwellian(n, spec.velocity_rms, rng)
    # equal rotational and translational temperature: I <w^2> = m <v^2>
    w_rms = spec.velocity_rms * math.sqrt(p.mass / p.inertia[0])
    omega = maxwellian(n, w_rms, rng)
    quat = random_quaternions(n, rng)
    return SphereSystem(
        box_length=spec.box_length, position=pos, velocity=vel, angular_velocity=omega, orientation=quat,
        radius=np.full(n, p.radius), mass=np.full(n, p.mass), inertia=np.full(n, p.inertia[0]))


def initial_ellipsoids(spec, p: Derived) -> EllipsoidSystem:
    """Start of an ellipsoid spec (paper 003 §4): bounding spheres (radius a) placed without overlap,
    uniformly random orientations, Maxwellian velocities, and spins about the two axes perpendicular to
    the symmetry axis at the translational temperature per degree of freedom (no spin about the axis,
    which frictionless contacts can neither create nor use: paper 003 sets omega_y(0) = 0)."""
    rng = np.random.default_rng(spec.seed)
    n = spec.n_particles
    a = p.semi_axes[0]
    try:
        pos = place_spheres(n, spec.box_length, a, rng)
    except SpecError as exc:
        raise SpecError(f"{exc} (ellipsoids are placed by their bounding spheres of radius a = {a:.4g} m, "
                        f"elongation = {spec.elongation:g})") from None
    vel = maxwellian(n, spec.velocity_rms, rng)
    quat = random_quaternions(n, rng)
    i_perp = p.inertia[1]
    # T per dof = m <v^2>/3 = I_perp <w_k^2> for each perpendicular body axis k
    w_b = rng.normal(size=(n, 2))
    w_b -= w_b.mean(axis=0) if n > 1 else 0.0
    w_b *= spec.velocity_rms * math.sqrt(p.mass / (3.0 * i_perp)) / math.sqrt(np.mean(w_b * w_b))
    w, x, y, z = quat.T
    e2 = np.stack([2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)], 1)
    e3 = np.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], 1)
    omega = w_b[:, :1] * e2 + w_b[:, 1:] * e3
    return EllipsoidSystem(
        box_length=spec.box_length, position=pos, velocity=vel, angular_velocity=omega, orientation=quat,
        semi_axes=np.tile(np.asarray(p.semi_axes, float), (n, 1)), mass=np.full(n, p.mass),
        inertia=np.tile(np.asarray(p.inertia, float), (n, 1)))
