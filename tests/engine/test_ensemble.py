"""Ensembles on the CPU: each scene of run_ensemble is the scene run alone; per-scene cancel, failure, resume."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from engine.backends.ensemble import SerialEnsemble, make_ensemble, resolve_backend
from engine.driver.ensemble import run_ensemble
from engine.driver.simulate import TIMINGS, RunSummary, SceneRun, drive, run
from engine.errors import BackendUnavailable, Cancelled, InstabilityError, SpecError
from engine.output.h5md import partial_path
from engine.setup.spec import SimulationSpec

# tests/engine/test_simulate.py's tiny scene, shortened
TINY = dict(n_particles=64, volume_fraction=0.05, box_length=0.5, t_end=0.03, thermalization=0.5,
            snapshots=3, backend="cpu", velocity_rms=1.0)
# three different scenes: N, phi (hence radius, mass, contact time and dt), e_n, e_t, seed, schedule
SCENES = [
    dict(TINY),
    dict(TINY, n_particles=96, volume_fraction=0.04, e_n=0.6, e_t=-1.0, seed=5, snapshots=2),
    dict(TINY, n_particles=48, volume_fraction=0.06, e_n=0.9, seed=2, thermalization=0.0,
         output_interval=0.0004, t_end=0.02),
]
# tests/engine/test_simulate.py's blow-up: the tails of the speed distribution overlap > 2 % of a radius
UNSTABLE = dict(TINY, velocity_rms=1.2, stiffness=1e6, overlap_limit=0.02, t_end=0.1)


def datasets(path) -> dict:
    out = {}
    with h5py.File(path) as f:
        f.visititems(lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    return out


def assert_same_file(a, b, exact=True):
    da, db = datasets(a), datasets(b)
    assert da.keys() == db.keys()
    assert "observables/temperature_translational/value" in da and "particles/all/position/value" in da
    for key in da:
        if exact or da[key].dtype.kind not in "f":
            assert np.array_equal(da[key], db[key]), key
        else:
            assert np.allclose(da[key], db[key], rtol=1e-9, atol=1e-12), key


@pytest.fixture(scope="module")
def alone(tmp_path_factory):
    """Each scene run alone with run()."""
    d = tmp_path_factory.mktemp("alone")
    paths = []
    for k, s in enumerate(SCENES):
        run(SimulationSpec(**s), d / f"{k}.h5")
        paths.append(d / f"{k}.h5")
    return paths


def test_each_scene_is_bit_identical_to_the_scene_run_alone(tmp_path, alone):
    outs = [tmp_path / f"e{k}.h5" for k in range(len(SCENES))]
    seen: dict = {}
    results = run_ensemble(SCENES, outs, progress=lambda k, p: seen.setdefault(k, []).append(p))
    assert all(isinstance(r, RunSummary) for r in results), results
    for k, out in enumerate(outs):
        assert results[k].output == out and not partial_path(out).exists()
        assert_same_file(alone[k], out)
        with h5py.File(out) as f:
            par = f["parameters"].attrs
            assert par["ensemble_size"] == 3 and par["ensemble_index"] == k and par["backend"] == "cpu"
        assert seen[k][-1].fraction == pytest.approx(1.0) and seen[k][-1].phase == "cooling"
        extra = dict(results[k].extra)
        timings = extra.pop("timings")
        assert extra.pop("ensemble_setup_s") > 0.0
        assert extra == {"ensemble_size": 3, "ensemble_index": k}
        assert set(timings) == set(TIMINGS) and all(v >= 0.0 for v in timings.values())
        assert timings["loop"] == results[k].loop_s and timings["records"] > 0.0
    assert len({len(v) for v in seen.values()}) > 1  # per-scene schedules


def test_lockstep_advancing_agrees_to_rounding(tmp_path, alone):
    """The packed-GPU policy (all scenes by the distance to the nearest stop of any scene) on the CPU:
    chunk boundaries move, so the velocity half kicks round differently; equal to rounding."""
    outs = [tmp_path / f"l{k}.h5" for k in range(len(SCENES))]
    scenes = [SceneRun(s, o) for s, o in zip(SCENES, outs)]
    results = drive(scenes, lambda systems, contacts: SerialEnsemble("cpu", systems, contacts), lockstep=True)
    assert all(isinstance(r, RunSummary) for r in results), results
    for k, out in enumerate(outs):
        assert_same_file(alone[k], out, exact=False)


def test_cancel_one_scene_the_others_finish(tmp_path, alone):
    outs = [tmp_path / f"c{k}.h5" for k in range(len(SCENES))]
    calls = []

    def cancel(k):
        if k == 1:
            calls.append(1)
            return len(calls) > 40
        return False

    results = run_ensemble(SCENES, outs, should_cancel=cancel)
    assert isinstance(results[1], Cancelled) and len(calls) == 41
    assert not outs[1].exists() and not partial_path(outs[1]).exists()
    for k in (0, 2):
        assert isinstance(results[k], RunSummary)
        assert_same_file(alone[k], outs[k])


def test_unstable_scene_fails_alone(tmp_path, alone):
    specs = [SCENES[0], UNSTABLE, SCENES[2]]
    outs = [tmp_path / f"u{k}.h5" for k in range(3)]
    results = run_ensemble(specs, outs)
    assert isinstance(results[1], InstabilityError)
    assert "at step" in str(results[1]) and "particle" in str(results[1]) and "likely cause" in str(results[1])
    assert not outs[1].exists() and not partial_path(outs[1]).exists()
    for k in (0, 2):
        assert isinstance(results[k], RunSummary)
        assert_same_file(alone[k], outs[k])


def _drive_serial(scenes):
    return drive(scenes, lambda systems, contacts: SerialEnsemble("cpu", systems, contacts))


def test_a_record_that_fails_ends_its_scene_only(tmp_path, alone, monkeypatch):
    """The energy check of a record raises: that scene ends with the error and no file, the others are
    unchanged."""
    orig = SceneRun._record

    def failing(self, step_done, t_sim, obs):
        if self.output.name == "f1.h5" and step_done >= 10:
            raise InstabilityError(f"total energy rose at step {step_done}", step=step_done)
        return orig(self, step_done, t_sim, obs)

    monkeypatch.setattr(SceneRun, "_record", failing)
    outs = [tmp_path / f"f{k}.h5" for k in range(len(SCENES))]
    results = _drive_serial([SceneRun(s, o) for s, o in zip(SCENES, outs)])
    assert isinstance(results[1], InstabilityError) and "energy rose" in str(results[1])
    assert not outs[1].exists() and not partial_path(outs[1]).exists()
    for k in (0, 2):
        assert isinstance(results[k], RunSummary)
        assert_same_file(alone[k], outs[k])


def test_a_cancelled_scene_leaves_no_file(tmp_path, alone):
    outs = [tmp_path / f"k{k}.h5" for k in range(len(SCENES))]
    calls = []

    def cancel():
        calls.append(1)
        return len(calls) > 40

    scenes = [SceneRun(s, o, should_cancel=cancel if k == 1 else None)
              for k, (s, o) in enumerate(zip(SCENES, outs))]
    results = _drive_serial(scenes)
    assert isinstance(results[1], Cancelled)
    assert not outs[1].exists() and not partial_path(outs[1]).exists()
    for k in (0, 2):
        assert_same_file(alone[k], outs[k])


def test_scene_that_cannot_start_fails_alone(tmp_path, alone):
    """An overlapping start makes the ensemble's construction fail; the driver finds the scene."""
    outs = [tmp_path / f"s{k}.h5" for k in range(2)]
    scenes = [SceneRun(SCENES[0], outs[0]), SceneRun(SCENES[1], outs[1])]
    scenes[1].system.position[1] = scenes[1].system.position[0]  # coincident centres
    results = drive(scenes, lambda systems, contacts: make_ensemble("cpu", systems, contacts),
                    build_one=lambda system, contact: SerialEnsemble("cpu", [system], [contact]))
    assert isinstance(results[1], InstabilityError) and "at the start" in str(results[1])
    assert not outs[1].exists() and not partial_path(outs[1]).exists()
    assert isinstance(results[0], RunSummary)
    assert_same_file(alone[0], outs[0])
    with h5py.File(outs[0]) as f:
        assert f["parameters"].attrs["ensemble_size"] == 1


def test_incompatible_specs_are_refused_naming_the_field(tmp_path):
    with pytest.raises(SpecError, match=r"precision = 'float32' of scene 1 differs from precision = 'float64'"):
        run_ensemble([TINY, dict(TINY, precision="float32")], [tmp_path / "a.h5", tmp_path / "b.h5"])
    ell = dict(TINY, shape="ellipsoid", elongation=1.5, e_t=-1.0)
    with pytest.raises(SpecError, match=r"shape = 'ellipsoid' of scene 1 differs"):
        run_ensemble([TINY, ell], [tmp_path / "a.h5", tmp_path / "b.h5"])
    with pytest.raises(SpecError, match=r"backend: scene 0 resolves to 'cpu' and scene 1 to 'cuda'"):
        run_ensemble([TINY, dict(TINY, backend="cuda")], [tmp_path / "a.h5", tmp_path / "b.h5"])
    with pytest.raises(ValueError, match="outputs: 1 paths for 2 specs"):
        run_ensemble([TINY, TINY], [tmp_path / "a.h5"])
    with pytest.raises(ValueError, match="same file"):
        run_ensemble([TINY, TINY], [tmp_path / "a.h5", tmp_path / "a.h5"])
    assert not any(tmp_path.iterdir())


def test_backend_resolution():
    from engine.backends.base import cuda_available

    assert resolve_backend("cpu") == "cpu" and resolve_backend("cpu", "ellipsoid") == "cpu"
    # ellipsoids have a CUDA backend (engine/shapes/spheroid/cuda_backend.py): same rules as spheres
    assert resolve_backend("cuda", "ellipsoid") == "cuda"
    assert resolve_backend("auto", "ellipsoid") == resolve_backend("auto") == ("cuda" if cuda_available() else "cpu")
    with pytest.raises(BackendUnavailable, match="unknown backend 'gpu'"):
        resolve_backend("gpu")


def test_checkpointed_ensemble_resumes_per_scene(tmp_path, alone):
    """Both scenes stopped mid-run with checkpoints; a new ensemble resumes each from its own."""
    specs = [dict(SCENES[0], thermalization=0.0), SCENES[2]]
    ref = [tmp_path / f"r{k}.h5" for k in range(2)]
    run(SimulationSpec(**specs[0]), ref[0])
    outs = [tmp_path / f"o{k}.h5" for k in range(2)]
    cks = [tmp_path / f"ck{k}" for k in range(2)]
    calls = {0: 0, 1: 0}

    def stop_midway(k):
        calls[k] += 1
        return calls[k] > 30

    results = run_ensemble(specs, outs, should_cancel=stop_midway, checkpoint_dirs=cks, checkpoint_interval=0.0)
    assert all(isinstance(r, Cancelled) for r in results)
    assert all((ck / "state.npz").exists() for ck in cks) and not any(o.exists() for o in outs)
    results = run_ensemble(specs, outs, checkpoint_dirs=cks, checkpoint_interval=0.0)
    assert all(isinstance(r, RunSummary) and r.resumed_from_step > 0 for r in results), results
    assert not any(ck.exists() for ck in cks)
    for a, b in ((ref[0], outs[0]), (alone[2], outs[1])):
        with h5py.File(a) as fa, h5py.File(b) as fb:
            for name in ("kinetic_energy_translational", "kinetic_energy_rotational", "contacts"):
                assert np.array_equal(fa[f"observables/{name}/step"][()], fb[f"observables/{name}/step"][()])
                # the resumed scene rebuilds its neighbour list at the resume point: equal to rounding
                assert np.allclose(fa[f"observables/{name}/value"][()], fb[f"observables/{name}/value"][()],
                                   rtol=1e-9, atol=0)


def test_scenes_set_up_on_threads_write_the_same_files(tmp_path, monkeypatch):
    """An ensemble of >= 8 small scenes is set up on several threads (engine.driver.ensemble._setup_threads); each
    scene's start comes from its own Generator, so every file equals the one-thread set-up's, bit for bit."""
    import engine.driver.ensemble as ens_mod

    specs = [dict(TINY, seed=s, thermalization=0.0, t_end=0.005, snapshots=1,
                  n_particles=64 + 8 * (s % 3)) for s in range(9)]
    assert ens_mod._setup_threads([SimulationSpec(**s) for s in specs]) > 1 or ens_mod.os.cpu_count() == 1
    threaded = [tmp_path / f"t{k}.h5" for k in range(len(specs))]
    assert all(isinstance(r, RunSummary) for r in run_ensemble(specs, threaded))
    monkeypatch.setattr(ens_mod, "_setup_threads", lambda specs: 1)
    single = [tmp_path / f"s{k}.h5" for k in range(len(specs))]
    assert all(isinstance(r, RunSummary) for r in run_ensemble(specs, single))
    for a, b in zip(threaded, single):
        assert_same_file(a, b)


def test_which_ensembles_are_set_up_on_threads():
    import engine.driver.ensemble as ens_mod

    small = [SimulationSpec(**dict(TINY, seed=s)) for s in range(8)]
    assert ens_mod._setup_threads(small[:7]) == 1                      # too few scenes
    big = SimulationSpec(n_particles=1 << 20, volume_fraction=0.058, box_length=2.0 * 256 ** (1 / 3))
    assert ens_mod._setup_threads(small[:7] + [big]) == 1              # a parallel (prange) start
    assert 1 <= ens_mod._setup_threads(small) <= 8


def _two_cpu_scenes():
    from engine.setup.params import derive
    from engine.setup.scene import initial_spheres
    from engine.driver.simulate import contact_params

    out = []
    for seed in (1, 2):
        spec = SimulationSpec(n_particles=64, volume_fraction=0.1, e_n=0.8, e_t=0.8, seed=seed, thermalization=0.0)
        p = derive(spec)
        out.append((initial_spheres(spec, p), contact_params(spec, p, thermalization=False)))
    return [s for s, _ in out], [c for _, c in out]


def test_advance_observing_by_default_observes_after_each_count_as_advance_then_observe_does():
    systems, contacts = _two_cpu_scenes()
    a, b = SerialEnsemble("cpu", systems, contacts), SerialEnsemble("cpu", systems, contacts)
    assert not a.observes_in_loop()
    failed, seen = a.advance_observing(30, [10, 25, 30])
    assert failed == {} and len(seen) == 3
    done = 0
    for k, obs in zip((10, 25, 30), seen):
        assert b.advance(k - done) == {}
        done = k
        assert b.observe() == obs       # the same steps on the same backend: bit for bit
    for bad in ([], [0, 30], [10, 10, 30], [10, 20]):
        with pytest.raises(ValueError, match="observation steps"):
            a.advance_observing(30, bad)
