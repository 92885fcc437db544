"""The parallel random start (engine/setup/cell_rsa.py, random sequential addition in cell rounds): exactly N spheres,
none overlapping, deterministic from the seed and independent of the slots per cell, and the structure of the sequential
random start (tests/engine/test_start.py checks that one against Carnahan-Starling). Spheroids: none overlapping, the
same on one thread and many, uniform orientations, and the near-contact pair count of a dilute equilibrium gas."""

from __future__ import annotations

import math

import numpy as np
import pytest

from engine.setup.cell_rsa import CellRsa, place_random
from engine.analysis.pairs import periodic_pairs
from engine.setup.scene import _stream_key, place_species

BOX = 1.0


def _radius(n: int, phi: float) -> float:
    return (phi * BOX**3 / n * 3.0 / (4.0 * math.pi)) ** (1.0 / 3.0)


def _keys(seed: int) -> tuple:
    return tuple(_stream_key(seed, s) for s in (6, 7, 8, 9))


def _place(g, keys, threads=True):
    """place_random's centres (spheres: its orientations are None)."""
    pos, quat = place_random(g, keys, threads)
    assert quat is None
    return pos


def _pair_distances(pos: np.ndarray, radius: float, reach: float, box: float = BOX) -> np.ndarray:
    """Centre distances / sigma of every pair closer than reach sigma."""
    pairs = periodic_pairs(pos, box, 2.0 * radius * reach)
    d = pos[pairs[:, 1]] - pos[pairs[:, 0]]
    d -= box * np.round(d / box)
    return np.sqrt(np.einsum("ij,ij->i", d, d)) / (2.0 * radius)


@pytest.mark.parametrize("phi", [0.008, 0.2, 0.3])
def test_exactly_n_spheres_none_overlapping_deterministic(phi):
    n = 20_000
    radius = _radius(n, phi)
    g = CellRsa.of(n, BOX, radius)
    assert g.nc % 2 == 0 and BOX / g.nc >= 2.0 * radius
    pos = _place(g, _keys(5))
    assert pos.shape == (n, 3) and pos.min() >= 0.0 and pos.max() < BOX
    assert _pair_distances(pos, radius, 1.0).size == 0             # no centres closer than sigma
    assert np.array_equal(pos, _place(g, _keys(5)))          # the same seed, the same start
    assert not np.array_equal(pos, _place(g, _keys(6)))
    # the spheres do not depend on the slots per cell (a full cell redoes the start with more)
    few = CellRsa(n=g.n, box=g.box, nc=g.nc, slots=2, unit=g.unit, thr=g.thr, cdf=g.cdf)
    assert np.array_equal(pos, _place(few, _keys(5)))


@pytest.mark.parametrize("phi", [0.058, 0.2])
def test_pair_structure_is_the_sequential_random_starts(phi):
    """g(r) over sigma <= r < 1.5 sigma (ten shells) and the neighbour counts within 1.4 sigma of the parallel start
    against the sequential start (engine/setup/scene.py place_species) of the same N: equal within their counting
    errors (each shell's pair count is Poisson: 4 standard errors of the difference)."""
    n = 60_000
    radius = _radius(n, phi)
    par = _pair_distances(_place(CellRsa.of(n, BOX, radius), _keys(1)), radius, 1.5)
    seq = _pair_distances(place_species([n], [radius], BOX, np.random.default_rng(1))[0], radius, 1.5)
    edges = np.linspace(1.0, 1.5, 11)
    hp, hs = np.histogram(par, edges)[0], np.histogram(seq, edges)[0]
    assert np.all(np.abs(hp - hs) < 4.0 * np.sqrt(hp + hs)), (hp, hs)


def test_a_spec_above_the_parallel_size_gets_the_parallel_random_start(monkeypatch):
    """initial_spheres of a one-size sphere spec of at least PARALLEL_START_MIN spheres (lowered here) places them
    with engine/setup/cell_rsa.py, Maxwellian and at equal rotational temperature as every start; a lattice asked for
    stays a lattice."""
    from engine.setup import start_kind
    from engine.setup.params import derive
    from engine.setup.scene import StartDraw, initial_spheres
    from engine.setup.spec import SimulationSpec

    monkeypatch.setattr(start_kind, "PARALLEL_START_MIN", 4096)
    spec = SimulationSpec(n_particles=8192, volume_fraction=0.1, seed=4)
    p = derive(spec)
    assert p.start == "random" and start_kind.start_generator(spec) == start_kind.PARALLEL_RSA_GENERATOR
    s = initial_spheres(spec, p)
    draw = StartDraw.of(8192, 4, [], spec.box_length, p.radius, "random")
    assert np.array_equal(s.position, _place(draw.rsa, draw.rsa_keys()))
    assert _pair_distances(s.position, p.radius, 1.0, spec.box_length).size == 0
    assert np.sqrt(np.mean(np.sum(s.velocity**2, axis=1))) == pytest.approx(spec.velocity_rms, rel=1e-12)
    assert abs(s.velocity.mean(axis=0)).max() < 1e-12
    lattice = initial_spheres(spec.model_copy(update={"start": "lattice"}), p)
    assert not np.array_equal(lattice.position, s.position)


# ---- spheroids ---------------------------------------------------------------------------------------------------


def _semi_axes(n: int, phi: float, xi: float) -> tuple:
    """(a, b) of n prolate spheroids of aspect ratio xi at volume fraction phi in the unit box."""
    r_eq = _radius(n, phi)
    b = r_eq / xi ** (1.0 / 3.0)
    return xi * b, b


def _spheroid_w0(pos: np.ndarray, quat: np.ndarray, a: float, b: float, reach: float) -> np.ndarray:
    """Perram-Wertheim W_0 of every pair whose bounding spheres come within reach x 2a (engine/physics/ellipsoid.py:
    both bodies scaled by W_0 about their centres just touch; W_0 < 1 overlaps)."""
    from engine.physics.ellipsoid import ellipsoid_overlap_pw

    pairs = periodic_pairs(pos, BOX, 2.0 * a * reach)
    d = pos[pairs[:, 1]] - pos[pairs[:, 0]]
    d -= BOX * np.round(d / BOX)
    out = np.empty(len(pairs))
    for k, (i, j) in enumerate(pairs):
        qa, qb = quat[i], quat[j]
        out[k] = ellipsoid_overlap_pw(d[k, 0], d[k, 1], d[k, 2], qa[0], qa[1], qa[2], qa[3], a, b, b,
                                      qb[0], qb[1], qb[2], qb[3], a, b, b, 1e-13, 0.5)[1]
    return out


def _mean_excluded_volume(a: float, b: float) -> float:
    """The excluded volume of two prolate spheroids (semi-axes a, b, b) averaged over independent uniform orientations:
    2 v + M S / (2 pi) (Isihara; Kihara), M the integral of the mean curvature over the surface, S its area (by
    quadrature over the polar angle t of the meridian (a cos t, b sin t); a sphere gives 32 pi R^3 / 3)."""
    t = np.linspace(0.0, math.pi, 200_001)
    speed = np.sqrt(a * a * np.sin(t) ** 2 + b * b * np.cos(t) ** 2)
    area_density = 2.0 * math.pi * b * np.sin(t) * speed
    mean_curvature = 0.5 * (a * b / speed**3 + a / (b * speed))
    s = np.trapezoid(area_density, t)
    m = np.trapezoid(mean_curvature * area_density, t)
    return 2.0 * (4.0 * math.pi / 3.0) * a * b * b + m * s / (2.0 * math.pi)


def test_excluded_volume_quadrature_of_a_sphere():
    assert _mean_excluded_volume(1.0, 1.0) == pytest.approx(32.0 * math.pi / 3.0, rel=1e-9)


@pytest.mark.parametrize(("phi", "xi"), [(0.05, 2.0), (0.015, 4.0)])
def test_spheroids_none_overlapping_the_same_on_one_thread_and_many(phi, xi):
    n = 6000
    a, b = _semi_axes(n, phi, xi)
    g = CellRsa.of(n, BOX, a, (a, b))
    assert g.spheroid and BOX / g.nc >= 2.0 * a
    pos, quat = place_random(g, _keys(3))
    assert pos.shape == (n, 3) and quat.shape == (n, 4)
    assert np.allclose(np.einsum("ij,ij->i", quat, quat), 1.0, rtol=0, atol=1e-15)
    w0 = _spheroid_w0(pos, quat, a, b, 1.0)
    assert w0.size > 50 and w0.min() >= 1.0                     # bounding spheres meet, the bodies do not
    serial = place_random(g, _keys(3), threads=False)
    assert np.array_equal(pos, serial[0]) and np.array_equal(quat, serial[1])
    few = CellRsa(n=g.n, box=g.box, nc=g.nc, slots=2, unit=g.unit, thr=g.thr, cdf=g.cdf, axes=g.axes)
    again = place_random(few, _keys(3))
    assert np.array_equal(pos, again[0]) and np.array_equal(quat, again[1])


def test_spheroid_orientations_are_uniform():
    """<P2(e1 . x_k)> of the symmetry axis e1 over the start is 0 for each box axis k (uniform orientations), within
    4 standard errors sqrt(1 / (5 N))."""
    n = 40_000
    a, b = _semi_axes(n, 0.05, 2.0)
    _, q = place_random(CellRsa.of(n, BOX, a, (a, b)), _keys(8))
    w, x, y, z = q.T
    e1 = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)], axis=1)
    p2 = 1.5 * e1**2 - 0.5
    assert np.all(np.abs(p2.mean(axis=0)) < 4.0 * math.sqrt(0.2 / n)), p2.mean(axis=0)


@pytest.mark.parametrize("xi", [2.0, 3.0])
def test_spheroid_near_contact_pairs_are_a_dilute_equilibrium_gas(xi):
    """Pairs with 1 <= W_0 < w in a dilute gas of hard spheroids: (N^2 / 2V) <V_ex> (w^3 - 1) g, where {W_0 < w} is
    the excluded region of the bodies scaled by w (volume w^3 V_ex) and <V_ex> the orientation average
    (:func:`_mean_excluded_volume`). Tolerance: 3 counting errors plus rho <V_ex>, the size of the first density
    correction to g (random sequential addition and equilibrium differ only from that order)."""
    n, phi, w = 100_000, 0.005, 1.5
    a, b = _semi_axes(n, phi, xi)
    pos, quat = place_random(CellRsa.of(n, BOX, a, (a, b)), _keys(11))
    w0 = _spheroid_w0(pos, quat, a, b, w)
    rho_vex = n / BOX**3 * _mean_excluded_volume(a, b)
    expected = 0.5 * n * rho_vex * (w**3 - 1.0)
    got = np.count_nonzero(w0 < w)
    assert abs(got / expected - 1.0) < 3.0 / math.sqrt(expected) + rho_vex, (got, expected, rho_vex)


def test_a_spheroid_spec_starts_random_where_its_bounding_spheres_allow():
    """A null start of a spheroid spec is the random one up to phi xi^2 = 0.3 (then no lattice to melt: no
    thermalisation at phi <= 0.02), the lattice above; its orientations are the start's, its velocities Maxwellian."""
    from engine.setup.params import derive
    from engine.setup.scene import initial_ellipsoids
    from engine.setup.spec import SimulationSpec

    spec = SimulationSpec(shape="ellipsoid", elongation=2.0, volume_fraction=0.01, n_particles=3000, seed=2)
    p = derive(spec)
    assert p.start == "random" and p.n_thermalization_steps == 0
    s = initial_ellipsoids(spec, p)
    g = CellRsa.of(3000, spec.box_length, p.semi_axes[0], tuple(p.semi_axes[:2]))
    from engine.setup.scene import rsa_keys
    pos, quat = place_random(g, rsa_keys(2), threads=False)
    assert np.array_equal(s.position, pos) and np.array_equal(s.orientation, quat)
    assert np.sqrt(np.mean(np.sum(s.velocity**2, axis=1))) == pytest.approx(spec.velocity_rms, rel=1e-12)
    dense = SimulationSpec(shape="ellipsoid", elongation=3.0, volume_fraction=0.04)
    assert derive(dense).start == "lattice"
