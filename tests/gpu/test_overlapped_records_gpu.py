"""Real-GPU check of the records done while the GPU runs the next steps (engine/simulate.py, _Deferred; the CUDA
ensemble's ``idle`` hook): a packed ensemble (spheres and ellipsoids) and one scene write the same files with it as
without it (DEMQ_OVERLAP_RECORDS=0) — the trajectories bit for bit, the observables to rounding as any two GPU
runs — and the record work did run inside the waits; one scene's frames also through host buffers page-locked in
place and through late-pinned ones. Skipped without a GPU."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from engine.backends.base import cuda_available

pytestmark = pytest.mark.skipif(not cuda_available(), reason="needs a CUDA GPU")


def _datasets(path):
    out = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    return out


def spy_units_in_waits(monkeypatch) -> list:
    """One entry per deferred record unit that ran inside CudaEnsemble.advance (in its waits for the GPU)."""
    from engine import simulate
    from engine.backends import cuda as cuda_mod

    in_advance, in_waits = [False], []
    orig_advance, orig_run_one = cuda_mod.CudaEnsemble.advance, simulate._Deferred.run_one

    def advance(self, nsteps):
        in_advance[0] = True
        try:
            return orig_advance(self, nsteps)
        finally:
            in_advance[0] = False

    def run_one(self):
        ran = orig_run_one(self)
        if ran and in_advance[0]:
            in_waits.append(1)
        return ran

    monkeypatch.setattr(cuda_mod.CudaEnsemble, "advance", advance)
    monkeypatch.setattr(simulate._Deferred, "run_one", run_one)
    return in_waits


@pytest.mark.parametrize("multistep", ["1", "0"])   # the waits of the many-steps kernel and of the per-phase loop
@pytest.mark.parametrize("kw", [
    dict(n_particles=2048, volume_fraction=0.1, e_n=0.8, e_t=0.5, t_end=0.02, snapshots=2, thermalization=1),
    dict(shape="ellipsoid", elongation=2.0, n_particles=1024, volume_fraction=0.1, e_n=0.9, t_end=0.01,
         snapshots=2, thermalization=0)])
def test_a_packed_ensemble_writes_the_same_files_with_records_overlapped(tmp_path, monkeypatch, kw, multistep):
    from engine.ensemble import run_ensemble
    from tests.engine.test_ensemble import spy_deferred_stops

    monkeypatch.setenv("DEMQ_CUDA_MULTISTEP", multistep)
    specs = [dict(kw, seed=s, backend="cuda") for s in range(12)]
    deferred = spy_deferred_stops(monkeypatch)
    in_waits = spy_units_in_waits(monkeypatch)
    files = {}
    for on in ("0", "1"):
        monkeypatch.setenv("DEMQ_OVERLAP_RECORDS", on)
        outs = [tmp_path / f"on{on}-{k}.h5" for k in range(len(specs))]
        res = run_ensemble(specs, outs)
        assert all(not isinstance(r, BaseException) for r in res), res
        files[on] = [_datasets(o) for o in outs]
    assert any(deferred) and sum(in_waits) > 0, (sum(deferred), sum(in_waits))
    differ = {}
    for a, b in zip(files["0"], files["1"]):
        assert a.keys() == b.keys()
        for name in a:
            if not np.array_equal(a[name], b[name]):
                differ[name] = max(differ.get(name, 0.0),
                                   float(np.max(np.abs(np.asarray(a[name], float) - np.asarray(b[name], float)))))
    print("\ndatasets that differ (max |difference|):", differ)
    assert not [n for n in differ if not n.startswith("observables/")], differ
    # the observables' block sums end in float atomics whose order varies between any two GPU runs
    for k in range(len(specs)):
        for name in differ:
            assert np.allclose(files["0"][k][name], files["1"][k][name], rtol=1e-9, atol=1e-12), name


def test_one_scene_overlaps_its_records_and_pins_its_large_frames_late(tmp_path, monkeypatch):
    """engine.run of one scene on the GPU: its records are done in the next steps' waits too (SerialEnsemble
    passes the hook to its CUDA backend), and frames of a large scene (PINNED_SLOT_BYTES = 0 makes this scene's
    frames large) go through host buffers page-locked in place or, where they cannot be (here: refused on
    purpose), through plain host buffers first and through buffers pinned by a thread later. The four runs write
    the same file: the trajectories bit for bit, the observables to rounding."""
    from engine.loops import cuda_frames
    from engine.backends import cuda as cuda_mod
    from engine.simulate import run
    from tests.engine.test_ensemble import spy_deferred_stops

    spec = dict(n_particles=4096, volume_fraction=0.1, e_n=0.8, e_t=0.5, t_end=0.02, snapshots=7, thermalization=1,
                seed=2, backend="cuda")
    deferred = spy_deferred_stops(monkeypatch)
    ran_in_waits = spy_units_in_waits(monkeypatch)
    pinned_frames, locked = [], []
    orig_slot, orig_lock = cuda_mod.CudaEnsemble._host_slot, cuda_frames._page_locked

    def host_slot(self, slot, nmax):
        ready = dict(getattr(self, "_pinned_slots", None) or {})
        bufs = orig_slot(self, slot, nmax)
        pinned_frames.append(any(bufs is b for b in ready.values()))
        return bufs

    monkeypatch.setattr(cuda_mod.CudaEnsemble, "_host_slot", host_slot)
    files = {}
    for label, overlap, slot_bytes, lock in (("plain", "0", cuda_frames.PINNED_SLOT_BYTES, True),
                                             ("overlap", "1", 32 << 20, True), ("locked", "1", 0, True),
                                             ("late-pinned", "1", 0, False)):
        monkeypatch.setenv("DEMQ_OVERLAP_RECORDS", overlap)
        monkeypatch.setattr(cuda_frames, "PINNED_SLOT_BYTES", slot_bytes)
        monkeypatch.setattr(cuda_frames, "_page_locked",
                            (lambda a: locked.append(orig_lock(a)) or locked[-1]) if lock else (lambda a: None))
        del deferred[:], pinned_frames[:], locked[:]
        run(spec, tmp_path / f"{label}.h5")
        files[label] = _datasets(tmp_path / f"{label}.h5")
        assert any(deferred) == (overlap == "1"), (label, deferred)
        if label == "locked":           # every large slot page-locked at once, none replaced later
            assert locked and all(p is not None for p in locked) and not any(pinned_frames), (locked, pinned_frames)
    assert len(pinned_frames) == 7 and not any(pinned_frames[:3]) and any(pinned_frames[3:]), pinned_frames
    assert sum(ran_in_waits) > 0
    for label in ("overlap", "locked", "late-pinned"):
        a, b = files["plain"], files[label]
        assert a.keys() == b.keys()
        for name in a:
            if name.startswith("observables/"):   # block sums ending in float atomics: equal to rounding
                assert np.allclose(a[name], b[name], rtol=1e-9, atol=1e-12), (label, name)
            elif not name.startswith("parameters"):
                assert np.array_equal(a[name], b[name]), (label, name)
