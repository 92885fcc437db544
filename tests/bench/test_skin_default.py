"""The backend-dependent default Verlet skin (issue 6): a null ``verlet_skin`` is 0.4 a on the CPU and 0.8 a on
CUDA (spheres), resolved where the backend is known (engine.simulate.SceneRun), recorded in the result file's
/parameters, the same in ensembles; an explicit value always wins; the CPU default is unchanged.
"""

from __future__ import annotations

import json

import h5py
import pytest
from pydantic import ValidationError

from engine.backends.ensemble import resolve_backend
from engine.ensemble import run_ensemble
from engine.params import derive
from engine.simulate import SceneRun, run
from engine.spec import DEFAULT_VERLET_SKIN, SimulationSpec, default_verlet_skin

# tests/engine/test_ensemble.py's tiny scene
TINY = dict(n_particles=64, volume_fraction=0.05, box_length=0.5, t_end=0.01, thermalization=0.2,
            snapshots=0, backend="cpu", velocity_rms=1.0)


def test_default_table():
    assert DEFAULT_VERLET_SKIN == {"cpu": 0.4, "cuda": 0.8}
    assert SimulationSpec().verlet_skin is None
    assert default_verlet_skin("cpu") == 0.4 and default_verlet_skin("cuda") == 0.8
    # ellipsoid skins are not measured on a GPU: they keep the CPU value; an unresolved 'auto' too
    assert default_verlet_skin("cuda", "ellipsoid") == 0.4 and default_verlet_skin("auto") == 0.4


@pytest.mark.parametrize("backend, want", [("cpu", 0.4), ("cuda", 0.8)])
def test_scene_resolves_the_backend_default(tmp_path, backend, want):
    spec = SimulationSpec(**TINY)
    scene = SceneRun(spec, tmp_path / "r.h5", backend=backend)     # builds no backend: no GPU needed
    assert scene.backend == backend and scene.verlet_skin == want
    assert scene.p.skin == want * scene.p.radius
    assert scene.cool.skin == scene.therm.skin == scene.p.skin
    assert scene.spec.verlet_skin is None and json.loads(scene.spec_json)["verlet_skin"] is None


def test_cpu_default_is_unchanged(tmp_path):
    """Bit for bit the former default 0.4 a: the same derived skin as an explicit 0.4."""
    explicit = derive(SimulationSpec(**TINY, verlet_skin=0.4))
    assert SceneRun(SimulationSpec(**TINY), tmp_path / "r.h5").p == explicit
    assert derive(SimulationSpec(**TINY)) == explicit


def test_auto_resolves_like_the_backend():
    spec = SimulationSpec(**{**TINY, "backend": "auto"})
    scene = SceneRun(spec, "unused.h5")
    assert scene.verlet_skin == default_verlet_skin(resolve_backend("auto"))


@pytest.mark.parametrize("backend", ["cpu", "cuda"])
def test_explicit_skin_wins(tmp_path, backend):
    scene = SceneRun(SimulationSpec(**TINY, verlet_skin=0.3), tmp_path / "r.h5", backend=backend)
    assert scene.verlet_skin == 0.3 and scene.p.skin == 0.3 * scene.p.radius


def test_cuda_spec_derives_the_cuda_default():
    """derive() alone (benches, validation scripts) reads the spec's own backend."""
    p = derive(SimulationSpec(**{**TINY, "backend": "cuda"}))
    assert p.skin == 0.8 * p.radius


def test_skin_in_result_parameters(tmp_path):
    out = tmp_path / "r.h5"
    run(SimulationSpec(**TINY), out)
    with h5py.File(out) as f:
        par = f["parameters"].attrs
        assert float(par["verlet_skin"]) == 0.4
        assert float(par["skin"]) == pytest.approx(0.4 * float(par["radius"]), rel=1e-15)
        assert json.loads(par["spec"])["verlet_skin"] is None


def test_ensemble_scenes_resolve_per_scene(tmp_path):
    outs = [tmp_path / "a.h5", tmp_path / "b.h5"]
    res = run_ensemble([SimulationSpec(**TINY), SimulationSpec(**TINY, verlet_skin=0.6, seed=1)], outs)
    assert all(not isinstance(r, BaseException) for r in res), res
    got = []
    for o in outs:
        with h5py.File(o) as f:
            got.append(float(f["parameters"].attrs["verlet_skin"]))
    assert got == [0.4, 0.6]


def test_box_check_uses_the_largest_default():
    # 27 spheres at phi = 0.2 in a box of 8.27 radii: 3 neighbour cutoffs are 7.2 a at L_v = 0.4 a, 8.4 a at 0.8 a
    tight = dict(n_particles=27, volume_fraction=0.2, box_length=0.2, velocity_rms=0.5)
    SimulationSpec(**tight, backend="cpu")                       # the CPU default fits
    SimulationSpec(**tight, backend="auto", verlet_skin=0.4)     # an explicit skin is checked as given
    for backend in ("auto", "cuda"):                              # the run may land on a GPU: 0.8 a must fit
        with pytest.raises(ValidationError, match="verlet_skin = 0.8, the default of backend"):
            SimulationSpec(**tight, backend=backend)
