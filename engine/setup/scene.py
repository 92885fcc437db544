"""Initial states: homogeneous non-overlapping placement and Maxwellian velocities (docs/physics.md §5).

Which placement a spec gets is engine/setup/start_kind.py's ``start_protocol``: "random" (random sequential addition,
below) for species and for one-size spheres where it is cheap, "lattice" (the protocol of Hidalgo et al. (2013))
otherwise.

Placement (one size, "lattice"): the sites of an fcc lattice with at least N sites fill the box; N of them are chosen at
random and each particle is displaced at random inside the free room around its site (at most half
the gap to its nearest neighbour), so no two particles overlap at any volume fraction the lattice can
hold (up to ~0.5 for awkward N, 0.74 at best) and the start is homogeneous. Dilute starts lose the
lattice memory within a few collisions of the thermalisation phase.

Placement ("random", one size or species): random sequential addition (RSA), the largest species first: uniform
random candidate centres (numpy Generator from the seed, in batches) are accepted when they overlap no
sphere placed so far (centre distance >= (R_i + R_j)(1 + 1e-9)), checked on one linked-cell grid per
species (cells >= 2 R_s, so the 27 neighbour cells hold every possible overlap of a candidate no larger
than R_s); compiled with Numba and deterministic from the seed. RSA jams (monodisperse near phi = 0.38)
and slows long before, so species specs are limited to volume_fraction <= SPECIES_MAX_VOLUME_FRACTION
(engine/setup/spec.py). Ids are then shuffled, so the species are interleaved in id order. Velocities: every
species at the same temperature T0 = <m> v_rms^2 / 3 (equipartition), Gaussian per particle with
variance T0/m_i per component, zero total momentum; spins with variance T0/I_i, zero total spin.

Large lattice starts (N >= PARALLEL_START_MIN, one size): the same protocol, drawn in parallel (Numba
prange) from a counter-based generator (SplitMix64 of seed, stream, particle and draw index; normals by
Box-Muller), so the start is the same whatever the thread count, and sums (mean momentum, energy) are taken
in fixed blocks; the N sites are those of smallest 64-bit key (a parallel radix select). These starts differ
from the sequential NumPy draws of smaller N (``start_generator`` says which one a spec gets; the result's
/parameters@start_generator records it). A GPU job draws its large sphere start on the device instead
(:class:`StartDraw`, engine/loops/cuda_start.py): the same draws from the same per-particle functions
(:func:`_site_position`, :func:`_stream_values`) and the same block sums, equal to the host's to rounding.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from engine.numba_support.numba_import import coverage_hidden

with coverage_hidden():
    import numba
import numpy as np

from engine.numba_support.jitcache import fast_loads  # before any cache=True kernel: keys the disk cache by source
from engine.backends.base import EllipsoidSystem, SphereSystem
from engine.neighbours.cells import cell_coords, cell_index_of, neighbour_cell, neighbour_cell_count
from engine.errors import SpecError
from engine.setup.cell_rsa import RSA_GAP, CellRsa, place_random
from engine.setup.counter_rng import _GOLDEN, _M1, _M2, _U, _bits, _normal_pair, _uniform, uniform_quaternion
from engine.setup.params import Derived, species_table
from engine.setup.start_kind import (PARALLEL_GENERATOR, PARALLEL_RSA_GENERATOR, PARALLEL_START_MIN,  # noqa: F401
                                     RANDOM, SEQUENTIAL_GENERATOR, device_start, start_generator, start_protocol)


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




@numba.njit(cache=True, nogil=True)   # nogil: an ensemble places its scenes on several threads
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
    zeros for a monodisperse spec (species radii are distinct, engine/setup/spec.py)."""
    radius = np.asarray(radius, np.float64)
    table = np.asarray(p.species_radius, np.float64)
    if table.size <= 1:
        return np.zeros(radius.shape[0], np.int32)
    order = np.argsort(table)
    k = np.clip(np.searchsorted(table[order], radius), 0, table.size - 1)
    lo = np.clip(k - 1, 0, table.size - 1)
    pick = np.where(np.abs(table[order][lo] - radius) < np.abs(table[order][k] - radius), lo, k)
    return order[pick].astype(np.int32)


def initial_spheres(spec, p: Derived, on_device: bool = False) -> SphereSystem:
    """The starting state of a sphere spec: placed, Maxwellian, spins at equal temperature. ``on_device`` (a GPU job
    for which :func:`device_start` holds, engine/driver/simulate.py): a large start comes as its :class:`StartDraw`
    (``system.draw``, no host arrays), drawn by the GPU backend when it is built."""
    if species_table(spec) is not None:
        return initial_species(spec, p)
    n = spec.n_particles
    w_rms = spec.velocity_rms * math.sqrt(p.mass / p.inertia[0])
    if start_generator(spec) in (PARALLEL_GENERATOR, PARALLEL_RSA_GENERATOR):
        streams, radius = parallel_start_streams(spec, p)
        draw = StartDraw.of(n, spec.seed, streams, spec.box_length, radius, start_protocol(spec))
        if on_device:    # drawn by the GPU job's backend (engine/loops/cuda_start.py)
            # one size: the constants as broadcast views (the backend keeps them per scene; no N-long host arrays)
            return SphereSystem(
                box_length=spec.box_length, position=None, velocity=None, angular_velocity=None, orientation=None,
                radius=np.broadcast_to(np.float64(p.radius), (n,)), mass=np.broadcast_to(np.float64(p.mass), (n,)),
                inertia=np.broadcast_to(np.float64(p.inertia[0]), (n,)), draw=draw)
        pos, (vel, omega, quat) = draw.on_host()
        return SphereSystem(
            box_length=spec.box_length, position=pos, velocity=vel, angular_velocity=omega, orientation=quat,
            radius=np.full(n, p.radius), mass=np.full(n, p.mass), inertia=np.full(n, p.inertia[0]))
    rng = np.random.default_rng(spec.seed)
    if start_protocol(spec) == RANDOM:
        pos, _ = place_species([n], [p.radius], spec.box_length, rng)
    else:
        pos = place_spheres(n, spec.box_length, p.radius, rng)
    vel = maxwellian(n, spec.velocity_rms, rng)
    # equal rotational and translational temperature: I <w^2> = m <v^2>
    omega = maxwellian(n, w_rms, rng)
    quat = random_quaternions(n, rng)
    return SphereSystem(
        box_length=spec.box_length, position=pos, velocity=vel, angular_velocity=omega, orientation=quat,
        radius=np.full(n, p.radius), mass=np.full(n, p.mass), inertia=np.full(n, p.inertia[0]))


def initial_ellipsoids(spec, p: Derived, on_device: bool = False) -> EllipsoidSystem:
    """Start of an ellipsoid spec: placed without overlap, uniformly random orientations, Maxwellian velocities, and
    spins about the two axes perpendicular to the symmetry axis at the translational temperature per degree of
    freedom; no spin about the axis when the contacts are frictionless (they can neither create nor use it:
    Rubio-Largo et al. (2015) set omega_y(0) = 0), a thermal one when they are rough (all three rotational dof exchange
    energy). Placed on a lattice by their bounding spheres (radius a; the protocol of Rubio-Largo et al. 2015, §4), or
    for ``start = "random"`` by random sequential addition of the spheroids themselves, each with its orientation
    (engine/setup/cell_rsa.py: cell rounds on the host's threads from the parallel start's size on, on one thread
    below it). ``on_device``: as :func:`initial_spheres`' (a large start comes as its :class:`StartDraw`)."""
    n = spec.n_particles
    a, b = p.semi_axes[0], p.semi_axes[1]
    random = start_protocol(spec) == RANDOM
    parallel = start_generator(spec) in (PARALLEL_GENERATOR, PARALLEL_RSA_GENERATOR)
    rng = None if parallel else np.random.default_rng(spec.seed)
    w_rms = _ellipsoid_spin_rms(spec, p)
    axes, inertia = np.asarray(p.semi_axes, float), np.asarray(p.inertia, float)
    try:
        if parallel:
            streams, _ = parallel_start_streams(spec, p)
            draw = StartDraw.of(n, spec.seed, streams, spec.box_length, a, start_protocol(spec),
                                (a, b) if random else ())
            if on_device:    # drawn by the GPU job's backend (engine/loops/cuda_start.py)
                return EllipsoidSystem(
                    box_length=spec.box_length, position=None, velocity=None, angular_velocity=None,
                    orientation=None, semi_axes=np.broadcast_to(axes, (n, 3)),
                    mass=np.broadcast_to(np.float64(p.mass), (n,)), inertia=np.broadcast_to(inertia, (n, 3)),
                    draw=draw)
            pos, vel, omega, quat = ellipsoid_draw_on_host(draw)
            return EllipsoidSystem(
                box_length=spec.box_length, position=pos, velocity=vel, angular_velocity=omega, orientation=quat,
                semi_axes=np.tile(axes, (n, 1)), mass=np.full(n, p.mass), inertia=np.tile(inertia, (n, 1)))
        if random:
            pos, quat = place_random(CellRsa.of(n, spec.box_length, a, (a, b)), rsa_keys(spec.seed), threads=False)
        else:
            pos = place_spheres(n, spec.box_length, a, rng)
    except SpecError as exc:
        raise SpecError(f"{exc} (ellipsoids are placed by their bounding spheres of radius a = {a:.4g} m, "
                        f"elongation = {spec.elongation:g})") from None
    vel = maxwellian(n, spec.velocity_rms, rng)
    if not random:
        quat = random_quaternions(n, rng)
    w_b = rng.normal(size=(n, 2))
    w_b -= w_b.mean(axis=0) if n > 1 else 0.0
    w_b *= w_rms[0] / math.sqrt(np.mean(w_b * w_b))
    w_a = np.zeros((n, 1))
    if not spec.smooth:
        # rough contacts exchange spin about the symmetry axis too: that dof starts thermal as well
        # (drawn after the others, from its own stream, so a smooth start is unchanged)
        w_a = rng.normal(size=(n, 1))
        w_a -= w_a.mean(axis=0) if n > 1 else 0.0
        w_a *= w_rms[1] / math.sqrt(np.mean(w_a * w_a))
    omega = np.empty((n, 3))
    _space_spins(quat, w_b, w_a, not spec.smooth, omega)
    return EllipsoidSystem(
        box_length=spec.box_length, position=pos, velocity=vel, angular_velocity=omega, orientation=quat,
        semi_axes=np.tile(axes, (n, 1)), mass=np.full(n, p.mass), inertia=np.tile(inertia, (n, 1)))


def is_rough_draw(streams) -> bool:
    """Whether an ellipsoid start's streams draw an axial spin (rough contacts)."""
    return any(s == STREAM_SPIN_AXIS for s, _, _ in streams)


def _ellipsoid_rows(streams, random: bool, drawn: list, n: int) -> tuple:
    """(velocity, space-frame spin, orientation) of an ellipsoid start from its drawn row blocks, in the order of
    ``streams`` (a random start's orientations last, drawn with its centres): the spins from the body-axis draws by
    :func:`_space_spin`."""
    by_stream = dict(zip([s for s, _, _ in streams] + ([STREAM_QUATERNION] if random else []), drawn))
    rough = is_rough_draw(streams)
    w_a = by_stream[STREAM_SPIN_AXIS] if rough else np.zeros((n, 1))
    omega = np.empty((n, 3))
    _space_spins_parallel(by_stream[STREAM_QUATERNION], by_stream[STREAM_SPIN], w_a, rough, omega)
    return by_stream[STREAM_VELOCITY], omega, by_stream[STREAM_QUATERNION]


def ellipsoid_draw_on_host(d) -> tuple:
    """(position, velocity, space-frame spin, orientation) of a large ellipsoid start drawn on the host from its
    :class:`StartDraw`."""
    pos, drawn = d.on_host()
    return (pos, *_ellipsoid_rows(d.streams, d.rsa is not None, drawn, d.n))


@numba.njit(cache=True, inline="always")
def _space_spin(w, x, y, z, wb0, wb1, wa, rough):
    """The space-frame spin of an ellipsoid of orientation (w, x, y, z) spinning at wb0, wb1 about its body axes
    e2, e3 (the columns of its rotation matrix) and, when ``rough``, at wa about its symmetry axis e1."""
    e2x, e2y, e2z = 2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)
    e3x, e3y, e3z = 2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)
    ox, oy, oz = wb0 * e2x + wb1 * e3x, wb0 * e2y + wb1 * e3y, wb0 * e2z + wb1 * e3z
    if rough:
        e1x, e1y, e1z = 1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)
        ox, oy, oz = ox + wa * e1x, oy + wa * e1y, oz + wa * e1z
    return ox, oy, oz


@numba.njit(cache=True)
def _space_spins(quat, w_b, w_a, rough, out):
    """:func:`_space_spin` of every row (a small start: one thread, so several scenes may be set up at once)."""
    for i in range(quat.shape[0]):
        out[i, 0], out[i, 1], out[i, 2] = _space_spin(quat[i, 0], quat[i, 1], quat[i, 2], quat[i, 3], w_b[i, 0],
                                                      w_b[i, 1], w_a[i, 0], rough)


@numba.njit(cache=True, parallel=True, nogil=True)
def _space_spins_parallel(quat, w_b, w_a, rough, out):
    """:func:`_space_spins` over threads (a large start, drawn by the parallel generator)."""
    for i in numba.prange(quat.shape[0]):
        out[i, 0], out[i, 1], out[i, 2] = _space_spin(quat[i, 0], quat[i, 1], quat[i, 2], quat[i, 3], w_b[i, 0],
                                                      w_b[i, 1], w_a[i, 0], rough)


def calls_compiled_start(spec) -> bool:
    """Whether a start of ``spec`` drawn on the host calls the compiled functions :func:`load_parallel_start` loads:
    a large one-size start (the parallel generators), or a random spheroid start at any size (its cell rounds,
    :func:`initial_ellipsoids`); a start NumPy draws (spheres below the parallel size, species, a small lattice) calls
    none."""
    return start_generator(spec) != SEQUENTIAL_GENERATOR or (
        spec.shape == "ellipsoid" and start_protocol(spec) == RANDOM)


def load_parallel_start(spec, p: Derived) -> bool:
    """Load every compiled function a large start of ``spec``'s kind calls (spec's shape and contact law; its
    n_particles is not read), for the argument types it calls them with, from numba's disk cache (or compile them):
    a start of a few particles is drawn through the same functions and discarded. False, and nothing loaded, for a
    species spec (its starts are drawn by NumPy). For the worker's standby process
    (engine.driver.simulate.warm_process): a later large start of this kind then loads nothing
    (tests/engine/test_time_to_result.py checks the types)."""
    if species_table(spec) is not None:
        return False
    n = 64
    streams, _ = parallel_start_streams(spec, p)
    random = start_protocol(spec) == RANDOM
    if random:     # the random start's rounds (engine/setup/cell_rsa.py)
        axes = (1.0, 0.5) if spec.shape == "ellipsoid" else ()
        _, drawn = StartDraw.of(n, spec.seed, streams, 20.0, 1.0, RANDOM, axes).on_host()
    else:          # unplaced: the same compiled calls with the same argument types (a site count of 0 selects none)
        _, drawn = _parallel_draws(n, spec.seed, streams)
    if spec.shape == "ellipsoid":
        _ellipsoid_rows(streams, random, drawn, n)
    return True


def _ellipsoid_spin_rms(spec, p: Derived) -> tuple:
    """rms spin of an ellipsoid about each perpendicular body axis, and about the symmetry axis: the
    translational temperature per degree of freedom, m <v^2>/3 = I_k <w_k^2>."""
    return (spec.velocity_rms * math.sqrt(p.mass / (3.0 * p.inertia[1])),
            spec.velocity_rms * math.sqrt(p.mass / (3.0 * p.inertia[0])))


def parallel_start_streams(spec, p: Derived) -> tuple:
    """The streams (stream, dim, rms or None for unit rows) of a spec's parallel start, in the order its shape
    takes them, and the radius its particles are placed by (a sphere's, an ellipsoid's bounding sphere's)."""
    if spec.shape == "ellipsoid":
        w_rms, w1_rms = _ellipsoid_spin_rms(spec, p)
        # every stream is its own sequence of draws: the axial spin's (rough contacts) leaves the others as they are;
        # a random start draws its orientations with its centres (engine/setup/cell_rsa.py)
        return [(STREAM_VELOCITY, 3, spec.velocity_rms)] + \
            ([] if start_protocol(spec) == RANDOM else [(STREAM_QUATERNION, 4, None)]) + \
            [(STREAM_SPIN, 2, w_rms * math.sqrt(2.0))] + \
            ([] if spec.smooth else [(STREAM_SPIN_AXIS, 1, w1_rms)]), p.semi_axes[0]
    # equal rotational and translational temperature: I <w^2> = m <v^2>
    w_rms = spec.velocity_rms * math.sqrt(p.mass / p.inertia[0])
    return [(STREAM_VELOCITY, 3, spec.velocity_rms), (STREAM_SPIN, 3, w_rms), (STREAM_QUATERNION, 4, None)], p.radius


# ---- large lattice starts in parallel ------------------------------------------------------------------

STREAM_SITES, STREAM_DISPLACEMENT, STREAM_VELOCITY, STREAM_SPIN, STREAM_QUATERNION, STREAM_SPIN_AXIS = range(6)
#: the random start's draws (engine/setup/cell_rsa.py): candidate centres, attempt counts, the last round's removal
#: order, and a spheroid candidate's orientation
STREAM_RSA_CENTRES, STREAM_RSA_ATTEMPTS, STREAM_RSA_REMOVAL, STREAM_RSA_ORIENTATION = range(6, 10)
_BLOCK = 1 << 14     # particles per block of the deterministic sums

@numba.njit(cache=True, inline="always")
def _site_position(j, i, m, a, half_gap, box, place_key):
    """Particle i's position (m) at site j of the fcc lattice of m^3 cells of edge ``a`` (numbered as
    :func:`fcc_sites` numbers them): the site displaced uniformly in a ball of radius ``half_gap`` (direction from
    three normals, radius from a uniform: draws 0-4 of particle i in the stream ``place_key``), wrapped into
    [0, box). One source for the host's draws (:func:`_draw_start`) and the GPU's (engine/loops/cuda_start.py)."""
    c = j // 4
    b = j - 4 * c
    ix = c // (m * m)
    iy = (c // m) % m
    iz = c % m
    bx = 0.5 * a if b == 1 or b == 2 else 0.0      # the cell's four sites: (0,0,0), (.5,.5,0), (.5,0,.5), (0,.5,.5)
    by = 0.5 * a if b == 1 or b == 3 else 0.0
    bz = 0.5 * a if b == 2 or b == 3 else 0.0
    g0, g1 = _normal_pair(place_key, i, 0)
    g2, _ = _normal_pair(place_key, i, 2)
    norm = math.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
    r = half_gap * _uniform(place_key, i, 4) ** (1.0 / 3.0) * (1.0 - 1e-9) / norm
    x = (ix * a + bx) + 0.25 * a + g0 * r
    y = (iy * a + by) + 0.25 * a + g1 * r
    z = (iz * a + bz) + 0.25 * a + g2 * r
    return x - box * math.floor(x / box), y - box * math.floor(y / box), z - box * math.floor(z / box)


@numba.njit(cache=True, inline="always")
def _stream_values(key, i, dim, unit):
    """Particle i's row of a stream (dim 1-4 values; the unused ones 0): standard normals from draws 0..dim-1 of
    the stream ``key``, normalised to a unit quaternion when ``unit`` (dim 4: uniform orientations). One source for
    the host's draws (:func:`_draw_start`) and the GPU's (engine/loops/cuda_start.py)."""
    if unit:
        return uniform_quaternion(key, i)
    g0, g1 = _normal_pair(key, i, 0)
    g2 = 0.0
    g3 = 0.0
    if dim > 2:
        g2, g3 = _normal_pair(key, i, 2)
    return g0, g1, g2, g3


_MASK64 = (1 << 64) - 1


def _stream_key(seed: int, stream: int) -> np.uint64:
    """The 64-bit key of one random stream of a seed: _mix64(seed * golden + stream + 1) mod 2^64, in Python
    integers (no compiled call before the start's own)."""
    x = ((seed % (1 << 64)) * int(_GOLDEN) + stream + 1) & _MASK64
    x = ((x ^ (x >> 30)) * int(_M1)) & _MASK64
    x = ((x ^ (x >> 27)) * int(_M2)) & _MASK64
    return _U(x ^ (x >> 31))


#: chunks of the site selection (a fixed number: the selection never depends on the thread count)
_SELECT_CHUNKS = 64
#: leading key bits of the selection's histogram
_SELECT_BITS = 12


@numba.njit(cache=True)
def _bucket_of(hist, n):
    """The histogram bucket (column of ``hist``, chunks x buckets) that holds the n-th smallest key, the count of
    keys below it, the count in it, and each chunk's first place among the bucket's keys. (Its own function:
    numba's parfors miscompiled this loop with a break inside a parallel function.)"""
    c_n, n_buckets = hist.shape
    below = 0
    for b in range(n_buckets):
        in_bucket = 0
        for c in range(c_n):
            in_bucket += hist[c, b]
        if below + in_bucket >= n:
            starts = np.zeros(c_n, np.int64)
            for c in range(1, c_n):
                starts[c] = starts[c - 1] + hist[c - 1, b]
            return b, below, in_bucket, starts
        below += in_bucket
    raise ValueError("fewer keys than sites to choose")


@numba.njit(cache=True)
def _offsets(less, equal, n):
    """Each chunk's first place among the n chosen sites and how many of its keys equal to the cut it takes (in
    site order)."""
    c_n = less.shape[0]
    left = n
    for c in range(c_n):      # a loop, not less.sum(): NumPy's sum would make a fresh process's cache load import
        left -= less[c]       # numba.np.arraymath and, through its BLAS check, scipy.linalg (0.15 s)
    quota = np.zeros(c_n, np.int64)
    offset = np.zeros(c_n, np.int64)
    for c in range(c_n):
        quota[c] = min(equal[c], left)
        left -= quota[c]
        if c > 0:
            offset[c] = offset[c - 1] + less[c - 1] + quota[c - 1]
    return offset, quota


@numba.njit(cache=True, inline="always")
def _smallest_sites(key, n_sites, n):
    """The numbers of the n sites of smallest key ``_bits(key, j, 0)``, ascending: a radix select (a histogram of
    the keys' leading bits finds the bucket that holds the n-th smallest key, a sort of that bucket alone the key
    itself), then the sites at or below it in site order. Keys equal to that one (2^-64 odds for a pair) are
    taken in site order."""
    c_n = _SELECT_CHUNKS
    n_buckets = 1 << _SELECT_BITS
    shift = _U(64 - _SELECT_BITS)
    size = (n_sites + c_n - 1) // c_n
    keys = np.empty(n_sites, np.uint64)
    hist = np.zeros((c_n, n_buckets), np.int64)
    for c1 in numba.prange(c_n):
        for j1 in range(c1 * size, min(n_sites, (c1 + 1) * size)):
            k1 = _bits(key, j1, 0)
            keys[j1] = k1
            hist[c1, np.int64(k1 >> shift)] += 1
    bucket, below, in_bucket, starts = _bucket_of(hist, n)
    cand = np.empty(in_bucket, np.uint64)
    for c4 in numba.prange(c_n):
        at = starts[c4]
        for j4 in range(c4 * size, min(n_sites, (c4 + 1) * size)):
            if np.int64(keys[j4] >> shift) == bucket:
                cand[at] = keys[j4]
                at += 1
    cand.sort()
    cut = cand[n - below - 1]
    less = np.zeros(c_n, np.int64)
    equal = np.zeros(c_n, np.int64)
    for c5 in numba.prange(c_n):
        for j5 in range(c5 * size, min(n_sites, (c5 + 1) * size)):
            if keys[j5] < cut:
                less[c5] += 1
            elif keys[j5] == cut:
                equal[c5] += 1
    offset, quota = _offsets(less, equal, n)
    chosen = np.empty(n, np.int64)
    for c8 in numba.prange(c_n):
        out = offset[c8]
        ties = quota[c8]
        for j8 in range(c8 * size, min(n_sites, (c8 + 1) * size)):
            kj = keys[j8]
            if kj < cut or (kj == cut and ties > 0):
                if kj == cut:
                    ties -= 1
                chosen[out] = j8
                out += 1
    return chosen


@numba.njit(cache=True, parallel=True, nogil=True)  # nogil: engine/driver/startup.py's thread works meanwhile
def _draw_start(n, n_sites, m, a, half_gap, box, site_key, place_key, keys, outs, unit):
    """The draws of a large one-size start in one compiled call (one disk-cache load in a fresh process).

    Positions (none when ``n_sites`` is 0): the n sites of smallest key (:func:`_smallest_sites`; all of them when
    n = n_sites) of the fcc lattice of m^3 cells of edge ``a`` (m), numbered as :func:`fcc_sites` numbers them, each
    displaced uniformly in a ball of radius ``half_gap`` (direction from three normals, radius from a uniform),
    wrapped into [0, box).
    Then for each stream s, ``outs[s]`` (n x dim) gets standard normals from ``keys[s]``; rows of a ``unit``
    stream (dim 4) are normalised (uniform quaternions, quat_unit). Returns the positions and, per stream, the
    column sums of each block of _BLOCK rows (S x blocks x 4; the start's mean, taken in fixed blocks for any
    thread count).
    """
    n_placed = n if n_sites > 0 else 0       # n_sites = 0: no positions
    chosen = _smallest_sites(site_key, n_sites, n) if 0 < n_sites and n < n_sites else np.arange(n_placed)
    pos = np.empty((n_placed, 3))
    for i in numba.prange(n_placed):
        pos[i, 0], pos[i, 1], pos[i, 2] = _site_position(chosen[i], i, m, a, half_gap, box, place_key)
    n_blocks = (n + _BLOCK - 1) // _BLOCK
    sums = np.zeros((len(outs), n_blocks, 4))
    for s in range(len(outs)):
        v = outs[s]
        dim = v.shape[1]
        key = keys[s]
        for i in numba.prange(n):
            v0, v1, v2, v3 = _stream_values(key, i, dim, unit[s])
            v[i, 0] = v0
            if dim > 1:
                v[i, 1] = v1
            if dim > 2:
                v[i, 2] = v2
            if dim > 3:
                v[i, 3] = v3
        if not unit[s]:
            for bl in numba.prange(n_blocks):
                for i in range(bl * _BLOCK, min(n, (bl + 1) * _BLOCK)):
                    for d in range(dim):
                        sums[s, bl, d] += v[i, d]
    return pos, sums


@numba.njit(cache=True, parallel=True, nogil=True)  # nogil: engine/driver/startup.py's thread works meanwhile
def _centre_and_square(outs, means, unit):
    """Subtract each (not unit) stream's mean and return the per-block column sums of squares (as _draw_start)."""
    n = outs[0].shape[0]
    n_blocks = (n + _BLOCK - 1) // _BLOCK
    sums = np.zeros((len(outs), n_blocks, 4))
    for s in range(len(outs)):
        if unit[s]:
            continue
        v = outs[s]
        dim = v.shape[1]
        for bl in numba.prange(n_blocks):
            for i in range(bl * _BLOCK, min(n, (bl + 1) * _BLOCK)):
                for d in range(dim):
                    x = v[i, d] - means[s, d]
                    v[i, d] = x
                    sums[s, bl, d] += x * x
    return sums


@numba.njit(cache=True, parallel=True, nogil=True)  # nogil: engine/driver/startup.py's thread works meanwhile
def _scale_streams(outs, scales, unit):
    """Multiply each (not unit) stream by its scale (sqrt(<|v|^2>) = rms exactly)."""
    for s in range(len(outs)):
        if unit[s]:
            continue
        v = outs[s]
        for i in numba.prange(v.shape[0]):
            for d in range(v.shape[1]):
                v[i, d] *= scales[s]


def _stream_sums(sums, s: int, dim: int) -> np.ndarray:
    """Stream s's per-block sums as the contiguous (blocks x dim) array NumPy then sums (in its own fixed order)."""
    return np.ascontiguousarray(sums[s, :, :dim])


def stream_mean(block_sums: np.ndarray, n: int, rms) -> np.ndarray:
    """A stream's mean (dim), from its (blocks x dim) block sums; 0 for unit rows (rms None) and n <= 1. The host's
    and the GPU's draws (engine/loops/cuda_start.py) both take it here, from the same block sums."""
    if rms is None or n <= 1:
        return np.zeros(block_sums.shape[1])
    return block_sums.sum(axis=0) / n


def stream_scale(block_squares: np.ndarray, n: int, rms) -> float:
    """The factor that makes a centred stream's sqrt(<|v|^2>) = rms, from its (blocks x dim) block sums of squares
    (1 for unit rows); as :func:`stream_mean`, one source for both draws."""
    if rms is None:
        return 1.0
    norm = math.sqrt(block_squares.sum() / n)
    return rms / norm if norm > 0 else 1.0


def lattice_of(n: int, box: float, radius: float) -> tuple:
    """place_spheres' lattice for n spheres of ``radius`` in a box of edge ``box``: (m, a, n_sites, half_gap), m^3
    fcc cells of edge a, and half the free gap around a site (SpecError when the spheres do not fit)."""
    m = max(1, math.ceil((n / 4.0) ** (1.0 / 3.0) - 1e-9))
    a = box / m
    n_sites = 4 * m ** 3
    return m, a, n_sites, 0.5 * lattice_gap(n, box, radius, n_sites, a / math.sqrt(2.0))


def _parallel_draws(n: int, seed: int, streams: list, place=None) -> tuple:
    """A large start's draws with the counter-based generator, in three compiled calls.

    ``place``: None, or (box, radius): place_spheres' protocol (fcc sites, n of them at random, a random
    displacement in the free room; SpecError when the spheres do not fit). ``streams``: (stream, dim, rms) per
    array drawn; rms None gives uniform unit quaternions (dim 4), a number Maxwellian components of zero
    mean and sqrt(<|v|^2>) = rms exactly (maxwellian()). Every stream is its own sequence of draws, so what one
    array holds does not depend on the others. Returns (positions or None, [arrays])."""
    if place is not None:
        box, radius = place
        m, a, n_sites, half_gap = lattice_of(n, box, radius)
    else:
        box, m, a, n_sites, half_gap = 1.0, 1, 1.0, 0, 0.0
    _check_streams(streams)
    outs = tuple(np.empty((n, dim)) for _, dim, _ in streams)
    keys = np.array([_stream_key(seed, stream) for stream, _, _ in streams], np.uint64)
    unit = np.array([rms is None for _, _, rms in streams])
    pos, sums = _draw_start(n, n_sites, m, a, half_gap, float(box), _stream_key(seed, STREAM_SITES),
                            _stream_key(seed, STREAM_DISPLACEMENT), keys, outs, unit)
    means = np.zeros((len(streams), 4))
    for s, (_, dim, rms) in enumerate(streams):
        means[s, :dim] = stream_mean(_stream_sums(sums, s, dim), n, rms)
    sums = _centre_and_square(outs, means, unit)
    scales = np.array([stream_scale(_stream_sums(sums, s, dim), n, rms) for s, (_, dim, rms) in enumerate(streams)])
    _scale_streams(outs, scales, unit)
    return (pos if place is not None else None), list(outs)


def _check_streams(streams) -> None:
    if any(rms is None and dim != 4 for _, dim, rms in streams):
        raise ValueError("unit rows are drawn for quaternions only (dim 4)")


# ---- large starts drawn on the GPU (engine/loops/cuda_start.py) --------------------------------------

@dataclass(frozen=True)
class StartDraw:
    """A large one-size start of spheres, to be drawn on the GPU that runs it (engine/loops/cuda_start.py) in
    place of the host's :func:`_parallel_draws`: the same counter-based draws, lattice and site selection, the same
    block sums and the same host arithmetic for means and scales. Sites are the same; values are equal to rounding
    (the device's log, cos, sin, pow are libdevice's, the host's libm's; the device may contract a * b + c into
    one fused multiply-add). ``streams``: as _parallel_draws'; positions on the lattice of ``lattice_of``."""

    n: int
    seed: int
    streams: tuple
    box: float
    radius: float
    m: int
    a: float
    n_sites: int
    half_gap: float
    #: None: the lattice protocol; else the random start's cells (engine/setup/cell_rsa.py ``CellRsa``)
    rsa: object = None

    @classmethod
    def of(cls, n: int, seed: int, streams, box: float, radius: float, protocol: str = "lattice",
           axes: tuple = ()) -> "StartDraw":
        """Checked on the host at once (SpecError when the spheres do not fit), drawn later on the device. ``axes``:
        a random spheroid start's semi-axes (a, b) (``radius`` = a; orientations drawn with the centres)."""
        _check_streams(streams)
        rsa = CellRsa.of(n, box, radius, axes) if protocol == RANDOM else None
        return cls(n, seed, tuple(tuple(s) for s in streams), float(box), float(radius), *lattice_of(n, box, radius),
                   rsa=rsa)

    def keys(self) -> tuple:
        """(sites' key, displacements' key, [each stream's key]) as numpy uint64."""
        return (_stream_key(self.seed, STREAM_SITES), _stream_key(self.seed, STREAM_DISPLACEMENT),
                [_stream_key(self.seed, stream) for stream, _, _ in self.streams])

    def rsa_keys(self) -> tuple:
        """The random start's keys (numpy uint64): candidate centres, attempt counts, removal order, orientations."""
        return rsa_keys(self.seed)

    def on_host(self, threads: bool = True) -> tuple:
        """The same start drawn on the host (positions, [arrays]): _parallel_draws, and for a random start the
        centres of engine/setup/cell_rsa.py ``place_random`` (a spheroid start's orientations appended to the
        arrays)."""
        if self.rsa is None:
            return _parallel_draws(self.n, self.seed, list(self.streams), place=(self.box, self.radius))
        _, drawn = _parallel_draws(self.n, self.seed, list(self.streams))
        pos, quat = place_random(self.rsa, self.rsa_keys(), threads)
        return pos, (drawn if quat is None else [*drawn, quat])


def rsa_keys(seed: int) -> tuple:
    """The keys of a random start's cell rounds (engine/setup/cell_rsa.py) for ``seed``: candidate centres, attempt
    counts, removal order, a spheroid candidate's orientation (numpy uint64)."""
    return tuple(_stream_key(seed, s) for s in (STREAM_RSA_CENTRES, STREAM_RSA_ATTEMPTS, STREAM_RSA_REMOVAL,
                                                STREAM_RSA_ORIENTATION))


def drawn_on_host(system):
    """``system`` with its arrays drawn on the host, if it holds a device draw (a job that ended up on the CPU)."""
    d = getattr(system, "draw", None)
    if d is None:
        return system
    if isinstance(system, EllipsoidSystem):
        pos, vel, omega, quat = ellipsoid_draw_on_host(d)
        return replace(system, position=pos, velocity=vel, angular_velocity=omega, orientation=quat, draw=None,
                       semi_axes=np.array(system.semi_axes), mass=np.array(system.mass),
                       inertia=np.array(system.inertia))
    pos, (vel, omega, quat) = d.on_host()
    # the CPU loops take writable arrays of their own, not the device start's broadcast constants
    return replace(system, position=pos, velocity=vel, angular_velocity=omega, orientation=quat, draw=None,
                   radius=np.array(system.radius), mass=np.array(system.mass), inertia=np.array(system.inertia))


fast_loads(globals())  # their disk-cache loads skip numba's target refresh (engine/numba_support/jitcache.py)
