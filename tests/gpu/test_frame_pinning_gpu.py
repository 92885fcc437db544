"""Real-GPU check of the snapshot frames of one large scene (engine/loops/cuda_frames.py): through host buffers
page-locked in place and, where they cannot be, through plain host buffers first and buffers pinned by a thread
later; every way writes the same file as the default slots. Skipped without a GPU."""

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


def test_one_scene_pins_its_large_frames_in_place_or_late(tmp_path, monkeypatch):
    """engine.run of one scene on the GPU: frames of a large scene (PINNED_SLOT_BYTES = 0 makes this scene's
    frames large) go through host buffers page-locked in place or, where they cannot be (here: refused on
    purpose), through plain host buffers first and through buffers pinned by a thread later. The three runs write
    the same file: the trajectories bit for bit, the observables to rounding."""
    from engine.loops import cuda_frames
    from engine.backends import cuda as cuda_mod
    from engine.driver.simulate import run

    spec = dict(n_particles=4096, volume_fraction=0.1, e_n=0.8, e_t=0.5, t_end=0.02, snapshots=7, thermalization=1,
                seed=2, backend="cuda")
    pinned_frames, locked = [], []
    orig_slot, orig_lock = cuda_mod.CudaEnsemble._host_slot, cuda_frames._page_locked

    def host_slot(self, slot, nmax):
        ready = dict(getattr(self, "_pinned_slots", None) or {})
        bufs = orig_slot(self, slot, nmax)
        pinned_frames.append(any(bufs is b for b in ready.values()))
        return bufs

    monkeypatch.setattr(cuda_mod.CudaEnsemble, "_host_slot", host_slot)
    files = {}
    for label, slot_bytes, lock in (("plain", cuda_frames.PINNED_SLOT_BYTES, True), ("locked", 0, True),
                                    ("late-pinned", 0, False)):
        monkeypatch.setattr(cuda_frames, "PINNED_SLOT_BYTES", slot_bytes)
        monkeypatch.setattr(cuda_frames, "_page_locked",
                            (lambda a: locked.append(orig_lock(a)) or locked[-1]) if lock else (lambda a: None))
        del pinned_frames[:], locked[:]
        run(spec, tmp_path / f"{label}.h5")
        files[label] = _datasets(tmp_path / f"{label}.h5")
        if label == "locked":           # every large slot page-locked at once, none replaced later
            assert locked and all(p is not None for p in locked) and not any(pinned_frames), (locked, pinned_frames)
    assert len(pinned_frames) == 7 and not any(pinned_frames[:3]) and any(pinned_frames[3:]), pinned_frames
    for label in ("locked", "late-pinned"):
        a, b = files["plain"], files[label]
        assert a.keys() == b.keys()
        for name in a:
            if name.startswith("observables/"):   # block sums ending in float atomics: equal to rounding
                assert np.allclose(a[name], b[name], rtol=1e-9, atol=1e-12), (label, name)
            elif not name.startswith("parameters"):
                assert np.array_equal(a[name], b[name]), (label, name)
