"""Spec validation messages and derived parameters of Hidalgo et al. (2013)."""

import math

import pytest
from pydantic import ValidationError

from engine.setup.params import derive, e_t_effective, gamma_n_from_restitution, k_t_paper
from engine.setup.spec import SimulationSpec


def test_defaults_are_hidalgo_2013():
    s = SimulationSpec()
    assert (s.n_particles, s.box_length, s.volume_fraction, s.stiffness, s.density) == (4096, 2.0, 0.008, 1e8, 2000.0)
    p = derive(s)
    # Hidalgo et al. (2013) scene (docs/physics.md §3.4): a = 0.015509 m, m = 1/32 kg, n = 512 m^-3, undamped
    # t_c = 3.93e-5 s
    assert p.radius == pytest.approx(0.015509, rel=1e-4)
    assert p.mass == pytest.approx(1 / 32, rel=1e-12)
    assert p.number_density == pytest.approx(512.0)
    assert p.contact_time == pytest.approx(3.93e-5, rel=1e-3)
    assert p.dt == pytest.approx(p.contact_time / 50)


@pytest.mark.parametrize("field,value,needle", [
    ("n_particles", 1, "n_particles = 1 is outside the allowed range 2"),
    ("e_n", 0.0, "e_n = 0.0 is outside the allowed range (0, 1]"),
    ("e_n", 1.2, "e_n = 1.2 is outside"),
    ("e_t", -1.5, "e_t = -1.5 is outside the allowed range [-1, 1]"),
    ("volume_fraction", 0.7, "above random close packing"),
    ("volume_fraction", 0.0, "volume_fraction = 0.0 is outside"),
    ("stiffness", -1.0, "stiffness = -1.0 must be a finite number > 0"),
    ("friction", -0.1, "friction = -0.1 is outside"),
    ("dt", 1e-3, "dt = 0.001 s cannot resolve a contact"),
    ("elongation", 2.0, "elongation must be 1 for spheres"),
    ("velocity_rms", 500.0, "velocity_rms = 500 m/s is too fast for stiffness"),
    # found by schemathesis: T0 underflowed to 0 and derive() divided by the collision rate (HTTP 500)
    ("velocity_rms", 3.7628546016618845e-180, "velocity_rms = 3.76285e-180 m/s is too slow"),
    ("precision", "float16", "precision"),
    ("n_particles", 3, "box_length = 2 m is too small for particles of radius"),
])
def test_invalid_values_name_field_value_and_range(field, value, needle):
    extra = {"volume_fraction": 0.4} if needle.startswith("box_length") else {}
    with pytest.raises(ValidationError) as exc:
        SimulationSpec(**{field: value}, **extra)
    text = str(exc.value)
    assert needle in text
    assert field in text


def test_unknown_key_is_refused():
    with pytest.raises(ValidationError, match="n_partikles"):
        SimulationSpec.model_validate({"n_partikles": 10})


def test_gamma_n_restores_e_n_exactly_under_rule_a():
    # e = exp(-pi beta / omega) with beta = gamma/(2 m12), omega = sqrt(k/m12 - beta^2)
    for e in (0.3, 0.6, 0.8, 0.95):
        k, m12 = 1e8, 1 / 64
        g = gamma_n_from_restitution(e, k, m12)
        beta = g / (2 * m12)
        omega = math.sqrt(k / m12 - beta**2)
        assert math.exp(-math.pi * beta / omega) == pytest.approx(e, rel=1e-12)
        # gamma/sqrt(k m12), contact ending at delta = 0 (docs/physics.md §1.2)
    assert gamma_n_from_restitution(0.8, 1.0, 1.0) == pytest.approx(0.141701, abs=1e-6)
    assert gamma_n_from_restitution(1.0, 1.0, 1.0) == 0.0


def test_k_t_eq4_and_effective_e_t():
    assert k_t_paper(1.0, 7.0) == pytest.approx(2.0)          # k_t/k_n = 2/7 at e_t = 1
    assert k_t_paper(-1.0, 7.0) == 0.0
    # docs/physics.md §1.3: e_n = e_t = 0.6 -> 0.6230; 0.8/0.8 -> 0.8038; 0.9/0.9 -> 0.9007
    assert e_t_effective(0.6, 0.6) == pytest.approx(0.6230, abs=1e-4)
    assert e_t_effective(0.8, 0.8) == pytest.approx(0.8038, abs=1e-4)
    assert e_t_effective(0.9, 0.9) == pytest.approx(0.9007, abs=1e-4)


def test_smooth_spec_has_no_tangential_spring():
    assert derive(SimulationSpec(e_t=-1.0)).k_t == 0.0
    assert derive(SimulationSpec(friction=0.0)).k_t == 0.0
