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

Large starts (N >= PARALLEL_START_MIN, one size; issue 14): the same protocol, drawn in parallel (Numba
prange) from a counter-based generator (SplitMix64 of seed, stream, particle and draw index; normals by
Box-Muller), so the start is the same whatever the thread count, and sums (mean momentum, energy) are taken
in fixed blocks. These starts differ from the sequential NumPy draws of smaller N (``start_generator``
says which one a spec gets; the result's /parameters@start_generator records it).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from engine.jitcache import fast_loads  # before any cache=True kernel: keys the disk cache by source
from engine.backends.base import EllipsoidSystem, SphereSystem
from engine.cells import cell_coords, cell_index_of, neighbour_cell, neighbour_cell_count
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


def lattice_gap(n: int, box: float, radius: float, n_sites: int, nn_dist: float) -> float:
    """The free gap between neighbouring spheres on the fcc start lattice; SpecError naming volume_fraction
    when the spheres do not fit."""
    gap = nn_dist - 2.0 * radius
    if gap <= 0:
        phi = n * 4.0 / 3.0 * math.pi * radius**3 / box**3
        raise SpecError(
            f"volume_fraction = {phi:.4g}: {n} spheres of radius {radius:.4g} m do not fit on the "
            f"{n_sites}-site fcc start lattice of a {box:g} m box; lower volume_fraction "
            f"(or choose n_particles = 4 m^3 for a full lattice)")
    return gap


def place_spheres(n: int, box: float, radius: float, rng: np.random.Generator) -> np.ndarray:
    """N non-overlapping sphere centres in [0, box)^3 (see module docstring)."""
    sites, nn_dist = fcc_sites(n, box)
    gap = lattice_gap(n, box, radius, len(sites), nn_dist)
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
            cx, cy, cz = cell_coords(x, y, z, inv_cell, nc)
            rr = (r_new + sp_radius[s]) * (1.0 + RSA_GAP)
            rr2 = rr * rr
            for k in range(neighbour_cell_count(nc)):
                j = head[sp_off[s] + neighbour_cell(cx, cy, cz, k, nc)]
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
        if ok:
            pos[n_placed, 0] = x
            pos[n_placed, 1] = y
            pos[n_placed, 2] = z
            nc = sp_nc[s_new]
            inv_cell = nc * inv_box
            cell = sp_off[s_new] + cell_index_of(x, y, z, inv_cell, nc)
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
    n = spec.n_particles
    w_rms = spec.velocity_rms * math.sqrt(p.mass / p.inertia[0])
    if start_generator(spec) == PARALLEL_GENERATOR:
        pos = _parallel_place(n, spec.box_length, p.radius, spec.seed)
        vel = _parallel_maxwellian(n, spec.velocity_rms, spec.seed, STREAM_VELOCITY, 3)
        omega = _parallel_maxwellian(n, w_rms, spec.seed, STREAM_SPIN, 3)
        quat = _parallel_quaternions(n, spec.seed)
        return SphereSystem(
            box_length=spec.box_length, position=pos, velocity=vel, angular_velocity=omega, orientation=quat,
            radius=np.full(n, p.radius), mass=np.full(n, p.mass), inertia=np.full(n, p.inertia[0]))
    rng = np.random.default_rng(spec.seed)
    pos = place_spheres(n, spec.box_length, p.radius, rng)
    vel = maxwellian(n, spec.velocity_rms, rng)
    # equal rotational and translational temperature: I <w^2> = m <v^2>
    omega = maxwellian(n, w_rms, rng)
    quat = random_quaternions(n, rng)
    return SphereSystem(
        box_length=spec.box_length, position=pos, velocity=vel, angular_velocity=omega, orientation=quat,
        radius=np.full(n, p.radius), mass=np.full(n, p.mass), inertia=np.full(n, p.inertia[0]))


def initial_ellipsoids(spec, p: Derived) -> EllipsoidSystem:
    """Start of an ellipsoid spec (paper 003 §4): bounding spheres (radius a) placed without overlap,
    uniformly random orientations, Maxwellian velocities, and spins about the two axes perpendicular to
    the symmetry axis at the translational temperature per degree of freedom; no spin about the axis when
    the contacts are frictionless (they can neither create nor use it: paper 003 sets omega_y(0) = 0), a
    thermal one when they are rough (issue 17: all three rotational dof exchange energy)."""
    n = spec.n_particles
    a = p.semi_axes[0]
    parallel = start_generator(spec) == PARALLEL_GENERATOR
    rng = None if parallel else np.random.default_rng(spec.seed)
    try:
        pos = _parallel_place(n, spec.box_length, a, spec.seed) if parallel else \
            place_spheres(n, spec.box_length, a, rng)
    except SpecError as exc:
        raise SpecError(f"{exc} (ellipsoids are placed by their bounding spheres of radius a = {a:.4g} m, "
                        f"elongation = {spec.elongation:g})") from None
    i_perp = p.inertia[1]
    # T per dof = m <v^2>/3 = I_perp <w_k^2> for each perpendicular body axis k
    w_rms = spec.velocity_rms * math.sqrt(p.mass / (3.0 * i_perp))
    if parallel:
        vel = _parallel_maxwellian(n, spec.velocity_rms, spec.seed, STREAM_VELOCITY, 3)
        quat = _parallel_quaternions(n, spec.seed)
        w_b = _parallel_maxwellian(n, w_rms * math.sqrt(2.0), spec.seed, STREAM_SPIN, 2)
    else:
        vel = maxwellian(n, spec.velocity_rms, rng)
        quat = random_quaternions(n, rng)
        w_b = rng.normal(size=(n, 2))
        w_b -= w_b.mean(axis=0) if n > 1 else 0.0
        w_b *= w_rms / math.sqrt(np.mean(w_b * w_b))
    w, x, y, z = quat.T
    e2 = np.stack([2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)], 1)
    e3 = np.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], 1)
    omega = w_b[:, :1] * e2 + w_b[:, 1:] * e3
    if not spec.smooth:
        # rough contacts exchange spin about the symmetry axis too: that dof starts thermal as well
        # (drawn after the others, from its own stream, so a smooth start is unchanged)
        w1_rms = spec.velocity_rms * math.sqrt(p.mass / (3.0 * p.inertia[0]))
        if parallel:
            w_a = _parallel_maxwellian(n, w1_rms, spec.seed, STREAM_SPIN_AXIS, 1)
        else:
            w_a = rng.normal(size=(n, 1))
            w_a -= w_a.mean(axis=0) if n > 1 else 0.0
            w_a *= w1_rms / math.sqrt(np.mean(w_a * w_a))
        e1 = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)], 1)
        omega = omega + w_a * e1
    return EllipsoidSystem(
        box_length=spec.box_length, position=pos, velocity=vel, angular_velocity=omega, orientation=quat,
        semi_axes=np.tile(np.asarray(p.semi_axes, float), (n, 1)), mass=np.full(n, p.mass),
        inertia=np.tile(np.asarray(p.inertia, float), (n, 1)))


# ---- large starts in parallel (issue 14) --------------------------------------------------------------

#: one-size starts of at least this many particles are drawn in parallel (module docstring)
PARALLEL_START_MIN = 1 << 20
SEQUENTIAL_GENERATOR = "numpy-pcg64"
PARALLEL_GENERATOR = "splitmix64-counter"
STREAM_SITES, STREAM_DISPLACEMENT, STREAM_VELOCITY, STREAM_SPIN, STREAM_QUATERNION, STREAM_SPIN_AXIS = range(6)
_DRAWS = 8           # counter values reserved per particle and stream
_BLOCK = 1 << 14     # particles per block of the deterministic sums

_U = np.uint64
_GOLDEN = _U(0x9E3779B97F4A7C15)
_M1 = _U(0xBF58476D1CE4E5B9)
_M2 = _U(0x94D049BB133111EB)


def start_generator(spec) -> str:
    """Which generator draws a spec's start: the sequential NumPy one, or the parallel counter-based one
    for one-size starts of N >= PARALLEL_START_MIN (species starts are always sequential: RSA)."""
    if species_table(spec) is None and spec.n_particles >= PARALLEL_START_MIN:
        return PARALLEL_GENERATOR
    return SEQUENTIAL_GENERATOR


@numba.njit(cache=True, inline="always")
def _mix64(x):
    """SplitMix64's finaliser (a bijection of uint64 with full avalanche)."""
    x = (x ^ (x >> _U(30))) * _M1
    x = (x ^ (x >> _U(27))) * _M2
    return x ^ (x >> _U(31))


@numba.njit(cache=True, inline="always")
def _bits(key, i, k):
    return _mix64(key + (_U(i) * _U(_DRAWS) + _U(k)) * _GOLDEN)


@numba.njit(cache=True, inline="always")
def _uniform(key, i, k):
    """A uniform double in (0, 1), draw k of particle i in the stream of ``key``."""
    return ((_bits(key, i, k) >> _U(11)) + 0.5) * (1.0 / 9007199254740992.0)


@numba.njit(cache=True, inline="always")
def _normal_pair(key, i, k):
    """Two independent standard normals (Box-Muller) from draws k, k + 1 of particle i."""
    r = math.sqrt(-2.0 * math.log(_uniform(key, i, k)))
    t = 2.0 * math.pi * _uniform(key, i, k + 1)
    return r * math.cos(t), r * math.sin(t)


@numba.njit(cache=True)
def _key(seed, stream):
    return _mix64(seed * _GOLDEN + _U(stream + 1))


def _stream_key(seed: int, stream: int) -> np.uint64:
    """The 64-bit key of one random stream of a seed (a compiled call: the inlined mixer is not cached)."""
    return _U(_key(_U(seed % (1 << 64)), stream))


@numba.njit(cache=True, parallel=True, nogil=True)  # nogil: engine/startup.py's thread works meanwhile
def _site_keys(key, n_sites):
    out = np.empty(n_sites, np.uint64)
    for j in numba.prange(n_sites):
        out[j] = _bits(key, j, 0)
    return out


@numba.njit(cache=True, parallel=True, nogil=True)  # nogil: engine/startup.py's thread works meanwhile
def _place_on_sites(chosen, m, a, key, half_gap, box):
    """Centres at the chosen fcc sites (as fcc_sites numbers them), each displaced uniformly in a ball of
    radius half_gap (direction from three normals, radius from a uniform), wrapped into [0, box)."""
    base = np.array([[0.0, 0.0, 0.0], [0.5, 0.5, 0.0], [0.5, 0.0, 0.5], [0.0, 0.5, 0.5]]) * a
    n = chosen.shape[0]
    pos = np.empty((n, 3))
    for i in numba.prange(n):
        j = chosen[i]
        c = j // 4
        b = j - 4 * c
        ix = c // (m * m)
        iy = (c // m) % m
        iz = c % m
        g0, g1 = _normal_pair(key, i, 0)
        g2, _ = _normal_pair(key, i, 2)
        norm = math.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
        r = half_gap * _uniform(key, i, 4) ** (1.0 / 3.0) * (1.0 - 1e-9) / norm
        x = (ix * a + base[b, 0]) + 0.25 * a + g0 * r
        y = (iy * a + base[b, 1]) + 0.25 * a + g1 * r
        z = (iz * a + base[b, 2]) + 0.25 * a + g2 * r
        pos[i, 0] = x - box * math.floor(x / box)
        pos[i, 1] = y - box * math.floor(y / box)
        pos[i, 2] = z - box * math.floor(z / box)
    return pos


def _parallel_place(n: int, box: float, radius: float, seed: int) -> np.ndarray:
    """place_spheres' protocol (fcc sites, n of them at random, a random displacement in the free room)
    with the counter-based generator: the n sites of smallest 64-bit key are chosen."""
    m = max(1, math.ceil((n / 4.0) ** (1.0 / 3.0) - 1e-9))
    a = box / m
    n_sites = 4 * m ** 3
    gap = lattice_gap(n, box, radius, n_sites, a / math.sqrt(2.0))
    if n == n_sites:
        chosen = np.arange(n, dtype=np.int64)
    else:
        keys = _site_keys(_stream_key(seed, STREAM_SITES), n_sites)
        chosen = np.sort(np.argpartition(keys, n - 1)[:n]).astype(np.int64)
    return _place_on_sites(chosen, m, a, _stream_key(seed, STREAM_DISPLACEMENT), 0.5 * gap, float(box))


@numba.njit(cache=True, parallel=True, nogil=True)  # nogil: engine/startup.py's thread works meanwhile
def _normals(key, n, dim):
    out = np.empty((n, dim))
    for i in numba.prange(n):
        for k in range(0, dim, 2):
            g0, g1 = _normal_pair(key, i, k)
            out[i, k] = g0
            if k + 1 < dim:
                out[i, k + 1] = g1
    return out


@numba.njit(cache=True, parallel=True, nogil=True)  # nogil: engine/startup.py's thread works meanwhile
def _block_sums(v, power):
    """Per block of _BLOCK rows, the column sums of v**power (a fixed summation order for any thread count)."""
    n, dim = v.shape
    nb = (n + _BLOCK - 1) // _BLOCK
    out = np.zeros((nb, dim))
    for b in numba.prange(nb):
        for i in range(b * _BLOCK, min(n, (b + 1) * _BLOCK)):
            for d in range(dim):
                out[b, d] += v[i, d] ** power
    return out


@numba.njit(cache=True, parallel=True, nogil=True)  # nogil: engine/startup.py's thread works meanwhile
def _shift_scale(v, shift, scale):
    for i in numba.prange(v.shape[0]):
        for d in range(v.shape[1]):
            v[i, d] = (v[i, d] - shift[d]) * scale


def _parallel_maxwellian(n: int, rms: float, seed: int, stream: int, dim: int) -> np.ndarray:
    """maxwellian() with the counter-based generator: zero mean and sqrt(<|v|^2>) = rms exactly."""
    v = _normals(_stream_key(seed, stream), n, dim)
    mean = _block_sums(v, 1).sum(axis=0) / n if n > 1 else np.zeros(dim)
    _shift_scale(v, mean, 1.0)
    norm = math.sqrt(_block_sums(v, 2).sum() / n)
    _shift_scale(v, np.zeros(dim), rms / norm if norm > 0 else 1.0)
    return v


@numba.njit(cache=True, parallel=True, nogil=True)  # nogil: engine/startup.py's thread works meanwhile
def _normalise_rows(q):
    for i in numba.prange(q.shape[0]):
        s = 0.0
        for d in range(q.shape[1]):
            s += q[i, d] * q[i, d]
        s = math.sqrt(s)
        for d in range(q.shape[1]):
            q[i, d] /= s


def _parallel_quaternions(n: int, seed: int) -> np.ndarray:
    """Uniformly random unit quaternions (w, x, y, z) with the counter-based generator."""
    q = _normals(_stream_key(seed, STREAM_QUATERNION), n, 4)
    _normalise_rows(q)
    return q


fast_loads(globals())  # their disk-cache loads skip numba's target refresh (engine/jitcache.py)
