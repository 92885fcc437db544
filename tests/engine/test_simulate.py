"""The driver end to end: result-file contract, atomic write, cancel, instability, checkpoint resume."""

import json

import h5py
import numpy as np
import pytest

from engine.driver.simulate import run
from engine.errors import Cancelled, InstabilityError
from engine.output.h5md import partial_path
from engine.setup.spec import SimulationSpec

# 64 spheres of radius 2.9 cm, ~8 collisions per particle per second at 1 m/s: ~1 collision each
TINY = dict(n_particles=64, volume_fraction=0.05, box_length=0.5, t_end=0.1, thermalization=0.5,
            snapshots=3, backend="cpu", velocity_rms=1.0)

CONTRACT = [
    "h5md", "particles/all/box/edges", "particles/all/position/value", "particles/all/velocity/value",
    "particles/all/orientation/value", "particles/all/angular_velocity/value", "particles/all/radius",
    "particles/all/mass", "particles/all/id",
    "observables/kinetic_energy_translational/step", "observables/kinetic_energy_translational/time",
    "observables/kinetic_energy_translational/value", "observables/kinetic_energy_rotational/value",
    "observables/temperature_translational/value", "observables/temperature_rotational/value",
    "observables/contacts/value",
]


def test_result_file_contract(tmp_path):
    out = tmp_path / "r.h5"
    progress = []
    s = run(SimulationSpec(**TINY), out, progress=progress.append)
    assert out.exists() and not partial_path(out).exists()
    assert s.steps > 0 and s.cundall > 0
    assert progress and progress[-1].fraction == pytest.approx(1.0)
    with h5py.File(out) as f:
        for path in CONTRACT:
            assert path in f, path
        assert list(f["h5md"].attrs["version"]) == [1, 1]
        assert "dem" in f["h5md/modules"]
        assert f["particles/all/position/value"].shape == (3, 64, 3)
        assert f["particles/all/orientation/value"].shape == (3, 64, 4)
        par = f["parameters"].attrs
        spec = json.loads(par["spec"])
        assert spec["n_particles"] == 64
        for key in ("dt", "contact_time", "gamma_n", "k_t", "radius", "mass", "inertia", "cundall_number",
                    "wall_time", "backend", "device", "engine_version"):
            assert key in par, key
        e = f["observables/kinetic_energy_translational/value"][()]
        assert np.all(np.isfinite(e)) and e[-1] < e[0]        # dissipative: the gas cooled
        t = f["observables/kinetic_energy_translational/time"][()]
        assert t[0] == 0.0 and abs(t[-1] - TINY["t_end"]) <= par["dt"]   # whole steps
        q = f["particles/all/orientation/value"][-1]
        assert np.allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)


def test_cancel_leaves_no_file(tmp_path):
    out = tmp_path / "c.h5"
    calls = []

    def cancel():
        calls.append(1)
        return len(calls) > 3

    with pytest.raises(Cancelled):
        run(SimulationSpec(**TINY), out, should_cancel=cancel)
    assert not out.exists() and not partial_path(out).exists()


def test_overlapping_collision_stops_with_step_and_cause(tmp_path):
    # velocity valid for the spec check (typical overlap < limit) but the tails overlap > 5 %:
    spec = SimulationSpec(**{**TINY, "velocity_rms": 1.2, "stiffness": 1e6, "overlap_limit": 0.02})
    out = tmp_path / "x.h5"
    with pytest.raises(InstabilityError) as exc:
        run(spec, out)
    msg = str(exc.value)
    assert "at step" in msg and "particle" in msg and "likely cause" in msg
    assert not out.exists() and not partial_path(out).exists()


def test_time_step_too_large_for_stiffness_is_refused_before_running():
    with pytest.raises(Exception) as exc:
        SimulationSpec(**{**TINY, "dt": 1e-3})
    assert "cannot resolve a contact" in str(exc.value)


def test_elongated_sphere_is_refused_clearly_and_writes_nothing(tmp_path):
    # rough ellipsoids run now (tests/engine/test_rough_ellipsoids.py); an elongation needs an elongated shape
    with pytest.raises(Exception, match="elongation = 2.0 but shape is 'sphere'"):
        run(SimulationSpec(**{**TINY, "shape": "sphere", "elongation": 2.0}), tmp_path / "e.h5")
    assert not (tmp_path / "e.h5").exists()


def test_spheres_without_orientations_run_the_same_and_leave_them_out(tmp_path):
    """orientations = false: the snapshots have no orientation element and the rest is the same, bit for bit (a
    sphere's orientation changes nothing else); a spheroid spec refuses it, naming the field."""
    files = {}
    for on in (True, False):
        s = run(SimulationSpec(**{**TINY, "orientations": on}), tmp_path / f"o{on}.h5")
        with h5py.File(s.output) as f:
            part = f["particles/all"]
            files[on] = {k: part[f"{k}/value"][...]
                         for k in part if isinstance(part[k], h5py.Group) and "value" in part[k]}
    assert sorted(files[True]) == ["angular_velocity", "orientation", "position", "velocity"]
    assert sorted(files[False]) == ["angular_velocity", "position", "velocity"]
    assert not np.array_equal(files[True]["orientation"][0], files[True]["orientation"][-1])
    for k, a in files[False].items():
        assert np.array_equal(a, files[True][k]), k
    with pytest.raises(Exception, match="orientations = false but shape is 'ellipsoid'"):
        SimulationSpec(shape="ellipsoid", elongation=2.0, orientations=False)


@pytest.mark.parametrize("precision", ["float64", "mixed"])
def test_checkpoint_resume_matches_uninterrupted_run(tmp_path, precision):
    spec = SimulationSpec(**{**TINY, "thermalization": 0.0, "t_end": 0.05, "precision": precision})
    # the resumed run rebuilds its neighbour list at the resume point: same physics, summation order may
    # differ, so agreement is to rounding amplified over a few hundred steps ('mixed' too: its float32 state and
    # float64 positions are checkpointed exactly)
    rtol = 1e-9
    ref = tmp_path / "ref.h5"
    run(spec, ref)
    ck = tmp_path / "ck"
    out = tmp_path / "res.h5"
    calls = []

    def cancel_midway():
        calls.append(1)
        return len(calls) == 120     # 120 of 200 records: mid-run, after checkpoints were written

    with pytest.raises(Cancelled):
        run(spec, out, should_cancel=cancel_midway, checkpoint_dir=ck, checkpoint_interval=0.0)
    assert (ck / "state.npz").exists() and not out.exists()
    s = run(spec, out, checkpoint_dir=ck, checkpoint_interval=0.0)
    assert s.resumed_from_step is not None and s.resumed_from_step > 0
    assert not ck.exists()                                   # cleared after success
    with h5py.File(ref) as a, h5py.File(out) as b:
        for name in ("kinetic_energy_translational", "kinetic_energy_rotational", "contacts", "collisions"):
            va = a[f"observables/{name}/value"][()]
            vb = b[f"observables/{name}/value"][()]
            assert va.shape == vb.shape
            assert np.array_equal(a[f"observables/{name}/step"][()], b[f"observables/{name}/step"][()])
            assert np.allclose(va, vb, rtol=rtol, atol=0), np.max(np.abs(vb / va - 1))
        for element in ("position", "velocity"):   # the resumed file's frames: each once, at the same steps
            assert np.array_equal(a[f"particles/all/{element}/step"][()], b[f"particles/all/{element}/step"][()])
            assert b[f"particles/all/{element}/value"].shape == a[f"particles/all/{element}/value"].shape
        pa = a["particles/all/position/value"][-1]
        pb = b["particles/all/position/value"][-1]
        assert pa.dtype == pb.dtype == np.float64
        assert np.abs(pa - pb).max() < rtol


def test_a_cpu_scene_writes_its_file_in_place(tmp_path, monkeypatch):
    """A CPU scene's file work runs in the calling thread (engine.driver.simulate._file_thread): it never asks for the
    I/O thread, and its file is whole."""
    import engine.output.h5md as h5md

    def no_thread():
        raise AssertionError("a CPU scene handed its file work to the I/O thread")

    monkeypatch.setattr(h5md, "_io", no_thread)
    run(SimulationSpec(**TINY), tmp_path / "a.h5")
    with h5py.File(tmp_path / "a.h5") as f:
        assert f["particles/all/position/value"].shape[0] == TINY["snapshots"]
        assert f["observables/kinetic_energy_translational/value"].shape[0] > 1


def test_resume_from_first_record_writes_it_once(tmp_path):
    """A checkpoint taken right after the t = 0 record must not make the resumed run repeat it."""
    spec = SimulationSpec(**{**TINY, "thermalization": 0.0, "t_end": 0.01})
    ck, out = tmp_path / "ck", tmp_path / "r.h5"
    with pytest.raises(Cancelled):
        run(spec, out, should_cancel=iter([False, True]).__next__, checkpoint_dir=ck, checkpoint_interval=0.0)
    s = run(spec, out, checkpoint_dir=ck, checkpoint_interval=0.0)
    assert s.resumed_from_step == 0
    with h5py.File(out) as f:
        t = f["observables/kinetic_energy_translational/time"][()]
    assert t[0] == 0.0 and (t[1:] > t[:-1]).all()


def test_summary_names_the_loop_time_and_the_job_time(tmp_path):
    """RunSummary: loop_s is the time loop's wall time (wall_s, the job queue's name for it), job_wall_s the whole
    job's from the spec to the closed file, which holds the loop; each Cundall number is N * steps over its time."""
    s = run(SimulationSpec(**TINY), tmp_path / "t.h5")
    assert s.job_wall_s > s.loop_s > 0
    assert s.job_wall_s > s.loop_s
    assert s.cundall == pytest.approx(s.n_particles * s.steps / s.loop_s, rel=1e-12)
    assert s.cundall_e2e == pytest.approx(s.n_particles * s.steps / s.job_wall_s, rel=1e-12)
