"""Initial states: homogeneous non-overlapping placement and Maxwellian velocities (paper 001 protocol).

Placement (one size): the sites of an fcc lattice with at least N sites fill the box; N of them are chosen at
random and each particle is displaced at random inside the free room around its site (at most half
the gap to its nearest neighbour), so no two particles overlap at any volume fraction the lattice can
hold (up to ~0.5 for awkward N, 0.74 at best) and the start is homogeneous. Dilute starts lose the
lattice memory within a few collisions of the thermalisation phase.

Placement (species, issue 7): random sequential addition (RSA), the largest species first: uniform
random candidate centres (numpy Generator from the seed, in batches) are accepted when they overlap no
sphere placed so far (centre distance >= (R_i + R_j)(1 + 1e-9)), checked on one linked-cell grid per
species (cells >= 2 R_s, so the 27 neighbour cells hold every possible overlap of a candidate no larger
than R_s); compiled with Numba and deterministic from the seed. RSA jams (monodisperse near phi = 0.38)
and slows long before, so species specs are limited to volume_fraction <= SPECIES_MAX_VOLUME_FRACTION
(engine/spec.py). Ids are then shuffled, so the species are interleaved in id order. Velocities: every
species at the same temperature T0 = <m> v_rms^2 / 3 (equipartition), Gaussian per particle with
variance T0/m_i per component, zero total momentum; spins with variance T0/I_i, zero total spin.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from engine.backends.base import EllipsoidSystem, SphereSystem
from engine.errors import SpecError
from engine.params import Derived, species_table


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


#: Relative gap RSA keeps between accepted spheres: rounding can never make a start overlap.
RSA_GAP = 1.0e-9


@numba.njit(cache=True)
def _rsa_batch(cand, r_new, s_new, target, pos, n_placed, sp_radius, sp_nc, sp_off, head, nxt, box):
    """Try the candidate centres in order for a sphere of radius r_new (species slot s_new) until
    ``target`` spheres are placed; returns (candidates used, spheres placed). Slots 0..s_new hold the
    grids of the species placed so far (larger or equal radius)."""
    inv_box = 1.0 / box
    used = 0
    for c in range(cand.shape[0]):
        if n_placed >= target:
            break
        used += 1
        x = cand[c, 0]
        y = cand[c, 1]
        z = cand[c, 2]
        ok = True
        for s in range(s_new + 1):
            nc = sp_nc[s]
            if nc == 0:
                continue
            inv_cell = nc * inv_box
            cx = min(int(x * inv_cell), nc - 1)
            cy = min(int(y * inv_cell), nc - 1)
            cz = min(int(z * inv_cell), nc - 1)
            lo = -1 if nc >= 3 else 0
            hi = 2 if nc >= 2 else 1
            rr = (r_new + sp_radius[s]) * (1.0 + RSA_GAP)
            rr2 = rr * rr
            for ox in range(lo, hi):
                ax = (cx + ox + nc) % nc
                for oy in range(lo, hi):
                    ay = (cy + oy + nc) % nc
                    for oz in range(lo, hi):
                        az = (cz + oz + nc) % nc
                        j = head[sp_off[s] + (ax * nc + ay) * nc + az]
                        while j >= 0:
                            dx = x - pos[j, 0]
                            dy = y - pos[j, 1]
                            dz = z - pos[j, 2]
                            dx -= box * math.floor(dx * inv_box + 0.5)
                            dy -= box * math.floor(dy * inv_box + 0.5)
                            dz -= box * math.floor(dz * inv_box + 0.5)
                            if dx * dx + dy * dy + dz * dz < rr2:
                                ok = False
                                break
                            j = nxt[j]
                        if not ok:
                            break
                    if not ok:
                        break
                if not ok:
                    break
            if not ok:
                break
        if ok:
            pos[n_placed, 0] = x
            pos[n_placed, 1] = y
            pos[n_placed, 2] = z
            nc = sp_nc[s_new]
            inv_cell = nc * inv_box
            cx = min(int(x * inv_cell), nc - 1)
            cy = min(int(y * inv_cell), nc - 1)
            cz = min(int(z * inv_cell), nc - 1)
            cell = sp_off[s_new] + (cx * nc + cy) * nc + cz
            nxt[n_placed] = head[cell]
            head[cell] = n_placed
            n_placed += 1
    return used, n_placed


def place_species(counts, radii, box: float, rng: np.random.Generator, max_tries: float = 100.0):
    """Random sequential addition of sum(counts) spheres, the largest species first (module docstring).

    counts, radii: per species (m); returns (positions (N,3) in [0, box), species index (N,) int32),
    in placement order (largest species first). Raises SpecError naming volume_fraction when a species
    cannot be placed within max_tries x N + 10^5 candidates.
    """
    counts = [int(c) for c in counts]
    radii = [float(r) for r in radii]
    n = sum(counts)
    order = sorted(range(len(radii)), key=lambda k: (-radii[k], k))
    sp_nc = np.zeros(len(order), np.int64)
    for slot, k in enumerate(order):
        nc = max(1, int(box / (2.0 * radii[k] * (1.0 + 1e-9))))
        while nc > 1 and nc**3 > max(8, 8 * counts[k]):
            nc -= 1
        sp_nc[slot] = nc
    sp_off = np.zeros(len(order) + 1, np.int64)
    sp_off[1:] = np.cumsum(sp_nc**3)
    head = np.full(int(sp_off[-1]), -1, np.int64)
    nxt = np.full(n, -1, np.int64)
    pos = np.zeros((n, 3))
    species = np.zeros(n, np.int32)
    sp_radius = np.array([radii[k] for k in order])
    budget = int(max_tries * n) + 100_000
    placed = 0
    for slot, k in enumerate(order):
        target = placed + counts[k]
        species[placed:target] = k
        while placed < target:
            if budget <= 0:
                phi = sum(c * 4.0 / 3.0 * math.pi * r**3 for c, r in zip(counts, radii)) / box**3
                raise SpecError(
                    f"volume_fraction = {phi:.4g}: random sequential placement found room for only {placed} of "
                    f"{n} spheres ({target - placed} of species {k}, radius {radii[k]:.4g} m, missing) after "
                    f"{int(max_tries * n) + 100_000} tries; lower volume_fraction")
            batch = min(budget, max(4096, 4 * (target - placed)))
            cand = rng.random((batch, 3)) * box
            used, placed = _rsa_batch(cand, radii[k], slot, target, pos, placed, sp_radius, sp_nc, sp_off,
                                      head, nxt, float(box))
            budget -= used
    return np.mod(pos, box), species


def _thermal(rng: np.random.Generator, inertia_like: np.ndarray, t0: float) -> np.ndarray:
    """Gaussian vectors with variance t0/inertia_like per component, zero weighted mean and exactly
    sum_i inertia_like_i |v_i|^2 = 3 N t0 (equipartition at temperature t0, J)."""
    n = inertia_like.shape[0]
    v = rng.normal(size=(n, 3)) * np.sqrt(t0 / inertia_like)[:, None]
    if n > 1:
        v -= (inertia_like[:, None] * v).sum(axis=0) / inertia_like.sum()
    e2 = float(np.sum(inertia_like[:, None] * v * v))
    return v * math.sqrt(3.0 * n * t0 / e2) if e2 > 0 else v


def initial_species(spec, p: Derived) -> SphereSystem:
    """The starting state of a species spec (module docstring): RSA placement, shuffled ids, every species
    at T0 = <m> v_rms^2 / 3 in translation and rotation."""
    sp = species_table(spec)
    rng = np.random.default_rng(spec.seed)
    pos, species = place_species(sp.count, sp.radius, spec.box_length, rng)
    perm = rng.permutation(spec.n_particles)
    pos, species = pos[perm], species[perm]
    radius = np.asarray(sp.radius)[species]
    mass = np.asarray(sp.mass)[species]
    inertia = np.asarray(sp.inertia)[species]
    vel = _thermal(rng, mass, p.temperature0)
    omega = _thermal(rng, inertia, p.temperature0)
    quat = random_quaternions(spec.n_particles, rng)
    return SphereSystem(box_length=spec.box_length, position=pos, velocity=vel, angular_velocity=omega,
                        orientation=quat, radius=radius, mass=mass, inertia=inertia)


def species_index(radius: np.ndarray, p: Derived) -> np.ndarray:
    """int32 species index of every particle (its position in the spec's species list), from its radius;
    zeros for a monodisperse spec (species radii are distinct, engine/spec.py)."""
    radius = np.asarray(radius, np.float64)
    table = np.asarray(p.species_radius, np.float64)
    if table.size <= 1:
        return np.zeros(radius.shape[0], np.int32)
    order = np.argsort(table)
    k = np.clip(np.searchsorted(table[order], radius), 0, table.size - 1)
    lo = np.clip(k - 1, 0, table.size - 1)
    pick = np.where(np.abs(table[order][lo] - radius) < np.abs(table[order][k] - radius), lo, k)
    return order[pick].astype(np.int32)


def initial_spheres(spec, p: Derived) -> SphereSystem:
    """The starting state of a sphere spec: placed, Maxwellian, spins at equal temperature."""
    if species_table(spec) is not None:
        return initial_species(spec, p)
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
