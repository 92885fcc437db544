"""Every derived parameter is made once, in engine/setup/params.py: a scene derives its spec once, and the skin of
the backend it resolves later (with_backend) is the skin a derivation with that skin named gives, bit for bit."""

from __future__ import annotations

import pytest

import engine.driver.simulate as simulate
from engine.driver.simulate import SceneRun
from engine.setup.params import default_verlet_skin, derive, with_backend
from engine.setup.spec import SimulationSpec

# tests/bench/test_skin_default.py's tiny scene
TINY = dict(n_particles=64, volume_fraction=0.05, box_length=0.5, t_end=0.01, thermalization=0.2,
            snapshots=0, backend="cpu", velocity_rms=1.0)
SPECIES = [{"radius_ratio": 1.0, "number_fraction": 0.5}, {"radius_ratio": 0.6, "number_fraction": 0.5}]


@pytest.mark.parametrize("backend", ["cpu", "cuda"])
def test_a_scene_derives_its_spec_once(tmp_path, monkeypatch, backend):
    calls = []

    def counted(spec):
        calls.append(spec)
        return derive(spec)

    monkeypatch.setattr(simulate, "derive", counted)
    scene = SceneRun(SimulationSpec(**TINY), tmp_path / "r.h5", backend=backend)   # builds no backend: no GPU
    assert len(calls) == 1
    assert scene.p.skin == default_verlet_skin(backend, "sphere", 0.05) * scene.p.radius


@pytest.mark.parametrize("extra", [{}, {"species": SPECIES}, {"shape": "ellipsoid", "elongation": 2.0, "e_t": -1.0},
                                   {"volume_fraction": 0.2, "box_length": 0.2}])
@pytest.mark.parametrize("backend", ["cpu", "cuda"])
def test_with_backend_is_the_derivation_with_that_skin(backend, extra):
    spec = SimulationSpec(**{**TINY, **extra})
    skin = default_verlet_skin(backend, spec.shape, spec.volume_fraction)
    assert with_backend(derive(spec), spec, backend) == derive(spec.model_copy(update={"verlet_skin": skin}))
    named = spec.model_copy(update={"verlet_skin": 0.3})          # a named skin wins over any backend's default
    assert with_backend(derive(named), named, backend).skin == derive(named).skin
