"""The start protocols: which start a spec gets, the thermalisation it needs, and how close the random start is
to an equilibrium gas (its pair correlation at contact against Carnahan-Starling, its velocity distribution)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from engine import SimulationSpec
from engine.analysis.pairs import periodic_pairs
from engine.setup.params import derive
from engine.setup.scene import initial_spheres
from engine.setup.start_kind import (LATTICE, PARALLEL_GENERATOR, PARALLEL_RSA_GENERATOR, PARALLEL_START_MIN, RANDOM,
                                     RANDOM_EQUILIBRIUM_MAX_VOLUME_FRACTION, SEQUENTIAL_GENERATOR, start_generator,
                                     start_protocol, thermalization_collisions)


def carnahan_starling(phi: float) -> float:
    return (1.0 - phi / 2.0) / (1.0 - phi) ** 3


def contact_value(position: np.ndarray, box: float, radius: float, shell: float = 0.03) -> tuple[float, float]:
    """g(sigma) as the pair density in the shell sigma <= r < sigma (1 + shell) over the ideal gas's (pairs closer
    than sigma, overlaps of soft spheres, are counted in), and its Poisson standard error."""
    sigma = 2.0 * radius
    pairs = float(len(periodic_pairs(position, box, sigma * (1.0 + shell))))
    ideal = 0.5 * len(position) ** 2 / box**3 * 4.0 / 3.0 * math.pi * sigma**3 * ((1.0 + shell) ** 3 - 1.0)
    return pairs / ideal, math.sqrt(pairs) / ideal


def test_null_start_is_random_where_cheap_and_lattice_elsewhere():
    assert start_protocol(SimulationSpec()) == RANDOM
    assert start_protocol(SimulationSpec(volume_fraction=0.3)) == RANDOM
    assert start_protocol(SimulationSpec(volume_fraction=0.35)) == LATTICE
    # a large one is random too, placed in parallel (engine/setup/cell_rsa.py)
    large = SimulationSpec(n_particles=PARALLEL_START_MIN, volume_fraction=0.05)
    assert start_protocol(large) == RANDOM and start_generator(large) == PARALLEL_RSA_GENERATOR
    assert start_generator(SimulationSpec(n_particles=PARALLEL_START_MIN - 1)) == SEQUENTIAL_GENERATOR
    assert start_generator(SimulationSpec(n_particles=PARALLEL_START_MIN, start="lattice")) == PARALLEL_GENERATOR
    # spheroids: random up to phi xi^2 = 0.3 (their bounding spheres' volume fraction), the lattice above
    assert start_protocol(SimulationSpec(shape="ellipsoid", elongation=2.0, volume_fraction=0.075)) == RANDOM
    assert start_protocol(SimulationSpec(shape="ellipsoid", elongation=2.0, volume_fraction=0.076)) == LATTICE
    assert start_generator(SimulationSpec(shape="ellipsoid", elongation=2.0, n_particles=PARALLEL_START_MIN)) \
        == PARALLEL_RSA_GENERATOR
    assert start_protocol(SimulationSpec(start="lattice")) == LATTICE
    assert start_protocol(SimulationSpec(start="random", n_particles=PARALLEL_START_MIN, volume_fraction=0.01)) \
        == RANDOM


def test_null_thermalization_is_what_the_start_needs_and_an_explicit_one_is_honoured():
    assert thermalization_collisions(SimulationSpec()) == 0.0           # Hidalgo et al. (2013) density: equilibrium
    assert derive(SimulationSpec()).n_thermalization_steps == 0
    assert thermalization_collisions(SimulationSpec(volume_fraction=0.1)) > 0.0
    assert thermalization_collisions(SimulationSpec(start="lattice")) == 1.0
    assert thermalization_collisions(SimulationSpec(thermalization=2.5)) == 2.5
    assert thermalization_collisions(SimulationSpec(start="lattice", thermalization=0)) == 0.0
    spec = SimulationSpec()
    p = derive(spec)
    # the default job's steps are the cooling run's: t_end / dt
    assert p.n_steps + p.n_thermalization_steps <= 1.1 * spec.t_end / p.dt


def test_start_errors_name_the_field():
    with pytest.raises(ValueError, match="start = 'random' needs volume_fraction"):
        SimulationSpec(start="random", volume_fraction=0.35)
    with pytest.raises(ValueError, match="start = 'lattice' but species"):
        SimulationSpec(start="lattice", species=[{"radius_ratio": 1.0, "number_fraction": 0.5},
                                                 {"radius_ratio": 0.5, "number_fraction": 0.5}])
    with pytest.raises(ValueError, match="start"):
        SimulationSpec(start="hexagonal")


def test_random_start_is_non_overlapping_uniform_and_maxwellian():
    spec = SimulationSpec(n_particles=20000, volume_fraction=0.1, seed=3)
    p = derive(spec)
    system = initial_spheres(spec, p)
    pos = np.asarray(system.position)
    assert len(periodic_pairs(pos, spec.box_length, 2.0 * p.radius)) == 0   # no two spheres overlap
    counts = np.histogramdd(pos, bins=4, range=[(0, spec.box_length)] * 3)[0].ravel()
    # 64 cells of ~312 spheres: a uniform start scatters by less than Poisson's sqrt(312) ~ 18 (hard cores)
    assert counts.std() < 1.5 * math.sqrt(counts.mean())
    v = np.asarray(system.velocity).ravel() / (spec.velocity_rms / math.sqrt(3.0))
    # Gaussian components: kurtosis 3 within its standard error sqrt(24/n) x 5
    assert abs(np.mean(v**4) / np.mean(v**2) ** 2 - 3.0) < 5.0 * math.sqrt(24.0 / v.size)
    w = np.asarray(system.angular_velocity)
    assert np.mean(np.sum(w * w, axis=1)) * p.inertia[0] == pytest.approx(p.mass * spec.velocity_rms**2, rel=1e-9)
    again = initial_spheres(spec, p)
    assert np.array_equal(np.asarray(again.position), pos)            # deterministic from the seed


@pytest.mark.parametrize("phi", [0.008, 0.058, 0.2, 0.3])
def test_random_start_contact_value_against_carnahan_starling(phi):
    """Random sequential addition gives g(sigma) = 1 + (5/3) phi + O(phi^2) against the equilibrium 1 + (5/2) phi
    + O(phi^2): equal to Carnahan-Starling within the measurement up to RANDOM_EQUILIBRIUM_MAX_VOLUME_FRACTION,
    measurably below it at the densities where the default thermalisation is not zero."""
    n = 300_000 if phi < 0.1 else 40_000
    spec = SimulationSpec(n_particles=n, volume_fraction=phi, seed=1)
    p = derive(spec)
    g, err = contact_value(np.asarray(initial_spheres(spec, p).position), spec.box_length, p.radius)
    cs = carnahan_starling(phi)
    if phi <= RANDOM_EQUILIBRIUM_MAX_VOLUME_FRACTION:
        assert abs(g / cs - 1.0) < 4.0 * err / cs + 0.01      # 4 sigma of the pair count, 1 % for the shell width
        assert thermalization_collisions(spec) == 0.0
    else:
        assert g < cs - 2.0 * err                             # RSA's deficit is resolved here
        assert thermalization_collisions(spec) > 0.0


@pytest.mark.parametrize("phi", [0.2, 0.3])
def test_default_thermalisation_relaxes_the_contact_value(phi, tmp_path):
    """After the default thermalisation of a dense random start g(sigma) has risen to within 4 % of
    Carnahan-Starling (soft spheres of k_n = 1e8 meet slightly inside sigma, which the shell count includes)."""
    import h5py

    from engine import run

    base = SimulationSpec(n_particles=8000, volume_fraction=phi, e_n=1.0, e_t=-1.0, seed=2, backend="cpu",
                          snapshots=2, t_end=1e-5)
    p = derive(base)
    assert p.n_thermalization_steps > 0
    run(base, tmp_path / "r.h5")
    with h5py.File(tmp_path / "r.h5") as f:
        start = f["/particles/all/position/value"][0]            # t = 0: after the thermalisation
    g, err = contact_value(start, base.box_length, p.radius)
    cs = carnahan_starling(phi)
    assert abs(g / cs - 1.0) < 0.04 + 3.0 * err / cs
