"""Polydisperse spheres (size distributions): the `species` spec, derived parameters, placement, a collision of
unequal spheres, and a run through the driver that writes species and radii to the H5MD file."""

import json
import math

import h5py
import numpy as np
import pytest
from pydantic import ValidationError

from engine.setup.params import (carnahan_starling_g, derive, enskog_rate_mixture, estimate_bytes_per_particle,
                                 estimate_cost, gamma_n_from_restitution, species_counts)
from engine.setup.scene import initial_spheres, species_index
from engine.setup.spec import SPECIES_MAX_VOLUME_FRACTION, SimulationSpec

TWO = [{"radius_ratio": 1.0, "number_fraction": 0.3}, {"radius_ratio": 0.4, "number_fraction": 0.7}]
# 60 spheres, ratio 2.5, soft contacts: ~4000 steps in all (thermalisation + cooling)
SMALL = dict(n_particles=60, volume_fraction=0.1, box_length=0.5, stiffness=1e5, velocity_rms=0.3, t_end=0.05,
             thermalization=0.5, snapshots=2, backend="cpu", species=TWO)


def _sp(*pairs):
    return [{"radius_ratio": r, "number_fraction": f} for r, f in pairs]


@pytest.mark.parametrize("extra,needle", [
    (dict(species=_sp((1.0, 0.5), (0.005, 0.5))), "radius_ratio = 0.005 is outside the allowed range [0.01, 1]"),
    (dict(species=_sp((1.5, 0.5), (1.0, 0.5))), "radius_ratio = 1.5 is outside the allowed range [0.01, 1]"),
    (dict(species=_sp((1.0, 1.0), (0.5, 0.0))), "number_fraction = 0.0 is outside the allowed range (0, 1]"),
    (dict(species=[]), "species has 0 entries, outside the allowed range 1 ... 16"),
    (dict(species=_sp(*[(1.0 - 0.05 * k, 1 / 17) for k in range(17)])), "outside the allowed range 1 ... 16"),
    (dict(species=TWO, shape="ellipsoid", elongation=2.0, e_t=-1.0), "species is given but shape is 'ellipsoid'"),
    (dict(species=TWO, volume_fraction=0.35), f"volume_fraction = 0.35 is above {SPECIES_MAX_VOLUME_FRACTION:g}"),
    (dict(species=_sp((1.0, 0.999), (0.5, 0.001)), n_particles=100),
     "species[1].number_fraction = 0.001 gives 0 of n_particles = 100"),
    (dict(species=_sp((1.0, 0.5), (0.1, 0.5)), velocity_rms=50.0), "velocity_rms = 50 m/s is too fast"),
])
def test_invalid_species_specs_name_field_and_limit(extra, needle):
    with pytest.raises(ValidationError) as exc:
        SimulationSpec(**extra)
    text = str(exc.value)
    assert needle in text
    field = "velocity_rms" if "velocity_rms" in needle else \
        "volume_fraction" if "volume_fraction" in needle else "species"
    assert field in text
    if needle.startswith(("radius_ratio =", "number_fraction =")):
        assert "species.1" in text or "species.0" in text          # the entry is located


def _normal(species):
    """The (radius_ratio, number_fraction) pairs a spec with ``species`` holds (a slow gas: any size ratio passes
    the overlap check)."""
    return [(s.radius_ratio, s.number_fraction) for s in SimulationSpec(species=species, velocity_rms=0.1).species]


def test_species_list_takes_its_normal_form():
    """No rule across the entries refuses a list the schema allows: the ratios are divided by the largest, the
    fractions by their sum, entries of equal size merged; the spec (stored verbatim) holds the normal form."""
    assert _normal(_sp((0.8, 0.2), (0.4, 0.2))) == [(1.0, 0.5), (0.5, 0.5)]
    assert _normal(_sp((0.5, 0.25), (1.0, 0.5), (0.5, 0.25))) == [(0.5, 0.5), (1.0, 0.5)]
    assert _normal(_sp((0.3, 0.4))) == [(1.0, 1.0)]                     # one size
    # the smallest ratio of the per-entry range is also the smallest ratio to the largest size
    assert _normal(_sp((0.5, 0.5), (0.01, 0.5)))[1][0] == pytest.approx(0.02, rel=1e-15)
    # a sum within 1e-9 of 1 is kept as given (specs that were valid before keep their bits)
    assert _normal(_sp((1.0, 0.5), (0.5, 0.5 + 4e-10))) == [(1.0, 0.5), (0.5, 0.5 + 4e-10)]
    # idempotent: the worker's re-validation of the stored spec gives the same bits
    for sp in (_sp((0.7, 0.3), (0.3, 0.3), (0.1, 0.3)), _sp((0.9, 1.0), (0.9, 1.0), (0.45, 1.0))):
        once = SimulationSpec(species=sp, velocity_rms=0.1)
        assert SimulationSpec.model_validate_json(once.to_json()).to_json() == once.to_json()
        assert max(s.radius_ratio for s in once.species) == 1.0
        assert math.fsum(s.number_fraction for s in once.species) == pytest.approx(1.0, abs=1e-15)


def test_scaled_species_lists_are_one_simulation(tmp_path):
    """Ratios [1, 0.4] with fractions [0.3, 0.7] and the same halved ([0.5, 0.2], [0.15, 0.35]) are one spec: the
    same stored spec and derived parameters, and bit-identical CPU runs for the same seed."""
    from engine.driver.simulate import run

    tiny = {**SMALL, "t_end": 0.004, "thermalization": 0.0}
    given = SimulationSpec(**tiny)
    halved = SimulationSpec(**{**tiny, "species": _sp((0.5, 0.15), (0.2, 0.35))})
    assert halved.to_json() == given.to_json() and derive(halved) == derive(given)
    outputs = [run(spec, tmp_path / f"{name}.h5").output for name, spec in (("given", given), ("halved", halved))]
    with h5py.File(outputs[0]) as a, h5py.File(outputs[1]) as b:
        assert a["parameters"].attrs["spec"] == b["parameters"].attrs["spec"]
        assert json.loads(a["parameters"].attrs["spec"])["species"] == TWO
        for name in ("particles/all/radius", "particles/all/species", "particles/all/position/value",
                     "particles/all/velocity/value", "observables/kinetic_energy_translational/value"):
            assert np.array_equal(a[name][()], b[name][()]), name
        assert a["particles/all/position/value"].shape == (2, 60, 3)


def test_counts_and_derived_parameters():
    assert species_counts(10, [0.25, 0.25, 0.5]) == (3, 3, 4)   # 2.5 -> 3 twice, remainder -2 to the largest
    assert species_counts(7, [0.5, 0.5]) == (3, 4)             # 4 + 4, the first of equal fractions gives one
    s = SimulationSpec(n_particles=1000, volume_fraction=0.2, box_length=1.0, velocity_rms=0.5, verlet_skin=0.4,
                       species=_sp((1.0, 0.1), (0.5, 0.3), (0.2, 0.6)))
    p = derive(s)
    assert sum(p.species_count) == 1000 and p.species_count == (100, 300, 600)
    solid = sum(c * 4 / 3 * math.pi * r**3 for c, r in zip(p.species_count, p.species_radius))
    assert solid == pytest.approx(0.2, rel=1e-12)                # phi L^3, rounding only
    assert p.radius == p.radius_max == p.species_radius[0]
    assert p.radius_min == p.species_radius[2] == pytest.approx(0.2 * p.radius_max, rel=1e-15)
    for r, m, i in zip(p.species_radius, p.species_mass, p.species_inertia):
        assert m == pytest.approx(2000 * 4 / 3 * math.pi * r**3, rel=1e-14)
        assert i == pytest.approx(0.4 * m * r * r, rel=1e-14)
    m_small = p.species_mass[2]
    assert p.m12 == pytest.approx(m_small / 2, rel=1e-15)       # smallest pair sets t_c and dt
    assert p.contact_time == pytest.approx(math.pi * math.sqrt(m_small / 2 / s.stiffness), rel=1e-14)
    assert p.dt == pytest.approx(p.contact_time / 50, rel=1e-15)
    assert p.gamma_n == pytest.approx(gamma_n_from_restitution(s.e_n, s.stiffness, m_small / 2), rel=1e-14)
    mean = sum(c * m for c, m in zip(p.species_count, p.species_mass)) / 1000
    assert p.mass_mean == pytest.approx(mean, rel=1e-14)
    assert p.temperature0 == pytest.approx(mean * 0.25 / 3, rel=1e-14)   # equipartition at <m> v_rms^2/3
    assert p.skin == pytest.approx(0.4 * p.radius_min, rel=1e-14)     # skin in units of the smallest radius
    assert p.cutoff == pytest.approx(2 * p.radius_max + p.skin, rel=1e-15)


def test_one_species_list_is_the_monodisperse_scene():
    one = SimulationSpec(species=_sp((1.0, 1.0)))
    base = SimulationSpec()
    assert derive(one) == derive(base)
    a, b = initial_spheres(one, derive(one)), initial_spheres(base, derive(base))
    assert np.array_equal(a.position, b.position) and np.array_equal(a.velocity, b.velocity)


def test_enskog_mixture_reduces_to_one_size():
    """The mixture rate (BMCSL g_ab) equals 4 (2a)^2 n g_CS sqrt(pi T/m) for one size, and is unchanged
    when one size is split into two labels."""
    a, m, n, V, T = 0.01, 2e-3, 1000, 1.0, 1e-4
    phi = n * 4 / 3 * math.pi * a**3 / V
    mono = 4 * (2 * a) ** 2 * (n / V) * carnahan_starling_g(phi) * math.sqrt(math.pi * T / m)
    assert enskog_rate_mixture((a,), (n,), (m,), V, T) == pytest.approx(mono, rel=1e-13)
    assert enskog_rate_mixture((a, a), (300, 700), (m, m), V, T) == pytest.approx(mono, rel=1e-13)


def test_cost_estimate_grows_with_the_size_ratio():
    base = estimate_cost(SimulationSpec())
    assert base["memory_bytes"] == 4096 * estimate_bytes_per_particle("float64")   # one size: as before
    slots = []
    for ratio in (1.0, 0.5, 0.2, 0.1):
        sp = _sp((1.0, 0.5), (ratio, 0.5)) if ratio < 1 else None
        frac = 0.5 if ratio == 1 else 1.0 / (1.0 + ratio**-3)      # equal solid volume of both species
        if sp is not None:
            sp = _sp((1.0, frac), (ratio, 1.0 - frac))
        # a fixed skin (0.8 smallest radii): the null default shrinks with density (engine.setup.spec)
        s = SimulationSpec(n_particles=100_000, volume_fraction=0.25, box_length=1.0, velocity_rms=0.1,
                           species=sp, verlet_skin=0.8)
        slots.append(estimate_cost(s)["list_slots"])
    assert slots[0] == 32 and slots[-1] > slots[-2] > 32
    assert slots[-1] > 3 * slots[-2] / 2


def test_placement_never_overlaps_and_interleaves():
    s = SimulationSpec(n_particles=3000, volume_fraction=0.3, box_length=1.0, velocity_rms=0.05, seed=4,
                       species=_sp((1.0, 0.05), (0.3, 0.25), (0.1, 0.7)))
    p = derive(s)
    sysA = initial_spheres(s, p)
    sysB = initial_spheres(s, p)
    assert np.array_equal(sysA.position, sysB.position) and np.array_equal(sysA.velocity, sysB.velocity)
    pos, r = sysA.position, sysA.radius
    assert np.all((pos >= 0) & (pos < s.box_length))
    sp = species_index(r, p)
    assert tuple(np.bincount(sp, minlength=3)) == p.species_count
    assert np.array_equal(np.asarray(p.species_radius)[sp], r)
    assert np.array_equal(np.asarray(p.species_mass)[sp], sysA.mass)
    # ids are shuffled: the first tenth holds every species
    assert set(sp[:300].tolist()) == {0, 1, 2}
    # no overlap anywhere (all pairs, minimum image), in chunks
    L = s.box_length
    for i0 in range(0, len(r), 500):
        d = pos[i0:i0 + 500, None, :] - pos[None, :, :]
        d -= L * np.round(d / L)
        dist = np.sqrt((d**2).sum(-1))
        gap = dist - (r[i0:i0 + 500, None] + r[None, :])
        idx = np.arange(i0, min(i0 + 500, len(r)))
        gap[np.arange(len(idx)), idx] = np.inf
        assert gap.min() >= 0.0


def test_equipartition_and_momentum():
    s = SimulationSpec(n_particles=4000, volume_fraction=0.1, box_length=1.0, velocity_rms=0.05, seed=9,
                       species=_sp((1.0, 0.2), (0.25, 0.8)))
    p = derive(s)
    sy = initial_spheres(s, p)
    m, v, w, inertia = sy.mass, sy.velocity, sy.angular_velocity, sy.inertia
    n = s.n_particles
    assert np.sum(m[:, None] * v * v) / (3 * n) == pytest.approx(p.temperature0, rel=1e-12)
    assert np.sum(inertia[:, None] * w * w) / (3 * n) == pytest.approx(p.temperature0, rel=1e-12)
    assert np.abs((m[:, None] * v).sum(0)).max() < 1e-14 * np.abs(m[:, None] * v).sum()
    sp = species_index(sy.radius, p)
    for k, count in enumerate(p.species_count):
        t_k = np.sum(m[sp == k, None] * v[sp == k] ** 2) / (3 * count)
        # statistical: the relative sd of a temperature from 3 N_k Gaussians is sqrt(2/(3 N_k)) < 3.7 %
        assert t_k == pytest.approx(p.temperature0, rel=0.12)


@pytest.mark.parametrize("e_n", [0.5, 0.8, 1.0])
def test_head_on_collision_of_unequal_spheres(e_n):
    """Radius ratio 3 (mass ratio 27) at the default dt of such a spec (t_c/50 of the SMALL pair)."""
    from engine.backends.base import ContactParams, SphereSystem
    from engine.shapes.sphere.cpu_backend import CpuBackend

    r1, r2, rho, k_n = 0.01, 0.03, 2000.0, 1e5
    m1, m2 = rho * 4 / 3 * math.pi * r1**3, rho * 4 / 3 * math.pi * r2**3
    m12 = m1 * m2 / (m1 + m2)
    dt = math.pi * math.sqrt(0.5 * m1 / k_n) / 50
    tc = math.pi * math.sqrt(m12 / k_n)
    coef = gamma_n_from_restitution(e_n, k_n, m12) / math.sqrt(m12)   # per pair: coef sqrt(m12)
    for v in (0.05, 0.0713, 0.0931):
        gap = 0.01 * r1
        pos = np.array([[0.5 - r1 - gap / 2, 0.5, 0.5], [0.5 + r2 + gap / 2, 0.5, 0.5]])
        # zero total momentum, approach speed v
        vel = np.array([[v * m2 / (m1 + m2), 0, 0], [-v * m1 / (m1 + m2), 0, 0]])
        system = SphereSystem(1.0, pos, vel, np.zeros((2, 3)), np.tile([1.0, 0, 0, 0], (2, 1)),
                              np.array([r1, r2]), np.array([m1, m2]), 0.4 * np.array([m1 * r1**2, m2 * r2**2]))
        params = ContactParams(k_n=k_n, gamma_n_coef=coef, k_t=None, friction=None, dt=dt, skin=0.4 * r1,
                               overlap_limit=0.5)
        be = CpuBackend(system, params)
        assert be.mg is not None                      # two sizes three apart: multigrid lists
        p0 = (be.mass[:, None] * be.vel).sum(0)
        be.advance(int((gap / v + 3 * tc) / dt) + 1)
        e = (be.vel[1, 0] - be.vel[0, 0]) / v
        # 1e-3 (docs/physics.md §3.4): the event-corrected contact leaves O(dt^2) (here dt = t_c,pair / 69)
        assert abs(e - e_n) < 1e-3, (v, e)
        p1 = (be.mass[:, None] * be.vel).sum(0)
        # pairwise equal and opposite forces: momentum to rounding of m v ~ 1e-4 kg m/s
        assert np.abs(p1 - p0).max() < 1e-15


def test_polydisperse_run_writes_species_and_radii(tmp_path):
    from engine.driver.simulate import run

    out = tmp_path / "poly.h5"
    summary = run(SimulationSpec(**SMALL), out)
    assert summary.steps > 0
    p = derive(SimulationSpec(**SMALL))
    with h5py.File(out) as f:
        part = f["particles/all"]
        sp = part["species"][()]
        r = part["radius"][()]
        m = part["mass"][()]
        assert sp.dtype == np.int32 and sp.shape == (60,)
        assert tuple(np.bincount(sp)) == p.species_count == (18, 42)
        assert np.array_equal(r, np.asarray(p.species_radius)[sp])
        assert np.array_equal(m, np.asarray(p.species_mass)[sp])
        assert part["radius"].attrs["unit"] == "m" and part["mass"].attrs["unit"] == "kg"
        assert part["position"]["value"].shape == (2, 60, 3)
        par = f["parameters"].attrs
        spec = json.loads(par["spec"])
        assert spec["species"] == TWO
        assert list(par["species_count"]) == [18, 42]
        assert np.allclose(par["species_radius"], p.species_radius, rtol=1e-15, atol=0)
        e = f["observables/kinetic_energy_translational/value"][()]
        assert np.all(np.isfinite(e)) and e[-1] < e[0]           # dissipative: the gas cooled
        assert f["observables/contacts/value"][()].max() >= 1         # the sizes did collide
