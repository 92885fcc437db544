"""The parallel random start (engine/setup/cell_rsa.py, random sequential addition in cell rounds): exactly N spheres,
none overlapping, deterministic from the seed and independent of the slots per cell, and the structure of the sequential
random start (tests/engine/test_start.py checks that one against Carnahan-Starling)."""

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
    return tuple(_stream_key(seed, s) for s in (6, 7, 8))


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
    pos = place_random(g, _keys(5))
    assert pos.shape == (n, 3) and pos.min() >= 0.0 and pos.max() < BOX
    assert _pair_distances(pos, radius, 1.0).size == 0             # no centres closer than sigma
    assert np.array_equal(pos, place_random(g, _keys(5)))          # the same seed, the same start
    assert not np.array_equal(pos, place_random(g, _keys(6)))
    # the spheres do not depend on the slots per cell (a full cell redoes the start with more)
    few = CellRsa(n=g.n, box=g.box, nc=g.nc, slots=2, unit=g.unit, thr=g.thr, cdf=g.cdf)
    assert np.array_equal(pos, place_random(few, _keys(5)))


@pytest.mark.parametrize("phi", [0.058, 0.2])
def test_pair_structure_is_the_sequential_random_starts(phi):
    """g(r) over sigma <= r < 1.5 sigma (ten shells) and the neighbour counts within 1.4 sigma of the parallel start
    against the sequential start (engine/setup/scene.py place_species) of the same N: equal within their counting
    errors (each shell's pair count is Poisson: 4 standard errors of the difference)."""
    n = 60_000
    radius = _radius(n, phi)
    par = _pair_distances(place_random(CellRsa.of(n, BOX, radius), _keys(1)), radius, 1.5)
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
    assert np.array_equal(s.position, place_random(draw.rsa, draw.rsa_keys()))
    assert _pair_distances(s.position, p.radius, 1.0, spec.box_length).size == 0
    assert np.sqrt(np.mean(np.sum(s.velocity**2, axis=1))) == pytest.approx(spec.velocity_rms, rel=1e-12)
    assert abs(s.velocity.mean(axis=0)).max() < 1e-12
    lattice = initial_spheres(spec.model_copy(update={"start": "lattice"}), p)
    assert not np.array_equal(lattice.position, s.position)
