"""A shape is a plug-in: a package plus one line in engine.shapes.SHAPES, no other engine edit.

The test writes a package ``ball`` (a sphere under another name: the sphere's traits, kernels and host classes,
with its own system type) into a temporary directory, registers it with one SHAPES entry, and runs the public
paths on it: spec validation, engine.run (a whole job to its result file), engine.run_ensemble and the backend
factory. The ball's results must be the sphere's, bit for bit (same physics, same compiled loop); the
unregistered name must be refused with the field and the registered names.
"""

from __future__ import annotations

import sys
import textwrap

import h5py
import numpy as np
import pytest

from engine.shapes import SHAPES, shape_of

TINY = dict(n_particles=64, volume_fraction=0.05, box_length=0.5, t_end=0.05, thermalization=0.2,
            snapshots=1, backend="cpu", velocity_rms=1.0)

PACKAGE = {
    "__init__.py": '''
        """A sphere under another name (test plug-in): the sphere's traits."""
        from engine.shapes.sphere import (ELONGATED, SPECIES, SKIN_BY_VOLUME_FRACTION, RANDOM_START,  # noqa: F401
                                          body, spec_error)

        NAME = "ball"
        SUMMARY = "a sphere under another name"
        ''',
    "kernels.py": '''
        from engine.shapes.sphere.kernels import *  # noqa: F401,F403  (the sphere's compiled loop)
        ''',
    "device.py": '''
        from engine.shapes.sphere.device import *  # noqa: F401,F403
        ''',
    "host.py": '''
        import dataclasses
        from typing import ClassVar

        from engine.backends.base import SphereSystem
        from engine.shapes.sphere import host as sphere


        @dataclasses.dataclass
        class BallSystem(SphereSystem):
            shape: ClassVar[str] = "ball"


        SYSTEM = BallSystem


        def initial_system(spec, p):
            s = sphere.initial_system(spec, p)
            return BallSystem(**{f.name: getattr(s, f.name) for f in dataclasses.fields(s)})


        writer_fields = sphere.writer_fields
        cpu_backend = sphere.cpu_backend
        cuda_ensemble = sphere.cuda_ensemble
        cuda_backend = sphere.cuda_backend
        ''',
}


@pytest.fixture
def ball(tmp_path, monkeypatch):
    pkg = tmp_path / "ball_shape"
    pkg.mkdir()
    for name, text in PACKAGE.items():
        (pkg / name).write_text(textwrap.dedent(text))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(SHAPES, "ball", "ball_shape")          # the one registry line
    yield
    for m in [m for m in sys.modules if m.startswith("ball_shape")]:
        del sys.modules[m]


def _series(path):
    with h5py.File(path) as f:
        obs = {k: f[f"observables/{k}/value"][()] for k in ("kinetic_energy_translational",
                                                              "kinetic_energy_rotational", "contacts")}
        obs["position"] = f["particles/all/position/value"][()]
    return obs


def test_a_registered_package_runs_through_every_public_path(ball, tmp_path):
    from engine import run
    from engine.backends.registry import make_backend
    from engine.driver.ensemble import run_ensemble
    from engine.setup.spec import SimulationSpec

    spec = SimulationSpec(shape="ball", **TINY)
    assert spec.shape == "ball"
    run(spec, tmp_path / "ball.h5")
    run(SimulationSpec(shape="sphere", **TINY), tmp_path / "sphere.h5")
    a, b = _series(tmp_path / "ball.h5"), _series(tmp_path / "sphere.h5")
    for key in ("kinetic_energy_translational", "kinetic_energy_rotational", "contacts", "position"):
        assert np.array_equal(a[key], b[key]), key      # the same physics and loop: bit for bit
    assert a["kinetic_energy_translational"].size > 2

    results = run_ensemble([spec, spec.model_copy(update={"seed": 2})], [tmp_path / "e0.h5", tmp_path / "e1.h5"])
    assert all(not isinstance(r, BaseException) for r in results), results
    assert np.array_equal(_series(tmp_path / "e0.h5")["position"], a["position"])

    from engine.setup.params import derive
    from engine.shapes import host

    system = host("ball").initial_system(spec, derive(spec))
    assert shape_of(system) == "ball"
    assert type(make_backend("cpu", system, _contact(spec))).__name__ == "CpuBackend"


def _contact(spec):
    from engine.backends.base import ContactParams
    from engine.setup.params import derive

    p = derive(spec)
    return ContactParams(k_n=p.k_n, gamma_n_coef=p.gamma_n_coef, k_t=p.k_t or None, friction=None, dt=p.dt,
                         skin=p.skin)


def test_an_unregistered_shape_is_refused_with_the_registered_names():
    from pydantic import ValidationError

    from engine.setup.spec import SimulationSpec

    with pytest.raises(ValidationError) as e:
        SimulationSpec(shape="ball", **TINY)
    msg = str(e.value)
    assert "shape" in msg and "'ball'" in msg and "'sphere' or 'ellipsoid'" in msg
