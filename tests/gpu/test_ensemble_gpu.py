"""run_ensemble on the GPU (packed CudaEnsemble): each scene as the scene run alone, to rounding; a
cancelled and an unstable scene drop out alone. Needs a CUDA GPU."""

import h5py
import numpy as np
import pytest

from engine.backends.base import cuda_available

pytestmark = pytest.mark.skipif(not cuda_available(), reason="needs a CUDA GPU")

BASE = dict(n_particles=512, volume_fraction=0.05, box_length=1.0, t_end=0.03, thermalization=0.3, snapshots=2,
            velocity_rms=1.0, backend="cuda")
#: per-scene N, phi (radius, mass, contact time, dt), e_n, e_t, friction, schedule and seed
SCENES = [dict(BASE), dict(BASE, n_particles=1000, volume_fraction=0.08, e_n=0.6, e_t=-1.0, seed=3),
          dict(BASE, n_particles=300, e_n=0.9, e_t=0.4, friction=0.3, seed=7, thermalization=0.0,
               output_interval=0.0004)]
UNSTABLE = dict(BASE, n_particles=64, volume_fraction=0.05, box_length=0.5, velocity_rms=1.2, stiffness=1e6,
                overlap_limit=0.02, t_end=0.1)


def _series(path):
    with h5py.File(path) as f:
        return {name: f[f"observables/{name}/value"][()] for name in f["observables"]}, \
            f["particles/all/position/value"][()], dict(f["parameters"].attrs)


def test_each_scene_of_a_cuda_ensemble_is_the_scene_run_alone(tmp_path):
    from engine.driver.ensemble import run_ensemble
    from engine.driver.simulate import RunSummary, run

    outs = [tmp_path / f"e{k}.h5" for k in range(len(SCENES))]
    results = run_ensemble(SCENES, outs)
    assert all(isinstance(r, RunSummary) and r.backend == "cuda" for r in results), results
    for k, spec in enumerate(SCENES):
        alone = run(spec, tmp_path / f"a{k}.h5")
        cpu = run({**spec, "backend": "cpu"}, tmp_path / f"c{k}.h5")
        (obs_e, pos_e, par_e), (obs_a, pos_a, _), (obs_c, _, _) = (
            _series(outs[k]), _series(alone.output), _series(cpu.output))
        assert par_e["ensemble_size"] == 3 and par_e["ensemble_index"] == k
        assert obs_e.keys() == obs_a.keys()
        for name in obs_e:  # a few collisions per particle: rounding differences stay small
            # the Sonine cumulants are (ratio of moments) - 1: their rounding is relative to 1 + a
            shift = 1.0 if name.startswith("sonine_") else 0.0
            assert np.allclose(obs_e[name] + shift, obs_a[name] + shift, rtol=1e-8, atol=1e-12), (k, name)
            assert np.allclose(obs_e[name] + shift, obs_c[name] + shift, rtol=1e-6, atol=1e-10), (k, name, "cpu")
        box = spec["box_length"]
        d = (pos_e - pos_a + box / 2) % box - box / 2
        assert np.abs(d).max() < 1e-9 * box, k


def test_cancelled_and_unstable_scenes_drop_out_alone_on_the_gpu(tmp_path):
    from engine.errors import Cancelled, InstabilityError
    from engine.driver.ensemble import run_ensemble
    from engine.driver.simulate import RunSummary

    specs = [SCENES[0], UNSTABLE, SCENES[2]]
    outs = [tmp_path / f"u{k}.h5" for k in range(3)]
    calls = []

    def cancel(k):
        calls.append(k)
        return k == 2 and calls.count(2) > 5

    results = run_ensemble(specs, outs, should_cancel=cancel)
    assert isinstance(results[0], RunSummary) and outs[0].exists()
    assert isinstance(results[1], InstabilityError) and "particle" in str(results[1]) and not outs[1].exists()
    assert isinstance(results[2], Cancelled) and not outs[2].exists()
    obs, _, par = _series(outs[0])
    assert par["ensemble_size"] == 3 and np.isfinite(obs["kinetic_energy_translational"]).all()
